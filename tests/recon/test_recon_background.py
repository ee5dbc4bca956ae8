"""Which background training renders over: random for opaque photographs, black where images
carry transparency (composited over black when loaded), the user's choice over both."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from tiger.recon.data import training_background, transparent_images
from tiger.render import Camera
from tiger.scene.cameras import intrinsics


def _camera(path, name: str) -> Camera:
    return Camera(torch.eye(4), intrinsics(5, 5, 3, 2), 6, 4, image_path=path, image_name=name)


def test_transparent_images_names_the_see_through_files(tmp_path):
    rgb = np.full((4, 6, 3), 90, np.uint8)
    Image.fromarray(rgb).save(tmp_path / "a.jpg")
    alpha = np.full((4, 6, 1), 255, np.uint8)
    Image.fromarray(np.concatenate([rgb, alpha], -1), "RGBA").save(tmp_path / "b.png")  # opaque alpha
    alpha[2, 3] = 0
    Image.fromarray(np.concatenate([rgb, alpha], -1), "RGBA").save(tmp_path / "c.png")
    cams = [_camera(tmp_path / n, n) for n in ("a.jpg", "b.png", "c.png")]
    assert transparent_images(cams) == ["c.png"]
    assert transparent_images(cams[:2]) == []
    assert transparent_images([_camera(None, "no file")]) == []


@pytest.mark.parametrize("transparent, requested, want, words", [
    ([], None, True, "no image has transparent pixels"),
    (["x.png"], None, False, "1 image with transparent pixels, e.g. x.png"),
    (["x.png", "y.png"], None, False, "2 images with transparent pixels"),
    ([], True, True, "asked for"),
    ([], False, False, "black (asked for)"),
    (["x.png"], False, False, "black (asked for)"),
    (["x.png"], True, True, "composited over black"),
])
def test_background_rule(transparent, requested, want, words):
    random_background, note = training_background(transparent, requested)
    assert random_background is want and words in note
    assert note.startswith("random colour" if want else "black")


def test_load_views_keeps_the_cameras_order_on_threads(tmp_path):
    """load_views decodes on a thread pool: each image still comes back beside its own camera
    (known answer: every image file is one flat colour that names its index)."""
    from tiger.recon.data import load_views

    cams = []
    for i in range(11):
        path = tmp_path / f"view_{i:02d}.png"
        Image.fromarray(np.full((6, 8, 3), 20 * i, dtype=np.uint8)).save(path)
        cams.append(Camera(torch.eye(4), intrinsics(8, 8, 4, 3), 8, 6, image_path=str(path), image_name=path.name))
    out_cams, imgs = load_views(cams)
    assert [c.image_name for c in out_cams] == [c.image_name for c in cams]
    for i, img in enumerate(imgs):
        assert torch.allclose(img, torch.full_like(img, 20 * i / 255.0), atol=1e-6), i
