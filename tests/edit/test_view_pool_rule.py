"""The edit's camera rule (EditConfig.view_pool): a pool of 256 camera sets by default, chosen by
measurement (benchmarks/edit_view_pool.py). Pinned here: the pool's cameras cover the views the
fresh sampler draws, a pooled edit reaches the analytic guidance's known answer as well as fresh
cameras do, a pool never renders more originals than the steps use, and the CLI says the same."""
import math

import torch

from tiger.cli.main import build_parser
from tiger.edit import EditConfig, EditSession, edit, resolve_target
from tiger.edit.config import DEFAULT_VIEW_POOL
from tiger.edit.views import CaptureLayout, ObjectViews
from tiger.scene import render_rgb
from tiger.scene.sh import rgb_to_sh
from tiger.testing.ideal_denoiser import IdealDenoiserGuidance, render_targets

from .scenes import query_a, two_objects

#: Every fresh camera has a pooled one within this angle (degrees, seen from the object's centre).
#: 256 sets of 4 (the default) give <= 5.9 deg at these seeds; 128 sets leave 6.9 deg gaps, 64 sets 11, 16 sets 19.
COVER_DEG = 6.5


def _directions(views, cams):
    d = torch.stack([c.center - views.center for c in cams])
    return d / d.norm(dim=1, keepdim=True)


def _largest_gap_deg(views, pool_sets, fresh_steps=500):
    g_pool, g_fresh = torch.Generator().manual_seed(7919), torch.Generator().manual_seed(1)
    pool = _directions(views, [c for _ in range(pool_sets) for c in views.sample(g_pool)])
    fresh = _directions(views, [c for _ in range(fresh_steps) for c in views.sample(g_fresh)])
    return math.degrees(float(torch.acos((fresh @ pool.T).clamp(-1, 1).max(1).values.min())))


def test_default_is_a_pool_of_256_sets_everywhere():
    assert DEFAULT_VIEW_POOL == 256 and EditConfig().view_pool == DEFAULT_VIEW_POOL
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    edit_cli = {a.dest: a for a in sub.choices["edit"]._actions}
    assert edit_cli["view_pool"].default == DEFAULT_VIEW_POOL
    assert "fresh" in edit_cli["view_pool"].help and "0" in edit_cli["view_pool"].help


def test_default_pool_covers_the_fresh_sampler_360_and_forward_facing():
    box = (-0.3 * torch.ones(3), 0.3 * torch.ones(3))
    ring = ObjectViews(torch.zeros(3), *box, force_360=True, width=32, height=32)
    arc = ObjectViews(torch.zeros(3), *box, width=32, height=32,
                      layout=CaptureLayout(False, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64),
                                           30.0, 140.0, 5.0, 35.0, 220.0))
    for views in (ring, arc):
        assert _largest_gap_deg(views, DEFAULT_VIEW_POOL) <= COVER_DEG
    assert _largest_gap_deg(ring, 64) > COVER_DEG  # the pin can fail: a smaller pool leaves gaps


def test_pooled_edit_reaches_the_known_answer_as_well_as_fresh():
    scene = two_objects()
    t = resolve_target(scene, query_a(), tau=0.5)
    truth = scene.clone()
    truth.sh_dc[t.mask] = rgb_to_sh(torch.tensor([0.86, 0.08, 0.08])).expand(t.count, 3)
    truth.sh_rest[t.mask] = 0
    # held out: azimuths between the fixed ring's, three elevations over the sampled range
    views = ObjectViews(t.center, t.bbox_min, t.bbox_max, force_360=True, width=32, height=32)
    az = (torch.arange(6, dtype=torch.float64) + 0.5) * (math.pi / 3)
    cams = [c for e in (3.0, 15.0, 27.0) for c in views.cameras_at(az, torch.full((6,), math.radians(e)))]
    want, foot = render_rgb(truth, cams, footprint=t.mask)
    obj = foot > 0.5
    psnr = {}
    for pool in (0, DEFAULT_VIEW_POOL):
        res = edit(scene, t, IdealDenoiserGuidance(render_targets(truth), seed=0), steps=60, width=32, height=32,
                   progress=False, lrs={"sh_dc": 0.05}, densify_every=0, view_pool=pool)
        got, _ = render_rgb(res.scene, cams, footprint=res.editable)
        psnr[pool] = -10 * math.log10(float((got - want).square().mean(-1)[obj].mean()))
    before, _ = render_rgb(scene, cams, footprint=t.mask)
    psnr_before = -10 * math.log10(float((before - want).square().mean(-1)[obj].mean()))
    assert psnr[0] > psnr_before + 10  # the edit did reach toward the target
    # (60 steps measure convergence, not coverage: what a pool's size costs shows after many reuses,
    # benchmarks/edit_view_pool.py; the coverage test above pins the size)
    assert psnr[DEFAULT_VIEW_POOL] >= psnr[0] - 1.0, psnr


def test_pool_renders_only_the_sets_it_draws():
    scene = two_objects()
    s = EditSession(scene, resolve_target(scene, query_a(), tau=0.5), IdealDenoiserGuidance(
        render_targets(scene)), None, EditConfig(steps=5, width=16, height=16, progress=False, densify_every=0))
    assert len(s.pool.cameras) == DEFAULT_VIEW_POOL and not any(s.pool.rendered)
    for _ in range(5):
        s.step_once()
    assert 1 <= sum(s.pool.rendered) <= 5
    k = s.pool.rendered.index(True)
    rgb, foot = render_rgb(s.original, s.pool.cameras[k], s.background, footprint=s.orig_indicator)
    assert s.pool.originals.dtype == torch.uint8  # 8-bit steps, as a photograph
    assert (s.pool.originals[k].float() / 255 - rgb.permute(0, 3, 1, 2)).abs().max() <= 0.5 / 255 + 1e-6
    assert (s.pool.masks[k].float() / 255 - foot[:, None]).abs().max() <= 0.5 / 255 + 1e-6
    assert not bool(s.pool.originals[[i for i, r in enumerate(s.pool.rendered) if not r]].any())
