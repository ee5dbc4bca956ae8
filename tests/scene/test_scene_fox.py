"""The real 'fox' capture (instant-ngp; 50 photographs with lens distortion).

Skipped when ``<repo>/../shared/data`` is absent (users of the package do not have it).
"""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from tiger.scene import SceneFormatError
from tiger.scene.dataset import load_dataset, look_at_point
from tiger.scene.images import load_image
from tiger.scene.nerf import load_transforms

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
FOX = DATA / "fox"
pytestmark = pytest.mark.skipif(not (FOX / "transforms.json").is_file(),
                                reason=f"real data not available: {FOX} is missing (it lives beside the repo "
                                       "as ../shared/data; see shared/data/README.md)")


def test_fox_cameras_split_and_conventions():
    ds = load_dataset(FOX)
    assert len(ds.cameras) == 50 and ds.kind == "nerf"
    train, test = ds.split(8)
    assert (len(train), len(test)) == (43, 7)
    assert test[0].image_name == "images/0001.jpg"
    c0 = ds.cameras[0]
    assert (c0.width, c0.height) == (1080, 1920) and c0.fx == pytest.approx(1375.52)
    assert c0.distortion is not None and c0.distortion.k1 == pytest.approx(0.0578421)
    # every camera looks at the figurine: the common look-at point is in front of each
    # camera and inside its image (a wrong OpenGL->OpenCV flip puts it behind them)
    p = look_at_point(ds.cameras)[None]
    for c in ds.cameras:
        uv, z = c.project(p)
        assert z[0] > 0
        assert 0.2 * c.width < uv[0, 0] < 0.8 * c.width and 0.2 * c.height < uv[0, 1] < 0.8 * c.height


def test_fox_original_transforms_reports_missing_images():
    with pytest.raises(SceneFormatError) as ei:
        load_transforms(FOX / "transforms_original.json")
    msg = str(ei.value)
    assert "transforms_original.json" in msg and "frames[4].file_path" in msg and "0005.jpg" in msg
    cams, _ = load_transforms(FOX / "transforms_original.json", skip_missing=True)
    ref = load_dataset(FOX).cameras
    assert [c.image_name for c in cams] == [c.image_name for c in ref]
    assert all(torch.equal(a.viewmat, b.viewmat) for a, b in zip(cams, ref))


def test_fox_image_undistorted_and_downscaled(tmp_path):
    cam = load_dataset(FOX).cameras[0]
    img, c = load_image(cam, 16, cache_dir=tmp_path)
    assert img.shape == (120, 68, 3) and c.distortion is None
    assert 0.05 < float(img.mean()) < 0.95 and float(img.std()) > 0.05
    assert len(list(tmp_path.rglob("*.png"))) == 1
