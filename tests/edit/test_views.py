"""Object-centred edit cameras: 360 vs forward-facing rule, fill distance, spacing, determinism."""
import math

import pytest
import torch

from tiger.edit.views import ObjectViews, capture_layout, fill_distance
from tiger.render.views import orbit_cameras, look_at, pinhole_K
from tiger.render import Camera


def _forward_capture(center=(0.0, 0.0, 0.0), n=9, arc_deg=60.0, radius=4.0):
    """Cameras on a 60 degree arc in front of the object (y down, world up = -y)."""
    cams = []
    for i in range(n):
        a = math.radians(-arc_deg / 2 + arc_deg * i / (n - 1))
        eye = [center[0] + radius * math.sin(a), center[1] - 0.5, center[2] - radius * math.cos(a)]
        cams.append(Camera(viewmat=look_at(eye, list(center)), K=pinhole_K(64, 48), width=64, height=48))
    return cams


def test_rule_360_and_forward():
    ring = orbit_cameras(12, 64, 48, center=(0.0, 0.0, 0.0), radius=3.0)
    lay = capture_layout(ring, torch.zeros(3))
    assert lay.is_360 and lay.largest_gap_deg == pytest.approx(30.0, abs=1e-4)
    fwd = capture_layout(_forward_capture(), torch.zeros(3))
    assert not fwd.is_360
    assert fwd.azimuth_span_deg == pytest.approx(60.0, abs=1.0)  # up: mean of slightly tilted camera ups
    # up is -y for both (OpenCV capture, y down)
    assert torch.allclose(lay.up, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64), atol=1e-6)


def _project(cam, pts):
    uv, z = cam.project(pts.double())
    return uv, z


def test_cameras_look_at_centre_and_box_fills_view():
    center = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    lo, hi = center - torch.tensor([0.2, 0.1, 0.15]), center + torch.tensor([0.2, 0.1, 0.15])
    ring = orbit_cameras(8, 64, 48, center=center.tolist(), radius=3.0)
    ov = ObjectViews(center, lo, hi, capture=ring, width=96, height=64, fov_deg=40.0, fill=1.0)
    cams = ov.sample(torch.Generator().manual_seed(3))
    assert len(cams) == 4
    corners = torch.stack([torch.tensor([x, y, z], dtype=torch.float64)
                           for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    # independent: the box's circumscribed sphere touches the frame at fill = 1
    r = 0.5 * float((hi - lo).norm())
    assert ov.distance == pytest.approx(r / math.sin(math.radians(40.0) / 2), rel=1e-9)
    for cam in cams:
        assert float((cam.center.double() - center).norm()) == pytest.approx(ov.distance, rel=1e-6)
        uv, z = _project(cam, center[None])
        assert torch.allclose(uv[0], torch.tensor([48.0, 32.0], dtype=torch.float64), atol=1e-4)
        uv, z = _project(cam, corners)
        assert bool((z > 0).all())
        assert bool((uv[:, 0] >= 0).all() and (uv[:, 0] <= 96).all() and (uv[:, 1] >= 0).all()
                    and (uv[:, 1] <= 64).all())
        # and the box is not tiny: its projection spans a good part of the smaller side
        assert float(uv[:, 1].max() - uv[:, 1].min()) > 0.3 * 64
    az = torch.tensor([c.metadata["azimuth_deg"] for c in cams])
    d = torch.remainder(az[1:] - az[:-1], 360.0)
    assert torch.allclose(d, torch.full_like(d, 90.0), atol=1e-6)
    el = torch.tensor([c.metadata["elevation_deg"] for c in cams])
    assert bool(((el >= 0) & (el <= 30)).all())


def test_forward_facing_stays_in_capture_arc_and_is_deterministic():
    cams0 = _forward_capture()
    ov = ObjectViews(torch.zeros(3), -0.1 * torch.ones(3), 0.1 * torch.ones(3), capture=cams0)
    assert not ov.is_360
    lay = ov.layout
    for seed in range(5):
        a = ov.sample(torch.Generator().manual_seed(seed))
        b = ov.sample(torch.Generator().manual_seed(seed))
        assert all(torch.equal(x.viewmat, y.viewmat) for x, y in zip(a, b))
        for c in a:
            rel = (c.metadata["azimuth_deg"] - lay.azimuth_start_deg) % 360.0
            assert rel <= lay.azimuth_span_deg + 1e-6
            assert lay.elevation_min_deg - 1e-6 <= c.metadata["elevation_deg"] <= lay.elevation_max_deg + 1e-6


def test_fill_distance_errors():
    with pytest.raises(ValueError, match="field of view"):
        fill_distance(torch.zeros(3), torch.ones(3), 0.0)
    with pytest.raises(ValueError, match="cameras"):
        capture_layout([], torch.zeros(3))
