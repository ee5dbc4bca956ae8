"""Edit metrics against hand-computed answers: CLIP direction similarity/consistency, locality PSNR."""
import math

import numpy as np
import pytest
import torch

from tiger.eval.edit import (PSNR_CAP, clip_direction_consistency, clip_direction_similarity, dilate_mask,
                             locality, psnr_outside)
from tiger.render.views import orbit_cameras
from tiger.scene import GaussianScene, render_rgb


def _np_cos(a, b):
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def test_direction_similarity_matches_numpy():
    g = torch.Generator().manual_seed(0)
    ib, ia = torch.randn(3, 8, generator=g), torch.randn(3, 8, generator=g)
    tb, ta = torch.randn(8, generator=g), torch.randn(8, generator=g)
    got = clip_direction_similarity(ib, ia, tb, ta)
    n = lambda v: v / np.linalg.norm(v)  # noqa: E731
    for k in range(3):
        want = _np_cos(n(ia[k].double().numpy()) - n(ib[k].double().numpy()), n(ta.double().numpy()) - n(tb.double().numpy()))
        assert float(got[k]) == pytest.approx(want, abs=1e-9)
    # an image change exactly along the caption change scores 1, the opposite -1
    tb1, ta1 = torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0])
    assert float(clip_direction_similarity(tb1[None], ta1[None], tb1, ta1)[0]) == pytest.approx(1.0)
    assert float(clip_direction_similarity(ta1[None], tb1[None], tb1, ta1)[0]) == pytest.approx(-1.0)


def test_direction_consistency_matches_numpy():
    g = torch.Generator().manual_seed(1)
    b, a = torch.randn(4, 6, generator=g), torch.randn(4, 6, generator=g)
    got = clip_direction_consistency(b, a)
    bn = b.double().numpy() / np.linalg.norm(b.double().numpy(), axis=1, keepdims=True)
    an = a.double().numpy() / np.linalg.norm(a.double().numpy(), axis=1, keepdims=True)
    for i in range(3):
        assert float(got[i]) == pytest.approx(_np_cos(an[i + 1] - an[i], bn[i + 1] - bn[i]), abs=1e-9)
    # an edit that adds the same offset in every view keeps the path's direction: 1
    same = clip_direction_consistency(b, b + 0.0)
    assert torch.allclose(same, torch.ones(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="2 views"):
        clip_direction_consistency(b[:1], a[:1])


def test_dilate_and_psnr_outside():
    m = torch.zeros(1, 9, 9, dtype=torch.bool)
    m[0, 4, 4] = True
    d = dilate_mask(m, 2)
    assert int(d.sum()) == 25 and bool(d[0, 2:7, 2:7].all())
    before = torch.rand(1, 9, 9, 3, generator=torch.Generator().manual_seed(2))
    after = before.clone()
    after[0, 3:6, 3:6] += 0.5  # inside the dilated mask only
    assert psnr_outside(before, after, m, dilate_px=2)["psnr"] == PSNR_CAP
    after[0, 0, 0] += 0.1  # one leaking pixel outside
    r = psnr_outside(before, after, m, dilate_px=2)
    mse = 0.1 ** 2 / (81 - 25)
    assert r["pixels"] == 81 - 25 and r["mse"] == pytest.approx(mse, rel=1e-5)
    assert r["psnr"] == pytest.approx(-10 * math.log10(mse), rel=1e-5)


def _two_blobs():
    means = torch.tensor([[-0.6, 0.0, 0.0], [0.6, 0.0, 0.0]]).repeat_interleave(50, 0)
    means += 0.05 * torch.randn(means.shape, generator=torch.Generator().manual_seed(3))
    s = GaussianScene.from_points(means, torch.full_like(means, 0.5), sh_degree=1, opacity=0.9,
                                  scales=torch.full((100,), 0.05))
    return s


def test_locality_sees_leaks_only():
    before = _two_blobs()
    obj = torch.arange(100) < 50
    cams = orbit_cameras(3, 64, 48, center=(0.0, 0.0, 0.0), radius=3.0, elevation_deg=10.0)
    after = before.clone()
    after.sh_dc[obj] += 1.0  # the object recoloured: nothing outside changes
    assert locality(before, after, cams, obj, obj)["psnr"] == PSNR_CAP
    after.sh_dc[~obj] += 2.0  # the other blob changes too: a leak
    leak = locality(before, after, cams, obj, obj)
    assert leak["psnr"] < 30


def test_rest_pixels_exclude_walks_an_edited_gaussian_ends():
    """A pixel whose walk an edited Gaussian ends (transmittance would fall below t_min: it is not
    composited, footprint exactly 0) still depends on it: lowering its opacity lets the Gaussian
    behind it in. Such pixels are "reached" (edited_reach), not "rest"; the rest stays exact."""
    from tiger.eval.edit import edited_reach
    from tiger.render import Camera
    from tiger.render.views import pinhole_K

    # four wide Gaussians on the axis of a camera at the origin looking down +z, front to back:
    # frozen 0.99 and 0.5 (T: 1 -> 0.01 -> 0.005), the edited one at 0.99 (0.005 -> 5e-5 < t_min:
    # the walk ends there), a frozen one behind it that only the edit lets through
    means = torch.tensor([[0.0, 0.0, z] for z in (2.0, 3.0, 4.0, 5.0)], dtype=torch.float64)
    s = GaussianScene.from_points(means, torch.tensor([[0.9, 0.1, 0.1], [0.1, 0.9, 0.1], [0.5, 0.5, 0.5],
                                                       [0.1, 0.1, 0.9]], dtype=torch.float64),
                                  sh_degree=0, scales=torch.full((4,), 3.0, dtype=torch.float64))
    s.opacity_logits = torch.logit(torch.tensor([0.99, 0.5, 0.999, 0.9], dtype=torch.float64))
    edited = torch.tensor([False, False, True, False])
    cam = Camera(viewmat=torch.eye(4, dtype=torch.float64), K=pinhole_K(16, 12, 60.0).double(), width=16, height=12)
    after = s.clone()
    after.opacity_logits[2] = torch.logit(torch.tensor(1e-4, dtype=torch.float64))  # below the threshold
    _, foot_before = render_rgb(s, [cam], footprint=edited)
    _, foot_after = render_rgb(after, [cam], footprint=edited)
    centre = (0, 6, 8)
    assert float(foot_before[centre]) == 0.0 and float(foot_after[centre]) == 0.0  # never composited
    reach = edited_reach(s, [cam], edited)
    assert bool(reach[centre]) and not bool(edited_reach(after, [cam], edited)[centre])
    loc = locality(s, after, [cam], edited, edited, dilate_px=0)
    assert loc["psnr"] < 60  # the pixels behind the edited Gaussian changed
    assert loc["parts"]["rest"]["max_abs_err"] == 0.0
    assert loc["parts"]["fringe"]["pixels"] > 0 and loc["parts"]["fringe"]["max_abs_err"] > 1e-3


def test_locality_of_an_object_that_fills_every_view_is_not_measured():
    """A footprint whose dilation covers every pixel leaves nothing to compare: no PSNR, no error
    (the edit CLI reports it after the edit instead of failing), and the summary line says why."""
    from tiger.eval.edit import locality_text

    before = _two_blobs()
    obj = torch.ones(100, dtype=torch.bool)  # everything is the object
    cams = orbit_cameras(2, 16, 12, center=(0.0, 0.0, 0.0), radius=1.2, elevation_deg=10.0)
    after = before.clone()
    after.sh_dc += 1.0
    loc = locality(before, after, cams, obj, obj, dilate_px=20)
    assert loc["psnr"] is None and loc["pixels"] == 0 and loc["parts"] is None
    assert "not measured" in locality_text(loc)
    obj[50:] = False
    loc = locality(before, after, orbit_cameras(2, 64, 48, center=(0.0, 0.0, 0.0), radius=3.0), obj, obj)
    assert loc["psnr"] is not None and locality_text(loc, "the ball").startswith("locality PSNR outside the ball")


def test_locality_text_never_rounds_a_measured_share_to_zero():
    """The summary's share of measured pixels: a fox that filled 99.6 % of the views printed "(0% of
    the pixels)" beside a PSNR; small and near-full shares keep a decimal or a bound."""
    from tiger.eval.edit import locality_text

    def share(fraction: float) -> str:
        return locality_text({"psnr": 40.0, "fraction": fraction}).split("(")[1].split(" of")[0]

    assert [share(f) for f in (0.00004, 0.0042, 0.091, 0.5, 0.934, 0.99996, 1.0)] == \
        ["<0.1%", "0.4%", "9.1%", "50%", "93.4%", ">99.9%", "100.0%"]
