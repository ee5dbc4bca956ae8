"""Lens distortion, undistortion of images, downscaling, the undistortion cache."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from tiger.render import Camera, Distortion
from tiger.scene import SceneFormatError
from tiger.scene.cameras import intrinsics
from tiger.scene.images import (distort_points, image_has_transparency, load_image, undistort_image,
                               undistort_points)

LENS = Distortion(k1=0.08, k2=-0.05, p1=-1e-3, p2=5e-4)


def opencv_distort(x: np.ndarray, y: np.ndarray, k1, k2, p1, p2, k3=0.0):
    """OpenCV's published distortion model, written out independently."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def test_distort_matches_opencv_formula_and_inverse():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.6, 0.6, size=(500, 2))
    d = Distortion(k1=0.08, k2=-0.05, p1=-1e-3, p2=5e-4, k3=0.01)
    ref = np.stack(opencv_distort(xy[:, 0], xy[:, 1], 0.08, -0.05, -1e-3, 5e-4, 0.01), 1)
    got = distort_points(torch.from_numpy(xy), d).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-15)
    back = undistort_points(torch.from_numpy(ref), d).numpy()
    np.testing.assert_allclose(back, xy, atol=1e-12)
    back32 = undistort_points(torch.from_numpy(ref).float(), d)
    assert back32.dtype == torch.float32
    np.testing.assert_allclose(back32.numpy(), xy, atol=2e-7)


def pattern(u: np.ndarray, v: np.ndarray, K: np.ndarray) -> np.ndarray:
    """A smooth test image defined on pinhole (undistorted) normalised coordinates."""
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    return np.stack([0.5 + 0.4 * np.sin(6 * x), 0.5 + 0.4 * np.cos(5 * y), 0.5 + 0.3 * np.sin(4 * x + 3 * y)], -1)


def distorted_capture(W=96, H=72):
    """What a lens with LENS records of ``pattern``: the value of the undistorted point
    of every distorted pixel centre (inverse model, independent of the image warp)."""
    K = intrinsics(80.0, 82.0, 47.0, 37.5)
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    xd = np.stack([(u - 47.0) / 80.0, (v - 37.5) / 82.0], -1)
    xu = undistort_points(torch.from_numpy(xd), LENS).numpy()
    img = pattern(xu[..., 0] * 80.0 + 47.0, xu[..., 1] * 82.0 + 37.5, K.numpy())
    return torch.from_numpy(img).float(), K


def test_undistort_image_recovers_the_pinhole_image():
    img_d, K = distorted_capture()
    H, W, _ = img_d.shape
    out = undistort_image(img_d, K, LENS)
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    ref = pattern(u, v, K.numpy())
    inner = (slice(4, H - 4), slice(4, W - 4))    # border pixels sample outside the capture
    err = np.abs(out.numpy()[inner] - ref[inner]).max()
    assert err < 2e-3, err                          # bilinear interpolation error of a smooth image
    naive = np.abs(img_d.numpy()[inner] - ref[inner]).max()
    assert naive > 20 * err                          # and the lens effect is far larger than that


def save_png(path, img: torch.Tensor):
    Image.fromarray((img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)).save(path)


def test_load_image_undistorts_downscales_and_caches(tmp_path):
    img_d, K = distorted_capture()
    save_png(tmp_path / "a.png", img_d)
    cam = Camera(torch.eye(4), K, 96, 72, image_path=tmp_path / "a.png", image_name="a.png", distortion=LENS)
    cache = tmp_path / "cache"
    img, c2 = load_image(cam, 2, cache_dir=cache)
    assert img.shape == (36, 48, 3) and (c2.width, c2.height) == (48, 36) and c2.distortion is None
    np.testing.assert_allclose(c2.K.numpy(), np.diag([0.5, 0.5, 1.0]) @ K.numpy())
    files = list(cache.rglob("*.png"))
    assert len(files) == 1
    # the reference: undistort at full resolution, then 2x2 box average
    full = undistort_image(torch.from_numpy(np.asarray(Image.open(tmp_path / "a.png"), np.float32) / 255), K, LENS)
    ref = full.reshape(36, 2, 48, 2, 3).mean((1, 3))
    assert (img - ref).abs().max() <= 1 / 255 + 1e-6
    # a cache hit returns the same pixels without touching the source
    mtime = files[0].stat().st_mtime_ns
    img2, _ = load_image(cam, 2, cache_dir=cache)
    assert torch.equal(img, img2) and files[0].stat().st_mtime_ns == mtime
    # a changed source invalidates the key
    save_png(tmp_path / "a.png", img_d * 0.5)
    img3, _ = load_image(cam, 2, cache_dir=cache)
    assert not torch.equal(img, img3) and len(list(cache.rglob("*.png"))) == 2


def test_load_image_rgba_and_errors(tmp_path):
    rgba = np.zeros((4, 6, 4), np.uint8)
    rgba[..., 0] = 255
    rgba[..., 3] = 128
    Image.fromarray(rgba).save(tmp_path / "r.png")
    cam = Camera(torch.eye(4), intrinsics(5, 5, 3, 2), 6, 4, image_path=tmp_path / "r.png", image_name="r")
    img, _ = load_image(cam, background=(0.0, 0.0, 1.0))
    np.testing.assert_allclose(img[0, 0].numpy(), [128 / 255, 0, 1 - 128 / 255], atol=1e-6)
    wrong = Camera(torch.eye(4), intrinsics(5, 5, 3, 2), 7, 4, image_path=tmp_path / "r.png", image_name="r")
    with pytest.raises(SceneFormatError, match="6x4 but its camera says 7x4"):
        load_image(wrong)
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    bad = Camera(torch.eye(4), intrinsics(5, 5, 3, 2), 6, 4, image_path=tmp_path / "bad.png", image_name="bad")
    with pytest.raises(SceneFormatError, match="bad.png.*cannot decode"):
        load_image(bad)
    gone = Camera(torch.eye(4), intrinsics(5, 5, 3, 2), 6, 4, image_path=tmp_path / "gone.png", image_name="g")
    with pytest.raises(SceneFormatError, match="gone.png.*not found"):
        load_image(gone)


def _write(path, arr: np.ndarray, mode: str, **save) -> None:
    Image.fromarray(arr, mode).save(path, **save)


def test_image_has_transparency_known_files(tmp_path):
    """Alpha below 255 somewhere -> True; no alpha channel, or one opaque everywhere -> False."""
    rgb = np.full((4, 6, 3), 200, np.uint8)
    rgba = np.dstack([rgb, np.full((4, 6), 255, np.uint8)])
    _write(tmp_path / "photo.jpg", rgb, "RGB")
    _write(tmp_path / "rgb.png", rgb, "RGB")
    _write(tmp_path / "opaque_rgba.png", rgba, "RGBA")
    one_pixel = rgba.copy()
    one_pixel[3, 5, 3] = 254
    _write(tmp_path / "one_pixel.png", one_pixel, "RGBA")
    grey_alpha = np.dstack([rgb[..., 0], np.zeros((4, 6), np.uint8)])
    _write(tmp_path / "la.png", grey_alpha, "LA")
    palette = Image.fromarray(np.arange(24, dtype=np.uint8).reshape(4, 6), "P")
    palette.putpalette([v for i in range(256) for v in (i, 255 - i, 7)])
    palette.save(tmp_path / "p_opaque.png")
    palette.save(tmp_path / "p_transparent.png", transparency=5)  # palette entry 5 is see-through
    palette.save(tmp_path / "p_unused.png", transparency=200)     # no pixel uses entry 200
    want = {"photo.jpg": False, "rgb.png": False, "opaque_rgba.png": False, "one_pixel.png": True,
            "la.png": True, "p_opaque.png": False, "p_transparent.png": True, "p_unused.png": False}
    assert {name: image_has_transparency(tmp_path / name) for name in want} == want
    with pytest.raises(SceneFormatError, match="gone.png.*not found"):
        image_has_transparency(tmp_path / "gone.png")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(SceneFormatError, match="bad.png.*cannot decode"):
        image_has_transparency(tmp_path / "bad.png")


@pytest.mark.parametrize("downscale", [1.0, 2.0, 3.0])
def test_undistortion_valid_mask_marks_exactly_the_unblended_pixels(downscale):
    """Undistorting an all-white file: the valid pixels are exactly those that come out
    fully white (no blend with the black outside), after the same downscale."""
    from tiger.scene.images import resize_image, undistortion_valid_mask

    W, H = 96, 72
    K = intrinsics(60.0, 62.0, 47.0, 37.5)                       # wide: a real border
    cam = Camera(torch.eye(4, dtype=torch.float64), K, W, H, distortion=Distortion(k1=0.25, k2=0.05))
    white = undistort_image(torch.ones(H, W, 3, dtype=torch.float64), K, cam.distortion)
    t = cam.scaled(downscale)
    white = resize_image(white, t.width, t.height)[..., 0]
    mask = undistortion_valid_mask(cam, downscale)
    assert mask.shape == (t.height, t.width) and 0 < int((~mask).sum()) < mask.numel() // 2
    assert torch.equal(mask, white >= 1.0 - 1e-6)                  # float32 sampling inside
    plain = Camera(torch.eye(4, dtype=torch.float64), K, W, H)
    assert undistortion_valid_mask(plain, downscale).all()
