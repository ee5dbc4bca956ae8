"""Loading the images of cameras: decoding, lens undistortion, downscaling, disk cache.

Undistortion keeps the camera's pinhole ``K`` and size: every output pixel (u, v) is
turned into normalised coordinates, pushed through the lens model (forward, exact) and
sampled bilinearly from the distorted file. Output pixels whose source lies outside the
file are black. :func:`undistort_points` inverts the lens model iteratively (for points,
and for the tests that check the two directions agree).
"""
from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
import torch.nn.functional as F

from tiger.utils.io import atomic_write

from tiger.render import Camera, Distortion
from .errors import SceneFormatError

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
_CACHE_VERSION = 1


def distort_points(xy: torch.Tensor, d: Distortion) -> torch.Tensor:
    """Apply the lens model to [..., 2] normalised pinhole coordinates (x, y) = (X/Z, Y/Z)."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
    if d.k4 or d.k5 or d.k6:
        radial = radial / (1 + r2 * (d.k4 + r2 * (d.k5 + r2 * d.k6)))
    xd = x * radial + 2 * d.p1 * x * y + d.p2 * (r2 + 2 * x * x)
    yd = y * radial + d.p1 * (r2 + 2 * y * y) + 2 * d.p2 * x * y
    return torch.stack([xd, yd], -1)


def undistort_points(xy_d: torch.Tensor, d: Distortion, iters: int = 30) -> torch.Tensor:
    """Invert :func:`distort_points` on [..., 2] distorted normalised coordinates.

    Newton's method (central-difference Jacobian, float64 inside) started at the
    distorted point; converges to round-off in a few steps for real lenses.
    """
    target = xy_d.double()
    xy = target.clone()
    h = 1e-7
    ex = torch.tensor([h, 0.0], dtype=torch.float64)
    ey = torch.tensor([0.0, h], dtype=torch.float64)
    for _ in range(iters):
        f = distort_points(xy, d) - target
        if float(f.abs().max()) < 1e-15:
            break
        jx = (distort_points(xy + ex, d) - distort_points(xy - ex, d)) / (2 * h)   # d f / d x
        jy = (distort_points(xy + ey, d) - distort_points(xy - ey, d)) / (2 * h)   # d f / d y
        a, c = jx[..., 0], jx[..., 1]
        b, e = jy[..., 0], jy[..., 1]
        det = a * e - b * c
        det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
        xy = xy - torch.stack([(e * f[..., 0] - b * f[..., 1]) / det,
                               (-c * f[..., 0] + a * f[..., 1]) / det], -1)
    return xy.to(xy_d.dtype)


def undistort_image(image: torch.Tensor, K: torch.Tensor, d: Distortion) -> torch.Tensor:
    """Resample a distorted [H, W, C] image to the pinhole camera with the same ``K``.

    Returns [H, W, C] (same dtype; float math inside); pixels whose source falls outside
    the input are zero.
    """
    if image.ndim != 3:
        raise ValueError(f"tiger: undistort_image expects [H, W, C], got {list(image.shape)}")
    H, W, _ = image.shape
    us, vs = _undistortion_sources(H, W, K, d)
    # grid_sample with align_corners=False: -1 and +1 are the outer pixel edges.
    grid = torch.stack([us / W * 2 - 1, vs / H * 2 - 1], -1).float()[None]
    src = image.permute(2, 0, 1)[None].float()
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[0].permute(1, 2, 0).to(image.dtype if image.is_floating_point() else torch.float32)


def _undistortion_sources(H: int, W: int, K: torch.Tensor, d: Distortion) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each pinhole pixel centre of an [H, W] image lands in the distorted file:
    (u [H, W], v [H, W]) in pixels, float64."""
    Kd = K.double()
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5,
                          torch.arange(W, dtype=torch.float64) + 0.5, indexing="ij")
    xy = torch.stack([(u - Kd[0, 2]) / Kd[0, 0], (v - Kd[1, 2]) / Kd[1, 1]], -1)
    xyd = distort_points(xy, d)
    return xyd[..., 0] * Kd[0, 0] + Kd[0, 2], xyd[..., 1] * Kd[1, 1] + Kd[1, 2]


def undistortion_valid_mask(camera: Camera, downscale: float = 1.0) -> torch.Tensor:
    """[h, w] bool: the pixels of ``camera``'s undistorted image at ``1/downscale`` (as
    :func:`load_image` makes it) that are fully inside the distorted file, i.e. not in the
    black border that undistortion leaves. All True for a camera without distortion."""
    target = camera.scaled(downscale)
    if camera.distortion is None:
        return torch.ones(target.height, target.width, dtype=torch.bool)
    us, vs = _undistortion_sources(camera.height, camera.width, camera.K, camera.distortion)
    # bilinear sampling reads the two pixel centres around a source point: both must exist
    inside = (us >= 0.5) & (us <= camera.width - 0.5) & (vs >= 0.5) & (vs <= camera.height - 0.5)
    frac = resize_image(inside.float()[..., None], target.width, target.height)[..., 0]
    return frac >= 1.0 - 1e-6


def resize_image(image: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[H, W, C] float image resized to [height, width, C]: box filter for integer
    factors, antialiased bilinear otherwise."""
    H, W, _ = image.shape
    if (H, W) == (height, width):
        return image
    x = image.permute(2, 0, 1)[None]
    if H % height == 0 and W % width == 0 and H // height == W // width:
        y = F.avg_pool2d(x, H // height)
    else:
        y = F.interpolate(x, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return y[0].permute(1, 2, 0)


def read_image_file(path: Path, background: Optional[tuple] = None) -> torch.Tensor:
    """Decode an image file to [H, W, 3] float32 in [0, 1]. RGBA is composited over
    ``background`` (RGB in [0, 1]; default black); greyscale is expanded."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode in ("I;16", "I;16B", "I", "F"):
                arr = np.asarray(im.convert("F"), dtype=np.float32)
                arr = arr / (65535.0 if mode.startswith("I;16") else max(float(arr.max()), 1.0))
                arr = np.repeat(arr[..., None], 3, -1)
            else:
                arr = np.asarray(im.convert("RGBA" if _has_alpha(im) else "RGB"), dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise SceneFormatError(path, "image file not found") from None
    except Exception as exc:  # PIL raises many types for corrupt files
        raise SceneFormatError(path, f"cannot decode image ({type(exc).__name__}: {exc})") from None
    img = torch.from_numpy(np.ascontiguousarray(arr))
    if img.shape[-1] == 4:
        bg = torch.tensor(background or (0.0, 0.0, 0.0), dtype=img.dtype)
        a = img[..., 3:]
        img = img[..., :3] * a + bg * (1 - a)
    return img


def _has_alpha(im) -> bool:
    """Whether a PIL image carries an alpha channel (an alpha band, or a palette with a
    transparent entry)."""
    return "A" in im.getbands() or (im.mode == "P" and "transparency" in im.info)


def image_has_transparency(path: PathLike) -> bool:
    """True when the image file has an alpha channel and at least one pixel of it is below
    fully opaque: the pixels :func:`read_image_file` composites over a background.

    Files without an alpha channel (JPEG, RGB PNG) are decided from the header alone; an
    alpha channel that is opaque everywhere counts as no transparency.
    Raises SceneFormatError for a missing or undecodable file.
    """
    from PIL import Image

    path = Path(path)
    try:
        with Image.open(path) as im:
            if not _has_alpha(im):
                return False
            alpha = (im.convert("RGBA") if im.mode == "P" else im).getchannel("A")
            return alpha.getextrema()[0] < 255
    except FileNotFoundError:
        raise SceneFormatError(path, "image file not found") from None
    except Exception as exc:  # PIL raises many types for corrupt files
        raise SceneFormatError(path, f"cannot decode image ({type(exc).__name__}: {exc})") from None


def default_cache_dir() -> Path:
    """``$TIGER_CACHE_DIR`` or ``~/.cache/tiger``."""
    env = os.environ.get("TIGER_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "tiger"


def _cache_key(camera: Camera, target: Camera, background: Optional[tuple]) -> str:
    p = camera.image_path
    st = p.stat()
    h = hashlib.sha1()
    h.update(repr((_CACHE_VERSION, str(p.resolve()), st.st_size, st.st_mtime_ns,
                   [round(float(v), 9) for v in camera.K.flatten()],
                   camera.distortion.as_tuple() if camera.distortion else None,
                   target.width, target.height, background)).encode())
    return h.hexdigest()


def load_image(camera: Camera, downscale: float = 1.0, cache_dir: Optional[PathLike] = None,
               background: Optional[tuple] = None, use_cache: bool = True) -> tuple:
    """The pinhole image of ``camera`` at ``1/downscale`` resolution.

    Distorted images are undistorted at full resolution, then downscaled, and the result
    is cached on disk (8-bit PNG, written atomically) under ``cache_dir`` (default
    :func:`default_cache_dir`), keyed by the file, its size and mtime, K, the lens and the
    output size, so it is computed once.

    Returns:
        (image [h, w, 3] float32 in [0, 1], the camera scaled to match, without distortion).
    Raises:
        SceneFormatError when the camera has no image file, the file is missing or
        undecodable, or its size disagrees with the camera.
    """
    if camera.image_path is None:
        raise SceneFormatError(None, f"camera '{camera.image_name}' has no image file")
    target = camera.scaled(downscale)
    target.distortion = None
    if not camera.image_path.is_file():
        raise SceneFormatError(camera.image_path, f"image of camera '{camera.image_name}' not found")
    cache_file = None
    if camera.distortion is not None and use_cache:
        cache_file = Path(cache_dir or default_cache_dir()) / "images" / (
            _cache_key(camera, target, background) + ".png")
        if cache_file.is_file():
            try:
                img = read_image_file(cache_file)
                if img.shape[:2] == (target.height, target.width):
                    return img, target
            except SceneFormatError:
                log.warning("ignoring a corrupt cache file %s", cache_file)
    img = read_image_file(camera.image_path, background)
    if img.shape[:2] != (camera.height, camera.width):
        raise SceneFormatError(camera.image_path, f"image is {img.shape[1]}x{img.shape[0]} but its camera "
                                                  f"says {camera.width}x{camera.height}", "width/height")
    if camera.distortion is not None:
        img = undistort_image(img, camera.K, camera.distortion).clamp(0, 1)
    img = resize_image(img, target.width, target.height)
    if cache_file is not None:
        _write_png(cache_file, img)
        img = read_image_file(cache_file)  # the same 8-bit values as a later cache hit
    return img, target


def _write_png(path: Path, img: torch.Tensor) -> None:
    from PIL import Image

    arr = (img.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()
    # a cache file: renamed into place whole, but not fsync'd (0.6 s a file on the H100 machine's
    # disk; a crash costs only its recomputation)
    with atomic_write(path, "wb", fsync=False) as fh:
        Image.fromarray(arr).save(fh, format="PNG", compress_level=1)
