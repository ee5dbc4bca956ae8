"""COLMAP sparse models: text vs binary, conventions, supported models, bad input."""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from .colmapref import write_model
from tiger.render import Distortion
from tiger.scene import SceneFormatError
from tiger.scene.colmap import colmap_cameras, read_cameras_binary, read_images_binary, read_model
from tiger.scene.dataset import load_colmap, load_dataset

CAMERAS = [
    (1, "SIMPLE_PINHOLE", 64, 48, (50.0, 32.0, 24.0)),
    (2, "PINHOLE", 64, 48, (51.0, 49.5, 31.5, 23.25)),
    (3, "SIMPLE_RADIAL", 64, 48, (52.0, 32.5, 24.5, 0.01)),
    (4, "RADIAL", 64, 48, (53.0, 31.0, 23.0, 0.02, -0.003)),
    (5, "OPENCV", 64, 48, (54.0, 55.0, 32.1, 23.9, 0.05, -0.08, -0.001, 0.0002)),
]


def make_model(tmp_path, binary: bool, cameras=CAMERAS, with_images: bool = True):
    rng = np.random.default_rng(0)
    images = []
    for i in range(7):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        t = rng.normal(size=3)
        pts = [(float(x), float(y), int(p)) for x, y, p in zip(rng.uniform(0, 64, 3), rng.uniform(0, 48, 3),
                                                                 [-1, 5, 7])] if i % 2 else []
        images.append((10 + i, tuple(q), tuple(t), cameras[i % len(cameras)][0], f"img_{i:02d}.png", pts))
    points = [(j, tuple(rng.normal(size=3)), tuple(int(v) for v in rng.integers(0, 256, 3)), 0.5,
               [(10, j), (11, j + 1)][: j % 3]) for j in range(9)]
    root = tmp_path / ("bin" if binary else "txt")
    write_model(root / "sparse" / "0", cameras, images, points, binary)
    if with_images:
        from PIL import Image

        (root / "images").mkdir(parents=True)
        for im in images:
            Image.new("RGB", (64, 48), (10, 20, 30)).save(root / "images" / im[4])
    return root, images, points


def test_text_and_binary_give_identical_cameras(tmp_path):
    rb, _, points = make_model(tmp_path, binary=True)
    rt, _, _ = make_model(tmp_path, binary=False)
    db, dt = load_colmap(rb), load_colmap(rt)
    assert len(db.cameras) == len(dt.cameras) == 7
    for a, b in zip(db.cameras, dt.cameras):
        assert a.image_name == b.image_name
        assert torch.equal(a.viewmat, b.viewmat) and torch.equal(a.K, b.K)
        assert a.distortion == b.distortion and (a.width, a.height) == (b.width, b.height)
    assert torch.equal(db.points, dt.points) and torch.equal(db.point_colors, dt.point_colors)
    np.testing.assert_allclose(db.points.numpy(), np.array([p[1] for p in points]), rtol=1e-6)
    np.testing.assert_array_equal((db.point_colors * 255).round().numpy(), np.array([p[2] for p in points]))


def test_pose_and_intrinsics_conventions(tmp_path):
    root, images, _ = make_model(tmp_path, binary=True)
    ds = load_colmap(root)
    X = np.random.default_rng(1).normal(size=(20, 3))
    for cam, (iid, q, t, cid, name, _) in zip(ds.cameras, sorted(images, key=lambda im: im[4])):
        assert cam.image_name == name and cam.camera_id == cid
        # independent COLMAP projection: x = R(q) X + t, q = (w, x, y, z); SciPy wants (x, y, z, w)
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        Xc = X @ R.T + np.array(t)
        params = dict((c[0], c) for c in CAMERAS)[cid][4]
        model = dict((c[0], c[1]) for c in CAMERAS)[cid]
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = params[0]
            cx, cy = params[1], params[2]
        else:
            fx, fy, cx, cy = params[:4]
        uv_ref = np.stack([fx * Xc[:, 0] / Xc[:, 2] + cx, fy * Xc[:, 1] / Xc[:, 2] + cy], 1)
        uv, z = cam.project(torch.from_numpy(X))
        np.testing.assert_allclose(uv.numpy(), uv_ref, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(z.numpy(), Xc[:, 2], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(cam.center.numpy(), -R.T @ np.array(t), atol=1e-12)
    by_model = {c.camera_id: c.distortion for c in ds.cameras}
    assert by_model[1] is None and by_model[2] is None
    assert by_model[3] == Distortion(k1=0.01)
    assert by_model[4] == Distortion(k1=0.02, k2=-0.003)
    assert by_model[5] == Distortion(k1=0.05, k2=-0.08, p1=-0.001, p2=0.0002)


def test_split_every_eighth_in_name_order(tmp_path):
    root, _, _ = make_model(tmp_path, binary=False)
    ds = load_dataset(root)
    train, test = ds.split(8)
    assert [c.image_name for c in test] == ["img_00.png"]
    assert len(train) == 6
    train, test = ds.split(3)
    assert [c.image_name for c in test] == ["img_00.png", "img_03.png", "img_06.png"]


def test_missing_images(tmp_path, caplog):
    root, images, _ = make_model(tmp_path, binary=True)
    (root / "images" / "img_03.png").unlink()
    with pytest.raises(SceneFormatError, match="img_03.png"):
        load_colmap(root)
    with caplog.at_level(logging.WARNING):
        ds = load_colmap(root, skip_missing=True)
    assert len(ds.cameras) == 6 and "skipped 1 of 7" in caplog.text


def test_unsupported_and_unknown_models(tmp_path):
    cams = [(1, "OPENCV_FISHEYE", 64, 48, (50.0, 50.0, 32.0, 24.0, 0.1, 0.0, 0.0, 0.0))]
    root, _, _ = make_model(tmp_path, binary=True, cameras=cams, with_images=False)
    cm, im, _ = read_model(root / "sparse" / "0")
    with pytest.raises(SceneFormatError, match="OPENCV_FISHEYE is not supported") as ei:
        colmap_cameras(cm, im, root / "images")
    assert "MODEL" in str(ei.value)
    txt = tmp_path / "cameras.txt"
    txt.write_text("1 WEIRD_MODEL 64 48 1 2 3\n")
    with pytest.raises(SceneFormatError, match="unknown camera model 'WEIRD_MODEL'"):
        read_model(tmp_path)
    txt.write_text("1 PINHOLE 64 48 1 2 3\n")
    with pytest.raises(SceneFormatError, match="takes 4 parameters"):
        read_model(tmp_path)


def test_binary_errors_name_file_and_field(tmp_path):
    root, _, _ = make_model(tmp_path, binary=True, with_images=False)
    d = root / "sparse" / "0"
    data = (d / "cameras.bin").read_bytes()
    (d / "cameras.bin").write_bytes(data[:-5])
    with pytest.raises(SceneFormatError) as ei:
        read_cameras_binary(d / "cameras.bin")
    assert "cameras.bin" in str(ei.value) and "truncated" in str(ei.value) and "params" in str(ei.value)
    data = bytearray((d / "images.bin").read_bytes())
    data[0:8] = (2 ** 40).to_bytes(8, "little")   # absurd image count
    (d / "images.bin").write_bytes(bytes(data))
    with pytest.raises(SceneFormatError, match="images.bin.*truncated"):
        read_images_binary(d / "images.bin")


def test_image_with_unknown_camera(tmp_path):
    root, _, _ = make_model(tmp_path, binary=False, with_images=False)
    d = root / "sparse" / "0"
    (d / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32 24\n")
    with pytest.raises(SceneFormatError, match="refers to camera 2"):
        read_model(d)
