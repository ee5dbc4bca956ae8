"""Virtual views: look-at matrices and the orbit around a point cloud."""
from __future__ import annotations

import torch

from tiger.render.camera import Camera
from tiger.render.views import look_at, orbit_cameras_around


def test_look_at_puts_the_target_straight_ahead():
    eye, target = (2.2, -1.0, 1.6), (0.0, 0.3, 0.1)
    V = look_at(eye, target, up=(0.0, 0.0, 1.0)).double()
    R = V[:3, :3]
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-6, rtol=0)
    assert float(torch.det(R)) > 0
    cam = lambda p: R @ torch.tensor(p, dtype=torch.float64) + V[:3, 3]  # noqa: E731
    torch.testing.assert_close(cam(eye), torch.zeros(3, dtype=torch.float64), atol=1e-6, rtol=0)
    t = cam(target)
    dist = float(torch.tensor(target, dtype=torch.float64).sub(torch.tensor(eye)).norm())
    torch.testing.assert_close(t, torch.tensor([0.0, 0.0, dist], dtype=torch.float64), atol=1e-6, rtol=0)
    # world up (+z) points up in the image (-y in OpenCV axes)
    assert float((R @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))[1]) < 0


def test_orbit_around_points_frames_their_bulk():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(5000, 3, generator=g) * torch.tensor([2.0, 1.0, 4.0]) + torch.tensor([10.0, 0.0, -2.0])
    pts[:10] = 1e4  # outliers do not move the orbit
    cams = orbit_cameras_around(pts, 6, 64, 48)
    assert len(cams) == 6 and all(isinstance(c, Camera) and (c.width, c.height) == (64, 48) for c in cams)
    lo, hi = torch.quantile(pts, 0.02, dim=0), torch.quantile(pts, 0.98, dim=0)
    centre, radius = (lo + hi) / 2, float((hi - lo).norm()) * 1.1
    for c in cams:
        uv, z = c.project(centre[None].double())
        torch.testing.assert_close(uv[0], torch.tensor([32.0, 24.0], dtype=torch.float64), atol=1e-3, rtol=0)
        assert abs(float((c.center.double() - centre.double()).norm()) - radius) < 1e-3 * radius
