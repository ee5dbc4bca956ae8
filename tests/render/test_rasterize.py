"""tiger.rasterize_gaussians against the float64 dense reference (forward and gradients)."""
from __future__ import annotations

import pytest
import torch

import tiger
from tiger.render.reference import render_ref

from .devices import DEVICES
from .scenes import camera, random_scene

F64 = torch.float64
NAMES = ("means", "quats", "scales", "opacities", "colors", "viewmat", "K", "background")


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().double(), b.detach().double()
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


def _inputs(n, c, w, h, dtype, seed=0, sh_degree=None, device="cpu", **kw):
    m, q, s, o, col = random_scene(n, c, dtype=F64, seed=seed, **kw)
    if sh_degree is not None:
        g = torch.Generator().manual_seed(seed + 7)
        col = 0.4 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=F64)
    V, K = camera(w, h)
    bg = torch.rand(3 if sh_degree is not None else c, generator=torch.Generator().manual_seed(seed),
                    dtype=F64)
    return [t.to(dtype).to(device) for t in (m, q, s, o, col, V, K, bg)]


def _loss(out, seed=11):
    g = torch.Generator().manual_seed(seed)
    wc = torch.randn(out["color"].shape, generator=g, dtype=F64).to(out["color"].device, out["color"].dtype)
    wa = torch.randn(out["alpha"].shape, generator=g, dtype=F64).to(out["color"].device, out["color"].dtype)
    wd = torch.randn(out["depth"].shape, generator=g, dtype=F64).to(out["color"].device, out["color"].dtype)
    return (out["color"] * wc).sum() + (out["alpha"] * wa).sum() + (out["depth"] * wd).sum()


def _grads(fn, tensors, w, h, **kw):
    leaves = [t.detach().clone().requires_grad_() for t in tensors]
    out = fn(*leaves[:7], w, h, background=leaves[7], **kw)
    _loss(out).backward()
    return out, [t.grad for t in leaves]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("channels", [1, 3, 64, 67])
def test_forward_float64_matches_reference(channels, device):
    w, h = 48, 40
    ins = _inputs(400, channels, w, h, F64, seed=channels, device=device)
    out = tiger.rasterize_gaussians(*ins[:7], w, h, background=ins[7])
    ref = render_ref(*ins[:7], w, h, background=ins[7])
    assert out["n_isects"] > 0
    for key in ("color", "alpha", "depth"):
        assert rel(out[key], ref[key]) <= 1e-10, key


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("sh_degree", [None, 0, 1, 3])
@pytest.mark.parametrize("device", DEVICES)
def test_gradients_float64_match_reference(antialiased, sh_degree, device):
    w, h = 40, 32
    ins = _inputs(200, 5, w, h, F64, seed=3, sh_degree=sh_degree, device=device)
    kw = dict(antialiased=antialiased, sh_degree=sh_degree)
    out, g = _grads(tiger.rasterize_gaussians, ins, w, h, **kw)
    ref, g_ref = _grads(render_ref, ins, w, h, **kw)
    assert rel(out["color"], ref["color"]) <= 1e-10
    for name, a, b in zip(NAMES, g, g_ref):
        assert rel(a, b) <= 1e-10, name


@pytest.mark.parametrize("device", DEVICES)
def test_float32_on_1k_scene_within_tolerances(device):
    """SPEC acceptance: float32 kernels vs float64 reference, forward <= 1e-5, grads <= 1e-4."""
    w, h = 64, 64
    ins64 = _inputs(1000, 67, w, h, F64, seed=5, device=device)
    ins32 = [t.float() for t in ins64]
    out, g = _grads(tiger.rasterize_gaussians, ins32, w, h)
    ref, g_ref = _grads(render_ref, ins64, w, h)
    for key in ("color", "alpha", "depth"):
        assert rel(out[key], ref[key]) <= 1e-5, key
    for name, a, b in zip(NAMES, g, g_ref):
        assert rel(a, b) <= 1e-4, name


@pytest.mark.parametrize("tile_size", [16, 13, 5])
def test_float32_cpu_vector_paths_on_ragged_tiles(tile_size):
    """The CPU float32 kernels evaluate alpha 8 pixels at a time and sum channels in vector
    blocks (64 + 3 channels here): ragged edge tiles and odd tile sizes exercise the short
    blocks. Forward, full and features-only gradients against the float64 reference."""
    w, h = 45, 37
    ins64 = _inputs(600, 67, w, h, F64, seed=tile_size)
    ins32 = [t.float() for t in ins64]
    out, g = _grads(tiger.rasterize_gaussians, ins32, w, h, tile_size=tile_size)
    ref, g_ref = _grads(render_ref, ins64, w, h)
    for key in ("color", "alpha", "depth"):
        assert rel(out[key], ref[key]) <= 1e-5, key
    for name, a, b in zip(NAMES, g, g_ref):
        assert rel(a, b) <= 1e-4, name
    # Features-only: only colours and background require grad.
    leaves = [t.detach().clone().requires_grad_(i in (4, 7)) for i, t in enumerate(ins32)]
    out_f = tiger.rasterize_gaussians(*leaves[:7], w, h, background=leaves[7], tile_size=tile_size)
    _loss(out_f).backward()
    assert rel(leaves[4].grad, g_ref[4]) <= 1e-4
    assert rel(leaves[7].grad, g_ref[7]) <= 1e-4


@pytest.mark.parametrize("device", DEVICES)
def test_outputs_and_radii(device):
    w, h = 32, 24
    ins = _inputs(50, 3, w, h, F64, seed=9, device=device)
    out = tiger.rasterize_gaussians(*ins[:7], w, h)
    assert out["color"].shape == (h, w, 3) and out["alpha"].shape == (h, w)
    assert out["depth"].shape == (h, w) and out["radii"].shape == (50,)
    assert out["radii"].dtype == torch.int32
    ref = render_ref(*ins[:7], w, h)
    # Culled Gaussians (radius 0) are exactly those invalid or entirely off screen.
    assert bool((out["radii"][~ref["valid"]] == 0).all())
    # Without background the colour is the alpha-weighted sum: bounded by alpha * max colour.
    assert bool((out["color"].amax(-1) <= out["alpha"] * ins[4].max() + 1e-12).all())


@pytest.mark.parametrize("device", DEVICES)
def test_means2d_gradient_available_for_densification(device):
    w, h = 32, 32
    ins = _inputs(60, 3, w, h, F64, seed=2, device=device)
    means = ins[0].clone().requires_grad_()
    out = tiger.rasterize_gaussians(means, *ins[1:7], w, h)
    out["means2d"].retain_grad()
    out["color"].sum().backward()
    g2 = out["means2d"].grad
    assert g2.shape == (60, 2) and bool(g2.abs().sum() > 0)
    assert bool((g2[out["radii"] == 0] == 0).all())


@pytest.mark.parametrize("device", DEVICES)
def test_background_only_where_transparent(device):
    w, h = 16, 16
    ins = _inputs(0, 3, w, h, F64, device=device)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=F64, device=device)
    out = tiger.rasterize_gaussians(*ins[:7], w, h, background=bg)
    assert torch.allclose(out["color"], bg.expand(h, w, 3))
    assert bool((out["alpha"] == 0).all()) and bool((out["depth"] == 0).all())
