"""Tiny random InstructPix2Pix (diffusers folder) and MVDream (original LDM .pt) shared by the edit tests."""
import math

import pytest
import torch

from tiger.render import Camera



@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory):
    pytest.importorskip("diffusers")
    from tiger.testing.random_models import save_random_ip2p, save_random_mvdream

    root = tmp_path_factory.mktemp("guidance_models")
    save_random_ip2p(root / "instruct-pix2pix")
    save_random_mvdream(root / "mvdream")
    return root


def _ring_cameras(center=(0.0, 0.0, 0.0), distance=3.0, elevation_deg=15.0, size=(16, 16)):
    """4 OpenCV cameras every 90 degrees around ``center`` in a z-up world, looking at it."""
    c = torch.tensor(center, dtype=torch.float64)
    cams = []
    for k in range(4):
        az, el = math.radians(90.0 * k), math.radians(elevation_deg)
        pos = c + distance * torch.tensor([math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az), math.sin(el)],
                                          dtype=torch.float64)
        fwd = (c - pos) / (c - pos).norm()
        right = torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        right = right / right.norm()
        down = torch.linalg.cross(fwd, right)
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, fwd, pos
        w, h = size
        K = torch.tensor([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1]], dtype=torch.float64)
        cams.append(Camera(torch.linalg.inv(c2w), K, w, h))
    return cams


@pytest.fixture
def ring_cameras():
    """The camera-ring builder (4 OpenCV cameras every 90 degrees around a centre, z up)."""
    return _ring_cameras
