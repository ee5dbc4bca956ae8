"""tiger::render_forward (the no-gradient render in one call) against the op-by-op render: the
same values bit for bit, every output; which path a render takes; opcheck."""
from __future__ import annotations

import pytest
import torch

import tiger
from tiger.render import rasterize as raster_mod
from tiger.render.rasterize import RasterSettings, composite, project_for_raster

from .devices import DEVICES
from .scenes import camera, random_scene

F64, F32 = torch.float64, torch.float32


def _inputs(device, dtype, c=3, sh_degree=None, n=300, w=52, h=40, seed=2):
    m, q, s, o, col = random_scene(n, c, dtype=F64, seed=seed, scale_range=(0.03, 0.25))
    V, K = camera(w, h)
    g = torch.Generator().manual_seed(seed)
    if sh_degree is not None:
        col = 0.4 * torch.randn(n, (sh_degree + 1) ** 2 + 1, 3, generator=g, dtype=F64)
    bg = torch.rand(3 if sh_degree is not None else c, generator=g, dtype=F64)
    return [t.to(device, dtype) for t in (m, q, s, o, col, V, K, bg)], w, h


def _op_by_op(m, q, s, o, col, V, K, w, h, **kw):
    settings = RasterSettings(check_finite=False)
    p = project_for_raster(m, q, s, o, col, V, K, w, h, settings=settings, **kw)
    return composite(p, w, h, settings)


def _check_same(got, want):
    assert set(got) == set(want)
    for k in want:
        if k == "n_isects":
            assert got[k] == want[k] > 0
        else:
            assert got[k].dtype == want[k].dtype and torch.equal(got[k], want[k]), k


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("case", ["rgb", "rgb+bg", "five channels", "sh0", "sh1+rest", "sh3+rest"])
def test_one_call_equals_the_op_by_op_render(device, dtype, case):
    sh = {"sh0": 0, "sh1+rest": 1, "sh3+rest": 3}.get(case)
    (m, q, s, o, col, V, K, bg), w, h = _inputs(device, dtype, c=5 if case == "five channels" else 3,
                                                 sh_degree=sh)
    kw = {"background": bg if case != "rgb" else None}
    if sh is not None:
        kw["sh_degree"] = sh
        if "rest" in case:  # DC and higher bands as a scene stores them
            kw["sh_rest"] = col[:, 1:]
            col = col[:, :1]
    with torch.no_grad():
        want = _op_by_op(m, q, s, o, col, V, K, w, h, **kw)
        got = tiger.rasterize_gaussians(m, q, s, o, col, V, K, w, h, check_finite=False, **kw)
    _check_same(got, want)


@pytest.mark.parametrize("device", DEVICES)
def test_half_precision_channels(device):
    (m, q, s, o, col, V, K, bg), w, h = _inputs(device, F32, c=8)
    for half in (torch.float16, torch.bfloat16):
        with torch.no_grad():
            want = _op_by_op(m, q, s, o, col.to(half), V, K, w, h, background=bg)
            got = tiger.rasterize_gaussians(m, q, s, o, col.to(half), V, K, w, h, background=bg,
                                            check_finite=False)
        _check_same(got, want)


def test_which_path_a_render_takes(monkeypatch):
    """No gradient recorded (no_grad, or no input requiring one): one render_forward call; an input
    that requires grad: op by op, with gradients."""
    (m, q, s, o, col, V, K, bg), w, h = _inputs("cpu", F64)
    calls = []
    real = raster_mod.render_forward
    monkeypatch.setattr(raster_mod, "render_forward", lambda *a, **k: calls.append(1) or real(*a, **k))
    tiger.rasterize_gaussians(m, q, s, o, col, V, K, w, h)
    with torch.no_grad():
        tiger.rasterize_gaussians(m, q, s, o, col.requires_grad_(), V, K, w, h)
    assert len(calls) == 2
    out = tiger.rasterize_gaussians(m, q, s, o, col, V, K, w, h)
    assert len(calls) == 2 and out["color"].requires_grad
    out["color"].sum().backward()
    assert col.grad is not None and col.grad.abs().sum() > 0


def test_bad_inputs_get_the_same_errors():
    (m, q, s, o, col, V, K, bg), w, h = _inputs("cpu", F64)
    with torch.no_grad(), pytest.raises(ValueError, match=r"quats must have shape \[300, 4\]"):
        tiger.rasterize_gaussians(m, q[:, :3], s, o, col, V, K, w, h)
    with torch.no_grad(), pytest.raises(ValueError, match=r"opacities\[0\].*outside \[0, 1\]"):
        tiger.rasterize_gaussians(m, q, s, o + 2, col, V, K, w, h)


@pytest.mark.parametrize("device", DEVICES)
def test_opcheck(device):
    (m, q, s, o, col, V, K, bg), w, h = _inputs(device, F32, n=60)
    args = (m, q, s, o, col, None, -1, bg, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False, 16, 0.99, 1e-4)
    torch.library.opcheck(torch.ops.tiger.render_forward.default, args,
                          test_utils=("test_schema", "test_faketensor"))
    sh = torch.randn(60, 4, 3, device=device)
    args = (m, q, s, o, sh, None, 1, bg, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False, 16, 0.99, 1e-4)
    torch.library.opcheck(torch.ops.tiger.render_forward.default, args,
                          test_utils=("test_schema", "test_faketensor"))
    with pytest.raises(RuntimeError, match="sh_degree must be -1"):
        torch.ops.tiger.render_forward(*args[:6], 4, *args[7:])


def test_fake_kernel_defaults_are_the_schema_defaults():
    """The fake kernel repeats the kernel choices' defaults that csrc/render/ops.cpp writes into the
    schema (from binning_choices.h and raster.h)."""
    import inspect

    from tiger.ops import render as render_ops

    schema = torch.ops.tiger.render_forward.default._schema
    defaults = {a.name: a.default_value for a in schema.arguments if a.has_default_value()}
    fake = inspect.signature(render_ops._render_forward_fake).parameters
    assert defaults and defaults == {k: fake[k].default for k in defaults}
