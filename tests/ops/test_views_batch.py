"""views=V of tiger::bin_gaussians and tiger::rasterize: V images in one call, each equal to its
own views=1 call (tile lists, pixels and gradients), opcheck with views, bad view counts."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.binning import bin_gaussians
from tiger.ops.raster import rasterize

from ..render.devices import CUDA_SKIP
from ..render.scenes import camera, random_scene
from .opargs import F64, ops

W, H = 37, 29  # not multiples of the 16-px tile: partial tiles at the right and bottom edges


def _views(v: int, n: int = 60, dtype=F64, seed: int = 0, device: str = "cpu"):
    """V projections of one scene (camera shifted per view, some Gaussians far larger than the
    image so they cover every tile of their view): per-view tuples (means2d, conics, depths,
    opacities, radii)."""
    m, q, s, o, _ = random_scene(n, 1, dtype=dtype, seed=seed, scale_range=(0.05, 0.4),
                                 opacity_range=(0.3, 0.9))
    s = s.clone()
    s[:3] *= 12.0  # straddle every border of the image (and so of the stacked images)
    out = []
    for k in range(v):
        V, K = camera(W, H, dtype=dtype)
        V = V.clone()
        V[0, 3] += 0.15 * k
        V[1, 3] -= 0.1 * k
        args = [t.to(device) for t in (m, q, s, o, V, K)]
        out.append(ops.project_gaussians(*args, W, H, 0.3, 0.01, 1e10, 1 / 255, False))
    return out


def _stack(per_view):
    return [torch.cat([p[i] for p in per_view]) for i in range(5)]


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("views", [1, 2, 5])
def test_binning_views_are_each_views_own_lists(dtype, views):
    per_view = _views(views, dtype=dtype)
    n = per_view[0][0].shape[0]
    m2, cn, d, op, r = _stack(per_view)
    to, ids = bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=views)
    tiles = ((W + 15) // 16) * ((H + 15) // 16)
    assert to.shape == (views * tiles + 1,)
    for v, (pm, pc, pd, po, pr) in enumerate(per_view):
        one_to, one_ids = bin_gaussians(pm, pc, po, pd, pr, W, H, 16, 1 / 255)
        seg = to[v * tiles:(v + 1) * tiles + 1]
        assert torch.equal(seg - seg[0], one_to), v
        assert torch.equal(ids[seg[0]:seg[-1]], one_ids + v * n), v
    assert int(to[-1]) == ids.numel() > 0


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("views", [1, 2, 5])
def test_rasterize_views_are_each_views_own_image_and_gradients(dtype, views):
    per_view = _views(views, dtype=dtype, seed=1)
    n = per_view[0][0].shape[0]
    g = torch.Generator().manual_seed(2)
    cols = torch.rand(views * n, 4, generator=g, dtype=dtype)
    bg = torch.rand(4, generator=g, dtype=dtype)
    w_col = torch.rand(views * H, W, 4, generator=g, dtype=dtype)
    w_a, w_d = torch.rand(views * H, W, generator=g, dtype=dtype), torch.rand(views * H, W, generator=g, dtype=dtype)

    def run(m2, cn, d, op, r, c, b, v, rows):
        leaves = [t.detach().clone().requires_grad_(True) for t in (m2, cn, op, c, d, b)]
        to, ids = bin_gaussians(leaves[0], leaves[1], leaves[2], leaves[4], r, W, H, 16, 1 / 255, views=v)
        color, alpha, depth, cnt, trans = rasterize(*leaves[:5], leaves[5], to, ids, W, H, 16, 0.99,
                                                    1 / 255, 1e-4, views=v)
        loss = ((color * w_col[rows]).sum() + (alpha * w_a[rows]).sum() + (depth * w_d[rows]).sum())
        loss.backward()
        return (color, alpha, depth, cnt, trans), [t.grad for t in leaves]

    m2, cn, d, op, r = _stack(per_view)
    outs, grads = run(m2, cn, d, op, r, cols, bg, views, slice(None))
    assert outs[0].shape == (views * H, W, 4)
    bg_grad = torch.zeros_like(bg)
    for v, (pm, pc, pd, po, pr) in enumerate(per_view):
        rows, ids = slice(v * H, (v + 1) * H), slice(v * n, (v + 1) * n)
        one, one_grads = run(pm, pc, pd, po, pr, cols[ids], bg, 1, rows)
        for k, (a, b) in enumerate(zip(outs, one)):
            assert torch.equal(a[rows], b), (v, k)
        for k in range(5):  # per-Gaussian gradients: the same sums in the same order
            assert torch.equal(grads[k][ids], one_grads[k]), (v, k)
        bg_grad += one_grads[5]
    # the background's gradient sums over the views' tiles in another order: float rounding
    tol = 1e-12 if dtype == F64 else 1e-5
    torch.testing.assert_close(grads[5], bg_grad, rtol=tol, atol=tol)
    assert float(outs[1].detach().max()) > 0.5  # something is drawn


def test_views_opcheck():
    per_view = _views(3, n=12)
    m2, cn, d, op, r = _stack(per_view)
    torch.library.opcheck(ops.bin_gaussians.default, (m2, cn, op, d, r, W, H, 16, 1 / 255),
                          {"views": 3}, test_utils=("test_schema", "test_faketensor"))
    to, ids = ops.bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=3)
    cols = torch.rand(m2.shape[0], 3, dtype=F64)
    bg = torch.rand(3, dtype=F64)
    args = (m2, cn, op, cols, d, bg, to, ids, W, H, 16, 0.99, 1 / 255, 1e-4)
    torch.library.opcheck(ops.rasterize.default, args, {"views": 3})
    _, _, _, cnt, tr = ops.rasterize(*args, views=3)
    vc, va, vd = torch.rand(3 * H, W, 3, dtype=F64), torch.rand(3 * H, W, dtype=F64), torch.rand(3 * H, W, dtype=F64)
    torch.library.opcheck(ops.rasterize_backward.default, (*args, tr, cnt, vc, va, vd), {"views": 3})
    torch.library.opcheck(ops.rasterize_backward_colors.default,
                          (m2, cn, op, to, ids, W, H, 16, 0.99, 1 / 255, 1e-4, cnt, vc), {"views": 3})


def test_views_gradcheck():
    per_view = _views(2, n=6, seed=3)
    m2, cn, d, op, r = _stack(per_view)
    to, ids = ops.bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=2)
    cols = torch.rand(m2.shape[0], 2, dtype=F64)
    bg = torch.rand(2, dtype=F64)
    ins = [t.clone().requires_grad_(True) for t in (m2, cn, op, cols, d, bg)]

    def f(a, b, c, e, g, h):
        out = rasterize(a, b, c, e, g, h, to, ids, W, H, 16, 0.99, 1 / 255, 1e-4, views=2)
        return out[0], out[1], out[2]

    assert torch.autograd.gradcheck(f, ins, eps=1e-7, atol=1e-6, rtol=1e-5)


def test_bad_view_counts_are_named():
    m2, cn, d, op, r = _stack(_views(2, n=7))
    with pytest.raises(RuntimeError, match="views=3 must divide the number of Gaussians \\(14\\)"):
        bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=3)
    with pytest.raises(RuntimeError, match="views must be at least 1"):
        bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=0)
    to, ids = bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=2)
    with pytest.raises(RuntimeError, match="tile_offsets"):  # lists of 2 images, 1 image drawn
        rasterize(m2, cn, op, torch.rand(14, 3, dtype=F64), d, None, to, ids, W, H, 16, 0.99, 1 / 255, 1e-4)


@pytest.mark.cuda
@CUDA_SKIP
def test_cuda_kernels_draw_one_image_per_call():
    """The CUDA kernels take views=1 only (render_views loops over the views there)."""
    m2, cn, d, op, r = [t.cuda() for t in _stack(_views(2, n=7))]
    with pytest.raises(RuntimeError, match="not implemented on CUDA"):
        bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=2)
    to, ids = bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255)
    to2 = torch.cat([to, to[1:] + to[-1]])
    with pytest.raises(RuntimeError, match="not implemented on CUDA"):
        rasterize(m2, cn, op, torch.rand(14, 3, dtype=F64, device="cuda"), d, None, to2, ids, W, H, 16,
                  0.99, 1 / 255, 1e-4, views=2)
