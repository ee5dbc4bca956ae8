"""The view pool's fixed order and the prefetch of the next step's set: every step takes the set the
pool's order names, each new set is rendered and handed to the guidance's ``prepare`` once and
before its step's ``grad``, the prefetch changes no value (CPU; on CUDA, where it runs in a worker
thread on a side stream, beside the rounding of the same kernels), and InstructPix2Pix's and
MVDream's ``prepare`` fill the caches their steps read."""
import threading

import pytest
import torch

from tiger.edit import CSDGuidance, EditConfig, EditSession, resolve_target
from tiger.edit.guidance import RecolorGuidance, ViewBatch
from tiger.edit.guidance.base import prepare_guidance

from .scenes import query_a, two_objects

SMALL = dict(width=24, height=24, progress=False, densify_every=0)


class _Prepared(RecolorGuidance):
    """Recolour with a ``prepare`` that caches a device value per pooled view and a ``grad`` that
    reads it (so a step run before its set's preparation would fail), recording both calls."""

    def __init__(self) -> None:
        super().__init__("make it red")
        self.events: list[tuple] = []
        self.cache: dict[int, torch.Tensor] = {}

    def prepare(self, views: ViewBatch) -> list[torch.Tensor]:
        made = []
        for i, img in zip(views.view_ids.tolist(), views.originals):
            self.cache[i] = img.mean(dim=(1, 2))  # [3] on the scene's device
            made.append(self.cache[i])
        self.events.append(("prepare", views.step, views.view_ids.tolist(), threading.current_thread().name))
        return made

    def grad(self, renders, views):
        self.events.append(("grad", views.step, views.view_ids.tolist()))
        shade = torch.stack([self.cache[i] for i in views.view_ids.tolist()])  # KeyError if not prepared
        g, info = super().grad(renders, views)
        return g + 1e-3 * shade[:, :, None, None].to(g), info


def _session(guidance, **cfg) -> EditSession:
    scene = two_objects()
    return EditSession(scene, resolve_target(scene, query_a(), tau=0.5), guidance, None,
                       EditConfig(**{**SMALL, **cfg}))


def test_pool_order_is_fixed_by_the_seed():
    a, b = _session(RecolorGuidance("red"), view_pool=5, steps=40), _session(RecolorGuidance("red"), view_pool=5,
                                                                            steps=40)
    c = _session(RecolorGuidance("red"), view_pool=5, steps=40, seed=1)
    assert a.pool.order == b.pool.order and a.pool.order != c.pool.order
    assert len(a.pool.order) == 40 and set(a.pool.order) <= set(range(5)) and len(set(a.pool.order)) > 1


@pytest.mark.parametrize("prefetch", [True, False])
def test_each_step_takes_its_set_prepared_once_before_its_grad(prefetch):
    g = _Prepared()
    s = _session(g, view_pool=3, steps=10, prefetch_views=prefetch)
    for _ in range(10):
        s.step_once()
    grads = [e for e in g.events if e[0] == "grad"]
    assert [ids[0] // 4 for _, _, ids in grads] == s.pool.order  # step s takes order[s]
    prepared = [tuple(e[2]) for e in g.events if e[0] == "prepare"]
    assert len(prepared) == len(set(prepared)) == len(set(s.pool.order))  # each drawn set once
    for i, e in enumerate(g.events):
        if e[0] == "grad":  # its set was prepared earlier
            assert ("prepare", tuple(e[2])) in [(p[0], tuple(p[2])) for p in g.events[:i]]
    assert s._pending is None  # nothing prefetched past the last step


def test_prefetch_changes_no_value():
    out = {}
    for prefetch in (True, False):
        s = _session(_Prepared(), view_pool=3, steps=6, prefetch_views=prefetch)
        for _ in range(6):
            s.step_once()
        out[prefetch] = s.result_scene()[0]
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc"):
        assert torch.equal(getattr(out[True], name), getattr(out[False], name)), name
    assert "prefetch_views" not in EditConfig().to_dict()  # changes no value: not in the record


def test_csd_prepares_both_parts_and_guidances_without_prepare_are_skipped():
    a, b = _Prepared(), _Prepared()
    csd = CSDGuidance(a, b)
    views = ViewBatch(cameras=[], originals=torch.rand(4, 3, 8, 8), view_ids=torch.arange(4, 8))
    made = csd.prepare(views)
    assert len(made) == 8 and sorted(a.cache) == sorted(b.cache) == [4, 5, 6, 7]
    assert prepare_guidance(RecolorGuidance("red"), views) == []


def test_ip2p_prepare_fills_the_condition_cache(tiny_models, ring_cameras, monkeypatch):
    pytest.importorskip("diffusers")
    from tiger.edit.guidance import ip2p as ip2p_module
    from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p

    g = InstructPix2PixGuidance(load_ip2p(tiny_models / "instruct-pix2pix"), "make it red", short_side=16,
                                keep_text_encoder=True, generator=torch.Generator().manual_seed(0))
    originals = torch.rand(4, 3, 16, 16)
    views = ViewBatch(cameras=ring_cameras(size=(16, 16)), originals=originals, view_ids=torch.arange(4),
                      object_center=torch.zeros(3))
    assert g.prepare(ViewBatch(cameras=views.cameras, originals=originals)) == []  # fresh: encoded in the step
    made = g.prepare(views)
    want = ip2p_module.encode_latents(g.models.vae, ip2p_module.resize(originals, (16, 16)), None)
    assert len(made) == 4 and torch.allclose(torch.stack(made), want, atol=1e-6)
    calls = []
    monkeypatch.setattr(ip2p_module, "encode_latents", lambda *a: calls.append(1) or want)
    renders = torch.rand(4, 3, 16, 16)
    grad, _ = g.grad(renders, views)
    assert not calls and torch.isfinite(grad).all()  # the step read the prepared latents


def test_mvdream_prepare_caches_the_cameras(tiny_models, ring_cameras):
    pytest.importorskip("diffusers")
    from tiger.edit.guidance.mvdream import MVDreamGuidance, load_mvdream

    views = ViewBatch(cameras=ring_cameras(size=(16, 16)), originals=torch.rand(4, 3, 16, 16),
                      view_ids=torch.arange(4), object_center=torch.zeros(3))
    lazy = MVDreamGuidance(lambda: load_mvdream(tiny_models / "mvdream"), "a fox", image_size=16)
    assert lazy.prepare(views) == [] and not lazy.loaded  # not loaded by a (worker's) prepare
    g = MVDreamGuidance(load_mvdream(tiny_models / "mvdream"), "a fox", image_size=16, keep_text_encoder=True)
    made = g.prepare(views)
    assert len(made) == 1 and g.camera_conditions(views) is made[0]
    assert g.prepare(ViewBatch(cameras=views.cameras, originals=views.originals, object_center=torch.zeros(3))) == []


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_prefetch_runs_beside_and_equals_inline(tiny_models):
    """On CUDA the next set is prepared in the worker thread (a side stream): the pool's originals
    and InstructPix2Pix's cached condition latents equal the inline preparation's, and the tiny CSD
    edit ends near where the inline one ends (float32; the rasterizer's atomics and Adam make two
    runs of either differ slightly; a race would give other originals or latents)."""
    pytest.importorskip("diffusers")
    from tiger.edit.build import build_guidance

    scene = two_objects(n=150).to("cuda")
    target = resolve_target(scene, query_a().cuda(), tau=0.5)
    runs = {}
    for prefetch in (True, False):
        csd = build_guidance("ip2p+mvdream", "make it red", models=str(tiny_models), seed=0, device="cuda",
                             dtype=torch.float32, ip2p_kwargs={"short_side": 32}, mvdream_kwargs={"image_size": 32})
        seen = []
        inner = csd.ip2p.prepare

        def recording(views, inner=inner, seen=seen):
            seen.append(threading.current_thread().name)
            return inner(views)

        csd.ip2p.prepare = recording
        s = EditSession(scene, target, csd, None, EditConfig(**{**SMALL, "width": 32, "height": 32}, steps=8,
                                                             view_pool=3, prefetch_views=prefetch))
        for _ in range(8):
            s.step_once()
        torch.cuda.synchronize()
        runs[prefetch] = (s, csd, seen)
    (on, csd_on, seen_on), (off, csd_off, seen_off) = runs[True], runs[False]
    assert any(t.startswith("tiger-beside") for t in seen_on)
    assert all(not t.startswith("tiger-beside") for t in seen_off)
    assert on.pool.order == off.pool.order and on.pool.rendered == off.pool.rendered
    assert torch.equal(on.pool.originals, off.pool.originals) and torch.equal(on.pool.masks, off.pool.masks)
    cache_on, cache_off = csd_on.ip2p._cond_cache, csd_off.ip2p._cond_cache
    assert sorted(cache_on) == sorted(cache_off) and len(cache_on) == 4 * sum(on.pool.rendered)
    for key in cache_off:
        torch.testing.assert_close(cache_on[key], cache_off[key], rtol=1e-5, atol=1e-5)
    out_on, out_off = on.result_scene()[0], off.result_scene()[0]
    for name in ("means", "sh_dc", "opacity_logits"):
        a, b, start = getattr(out_on, name), getattr(out_off, name), getattr(scene, name)
        moved = float((b - start).abs().max())
        assert moved > 0 and float((a - b).abs().max()) <= 0.1 * moved, (name, float((a - b).abs().max()), moved)


class _FailingPrepare(_Prepared):
    def prepare(self, views):
        if views.step > 0:
            raise RuntimeError("prepare failed on purpose")
        return super().prepare(views)


def test_a_failed_prefetch_surfaces_at_its_step_and_never_hides_another_error():
    s = _session(_FailingPrepare(), view_pool=3, steps=10)
    with pytest.raises(RuntimeError, match="on purpose"):  # a later step's new set: at its join
        for _ in range(10):
            s.step_once()
    s = _session(_FailingPrepare(), view_pool=3, steps=10, prefetch_views=False)
    s.step_once()
    k = next(i for i in range(3) if not s.pool.rendered[i])
    s.pool.rendered[k] = True  # as a worker flags its set before a later failure would show

    def broken():
        raise RuntimeError("prefetch broke")

    s._pending = (k, broken)
    s.device = torch.device("cuda")  # where a worker may have started: the join waits for it (no CUDA work here)
    s._join_prefetch(quiet=True)  # at the loop's end: logged, the set left to be prepared again
    assert s._pending is None and not s.pool.rendered[k]


def test_an_unjoined_prefetch_is_dropped_at_the_loops_end_on_the_cpu():
    g = _Prepared()
    s = _session(g, view_pool=3, steps=10)
    s.step_once()
    k = next(i for i in range(3) if not s.pool.rendered[i])
    s._pending = (k, lambda: s._prepare_set(k, 1))  # as run_beside defers it off CUDA
    s._join_prefetch(quiet=True)
    assert s._pending is None and not s.pool.rendered[k]  # not rendered now; prepared when drawn
