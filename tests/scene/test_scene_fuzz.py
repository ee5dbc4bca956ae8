"""Fuzzing the readers: mutated PLY, COLMAP and transforms.json bytes either load or raise
SceneFormatError -- never another exception, a crash or a hang."""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from .colmapref import write_model
from .plyref import random_columns, write_ply
from tiger.scene import SceneFormatError
from tiger.scene.colmap import (read_cameras_binary, read_cameras_text, read_images_binary, read_images_text,
                                read_points3d_binary, read_points3d_text)
from tiger.scene.dataset import load_colmap
from tiger.scene.nerf import load_transforms
from tiger.scene import read_ply

FUZZ = settings(max_examples=300, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

mutation = st.tuples(st.sampled_from(["set", "insert", "delete", "truncate", "digits"]),
                     st.floats(0, 1, exclude_max=True), st.binary(min_size=1, max_size=6))
mutations = st.lists(mutation, min_size=1, max_size=4)


def mutate(data: bytes, muts) -> bytes:
    b = bytearray(data)
    for op, where, payload in muts:
        i = int(where * len(b)) if b else 0
        if op == "set":
            b[i:i + len(payload)] = payload
        elif op == "insert":
            b[i:i] = payload
        elif op == "delete":
            del b[i:i + len(payload)]
        elif op == "truncate":
            del b[i:]
        else:  # rewrite a digit run into a huge / negative / odd number: hits counts and sizes
            j = i
            while j < len(b) and not chr(b[j]).isdigit():
                j += 1
            k = j
            while k < len(b) and chr(b[k]).isdigit():
                k += 1
            b[j:k] = [b"99999999999999999999", b"-1", b"0", b"1e9", b"nan"][payload[0] % 5]
    return bytes(b)


def check(reader, path: Path, data: bytes) -> None:
    path.write_bytes(data)
    try:
        reader(path)
    except SceneFormatError as exc:
        assert str(exc)
    # any other exception propagates and fails the test


def _ply_seed(fmt: str) -> bytes:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "s.ply"
        write_ply(p, random_columns(4, 1, lang=2), fmt, comments=('tiger_metadata {"a":1}',))
        return p.read_bytes()


PLY_BIN, PLY_ASCII = _ply_seed("binary_little_endian"), _ply_seed("ascii")


@pytest.mark.timeout(240)
@FUZZ
@given(seed=st.sampled_from([PLY_BIN, PLY_ASCII]), muts=mutations)
def test_fuzz_ply(seed, muts):
    with tempfile.TemporaryDirectory() as d:
        check(read_ply, Path(d) / "f.ply", mutate(seed, muts))


def _colmap_seed(binary: bool) -> dict:
    cams = [(1, "OPENCV", 32, 24, (30.0, 31.0, 16.0, 12.0, 0.01, 0.0, 0.0, 0.0)), (2, "PINHOLE", 32, 24, (30.0, 30, 16, 12))]
    imgs = [(1, (1.0, 0, 0, 0), (0.0, 0, 1), 1, "a.png", [(1.0, 2.0, 0)]), (2, (0.0, 1, 0, 0), (0.0, 0, 1), 2, "b.png", [])]
    pts = [(0, (0.0, 0, 0), (1, 2, 3), 0.1, [(1, 0)]), (1, (1.0, 0, 0), (4, 5, 6), 0.2, [])]
    with tempfile.TemporaryDirectory() as d:
        write_model(Path(d), cams, imgs, pts, binary)
        ext = ".bin" if binary else ".txt"
        return {n: (Path(d) / f"{n}{ext}").read_bytes() for n in ("cameras", "images", "points3D")}


COLMAP_BIN, COLMAP_TXT = _colmap_seed(True), _colmap_seed(False)
READERS = {("cameras", True): read_cameras_binary, ("images", True): read_images_binary,
           ("points3D", True): read_points3d_binary, ("cameras", False): read_cameras_text,
           ("images", False): read_images_text, ("points3D", False): read_points3d_text}


@pytest.mark.timeout(240)
@FUZZ
@given(which=st.sampled_from(sorted(READERS, key=str)), muts=mutations)
def test_fuzz_colmap_files(which, muts):
    name, binary = which
    seed = (COLMAP_BIN if binary else COLMAP_TXT)[name]
    with tempfile.TemporaryDirectory() as d:
        check(READERS[which], Path(d) / f"{name}{'.bin' if binary else '.txt'}", mutate(seed, muts))


@pytest.mark.timeout(240)
@settings(max_examples=100, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(binary=st.booleans(), name=st.sampled_from(["cameras", "images", "points3D"]), muts=mutations)
def test_fuzz_colmap_dataset(binary, name, muts):
    """Whole-dataset loading (cameras built from the records) on a mutated model."""
    files = dict(COLMAP_BIN if binary else COLMAP_TXT)
    files[name] = mutate(files[name], muts)
    ext = ".bin" if binary else ".txt"
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "sparse").mkdir()
        (Path(d) / "images").mkdir()
        for n, data in files.items():
            (Path(d) / "sparse" / f"{n}{ext}").write_bytes(data)
        for n in ("a.png", "b.png"):
            Image.new("RGB", (32, 24)).save(Path(d) / "images" / n)
        try:
            load_colmap(d, skip_missing=True)
        except SceneFormatError:
            pass


def _transforms_seed() -> bytes:
    frames = [{"file_path": "images/0.png", "transform_matrix": np.eye(4).tolist(), "fl_x": 20.0},
              {"file_path": "images/1", "transform_matrix": np.eye(4)[:3].tolist()}]
    top = {"camera_angle_x": 0.8, "w": 16, "h": 12, "cx": 8.0, "cy": 6, "k1": 0.01, "p1": 0.001, "frames": frames}
    return json.dumps(top, indent=1).encode()


TRANSFORMS = _transforms_seed()


@pytest.mark.timeout(240)
@FUZZ
@given(muts=mutations)
def test_fuzz_transforms_json(muts):
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "images").mkdir()
        for n in ("0.png", "1.png"):
            Image.new("RGB", (16, 12)).save(Path(d) / "images" / n)
        check(lambda p: load_transforms(p, skip_missing=True), Path(d) / "transforms.json", mutate(TRANSFORMS, muts))
