"""Virtual views: look-at matrices, the orbit around a point cloud, and views of a captured
scene: evenly spread along the camera path, or an arc over the side the scene's view-dependent
colour was fitted for."""
from __future__ import annotations

import math

import pytest
import torch

from tiger.render import Camera
from tiger.render.views import fibonacci_directions, look_at, orbit_cameras_around, path_view_indices
from tiger.scene import GaussianScene
from tiger.scene.observed import observed_direction, observed_orbit_cameras
from tiger.scene.sh import rgb_to_sh

SH_C1 = 0.4886025119029199  # real SH band-1 constant, sqrt(3 / (4 pi))


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


def test_path_view_indices():
    assert path_view_indices(50) == [0, 7, 14, 21, 28, 35, 42, 49]  # 8 by default, ends included
    assert path_view_indices(50, 3) == path_view_indices(50, "3") == [0, 24, 49]
    assert path_view_indices(50, "0,12,24") == [0, 12, 24]
    assert path_view_indices(50, "12,") == [12]
    assert path_view_indices(5, 1) == [0] and path_view_indices(5, 9) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match=r"view indices \[50, 60\] are out of range: there are 50"):
        path_view_indices(50, [1, 50, 60])
    with pytest.raises(ValueError, match="must be positive"):
        path_view_indices(50, 0)
    with pytest.raises(ValueError, match="count .* or comma-separated indices"):
        path_view_indices(50, "a,b")


def test_fibonacci_directions_cover_the_sphere():
    d = fibonacci_directions(200)
    assert torch.allclose(d.norm(dim=1), torch.ones(200, dtype=torch.float64))
    assert d.mean(0).norm() < 0.02  # balanced
    probe = fibonacci_directions(7)  # every direction has a lattice point within ~15 degrees
    assert float((probe @ d.T).max(1).values.min()) > math.cos(math.radians(15))


def _scene_observed_from(front: torch.Tensor, sh_degree: int = 1) -> GaussianScene:
    """Gaussians whose band-1 colour stays in [0, 1] when seen from ``front``'s side and leaves
    it (below 0) when seen from the far side: colour(v) = 0.2 + 0.5 <v, -front> for view
    direction v (from the camera to the Gaussian), as a fit from one side extrapolates."""
    g = torch.Generator().manual_seed(0)
    scene = GaussianScene.random_in_box(300, [-1, -1, -1], [1, 1, 1], sh_degree=sh_degree, generator=g)
    scene.sh_dc = rgb_to_sh(torch.full((300, 3), 0.2))
    a = -front / front.norm() * 0.5
    # INRIA order of band 1: -C1 y, C1 z, -C1 x
    band1 = torch.stack([-a[1] / SH_C1, a[2] / SH_C1, -a[0] / SH_C1]).float()
    rest = torch.zeros_like(scene.sh_rest)
    rest[:, :3, :] = band1[:, None].expand(3, 3) + 0.02 * torch.randn(300, 3, 3, generator=g)
    scene.sh_rest = rest
    return scene


@pytest.mark.parametrize("front", [[0.0, 0.0, -1.0], [0.6, -0.3, 0.7]])
def test_observed_direction_finds_the_fitted_side(front):
    f = torch.tensor(front, dtype=torch.float64)
    f = f / f.norm()
    d = observed_direction(_scene_observed_from(f))
    assert d is not None and math.degrees(math.acos(float(d @ f))) < 15


def test_observed_orbit_stays_on_the_observed_side():
    f = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    scene = _scene_observed_from(f)
    cams = observed_orbit_cameras(scene, 5, 64, 48)
    c = scene.means.detach().double().mean(0)
    for cam in cams:
        to_cam = (cam.center - c) / (cam.center - c).norm()
        assert float(to_cam @ f) > math.cos(math.radians(75))  # within the 120-degree arc (+ elevation)
        # and looking at the scene: its centre projects into the picture
        uv, z = cam.project(c[None].float())
        assert z.item() > 0 and 0 <= uv[0, 0] <= 64 and 0 <= uv[0, 1] <= 48


def test_degree_zero_scene_has_no_observed_side_and_gets_the_full_orbit():
    scene = GaussianScene.random_in_box(50, [-1, -1, -1], [1, 1, 1], sh_degree=0,
                                        generator=torch.Generator().manual_seed(1))
    assert observed_direction(scene) is None
    cams = observed_orbit_cameras(scene, 4, 32, 24)
    centers = torch.stack([c.center for c in cams]) - scene.means.double().mean(0)
    assert float(centers.mean(0).norm()) < 0.3 * float(centers.norm(dim=1).mean())  # all around
