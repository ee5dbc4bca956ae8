"""NeRF / instant-ngp / nerfstudio ``transforms.json`` cameras.

Intrinsics may be global or per frame (a frame's keys override the global ones):
``fl_x``/``fl_y`` (or ``camera_angle_x``/``camera_angle_y``), ``cx``/``cy`` (default the
image centre), ``w``/``h`` (default: read from the image), distortion ``k1 k2 k3 p1 p2``
and nerfstudio's ``camera_model`` (``OPENCV``, ``PINHOLE``, ``SIMPLE_PINHOLE``).
``transform_matrix`` is camera-to-world in OpenGL axes (+x right, +y up, looking down
-z); it is converted to TIGER's world-to-camera OpenCV matrix.
"""
from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any, Optional, Union

import torch

from tiger.render import Camera, Distortion
from tiger.render.camera import rigid_inverse
from .cameras import intrinsics
from .errors import MissingImagesError, SceneFormatError

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]

#: OpenGL camera axes -> OpenCV camera axes (flip y and z).
GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
_INTRINSIC_KEYS = ("fl_x", "fl_y", "camera_angle_x", "camera_angle_y", "cx", "cy", "w", "h",
                   "k1", "k2", "k3", "p1", "p2", "camera_model", "is_fisheye")
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".JPG", ".PNG", ".JPEG")


def read_json(path: PathLike) -> Any:
    """``json.load`` with errors that name the file, line and column."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SceneFormatError(path, "file not found") from None
    except IsADirectoryError:
        raise SceneFormatError(path, "is a directory, not a JSON file") from None
    except UnicodeDecodeError as exc:
        raise SceneFormatError(path, f"not UTF-8 text (byte offset {exc.start})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise SceneFormatError(path, f"invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    except RecursionError:
        raise SceneFormatError(path, "invalid JSON: nesting too deep") from None


def _number(v: Any, path: Path, field: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneFormatError(path, f"must be a number, got {type(v).__name__} {str(v)[:40]}", field)
    try:
        v = float(v)
    except OverflowError:
        raise SceneFormatError(path, "number too large", field) from None
    if not math.isfinite(v):
        raise SceneFormatError(path, f"must be finite, got {v}", field)
    return v


def _matrix(m: Any, path: Path, field: str) -> torch.Tensor:
    if not isinstance(m, list) or len(m) not in (3, 4) or not all(isinstance(r, list) and len(r) == 4 for r in m):
        raise SceneFormatError(path, "must be a 4x4 (or 3x4) list of numbers", field)
    vals = [[_number(v, path, field) for v in row] for row in m]
    T = torch.eye(4, dtype=torch.float64)
    T[: len(vals)] = torch.tensor(vals, dtype=torch.float64)
    R = T[:3, :3]
    err = float((R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max())
    if err > 1e-2 or float(torch.det(R)) <= 0:
        raise SceneFormatError(path, f"rotation part is not a rotation (|RᵀR - I| = {err:.3g}, "
                                     f"det = {float(torch.det(R)):.3g})", field)
    if err > 1e-9:  # round-off in the file: project onto the nearest rotation
        U, _, Vh = torch.linalg.svd(R)
        T[:3, :3] = U @ Vh
    return T


def resolve_image(base: Path, file_path: str) -> Optional[Path]:
    """The image ``file_path`` (relative to ``base``); tries common extensions when the
    name has none (NeRF-synthetic writes ``./train/r_0``). None when nothing exists."""
    try:
        p = (base / file_path)
        if p.is_file():
            return p
        if not p.suffix or p.suffix.lower() not in _IMAGE_EXTS:
            for ext in _IMAGE_EXTS:
                q = p.with_name(p.name + ext)
                if q.is_file():
                    return q
    except (OSError, ValueError):  # NUL bytes, names too long: no such image
        return None
    return None


def load_transforms(path: PathLike, skip_missing: bool = False) -> tuple:
    """Cameras of a ``transforms.json`` file (or a folder holding one).

    Args:
        path: the JSON file or its folder.
        skip_missing: skip frames whose image is missing (with a warning) instead of raising.
    Returns:
        (cameras sorted by image name, the JSON's top-level fields other than frames).
    Raises:
        SceneFormatError naming the file, the frame and the key.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    meta = read_json(path)
    if not isinstance(meta, dict):
        raise SceneFormatError(path, "top level must be a JSON object")
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise SceneFormatError(path, "missing or not a list", "frames")
    base = path.parent
    cams: list = []
    missing: list = []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise SceneFormatError(path, "must be an object", f"frames[{i}]")
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise SceneFormatError(path, "missing or not a string", f"frames[{i}].file_path")
        if "transform_matrix" not in fr:
            raise SceneFormatError(path, "missing", f"frames[{i}].transform_matrix")
        img = resolve_image(base, fp)
        if img is None:
            missing.append((i, fp))
            continue
        c2w_gl = _matrix(fr["transform_matrix"], path, f"frames[{i}].transform_matrix")
        K, dist, w, h = _frame_intrinsics(meta, fr, i, img, path)
        vm = rigid_inverse(c2w_gl @ GL_TO_CV)
        name = os.path.relpath(img, base)
        try:
            cams.append(Camera(vm, K, w, h, image_path=img, image_name=name, distortion=dist,
                               metadata={"frame_index": i}))
        except ValueError as exc:
            raise SceneFormatError(path, str(exc), f"frames[{i}]") from None
    if missing and not skip_missing:
        raise MissingImagesError(path, [fp for _, fp in missing], len(frames),
                                 f"frames[{missing[0][0]}].file_path")
    if missing:
        log.warning("%s: skipped %d of %d frames whose image is missing (first: %s)", path, len(missing),
                    len(frames), missing[0][1])
    if not cams:
        raise SceneFormatError(path, "no usable frames", "frames")
    extra = {k: v for k, v in meta.items() if k != "frames"}
    return sorted(cams, key=lambda c: c.image_name), extra


def _frame_intrinsics(meta: dict, fr: dict, i: int, img: Path, path: Path) -> tuple:
    def get(key: str) -> Any:
        if key in fr:
            return fr[key], f"frames[{i}].{key}"
        return meta.get(key), key

    model, field = get("camera_model")
    if model is not None and model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise SceneFormatError(path, f"camera model '{str(model)[:40]}' is not supported "
                                     "(OPENCV, PINHOLE, SIMPLE_PINHOLE)", field)
    fish, field = get("is_fisheye")
    if fish:
        raise SceneFormatError(path, "fisheye cameras are not supported", field)

    def num(key: str, default: Optional[float] = None) -> Optional[float]:
        v, f = get(key)
        return default if v is None else _number(v, path, f)

    w, h = num("w"), num("h")
    if w is None or h is None:
        from PIL import Image

        try:
            with Image.open(img) as im:
                size = im.size
        except Exception as exc:  # PIL raises many types on bad images
            raise SceneFormatError(img, f"cannot read the image size ({exc}); give 'w' and 'h'") from None
        w = size[0] if w is None else w
        h = size[1] if h is None else h
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise SceneFormatError(path, f"image size must be positive integers, got {w}x{h}", f"frames[{i}].w/h")
    fx, fy = num("fl_x"), num("fl_y")
    ax, ay = num("camera_angle_x"), num("camera_angle_y")
    if fx is None and ax is not None:
        if not 0 < ax < math.pi:
            raise SceneFormatError(path, f"must be in (0, pi), got {ax}", "camera_angle_x")
        fx = 0.5 * w / math.tan(0.5 * ax)
    if fy is None and ay is not None:
        if not 0 < ay < math.pi:
            raise SceneFormatError(path, f"must be in (0, pi), got {ay}", "camera_angle_y")
        fy = 0.5 * h / math.tan(0.5 * ay)
    if fx is None and fy is None:
        raise SceneFormatError(path, "no focal length (fl_x, fl_y, camera_angle_x or camera_angle_y)",
                               f"frames[{i}].fl_x")
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    if fx <= 0 or fy <= 0:
        raise SceneFormatError(path, f"focal lengths must be positive, got {fx}, {fy}", f"frames[{i}].fl_x")
    cx, cy = num("cx", w / 2.0), num("cy", h / 2.0)
    dist = None
    if model != "PINHOLE" and model != "SIMPLE_PINHOLE":
        dist = Distortion(k1=num("k1", 0.0), k2=num("k2", 0.0), k3=num("k3", 0.0),
                          p1=num("p1", 0.0), p2=num("p2", 0.0))
    return intrinsics(fx, fy, cx, cy), dist, int(w), int(h)
