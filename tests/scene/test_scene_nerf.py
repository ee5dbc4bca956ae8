"""transforms.json conventions, checked by projecting known 3D points."""
from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch
from PIL import Image

from tiger.render import Distortion
from tiger.scene import SceneFormatError
from tiger.scene.dataset import load_dataset
from tiger.scene.nerf import load_transforms


def gl_c2w(rng) -> np.ndarray:
    """A random camera-to-world matrix (OpenGL axes) looking roughly at the origin."""
    eye = rng.normal(size=3)
    eye = 4 * eye / np.linalg.norm(eye)
    back = eye / np.linalg.norm(eye)               # OpenGL camera looks down -z: z points back
    right = np.cross(rng.normal(size=3), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, up, back, eye
    return T


def project_gl(c2w: np.ndarray, X: np.ndarray, fx, fy, cx, cy) -> np.ndarray:
    """Independent OpenGL-convention pinhole projection (y up, looking down -z)."""
    Xc = (np.linalg.inv(c2w) @ np.c_[X, np.ones(len(X))].T).T[:, :3]
    depth = -Xc[:, 2]
    return np.stack([cx + fx * Xc[:, 0] / depth, cy - fy * Xc[:, 1] / depth], 1), depth


def write_dataset(root, frames, top, sizes=None):
    (root / "images").mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(frames):
        w, h = (sizes or {}).get(i, (40, 30))
        Image.new("RGB", (w, h), (i, 2 * i, 3 * i)).save(root / (fr["file_path"] if fr["file_path"].endswith(".png")
                                                                 else fr["file_path"] + ".png"))
    (root / "transforms.json").write_text(json.dumps({**top, "frames": frames}))


def test_projection_matches_opengl_convention(tmp_path):
    rng = np.random.default_rng(0)
    c2ws = [gl_c2w(rng) for _ in range(4)]
    frames = [{"file_path": f"images/{i:03d}.png", "transform_matrix": c.tolist()} for i, c in enumerate(c2ws)]
    frames[2].update(fl_x=70.0, cx=18.5)           # per-frame overrides
    top = {"fl_x": 50.0, "fl_y": 52.0, "cx": 21.0, "cy": 14.0, "w": 40, "h": 30}
    write_dataset(tmp_path, frames, top)
    cams, extra = load_transforms(tmp_path)
    assert [c.image_name for c in cams] == [f"images/{i:03d}.png" for i in range(4)]
    X = rng.normal(size=(25, 3)) * 0.5
    for i, (cam, c2w) in enumerate(zip(cams, c2ws)):
        fx, cx = (70.0, 18.5) if i == 2 else (50.0, 21.0)
        uv_ref, d_ref = project_gl(c2w, X, fx, 52.0, cx, 14.0)
        uv, d = cam.project(torch.from_numpy(X))
        np.testing.assert_allclose(uv.numpy(), uv_ref, atol=1e-9)
        np.testing.assert_allclose(d.numpy(), d_ref, atol=1e-12)
        np.testing.assert_allclose(cam.center.numpy(), c2w[:3, 3], atol=1e-12)
        assert cam.distortion is None and (cam.width, cam.height) == (40, 30)


def test_camera_angle_and_image_size_from_file(tmp_path):
    rng = np.random.default_rng(1)
    c2w = gl_c2w(rng)
    frames = [{"file_path": "images/a", "transform_matrix": c2w.tolist()}]  # no extension (NeRF-synthetic)
    write_dataset(tmp_path, frames, {"camera_angle_x": 0.9}, sizes={0: (64, 48)})
    (cam,), _ = load_transforms(tmp_path / "transforms.json")
    f = 0.5 * 64 / math.tan(0.45)
    assert (cam.width, cam.height) == (64, 48)
    assert cam.fx == pytest.approx(f) and cam.fy == pytest.approx(f)
    assert (cam.cx, cam.cy) == (32.0, 24.0)
    X = rng.normal(size=(10, 3)) * 0.3
    uv_ref, _ = project_gl(c2w, X, f, f, 32.0, 24.0)
    np.testing.assert_allclose(cam.project(torch.from_numpy(X))[0].numpy(), uv_ref, atol=1e-9)


def test_distortion_fields_and_models(tmp_path):
    rng = np.random.default_rng(2)
    frames = [{"file_path": f"images/{i}.png", "transform_matrix": gl_c2w(rng).tolist()} for i in range(2)]
    frames[1]["k1"] = 0.2
    write_dataset(tmp_path, frames, {"fl_x": 30, "w": 40, "h": 30, "k1": 0.1, "k2": -0.05, "p1": 1e-3,
                                     "p2": -2e-3})
    cams, _ = load_transforms(tmp_path)
    assert cams[0].distortion == Distortion(k1=0.1, k2=-0.05, p1=1e-3, p2=-2e-3)
    assert cams[1].distortion == Distortion(k1=0.2, k2=-0.05, p1=1e-3, p2=-2e-3)
    write_dataset(tmp_path, frames, {"fl_x": 30, "w": 40, "h": 30, "k1": 0.1, "camera_model": "PINHOLE"})
    assert load_transforms(tmp_path)[0][0].distortion is None
    write_dataset(tmp_path, frames, {"fl_x": 30, "w": 40, "h": 30, "camera_model": "OPENCV_FISHEYE"})
    with pytest.raises(SceneFormatError, match="camera_model.*OPENCV_FISHEYE"):
        load_transforms(tmp_path)


def test_errors_name_file_frame_and_key(tmp_path, caplog):
    rng = np.random.default_rng(3)
    frames = [{"file_path": f"images/{i}.png", "transform_matrix": gl_c2w(rng).tolist()} for i in range(3)]
    write_dataset(tmp_path, frames, {"fl_x": 30, "w": 40, "h": 30})
    (tmp_path / "images" / "1.png").unlink()
    with pytest.raises(SceneFormatError) as ei:
        load_transforms(tmp_path)
    assert "transforms.json" in str(ei.value) and "frames[1].file_path" in str(ei.value)
    with caplog.at_level(logging.WARNING):
        cams, _ = load_transforms(tmp_path, skip_missing=True)
    assert len(cams) == 2 and "skipped 1 of 3" in caplog.text

    bad = json.loads((tmp_path / "transforms.json").read_text())
    bad["frames"][0]["transform_matrix"][0][0] = "x"
    (tmp_path / "transforms.json").write_text(json.dumps(bad))
    with pytest.raises(SceneFormatError, match=r"frames\[0\].transform_matrix"):
        load_transforms(tmp_path, skip_missing=True)
    bad["frames"][0]["transform_matrix"] = (2 * np.eye(4)).tolist()
    (tmp_path / "transforms.json").write_text(json.dumps(bad))
    with pytest.raises(SceneFormatError, match="not a rotation"):
        load_transforms(tmp_path, skip_missing=True)
    (tmp_path / "transforms.json").write_text('{"frames": [\n{"file_path": ')
    with pytest.raises(SceneFormatError, match="invalid JSON at line 2"):
        load_transforms(tmp_path)
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": frames, "w": 40, "h": 30}))
    with pytest.raises(SceneFormatError, match="no focal length"):
        load_transforms(tmp_path, skip_missing=True)


def test_nerf_synthetic_split(tmp_path):
    rng = np.random.default_rng(4)
    for split, n in (("train", 3), ("test", 2)):
        (tmp_path / split).mkdir()
        frames = [{"file_path": f"./{split}/r_{i}", "transform_matrix": gl_c2w(rng).tolist()} for i in range(n)]
        for i in range(n):
            Image.new("RGBA", (20, 20), (255, 0, 0, 128)).save(tmp_path / split / f"r_{i}.png")
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    ds = load_dataset(tmp_path)
    train, test = ds.split()
    assert len(train) == 3 and len(test) == 2
    assert all(c.image_name.startswith("test") for c in test)


def test_missing_images_are_all_named(tmp_path):
    """Every missing file is counted and the first ten are named, not only the first."""
    from tiger.scene import MissingImagesError

    rng = np.random.default_rng(4)
    frames = [{"file_path": f"images/{i:02d}.png", "transform_matrix": gl_c2w(rng).tolist()} for i in range(15)]
    write_dataset(tmp_path, frames, {"fl_x": 30, "w": 40, "h": 30})
    gone = [1, 2, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14]
    for i in gone:
        (tmp_path / "images" / f"{i:02d}.png").unlink()
    with pytest.raises(MissingImagesError) as ei:
        load_transforms(tmp_path)
    msg = str(ei.value)
    assert "12 of 15 images not found" in msg and "frames[1].file_path" in msg
    for i in gone[:10]:
        assert f"{i:02d}.png" in msg
    assert "12.png" not in msg and "and 2 more" in msg
    assert ei.value.missing == [f"images/{i:02d}.png" for i in gone]
    assert "skip_missing=True" in msg
    assert "--skip-missing" in str(ei.value.with_hint("pass --skip-missing to skip them"))
