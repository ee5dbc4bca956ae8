"""COLMAP sparse models (``cameras``, ``images``, ``points3D``; ``.bin`` and ``.txt``).

The record layouts are COLMAP's (src/colmap/scene/reconstruction_io.cc). Every count
read from a binary file is checked against the bytes left before anything is allocated,
so truncated or corrupted files raise :class:`SceneFormatError` naming the file, the
record and the field, never a crash or a huge allocation.
"""
from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from tiger.render import Camera, Distortion
from .cameras import intrinsics, quat_to_rotmat
from .errors import SceneFormatError

PathLike = Union[str, os.PathLike]

#: COLMAP camera model id -> (name, number of parameters).
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_IDS = {name: (mid, n) for mid, (name, n) in CAMERA_MODELS.items()}
#: Models that a pinhole camera plus :class:`Distortion` represents exactly.
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: tuple


@dataclass
class ColmapImage:
    id: int
    qvec: tuple   # (w, x, y, z) world-to-camera rotation
    tvec: tuple   # world-to-camera translation
    camera_id: int
    name: str


@dataclass
class ColmapPoints:
    ids: np.ndarray     # [P] int64
    xyz: np.ndarray     # [P, 3] float64
    rgb: np.ndarray     # [P, 3] uint8
    error: np.ndarray   # [P] float64


# ---------------------------------------------------------------------------------------
# Binary
# ---------------------------------------------------------------------------------------
class _Bin:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = _read_bytes(path)
        self.pos = 0

    def left(self) -> int:
        return len(self.data) - self.pos

    def need(self, n: int, field: str) -> None:
        if n < 0 or n > self.left():
            raise SceneFormatError(self.path, f"truncated: {n} bytes needed at offset {self.pos}, "
                                              f"{self.left()} left", field)

    def read(self, fmt: str, field: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        self.need(size, field)
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def skip(self, n: int, field: str) -> None:
        self.need(n, field)
        self.pos += n

    def cstring(self, field: str) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise SceneFormatError(self.path, "truncated: unterminated string", field)
        raw = self.data[self.pos:end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise SceneFormatError(self.path, f"string at offset {self.pos} is not UTF-8", field) from None

    def done(self) -> None:
        if self.left():
            raise SceneFormatError(self.path, f"{self.left()} unexpected bytes after the last record")


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise SceneFormatError(path, "file not found") from None
    except IsADirectoryError:
        raise SceneFormatError(path, "is a directory, not a COLMAP model file") from None


def read_cameras_binary(path: PathLike) -> dict[int, ColmapCamera]:
    r = _Bin(Path(path))
    (n,) = r.read("Q", "num_cameras")
    cams: dict[int, ColmapCamera] = {}
    for i in range(n):
        cid, mid, w, h = r.read("iiQQ", f"camera #{i}")
        if mid not in CAMERA_MODELS:
            raise SceneFormatError(r.path, f"camera {cid}: unknown camera model id {mid}", "model_id")
        name, npar = CAMERA_MODELS[mid]
        params = r.read("d" * npar, f"camera {cid} params")
        _add_camera(cams, ColmapCamera(cid, name, w, h, params), r.path)
    r.done()
    return cams


def read_images_binary(path: PathLike) -> dict[int, ColmapImage]:
    r = _Bin(Path(path))
    (n,) = r.read("Q", "num_reg_images")
    imgs: dict[int, ColmapImage] = {}
    for i in range(n):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = r.read("idddddddi", f"image #{i}")
        name = r.cstring(f"image {iid} name")
        (npts,) = r.read("Q", f"image {iid} num_points2D")
        if npts > r.left() // 24:
            raise SceneFormatError(r.path, f"image {iid}: {npts} 2D points do not fit in the "
                                           f"{r.left()} bytes left (truncated?)", "num_points2D")
        r.skip(24 * npts, f"image {iid} points2D")
        _add_image(imgs, ColmapImage(iid, (qw, qx, qy, qz), (tx, ty, tz), cid, name), r.path)
    r.done()
    return imgs


def read_points3d_binary(path: PathLike) -> ColmapPoints:
    r = _Bin(Path(path))
    (n,) = r.read("Q", "num_points3D")
    rec = struct.Struct("<QdddBBBdQ")
    if n > r.left() // rec.size:
        raise SceneFormatError(r.path, f"{n} points do not fit in the {r.left()} bytes left (truncated?)",
                               "num_points3D")
    ids = np.empty(n, np.int64)
    xyz = np.empty((n, 3), np.float64)
    rgb = np.empty((n, 3), np.uint8)
    err = np.empty(n, np.float64)
    data = r.data
    for i in range(n):
        r.need(rec.size, f"point #{i}")
        pid, x, y, z, cr, cg, cb, e, tl = rec.unpack_from(data, r.pos)
        r.pos += rec.size
        if tl > r.left() // 8:
            raise SceneFormatError(r.path, f"point {pid}: track length {tl} does not fit in the "
                                           f"{r.left()} bytes left (truncated?)", "track_length")
        r.pos += 8 * tl
        ids[i], xyz[i], rgb[i], err[i] = pid, (x, y, z), (cr, cg, cb), e
    r.done()
    _check_points(ColmapPoints(ids, xyz, rgb, err), r.path)
    return ColmapPoints(ids, xyz, rgb, err)


# ---------------------------------------------------------------------------------------
# Text
# ---------------------------------------------------------------------------------------
def _text_lines(path: Path) -> list:
    data = _read_bytes(path)
    try:
        return data.decode("utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise SceneFormatError(path, f"not UTF-8 text (byte offset {exc.start})") from None


def _num(tok: str, kind: type, path: Path, lineno: int, field: str):
    try:
        v = kind(tok)
    except ValueError:
        raise SceneFormatError(path, f"line {lineno}: '{tok[:30]}' is not a valid {kind.__name__}", field) from None
    if kind is float and not math.isfinite(v):
        raise SceneFormatError(path, f"line {lineno}: non-finite value {tok}", field)
    if kind is int and not -(1 << 63) <= v < (1 << 63):   # COLMAP ids are at most 64-bit
        raise SceneFormatError(path, f"line {lineno}: integer {tok[:30]} out of range", field)
    return v


def read_cameras_text(path: PathLike) -> dict[int, ColmapCamera]:
    path = Path(path)
    cams: dict[int, ColmapCamera] = {}
    for lineno, line in enumerate(_text_lines(path), 1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if len(tok) < 4:
            raise SceneFormatError(path, f"line {lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]", "CAMERA_ID")
        cid = _num(tok[0], int, path, lineno, "CAMERA_ID")
        model = tok[1]
        if model not in MODEL_IDS:
            raise SceneFormatError(path, f"line {lineno}: unknown camera model '{model[:40]}'", "MODEL")
        npar = MODEL_IDS[model][1]
        if len(tok) != 4 + npar:
            raise SceneFormatError(path, f"line {lineno}: model {model} takes {npar} parameters, "
                                         f"got {len(tok) - 4}", "PARAMS")
        w = _num(tok[2], int, path, lineno, "WIDTH")
        h = _num(tok[3], int, path, lineno, "HEIGHT")
        params = tuple(_num(t, float, path, lineno, "PARAMS") for t in tok[4:])
        _add_camera(cams, ColmapCamera(cid, model, w, h, params), path)
    return cams


def read_images_text(path: PathLike) -> dict[int, ColmapImage]:
    path = Path(path)
    lines = _text_lines(path)
    imgs: dict[int, ColmapImage] = {}
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        lineno = i
        tok = line.split(None, 9)
        if len(tok) < 10:
            fields = ["IMAGE_ID", "QW", "QX", "QY", "QZ", "TX", "TY", "TZ", "CAMERA_ID", "NAME"]
            raise SceneFormatError(path, "line {}: expected {}".format(lineno, " ".join(fields)),
                                   fields[len(tok)])
        iid = _num(tok[0], int, path, lineno, "IMAGE_ID")
        q = tuple(_num(t, float, path, lineno, f) for t, f in zip(tok[1:5], ("QW", "QX", "QY", "QZ")))
        t = tuple(_num(v, float, path, lineno, f) for v, f in zip(tok[5:8], ("TX", "TY", "TZ")))
        cid = _num(tok[8], int, path, lineno, "CAMERA_ID")
        name = tok[9].rstrip("\r\n")
        # The next line lists the 2D points (possibly empty); it is not needed here, but
        # it must be skipped even when it is blank.
        i += 1
        _add_image(imgs, ColmapImage(iid, q, t, cid, name), path)
    return imgs


def read_points3d_text(path: PathLike) -> ColmapPoints:
    path = Path(path)
    ids, xyz, rgb, err = [], [], [], []
    for lineno, line in enumerate(_text_lines(path), 1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if len(tok) < 8 or (len(tok) - 8) % 2:
            raise SceneFormatError(path, f"line {lineno}: expected POINT3D_ID X Y Z R G B ERROR TRACK[]", "TRACK")
        ids.append(_num(tok[0], int, path, lineno, "POINT3D_ID"))
        xyz.append([_num(v, float, path, lineno, f) for v, f in zip(tok[1:4], "XYZ")])
        c = [_num(v, int, path, lineno, f) for v, f in zip(tok[4:7], "RGB")]
        if not all(0 <= v <= 255 for v in c):
            raise SceneFormatError(path, f"line {lineno}: colour {c} outside 0..255", "RGB")
        rgb.append(c)
        err.append(_num(tok[7], float, path, lineno, "ERROR"))
    pts = ColmapPoints(np.array(ids, np.int64), np.array(xyz, np.float64).reshape(-1, 3),
                       np.array(rgb, np.uint8).reshape(-1, 3), np.array(err, np.float64))
    _check_points(pts, path)
    return pts


# ---------------------------------------------------------------------------------------
# Checks and the model
# ---------------------------------------------------------------------------------------
def _add_camera(cams: dict, c: ColmapCamera, path: Path) -> None:
    if c.id in cams:
        raise SceneFormatError(path, f"camera id {c.id} appears twice", "CAMERA_ID")
    if not (0 < c.width < 1 << 20 and 0 < c.height < 1 << 20):
        raise SceneFormatError(path, f"camera {c.id}: implausible size {c.width}x{c.height}", "WIDTH/HEIGHT")
    if not all(math.isfinite(p) for p in c.params):
        raise SceneFormatError(path, f"camera {c.id}: non-finite parameter", "PARAMS")
    cams[c.id] = c


def _add_image(imgs: dict, im: ColmapImage, path: Path) -> None:
    if im.id in imgs:
        raise SceneFormatError(path, f"image id {im.id} appears twice", "IMAGE_ID")
    if not all(math.isfinite(v) for v in im.qvec + im.tvec):
        raise SceneFormatError(path, f"image {im.id} ({im.name}): non-finite pose", "QVEC/TVEC")
    if sum(v * v for v in im.qvec) < 1e-12:
        raise SceneFormatError(path, f"image {im.id} ({im.name}): zero quaternion", "QVEC")
    if not im.name:
        raise SceneFormatError(path, f"image {im.id}: empty name", "NAME")
    imgs[im.id] = im


def _check_points(p: ColmapPoints, path: Path) -> None:
    if p.xyz.size and not np.isfinite(p.xyz).all():
        raise SceneFormatError(path, "non-finite point coordinates", "XYZ")


def find_model_dir(root: PathLike) -> Path:
    """The folder holding ``cameras.{bin,txt}``: ``root`` itself, ``root/sparse/0`` or
    ``root/sparse``."""
    root = Path(root)
    for cand in (root, root / "sparse" / "0", root / "sparse"):
        if (cand / "cameras.bin").is_file() or (cand / "cameras.txt").is_file():
            return cand
    raise SceneFormatError(root, "no COLMAP model found (looked for cameras.bin/.txt in ., sparse/0, sparse)")


def read_model(model_dir: PathLike, ext: Optional[str] = None,
               read_points: bool = True) -> tuple:
    """Read ``cameras``, ``images`` and (optionally) ``points3D`` from ``model_dir``.

    Args:
        ext: ``".bin"`` or ``".txt"``; default: binary when ``cameras.bin`` exists.
    Returns:
        (cameras {id: ColmapCamera}, images {id: ColmapImage}, ColmapPoints or None).
    """
    d = Path(model_dir)
    if ext is None:
        ext = ".bin" if (d / "cameras.bin").is_file() else ".txt"
    if ext not in (".bin", ".txt"):
        raise ValueError(f"tiger: COLMAP model extension must be '.bin' or '.txt', got '{ext}'")
    binary = ext == ".bin"
    cams = (read_cameras_binary if binary else read_cameras_text)(d / f"cameras{ext}")
    imgs = (read_images_binary if binary else read_images_text)(d / f"images{ext}")
    pts = None
    if read_points and (d / f"points3D{ext}").is_file():
        pts = (read_points3d_binary if binary else read_points3d_text)(d / f"points3D{ext}")
    for im in imgs.values():
        if im.camera_id not in cams:
            raise SceneFormatError(d / f"images{ext}", f"image {im.id} ({im.name}) refers to camera "
                                                       f"{im.camera_id}, which cameras{ext} lacks", "CAMERA_ID")
    return cams, imgs, pts


def pinhole_and_distortion(cam: ColmapCamera, path: PathLike = "") -> tuple:
    """[3, 3] K and :class:`Distortion` (or None) of a COLMAP camera.

    Raises SceneFormatError for models that are not pinhole + OpenCV distortion.
    """
    p = cam.params
    m = cam.model
    if m == "SIMPLE_PINHOLE":
        return intrinsics(p[0], p[0], p[1], p[2]), None
    if m == "PINHOLE":
        return intrinsics(p[0], p[1], p[2], p[3]), None
    if m == "SIMPLE_RADIAL":
        return intrinsics(p[0], p[0], p[1], p[2]), Distortion(k1=p[3])
    if m == "RADIAL":
        return intrinsics(p[0], p[0], p[1], p[2]), Distortion(k1=p[3], k2=p[4])
    if m == "OPENCV":
        return intrinsics(p[0], p[1], p[2], p[3]), Distortion(k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    if m == "FULL_OPENCV":
        return intrinsics(p[0], p[1], p[2], p[3]), Distortion(*p[4:8], k3=p[8], k4=p[9], k5=p[10], k6=p[11])
    raise SceneFormatError(path, f"camera {cam.id}: camera model {m} is not supported (supported: "
                                 f"{', '.join(SUPPORTED_MODELS)}); undistort the images with COLMAP first",
                           "MODEL")


def colmap_cameras(cams: dict, imgs: dict, images_dir: Path, model_path: PathLike = "") -> list:
    """One :class:`Camera` per registered image, sorted by image name."""
    out = []
    for im in sorted(imgs.values(), key=lambda im: im.name):
        c = cams[im.camera_id]
        K, dist = pinhole_and_distortion(c, model_path)
        R = quat_to_rotmat(torch.tensor(im.qvec, dtype=torch.float64))
        vm = torch.eye(4, dtype=torch.float64)
        vm[:3, :3] = R
        vm[:3, 3] = torch.tensor(im.tvec, dtype=torch.float64)
        try:
            out.append(Camera(vm, K, c.width, c.height, image_path=images_dir / im.name, image_name=im.name,
                              distortion=dist, camera_id=c.id))
        except ValueError as exc:  # e.g. a non-positive focal length
            raise SceneFormatError(model_path, f"camera {c.id} / image {im.id}: {exc}", "PARAMS") from None
    return out
