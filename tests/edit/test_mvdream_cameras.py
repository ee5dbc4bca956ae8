"""MVDream camera convention: hand-computed cameras and MVDream's own camera construction
(create_camera_to_world_matrix + convert_opengl_to_blender, written here from its definition)."""
import math

import pytest
import torch

from tiger.edit.guidance.mvdream_cameras import estimate_world_up, mvdream_cameras
from tiger.render import Camera

K = torch.tensor([[16.0, 0, 8], [0, 16, 8], [0, 0, 1]])


def test_hand_computed_front_camera():
    # z-up world, object at c, camera at c + (0, -5, 0) looking along +y with +z up.
    # OpenCV axes in world: x = (1,0,0), y (down) = (0,0,-1), z (forward) = (0,1,0).
    c = torch.tensor([2.0, 3.0, 1.0])
    c2w = torch.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 0, -1]), torch.tensor([0.0, 1, 0])
    c2w[:3, 3] = c + torch.tensor([0.0, -5.0, 0.0])
    cam = Camera(torch.linalg.inv(c2w), K, 16, 16)
    got = mvdream_cameras([cam], c, world_up=torch.tensor([0.0, 0.0, 1.0]))
    # MVDream at azimuth 0, elevation 0: OpenGL c2w = identity rotation at (0,0,1); flip_yz -> rows
    # (1,0,0 | 0), (0,0,-1 | -1), (0,1,0 | 0).
    want = torch.tensor([1.0, 0, 0, 0, 0, 0, -1, -1, 0, 1, 0, 0, 0, 0, 0, 1])
    assert torch.allclose(got[0], want, atol=1e-6)


def _mvdream_reference(elevation, azimuth):
    el, az = math.radians(elevation), math.radians(azimuth)
    pos = torch.tensor([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)], dtype=torch.float64)
    fwd = -pos / pos.norm()
    right = torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    right = right / right.norm()
    up = torch.linalg.cross(right, fwd)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up / up.norm(), -fwd, pos
    flip_yz = torch.tensor([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=torch.float64)
    return flip_yz @ m  # MVDream's get_camera(blender_coord=True)


@pytest.mark.parametrize("y_up", [False, True])
def test_matches_mvdream_get_camera(y_up):
    center = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    cams, want = [], []
    unflip = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=torch.float64)
    for az in (0.0, 90.0, 180.0, 270.0):
        m = _mvdream_reference(15.0, az)
        want.append(m.reshape(16))
        world = unflip @ m if y_up else m.clone()  # the same camera in a y-up world (OpenGL's)
        world[:3, 3] = world[:3, 3] * 2.5 + center  # a distance and a centre of our own
        cv = world.clone()
        cv[:3, 1:3] = -cv[:3, 1:3]  # OpenGL camera axes -> OpenCV
        cams.append(Camera(torch.linalg.inv(cv), K, 16, 16))
    up = torch.tensor([0.0, 1.0, 0.0] if y_up else [0.0, 0.0, 1.0])
    got = mvdream_cameras(cams, center, world_up=up)
    assert torch.allclose(got.double(), torch.stack(want), atol=1e-5)
    assert torch.allclose(mvdream_cameras(cams, center), got, atol=1e-5)  # up estimated from the ring


def test_estimated_up_and_errors(ring_cameras):
    cams = ring_cameras(center=(1.0, 2.0, 3.0), elevation_deg=30.0)
    assert torch.allclose(estimate_world_up(cams), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-9)
    with pytest.raises(ValueError, match="object_center"):
        mvdream_cameras(cams, torch.zeros(2))
    with pytest.raises(ValueError, match="world_up"):
        mvdream_cameras(cams, torch.zeros(3), world_up=torch.zeros(3))
