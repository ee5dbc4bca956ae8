"""`tiger prepare` on bad input: one clear line, nothing lost. A capture with no images or no poses,
a scene no capture view sees, a features stage redone with another PCA basis or model, and a stage
killed mid-way (the next run continues it)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch

from .datasets import tabletop_dataset
from .test_cli_pipeline import _run, _tiny_models

TINY = ["--recon-steps", "30", "--init-points", "400", "--test-every", "3", "--upsampler", "bilinear",
        "--long-side", "32", "--clip-long-side", "64", "--pca-dim", "16", "--embed-steps", "5", "--device", "cpu"]


def _one_line_error(r, *words):
    lines = [ln for ln in r.stderr.strip().splitlines() if "Warning" not in ln and ln.strip()]
    assert r.returncode == 2, r.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("tiger prepare: error:"), r.stderr[-2000:]
    for w in words:
        assert w in lines[0], lines[0]


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("prepare_errors")
    return tabletop_dataset(root / "data", n_views=4), _tiny_models(root / "models")


def test_capture_without_images_or_poses(tmp_path, capture):
    data, cfg = capture
    empty = tmp_path / "empty"
    empty.mkdir()
    no_poses = tmp_path / "no_poses"
    shutil.copytree(data / "images", no_poses / "images")
    no_images = tmp_path / "no_images"
    no_images.mkdir()
    shutil.copy(data / "transforms.json", no_images)
    no_frames = tmp_path / "no_frames"
    shutil.copytree(data, no_frames)
    meta = json.loads((no_frames / "transforms.json").read_text())
    meta["frames"] = []
    (no_frames / "transforms.json").write_text(json.dumps(meta))
    cases = [(empty, ["no dataset found", "transforms.json", "COLMAP"]),
             (no_poses, ["no dataset found"]),
             (no_images, ["4 of 4 images not found", "--skip-missing"]),
             (no_frames, ["'frames'", "no usable frames"])]
    for folder, words in cases:
        out = tmp_path / f"out_{folder.name}"
        r = _run("prepare", str(folder), "--out", str(out), "--models", str(cfg), *TINY)
        _one_line_error(r, str(folder.name), *words)
        assert not out.exists(), f"{folder.name}: the output folder was made before the capture was checked"


def test_scene_no_view_sees(tmp_path, capture):
    from tiger.demo import tabletop_scene

    data, cfg = capture
    scene = tabletop_scene(density=0.05).scene
    with torch.no_grad():
        scene.means += torch.tensor([0.0, 0.0, 500.0])  # far outside every view
    far = tmp_path / "far.ply"
    scene.save_ply(far)
    out = tmp_path / "out"
    r = _run("prepare", str(data), "--scene", str(far), "--out", str(out), "--models", str(cfg), *TINY)
    _one_line_error(r, "far.ply", f"none of its {len(scene)} Gaussians", "cameras", "coordinate frame")
    assert not out.exists()
    # the same scene where the capture sees it is taken
    near = tmp_path / "near.ply"
    tabletop_scene(density=0.05).scene.save_ply(near)
    from tiger.cli.common import open_dataset
    from tiger.cli.prepare import check_scene_seen

    check_scene_seen(near, open_dataset(str(data)).cameras, data)


def _wait_for(path_glob, proc, timeout=600):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if list(path_glob()):
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.02)
    return False


@pytest.fixture(scope="module")
def long_capture(tmp_path_factory, capture):
    """The same tiny models with 24 views: a features stage long enough to be killed part-way
    (with 4 views an idle machine can finish the stage between the first cached image and the kill)."""
    root = tmp_path_factory.mktemp("prepare_long")
    return tabletop_dataset(root / "data", n_views=24), capture[1]


def test_killed_stage_resumes_and_other_features_are_refused(tmp_path, long_capture):
    data, cfg = long_capture
    n_views = len(json.loads((data / "transforms.json").read_text())["frames"])
    out = tmp_path / "prep"
    args = [sys.executable, "-m", "tiger.cli.main", "prepare", str(data), "--out", str(out), "--models", str(cfg),
            *TINY]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    cache = out / "features" / "cache"
    started = _wait_for(lambda: cache.glob("*.pt") if cache.is_dir() else [], proc)
    proc.send_signal(signal.SIGKILL)  # mid-way through the features stage: no clean-up runs
    proc.communicate(timeout=60)
    assert started, "the features stage never wrote its first image"
    rec = json.loads((out / "prepare.json").read_text())
    assert rec["stages"]["reconstruct"]["done"] and not rec["stages"]["features"].get("done")
    done_before = {p.name for p in cache.glob("*.pt")}

    r = _run("prepare", str(data), "--out", str(out), "--models", str(cfg), *TINY)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "[1/3] reconstruct: done before" in r.stdout and "[2/3] features: continuing" in r.stdout
    stages = json.loads((out / "prepare.json").read_text())["stages"]
    assert all(s["done"] for s in stages.values()) and stages["features"]["quality"]["maps"] == n_views
    assert done_before <= {p.name for p in cache.glob("*.pt")}
    lang_mtime = (out / "scene_lang.ply").stat().st_mtime_ns

    # a features stage redone with another PCA basis or another model: refused, naming the setting
    r = _run("prepare", str(data), "--out", str(out), "--models", str(cfg), *[a if a != "16" else "8" for a in TINY])
    _one_line_error(r, "stage 'features' finished with other inputs (pca_dim: 16 -> 8)", "--force")
    other = tmp_path / "other_models.json"
    other.write_text(cfg.read_text())
    r = _run("prepare", str(data), "--out", str(out), "--models", str(other), *TINY)
    _one_line_error(r, "stage 'features' finished with other inputs (models:", "other_models.json")
    assert (out / "scene_lang.ply").stat().st_mtime_ns == lang_mtime  # nothing lost


def test_view_takes_a_prepared_folder(tmp_path):
    from tiger.cli.common import CliError
    from tiger.cli.view import _scene_file

    prepared = tmp_path / "prepared"
    (prepared / "recon").mkdir(parents=True)
    (prepared / "recon" / "scene.ply").write_bytes(b"ply")
    (prepared / "prepare.json").write_text("{}")
    with pytest.raises(CliError, match="embed stage has not finished"):
        _scene_file(str(prepared))
    (prepared / "scene_lang.ply").write_bytes(b"ply")
    assert _scene_file(str(prepared)) == prepared / "scene_lang.ply"
