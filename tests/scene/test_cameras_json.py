"""cameras.json beside a scene: INRIA's fields, round trip, INRIA-written files, clear errors."""
from __future__ import annotations

import json
import math

import pytest
import torch

from tiger.render import Camera
from tiger.scene import SceneFormatError
from tiger.scene.cameras import intrinsics
from tiger.scene.cameras_json import cameras_json_path, read_cameras_json, write_cameras_json


def _rotation(axis, angle):
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    Kx = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx


def _camera(i):
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = _rotation([1.0, 2.0, 0.5 + i], 0.3 + 0.2 * i)
    V[:3, 3] = torch.tensor([0.1 * i, -0.2, 3.0])
    return Camera(V, intrinsics(500.0 + i, 505.0, 320.5, 239.0), 640, 480, image_name=f"images/{i:04d}.jpg")


def test_round_trip_and_inria_fields(tmp_path):
    cams = [_camera(i) for i in range(3)]
    path = write_cameras_json(cameras_json_path(tmp_path / "scene.ply"), cams)
    assert path == tmp_path / "cameras.json"
    entries = json.loads(path.read_text())
    for cam, e in zip(cams, entries):
        # INRIA: position/rotation are camera-to-world (OpenCV axes); img_name has no extension
        assert set(e) >= {"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"}
        assert e["img_name"] == cam.image_name[len("images/"):-len(".jpg")]
        R = cam.viewmat[:3, :3]
        assert torch.allclose(torch.tensor(e["position"], dtype=torch.float64), -R.T @ cam.viewmat[:3, 3])
        assert torch.allclose(torch.tensor(e["rotation"], dtype=torch.float64), R.T)
    back = read_cameras_json(path)
    for a, b in zip(cams, back):
        assert torch.allclose(a.viewmat, b.viewmat, atol=1e-12) and torch.allclose(a.K, b.K)
        assert (a.width, a.height, a.image_name) == (b.width, b.height, b.image_name)


def test_reads_a_file_written_by_inria(tmp_path):
    """INRIA's entry (no cx/cy: principal point at the centre), written by hand from its code."""
    R_c2w = _rotation([0.0, 1.0, 0.0], 0.5)
    entry = {"id": 0, "img_name": "0001", "width": 800, "height": 600, "position": [1.0, 2.0, 3.0],
             "rotation": R_c2w.tolist(), "fy": 700.0, "fx": 710.0}
    (tmp_path / "cameras.json").write_text(json.dumps([entry]))
    cam, = read_cameras_json(tmp_path / "cameras.json")
    assert torch.allclose(cam.center, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    assert torch.allclose(cam.viewmat[:3, :3], R_c2w.T)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.image_name) == (710.0, 700.0, 400.0, 300.0, "0001")


@pytest.mark.parametrize("text,message", [
    ("[]", "non-empty list"),
    ("{not json", "invalid JSON"),
    ('[{"width": 10, "height": 10, "fx": 5, "fy": 5, "position": [0, 0, 0]}]', r"\[0\].rotation"),
    ('[{"width": 10, "height": 10, "fx": 5, "position": [0, 0, 0], "rotation": [[1,0,0],[0,1,0],[0,0,1]]}]',
     r"\[0\].fy"),
    ('[{"width": 10, "height": 10, "fx": 5, "fy": 5, "position": [0, 0], "rotation": [[1,0,0],[0,1,0],[0,0,1]]}]',
     r"\[0\].position': must have shape \[3\]"),
    ('[{"width": 10, "height": 10, "fx": 5, "fy": 5, "position": [0, 0, 0], "rotation": [[2,0,0],[0,1,0],[0,0,1]]}]',
     "not a rotation"),
])
def test_errors_name_the_entry_and_field(tmp_path, text, message):
    (tmp_path / "cameras.json").write_text(text)
    with pytest.raises(SceneFormatError, match=message):
        read_cameras_json(tmp_path / "cameras.json")
