"""views=V of tiger::bin_gaussians and tiger::rasterize: V images in one call, each equal to its
own views=1 call (tile lists, pixels and gradients), opcheck with views, bad view counts; on
CUDA (both binning paths, every walker, both backward kernels and their kernel choices) the
same, with the gradients equal up to the atomics' summation order."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.binning import bin_gaussians
from tiger.ops.raster import rasterize

from ..render.devices import CUDA_SKIP
from ..render.scenes import camera, random_scene
from .opargs import F64, ops

W, H = 37, 29  # not multiples of the 16-px tile: partial tiles at the right and bottom edges


def _views(v: int, n: int = 60, dtype=F64, seed: int = 0, device: str = "cpu", w: int = W, h: int = H):
    """V projections of one scene into w x h images (camera shifted per view, some Gaussians far
    larger than the image so they cover every tile of their view): per-view tuples (means2d,
    conics, depths, opacities, radii)."""
    m, q, s, o, _ = random_scene(n, 1, dtype=dtype, seed=seed, scale_range=(0.05, 0.4),
                                 opacity_range=(0.3, 0.9))
    s = s.clone()
    s[:3] *= 12.0  # straddle every border of the image (and so of the stacked images)
    out = []
    for k in range(v):
        V, K = camera(w, h, dtype=dtype)
        V = V.clone()
        V[0, 3] += 0.15 * k
        V[1, 3] -= 0.1 * k
        args = [t.to(device) for t in (m, q, s, o, V, K)]
        out.append(ops.project_gaussians(*args, w, h, 0.3, 0.01, 1e10, 1 / 255, False))
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


# -- CUDA: the same contract, checked against per-view CUDA calls and the CPU's lists ---------

CW, CH = 203, 149  # 13 x 10 tiles per view: the large Gaussians go to the warp and block walkers


@pytest.mark.cuda
@CUDA_SKIP
@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("views", [1, 2, 5])
@pytest.mark.parametrize("choice", [dict(path="tiles"), dict(path="global"),
                                    dict(path="global", giant_tiles=40), dict(path="tiles", _serial=True),
                                    dict(path="tiles", block_sort_keys=64, warp_sort_keys=8)])
def test_cuda_binning_views_are_each_views_own_lists(dtype, views, choice):
    """Batched CUDA lists = per-view CUDA lists (ids offset) = the CPU's batched lists, for every
    path and walker (giant_tiles=40: block walks; small sort classes: merged runs)."""
    from tiger.ops.binning import BinningSettings

    settings = BinningSettings(**choice)
    per_view = _views(views, n=300, dtype=dtype, seed=4, device="cuda", w=CW, h=CH)
    n = per_view[0][0].shape[0]
    m2, cn, d, op, r = _stack(per_view)
    to, ids = bin_gaussians(m2, cn, op, d, r, CW, CH, 16, 1 / 255, settings, views=views)
    tiles = ((CW + 15) // 16) * ((CH + 15) // 16)
    assert to.shape == (views * tiles + 1,) and to.is_cuda
    for v, (pm, pc, pd, po, pr) in enumerate(per_view):
        one_to, one_ids = bin_gaussians(pm, pc, po, pd, pr, CW, CH, 16, 1 / 255, settings)
        seg = to[v * tiles:(v + 1) * tiles + 1]
        assert torch.equal(seg - seg[0], one_to), v
        assert torch.equal(ids[seg[0]:seg[-1]], one_ids + v * n), v
    cpu_to, cpu_ids = bin_gaussians(*[t.cpu() for t in (m2, cn, op, d, r)], CW, CH, 16, 1 / 255, views=views)
    assert torch.equal(to.cpu(), cpu_to) and torch.equal(ids.cpu(), cpu_ids)
    assert int((r[:, 0] > 0).sum()) > 0 and ids.numel() > views * tiles  # a full scene, not an empty one


def _cuda_raster_case(views: int, dtype, channels: int, cdtype=None):
    per_view = _views(views, n=300, dtype=dtype, seed=7, device="cuda", w=CW, h=CH)
    n = per_view[0][0].shape[0]
    g = torch.Generator().manual_seed(8)
    cols = torch.rand(views * n, channels, generator=g, dtype=dtype).cuda()
    if cdtype is not None:
        cols = cols.to(cdtype)
    bg = torch.rand(channels, generator=g, dtype=dtype).cuda()
    w_col = torch.rand(views * CH, CW, channels, generator=g, dtype=dtype).cuda()
    w_a = torch.rand(views * CH, CW, generator=g, dtype=dtype).cuda()
    w_d = torch.rand(views * CH, CW, generator=g, dtype=dtype).cuda()
    return per_view, n, cols, bg, w_col, w_a, w_d


@pytest.mark.cuda
@CUDA_SKIP
@pytest.mark.parametrize("views", [1, 2, 5])
@pytest.mark.parametrize("dtype,channels,kernels,cdtype", [
    (torch.float32, 3, {}, None),                                      # two pixels per backward thread
    (torch.float32, 3, dict(backward_pixels_per_thread=1), None),      # one pixel per thread
    (torch.float32, 67, {}, None),                                     # a 64-channel block + a tail
    (torch.float32, 40, dict(forward_channel_block=32, backward_channel_block=32,
                             colors_channel_block=32), None),          # 32-channel blocks + a tail
    (torch.float32, 8, {}, torch.float16),                             # half-precision colour storage
    (F64, 5, {}, None),                                                # float64: 8-channel blocks
])
@pytest.mark.parametrize("features_only", [False, True])
def test_cuda_rasterize_views_are_each_views_own_image_and_gradients(views, dtype, channels, kernels,
                                                                      cdtype, features_only):
    """views=V on CUDA: every output of image v bit-identical to a views=1 CUDA call on block v;
    the gradients (full and features-only backward) equal to the atomics' rounding."""
    from tiger.ops.raster import RasterKernelSettings

    ks = RasterKernelSettings(**kernels)
    per_view, n, cols, bg, w_col, w_a, w_d = _cuda_raster_case(views, dtype, channels, cdtype)

    def run(m2, cn, d, op, r, c, v, rows):
        geometry = not features_only
        leaves = [t.detach().clone().requires_grad_(geometry or k in (3, 5))
                  for k, t in enumerate((m2, cn, op, c, d, bg))]
        to, ids = bin_gaussians(leaves[0], leaves[1], leaves[2], leaves[4], r, CW, CH, 16, 1 / 255, views=v)
        outs = rasterize(*leaves[:5], leaves[5], to, ids, CW, CH, 16, 0.99, 1 / 255, 1e-4, ks, views=v)
        color, alpha, depth = outs[:3]
        loss = (color * w_col[rows]).sum()
        if geometry:
            loss = loss + (alpha * w_a[rows]).sum() + (depth * w_d[rows]).sum()
        loss.backward()
        return outs, [t.grad for t in leaves]

    m2, cn, d, op, r = _stack(per_view)
    outs, grads = run(m2, cn, d, op, r, cols, views, slice(None))
    assert outs[0].shape == (views * CH, CW, channels)
    tol = 1e-10 if dtype == F64 else (1e-2 if cdtype is not None else 1e-4)
    bg_grad = torch.zeros_like(bg)
    for v, (pm, pc, pd, po, pr) in enumerate(per_view):
        rows, ids = slice(v * CH, (v + 1) * CH), slice(v * n, (v + 1) * n)
        one, one_grads = run(pm, pc, pd, po, pr, cols[ids], 1, rows)
        for k, (a, b) in enumerate(zip(outs, one)):
            assert torch.equal(a[rows], b), (v, k)  # the same sums in the same order
        for k in range(5):
            if one_grads[k] is None:
                assert grads[k] is None, k
                continue
            scale = float(one_grads[k].abs().max().clamp_min(1e-30))
            torch.testing.assert_close(grads[k][ids], one_grads[k], rtol=tol, atol=tol * scale,
                                       msg=f"view {v} input {k}")
        bg_grad += one_grads[5]
    torch.testing.assert_close(grads[5], bg_grad, rtol=tol, atol=tol * float(bg_grad.abs().max()))
    assert float(outs[1].detach().max()) > 0.5  # something is drawn
    assert grads[3].abs().max() > 0 and (features_only or grads[0].abs().max() > 0)


@pytest.mark.cuda
@CUDA_SKIP
def test_cuda_views_bad_inputs_are_named():
    """The CUDA ops refuse what the CPU ops refuse: a view count that does not divide the
    Gaussians, views < 1, tile lists of another number of images, per-pixel gradients of the
    wrong stacked height."""
    m2, cn, d, op, r = [t.cuda() for t in _stack(_views(2, n=7))]
    with pytest.raises(RuntimeError, match="views=3 must divide the number of Gaussians \\(14\\)"):
        bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=3)
    with pytest.raises(RuntimeError, match="views must be at least 1"):
        bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=0)
    to, ids = bin_gaussians(m2, cn, op, d, r, W, H, 16, 1 / 255, views=2)
    cols = torch.rand(14, 3, dtype=F64, device="cuda")
    with pytest.raises(RuntimeError, match="tile_offsets"):  # lists of 2 images, 1 image drawn
        rasterize(m2, cn, op, cols, d, None, to, ids, W, H, 16, 0.99, 1 / 255, 1e-4)
    _, _, _, cnt, tr = ops.rasterize(m2, cn, op, cols, d, None, to, ids, W, H, 16, 0.99, 1 / 255, 1e-4,
                                     views=2)
    assert cnt.shape == (2 * H, W)
    with pytest.raises(RuntimeError, match="v_color"):  # one image's gradient for two images
        ops.rasterize_backward(m2, cn, op, cols, d, None, to, ids, W, H, 16, 0.99, 1 / 255, 1e-4, tr, cnt,
                               torch.rand(H, W, 3, dtype=F64, device="cuda"), None, None, views=2)
    with pytest.raises(RuntimeError, match="v_color"):
        ops.rasterize_backward_colors(m2, cn, op, to, ids, W, H, 16, 0.99, 1 / 255, 1e-4, cnt,
                                      torch.rand(H, W, 3, dtype=F64, device="cuda"), views=2)
