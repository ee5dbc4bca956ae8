"""The capture's cameras beside a scene: ``cameras.json`` in the PLY's folder, INRIA's format.

INRIA's 3DGS writes ``cameras.json`` into its output folder: a list with one entry per view,
``{"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"}`` where
``position`` [3] and ``rotation`` [3][3] (rows) are the camera-to-world transform with OpenCV
axes, and the principal point is the image centre. TIGER writes the same fields (so viewers
that read INRIA's file read ours) plus ``cx``, ``cy`` (pixels; read when present, else the
image centre) and ``image_name`` (the dataset's name of the image), in capture order. The PLY
itself stays a plain INRIA PLY. Reading raises :class:`SceneFormatError` naming the file, the
entry and the field.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence, Union

import torch

from tiger.utils.io import atomic_write

from tiger.render import Camera
from tiger.render.camera import rigid_inverse
from .cameras import intrinsics
from .errors import SceneFormatError

PathLike = Union[str, os.PathLike]
FILE_NAME = "cameras.json"


def cameras_json_path(scene_path: PathLike) -> Path:
    """Where the cameras of the scene file ``scene_path`` live: ``cameras.json`` beside it."""
    return Path(scene_path).with_name(FILE_NAME)


def write_cameras_json(path: PathLike, cameras: Sequence[Camera]) -> Path:
    """Write ``cameras`` (in order) as an INRIA-style ``cameras.json`` (atomically)."""
    entries = []
    for i, cam in enumerate(cameras):
        c2w = rigid_inverse(cam.viewmat.double().cpu())
        name = str(cam.image_name or f"view{i:04d}")
        entries.append({
            "id": i, "img_name": Path(name).stem, "width": cam.width, "height": cam.height,
            "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "image_name": name,
        })
    with atomic_write(path, "w") as fh:
        json.dump(entries, fh, indent=1)
    return Path(path)


def _number(entry: dict, key: str, path: Path, where: str) -> float:
    v = entry.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneFormatError(path, f"missing or not a number: {v!r}", f"{where}.{key}")
    return float(v)


def _matrix(entry: dict, key: str, shape: tuple, path: Path, where: str) -> torch.Tensor:
    try:
        t = torch.tensor(entry[key], dtype=torch.float64)
    except (KeyError, TypeError, ValueError):
        raise SceneFormatError(path, "missing or not numbers", f"{where}.{key}") from None
    if tuple(t.shape) != shape:
        raise SceneFormatError(path, f"must have shape {list(shape)}, got {list(t.shape)}", f"{where}.{key}")
    return t


def read_cameras_json(path: PathLike) -> list[Camera]:
    """The cameras of an INRIA-style ``cameras.json`` (ours or INRIA's), in file order."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise SceneFormatError(path, "not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SceneFormatError(path, f"invalid JSON ({e})") from None
    if not isinstance(data, list) or not data:
        raise SceneFormatError(path, "must be a non-empty list of cameras")
    cams = []
    for i, entry in enumerate(data):
        where = f"[{i}]"
        if not isinstance(entry, dict):
            raise SceneFormatError(path, "must be an object", where)
        w, h = _number(entry, "width", path, where), _number(entry, "height", path, where)
        fx, fy = _number(entry, "fx", path, where), _number(entry, "fy", path, where)
        cx = _number(entry, "cx", path, where) if "cx" in entry else w / 2
        cy = _number(entry, "cy", path, where) if "cy" in entry else h / 2
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = _matrix(entry, "rotation", (3, 3), path, where)
        c2w[:3, 3] = _matrix(entry, "position", (3,), path, where)
        if not torch.allclose(c2w[:3, :3] @ c2w[:3, :3].T, torch.eye(3, dtype=torch.float64), atol=1e-4):
            raise SceneFormatError(path, "is not a rotation matrix", f"{where}.rotation")
        name = entry.get("image_name") or entry.get("img_name") or f"view{i:04d}"
        try:
            cams.append(Camera(rigid_inverse(c2w), intrinsics(fx, fy, cx, cy), int(w), int(h),
                               image_name=str(name)))
        except ValueError as e:
            raise SceneFormatError(path, str(e), where) from None
    return cams
