"""The edit loop on a two-object scene: known answer with the ideal denoiser, locality, sparse
optimizer state, densification limits and inheritance, exact resume."""
import math

import pytest
import torch

from tiger.edit import EditConfig, EditSession, edit, resolve_target
from tiger.edit.guidance import GuidanceInfo, RecolorGuidance
from tiger.scene import render_rgb
from tiger.testing.ideal_denoiser import IdealDenoiserGuidance, render_targets
from tiger.scene.sh import rgb_to_sh

from .scenes import query_a, two_objects

SMALL = dict(width=48, height=48, progress=False, densify_every=0)


def _target_scene(scene, mask, rgb=(0.86, 0.08, 0.08)):
    t = scene.clone()
    t.sh_dc[mask] = rgb_to_sh(torch.tensor(rgb)).expand(int(mask.sum()), 3)
    t.sh_rest[mask] = 0
    return t


def test_known_answer_ideal_denoiser_reaches_30db_on_object():
    scene = two_objects()
    mask = resolve_target(scene, query_a(), tau=0.5).mask
    truth = _target_scene(scene, mask)
    guide = IdealDenoiserGuidance(render_targets(truth), seed=0)
    res = edit(scene, query_a(), guide, tau=0.5, steps=100,
               lrs={"sh_dc": 0.05}, **SMALL)
    # independent check from fixed cameras the loop never drew
    from tiger.edit.views import ObjectViews

    t = resolve_target(scene, query_a(), tau=0.5)
    cams = ObjectViews(t.center, t.bbox_min, t.bbox_max, force_360=True, width=64, height=64).fixed(6, 15.0)
    got, _ = render_rgb(res.scene, cams, footprint=res.editable)
    want, foot = render_rgb(truth, cams, footprint=mask)
    obj = foot > 0.5
    mse = float((got.clamp(0, 1) - want.clamp(0, 1)).square().mean(-1)[obj].mean())
    assert -10 * math.log10(mse) >= 30.0
    # before the edit the object's pixels were far from the target
    before, _ = render_rgb(scene, cams, footprint=mask)
    assert float((before.clamp(0, 1) - want.clamp(0, 1)).square().mean(-1)[obj].mean()) > 100 * mse


def test_zero_relevance_gaussians_bit_identical_and_sh_zeroed():
    scene = two_objects()
    res = edit(scene, query_a(), RecolorGuidance("make it red"), tau=0.5, steps=5, **SMALL)
    frozen_before = ~resolve_target(scene, query_a(), tau=0.5).mask
    frozen_after = res.weights == 0
    a, b = scene.subset(frozen_before), res.scene.subset(frozen_after)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest", "lang"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert bool((res.scene.sh_rest[res.editable] == 0).all())  # view-independent colour while editing
    assert not torch.equal(res.scene.sh_dc[res.editable], scene.sh_dc[~frozen_before])
    assert res.rounds[-1]["instruction"] == "make it red" and len(res.rounds) == 1


def test_optimizer_state_proportional_to_editable_count():
    scene = two_objects()
    sizes = {}
    for name, target in (("a", query_a()), ("ab", torch.ones(len(scene), dtype=torch.bool)),
                         ("few", torch.arange(len(scene)) < 7)):
        t = resolve_target(scene, target, tau=0.5)
        s = EditSession(scene, t, RecolorGuidance("red"), None, EditConfig(steps=2, **SMALL))
        s.step_once()
        sizes[name] = (t.count, s.optimizer_state_numel)
    per = 2 * (3 + 3 + 4 + 1 + 3)  # Adam's two moments of means, log-scales, quats, opacity, base colour
    for count, numel in sizes.values():
        assert numel == per * count
    assert sizes["few"][1] == per * 7


def test_relevance_scales_updates():
    scene = two_objects()
    w = torch.zeros(len(scene))
    w[:300] = 1.0
    w[:150] = 0.25
    res = edit(scene, w, RecolorGuidance("red"), steps=1, **SMALL)
    d = (res.scene.sh_dc - scene.sh_dc)[:300]
    # one Adam step moves each coordinate by lr * sign(g) (first step); scaled by the weight
    moved = d.abs()[d.abs() > 0]
    big, small = d[150:300].abs(), d[:150].abs()
    assert torch.allclose(small[small > 0], torch.full_like(small[small > 0], 0.25 * 1e-2), rtol=1e-3)
    assert torch.allclose(big[big > 0], torch.full_like(big[big > 0], 1e-2), rtol=1e-3)
    assert moved.numel() > 0


def test_densification_limits_and_inheritance():
    scene = two_objects()
    scene.opacity_logits[:5] = -8.0  # five transparent editable Gaussians: pruned at densification
    cfg = dict(SMALL, densify_every=2, densify_from=2, densify_until=6)
    t = resolve_target(scene, query_a(), tau=0.5)
    s = EditSession(scene, t, RecolorGuidance("red"), None, EditConfig(steps=6, **cfg))
    parent_lang = {tuple(r.tolist()) for r in scene.lang[t.mask]}
    records = [s.step_once() for _ in range(6)]
    dens = [r["densify"] for r in records if "densify" in r]
    assert len(dens) == 3
    for d in dens:
        grown = d["cloned"] + d["split"]  # a clone adds one Gaussian, a split replaces one by two
        assert 0 < grown <= math.floor(0.01 * d["editable_before"])
    assert dens[0]["pruned"] >= 5 and len(s.scene) == len(scene) - sum(d["pruned"] for d in dens) + sum(
        d["cloned"] + d["split"] for d in dens)
    out, w = s.result_scene()
    last = dens[-1]
    kids = slice(len(out) - last["cloned"] - 2 * last["split"], None)  # children are appended
    assert all(tuple(r.tolist()) in parent_lang for r in out.lang[kids])  # lang copied from a parent
    assert bool((w[kids] > 0).all()) and bool(s.opt.trainable_mask()[kids].all())
    assert s.optimizer_state_numel == 2 * 14 * s.opt.num_trainable


class _InterruptAt:
    """Wraps a guidance and raises KeyboardInterrupt at one step, like Ctrl-C."""

    def __init__(self, inner, at):
        self.inner, self.at, self.name, self.instruction = inner, at, inner.name, inner.instruction
        self.settings, self.generators, self.reset_caches = inner.settings, inner.generators, inner.reset_caches

    def grad(self, renders, views):
        if views.step == self.at:
            raise KeyboardInterrupt
        return self.inner.grad(renders, views)


def test_resume_after_interrupt_equals_uninterrupted(tmp_path):
    scene = two_objects()
    mask = resolve_target(scene, query_a(), tau=0.5).mask
    truth = _target_scene(scene, mask)
    cfg = dict(SMALL, densify_every=2, densify_from=2, steps=6)
    full = edit(scene, query_a(), IdealDenoiserGuidance(render_targets(truth), seed=3), tau=0.5, **cfg)
    ck = tmp_path / "edit.ckpt"
    with pytest.raises(KeyboardInterrupt):
        edit(scene, query_a(), _InterruptAt(IdealDenoiserGuidance(render_targets(truth), seed=3), 3),
             tau=0.5, checkpoint=ck, **cfg)
    assert ck.exists()
    res = edit(scene, query_a(), IdealDenoiserGuidance(render_targets(truth), seed=3), tau=0.5,
               checkpoint=ck, resume=True, **cfg)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest", "lang"):
        assert torch.equal(getattr(full.scene, name), getattr(res.scene, name)), name
    with pytest.raises(ValueError, match="another edit"):
        edit(scene, query_a(), RecolorGuidance("blue"), tau=0.5, checkpoint=ck, resume=True, **cfg)


def test_multi_round_keeps_records_and_language():
    scene = two_objects()
    r1 = edit(scene, query_a(), RecolorGuidance("make A red"), tau=0.5, steps=2, **SMALL)
    r2 = edit(r1.scene, torch.eye(8)[1], RecolorGuidance("make B gold"), tau=0.5, steps=2, **SMALL)
    assert [r["instruction"] for r in r2.rounds] == ["make A red", "make B gold"]
    assert r2.scene.lang is not None and r2.scene.lang.shape == (len(r2.scene), 8)


def test_errors():
    scene = two_objects()
    with pytest.raises(ValueError, match="selects no Gaussian"):
        edit(scene, torch.zeros(len(scene), dtype=torch.bool), RecolorGuidance("red"), **SMALL)
    no_lang = two_objects()
    no_lang.lang = None
    with pytest.raises(ValueError, match="no language features"):
        edit(no_lang, "the ball", RecolorGuidance("red"), **SMALL)


def test_view_pool_renders_originals_once_and_resumes_exactly(tmp_path, monkeypatch):
    """With ``view_pool=K`` the original renders are made once per pooled camera (not per step),
    every step's cameras come from the pool with their pool ids, and resume stays exact."""
    scene = two_objects()
    mask = resolve_target(scene, query_a(), tau=0.5).mask
    truth = _target_scene(scene, mask)
    calls = []
    original = EditSession._render_originals

    def counting(self, cams):
        calls.append(len(cams))
        return original(self, cams)

    monkeypatch.setattr(EditSession, "_render_originals", counting)
    seen = []

    class _Record(IdealDenoiserGuidance):
        def grad(self, renders, views):
            seen.append((views.cameras, views.view_ids.tolist()))
            return super().grad(renders, views)

    cfg = dict(SMALL, steps=8, view_pool=3)
    full = edit(scene, query_a(), _Record(render_targets(truth), seed=3), tau=0.5, **cfg)
    assert calls == [4, 4, 4]  # the pool, once; no render of originals per step
    sessions = EditSession(scene, resolve_target(scene, query_a(), tau=0.5), IdealDenoiserGuidance(
        render_targets(truth), seed=3), None, EditConfig(**cfg))
    pool = sessions.pool
    assert pool.originals.shape == (3, 4, 3, 48, 48) and pool.masks.shape == (3, 4, 1, 48, 48)
    for cams, ids in seen:
        k = ids[0] // 4
        assert ids == list(range(4 * k, 4 * k + 4))
        assert [c.viewmat.tolist() for c in cams] == [c.viewmat.tolist() for c in pool.cameras[k]]
    assert len({ids[0] for _, ids in seen}) > 1  # the steps draw different sets
    ck = tmp_path / "edit.ckpt"
    with pytest.raises(KeyboardInterrupt):
        edit(scene, query_a(), _InterruptAt(IdealDenoiserGuidance(render_targets(truth), seed=3), 5),
             tau=0.5, checkpoint=ck, **cfg)
    res = edit(scene, query_a(), IdealDenoiserGuidance(render_targets(truth), seed=3), tau=0.5,
               checkpoint=ck, resume=True, **cfg)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc"):
        assert torch.equal(getattr(full.scene, name), getattr(res.scene, name)), name
    with pytest.raises(ValueError, match="view_pool"):
        EditConfig(view_pool=-1)


def test_view_pool_zero_draws_fresh_views_every_step():
    """``view_pool=0``: the paper's rule (§3.2), 4 cameras re-drawn every step, no pool."""
    seen = []

    class _Record(RecolorGuidance):
        def grad(self, renders, views):
            seen.append((views.view_ids, tuple(c.viewmat.sum().item() for c in views.cameras)))
            return super().grad(renders, views)

    s = EditSession(two_objects(), resolve_target(two_objects(), query_a(), tau=0.5), _Record("red"),
                    None, EditConfig(**dict(SMALL, view_pool=0)))
    for _ in range(3):
        s.step_once()
    assert s.pool is None and all(ids is None for ids, _ in seen) and len({c for _, c in seen}) == 3


def test_step_renders_with_the_edit_raster_kernels():
    """The step's render hands the rasterizer the edit's kernel choices (tiger.edit.loop.
    EDIT_RASTER_KERNELS: one pixel per backward thread), read off the dispatched calls."""
    from torch.utils._python_dispatch import TorchDispatchMode

    from tiger.edit.loop import EDIT_RASTER_KERNELS

    calls = []

    class _Log(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if str(func) in ("tiger.rasterize.default", "tiger.rasterize_backward.default"):
                calls.append((str(func), args))
            return func(*args, **(kwargs or {}))

    s = EditSession(two_objects(), resolve_target(two_objects(), query_a(), tau=0.5), RecolorGuidance("red"),
                    None, EditConfig(**dict(SMALL, view_pool=0)))
    with _Log():
        s.step_once()
    k = EDIT_RASTER_KERNELS
    forward = [a for f, a in calls if f == "tiger.rasterize.default"]
    backward = [a for f, a in calls if f == "tiger.rasterize_backward.default"]
    assert forward and backward
    assert forward[-1][14:18] == k.op_args()  # (a trailing default such as tile_order is not dispatched)
    assert backward[-1][19:21] == (k.backward_channel_block, k.backward_pixels_per_thread) == (64, 1)
