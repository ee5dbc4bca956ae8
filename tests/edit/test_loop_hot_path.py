"""The edit step's own work: rendered in the frozen-then-editable layout (autograd over the
editable rows only) with the same images and gradients as the scene-order render, and no read-back
of device values outside densification."""
import traceback
from collections import Counter

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from tiger.edit import EditConfig, EditSession, resolve_target
from tiger.edit.guidance import RecolorGuidance
from tiger.edit.loop import device_cameras
from tiger.scene import render_views

from .scenes import query_a, two_objects

SMALL = dict(width=32, height=32, progress=False)

#: Operators that hand a tensor's value to the host (on CUDA: wait for the device).
READ_BACKS = {"aten._local_scalar_dense.default", "aten.nonzero.default", "aten.is_nonzero.default",
              "aten.equal.default", "aten.masked_select.default", "aten.unique.default", "aten._unique2.default"}


class ReadBackProbe(TorchDispatchMode):
    """Records each read-back operator with the innermost ``tiger/`` frame that issued it, except
    those of host-side work: camera sampling (float64 CPU tensors in every run), Adam's step counter
    (a CPU tensor on the CPU; CUDA's fused Adam keeps it on the device and never reads it) and the
    guidance's own diagnostics."""

    HOST_SIDE = ("tiger/edit/views.py", "torch/optim/", "tiger/edit/guidance/", "tiger/testing/")

    def __init__(self) -> None:
        super().__init__()
        self.hits: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func)
        bool_index = name == "aten.index.Tensor" and any(
            torch.is_tensor(i) and i.dtype == torch.bool for i in (args[1] or []))
        if name in READ_BACKS or bool_index:
            stack = traceback.extract_stack()
            inner = [f for f in stack if "/tiger/" in f.filename]
            host = any(any(h in f.filename for h in self.HOST_SIDE) for f in stack)
            if not host:
                where = f"{inner[-1].filename.split('/tiger/')[-1]}:{inner[-1].lineno}" if inner else "?"
                self.hits[(name, where)] += 1
        return func(*args, **(kwargs or {}))


def _session(view_pool=0, densify_every=3, steps=12):
    scene = two_objects()
    t = resolve_target(scene, query_a(), tau=0.5)
    return EditSession(scene, t, RecolorGuidance("make it red"), None,
                       EditConfig(steps=steps, view_pool=view_pool, densify_every=densify_every,
                                  densify_from=densify_every, **SMALL))


@pytest.mark.parametrize("view_pool", [0, 4])
def test_step_reads_nothing_back_outside_densification(view_pool):
    s = _session(view_pool)
    s.step_once()  # step 1; densification after steps 3, 6, ...
    probe = ReadBackProbe()
    with probe:
        rec = s.step_once()
    assert "densify" not in rec and not probe.hits, dict(probe.hits)
    s.step_once()
    with probe:
        rec = s.step_once()  # step 4: first step on a densified (re-laid-out) scene
    assert not probe.hits, dict(probe.hits)


def test_render_layout_equals_scene_order_render():
    """Frozen rows first, editable leaves behind: same images, same leaf gradients and the same
    screen-space gradients (mapped back to scene order) as rendering the scene in its own order."""
    s = _session(densify_every=2)
    for _ in range(4):  # densified twice: children appended, transparent ones pruned
        s.step_once()
    layout = s.render_layout()
    mask = s.opt.trainable_mask()
    assert layout.frozen_rows == int((~mask).sum())
    assert torch.equal(layout.order[layout.frozen_rows:], s.opt.trainable_index)
    assert all(not t.requires_grad for t in layout.frozen.values())
    cams = device_cameras(s.views.fixed(3), s.device, s.scene.dtype)
    g_color = torch.randn(3, 32, 32, 3, generator=torch.Generator().manual_seed(1))
    results = []
    for scene in (layout.scene(s.opt.leaves), s.opt.render_scene()):
        out = render_views(scene, cams, "rgb", background=s.background)
        out["means2d"].retain_grad()
        (out["color"] * g_color).sum().backward()
        grads = {n: p.grad.clone() for n, p in s.opt.leaves.items()}
        for p in s.opt.leaves.values():
            p.grad = None
        results.append((out["color"].detach(), grads, out["means2d"].grad, out["radii"]))
    (c_lay, g_lay, m_lay, r_lay), (c_ref, g_ref, m_ref, r_ref) = results
    torch.testing.assert_close(c_lay, c_ref, rtol=0, atol=1e-6)
    for n in g_ref:
        torch.testing.assert_close(g_lay[n], g_ref[n], rtol=1e-5, atol=1e-7, msg=n)
    torch.testing.assert_close(layout.to_scene_order(m_lay), m_ref, rtol=1e-5, atol=1e-8)
    assert torch.equal(layout.to_scene_order(r_lay), r_ref)


def test_autograd_graph_spans_editable_rows_only():
    """The leaves are the M editable rows; the rendered frozen rows carry no autograd history."""
    s = _session()
    rows = s.render_layout().scene(s.opt.leaves)
    F = s.render_layout().frozen_rows
    M = s.opt.num_trainable
    assert all(p.shape[0] == M for p in s.opt.leaves.values()) and F + M == len(s.scene)
    g = torch.autograd.grad(rows.scales.sum() + rows.opacities.sum() + rows.means.sum(),
                            [s.opt.leaves[n] for n in ("log_scales", "opacity_logits", "means")])
    assert all(x.shape[0] == M for x in g)
    frozen = s.scene.subset(~s.opt.trainable_mask())
    torch.testing.assert_close(rows.scales[:F], frozen.scales, rtol=0, atol=0)
    torch.testing.assert_close(rows.means[:F], frozen.means, rtol=0, atol=0)


def test_device_cameras_equal_casts_and_stay_put():
    s = _session()
    cams = s.views.fixed(4)
    moved = device_cameras(cams, s.device, torch.float32)
    for a, b in zip(cams, moved):
        assert torch.equal(b.viewmat, a.viewmat.float()) and torch.equal(b.K, a.K.float())
        assert (b.width, b.height, b.image_name) == (a.width, a.height, a.image_name)
        assert b.to(device=s.device, dtype=torch.float32) is b  # the renderer's cast: nothing to do


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_loop_parts_do_not_synchronise():
    """On CUDA the loop's own parts (cameras up, the layout's render scene, statistics, Adam with
    the relevance scaling, history) run with torch's sync debug mode set to error."""
    scene = two_objects().to("cuda")
    t = resolve_target(scene, query_a().cuda(), tau=0.5)
    s = EditSession(scene, t, RecolorGuidance("make it red"), None,
                    EditConfig(steps=8, densify_every=4, densify_from=4, **SMALL))
    s.step_once()
    layout = s.render_layout()
    cams = s.views.sample(torch.Generator().manual_seed(0))
    out = render_views(layout.scene(s.opt.leaves), device_cameras(cams, s.device, s.scene.dtype), "rgb",
                       background=s.background, check_finite=False)
    out["means2d"].retain_grad()
    out["color"].sum().backward()  # the rasterizer's own work is not the loop's
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        on_device = device_cameras(cams, s.device, s.scene.dtype)
        rows = layout.scene(s.opt.leaves)
        s.strategy.observe_grad(2, layout.to_scene_order(out["means2d"].grad), layout.to_scene_order(out["radii"]),
                                32, 32)
        s.opt.update()
        s.history.append({"step": 2, "loss": out["color"].detach().mean()})
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert on_device[0].viewmat.is_cuda and rows.means.is_cuda
    s.settle_history()
    assert isinstance(s.history[-1]["loss"], float)
