"""tiger::rasterize's ``trainable`` mask: the backward adds gradients only for the trainable
Gaussians. Their gradients equal the full backward's (CPU: bit for bit; CUDA: up to the
atomics' order), the frozen ones get zeros, for the full and the features-only backward, with
stacked views, and through render_views; a bad mask is named."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.binning import bin_gaussians
from tiger.ops.raster import RasterKernelSettings, rasterize

from ..render.devices import DEVICES
from .opargs import F64
from .test_views_batch import CH, CW, _stack, _views


def _grads(per_view, views, cols, bg, trainable, features_only, kernels, device):
    m2, cn, d, op, r = _stack(per_view)
    leaves = [t.detach().clone().requires_grad_(not features_only or k in (3, 5))
              for k, t in enumerate((m2, cn, op, cols, d, bg))]
    to, ids = bin_gaussians(leaves[0], leaves[1], leaves[2], leaves[4], r, CW, CH, 16, 1 / 255, views=views)
    color, alpha, depth, _, _ = rasterize(*leaves[:5], leaves[5], to, ids, CW, CH, 16, 0.99, 1 / 255, 1e-4,
                                          kernels, views=views, trainable=trainable)
    g = torch.Generator().manual_seed(3)
    loss = (color * torch.rand(color.shape, generator=g, dtype=color.dtype).to(device)).sum()
    if not features_only:
        loss = loss + (alpha * torch.rand(alpha.shape, generator=g, dtype=alpha.dtype).to(device)).sum() \
            + 0.1 * depth.sum()
    loss.backward()
    return color.detach(), [t.grad for t in leaves]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("views", [1, 3])
@pytest.mark.parametrize("features_only", [False, True])
@pytest.mark.parametrize("kernels", [RasterKernelSettings(), RasterKernelSettings(backward_pixels_per_thread=1)],
                         ids=["2px", "1px"])
@pytest.mark.parametrize("share", [0.3, 0.03])  # 3 %: most tiles have none, the rest few (the CUDA walk's early stop)
def test_trainable_mask_keeps_the_trainable_gradients_and_zeroes_the_frozen(device, dtype, views,
                                                                            features_only, kernels, share):
    per_view = _views(views, n=200, dtype=dtype, seed=9, device=device, w=CW, h=CH)
    n = views * per_view[0][0].shape[0]
    g = torch.Generator().manual_seed(10)
    cols = torch.rand(n, 3, generator=g, dtype=dtype).to(device)
    bg = torch.rand(3, generator=g, dtype=dtype).to(device)
    trainable = (torch.rand(n, generator=g) < share).to(device)
    trainable[:3] = False  # the large Gaussians (every tile) frozen: they shape the others' gradients
    color_all, full = _grads(per_view, views, cols, bg, None, features_only, kernels, device)
    color_some, masked = _grads(per_view, views, cols, bg, trainable, features_only, kernels, device)
    assert torch.equal(color_all, color_some)  # the forward ignores the mask
    tol = 1e-12 if dtype == F64 else 2e-5
    for k, (a, b) in enumerate(zip(full, masked)):
        if a is None:
            assert b is None, k
            continue
        if k == 5:  # the background's gradient does not depend on the mask
            torch.testing.assert_close(b, a, rtol=tol, atol=tol * float(a.abs().max()))
            continue
        assert a[trainable].abs().max() > 0, k
        assert not b[~trainable].any(), f"input {k}: frozen Gaussians got gradients"
        if device == "cpu":
            assert torch.equal(b[trainable], a[trainable]), k
        else:
            torch.testing.assert_close(b[trainable], a[trainable], rtol=tol,
                                       atol=tol * float(a.abs().max()), msg=f"input {k}")


@pytest.mark.parametrize("device", DEVICES)
def test_bad_trainable_masks_are_named(device):
    per_view = _views(1, n=20, device=device)
    m2, cn, d, op, r = _stack(per_view)
    to, ids = bin_gaussians(m2, cn, op, d, r, 37, 29, 16, 1 / 255)
    cols = torch.rand(20, 3, dtype=F64, device=device)
    for bad, msg in ((torch.ones(20, dtype=torch.uint8, device=device), "trainable"),
                     (torch.ones(19, dtype=torch.bool, device=device), "trainable")):
        with pytest.raises(RuntimeError, match=msg):
            rasterize(m2, cn, op, cols, d, None, to, ids, 37, 29, 16, 0.99, 1 / 255, 1e-4, trainable=bad)


@pytest.mark.parametrize("device", DEVICES)
def test_render_views_trainable_gradients(device):
    """render_views(trainable=mask): the scene's gradients of the trainable Gaussians are the
    full render's; the frozen rows are zero (their projections get no screen gradient)."""
    from tiger.render import Camera
    from tiger.render.views import look_at, pinhole_K
    from tiger.scene import GaussianScene, render_views

    g = torch.Generator().manual_seed(0)
    scene = GaussianScene.random_in_box(300, [-1, -1, -1], [1, 1, 1], sh_degree=1, generator=g).to(device=device)
    cams = [Camera(look_at((3 * x, -1.0, -3.0), (0, 0, 0)), pinhole_K(40, 30), 40, 30) for x in (-0.5, 0.0, 0.7)]
    trainable = (torch.arange(len(scene)) % 4 == 1).to(device)
    weights = torch.rand(3, 30, 40, 3, generator=g).to(device)

    def grads(mask):
        scene.parameter_groups()
        out = render_views(scene, cams, trainable=mask)
        ((out["color"] * weights).sum() + out["alpha"].sum()).backward()
        return {k: t.grad for k, t in scene.params().items()}

    full, masked, again = grads(None), grads(trainable), grads(None)
    for k, a in full.items():
        b = masked[k]
        assert not b[~trainable].any(), k
        assert a[trainable].abs().max() > 0, k
        # CUDA accumulates with atomics: two full backward passes already differ in the last bits
        # (the sum's order), and the quaternions' gradients cancel; the masked pass must agree with
        # the full one as closely as the full one agrees with itself (exactly on the CPU)
        spread = float((again[k] - a).abs().max())
        err = float((b[trainable] - a[trainable]).abs().max())
        assert err <= 10 * spread + 1e-6 * float(a.abs().max()), (k, err, spread)
    with pytest.raises(ValueError, match=r"trainable must be a bool tensor \[N=300\]"):
        render_views(scene, cams, trainable=trainable[:10])


def test_trainable_opcheck():
    from .opargs import ops

    m2, cn, d, op, r = _stack(_views(2, n=10))
    to, ids = ops.bin_gaussians(m2, cn, op, d, r, 37, 29, 16, 1 / 255, views=2)
    cols, bg = torch.rand(20, 3, dtype=F64), torch.rand(3, dtype=F64)
    mask = torch.arange(20) % 3 == 0
    args = (m2, cn, op, cols, d, bg, to, ids, 37, 29, 16, 0.99, 1 / 255, 1e-4)
    torch.library.opcheck(ops.rasterize.default, args, {"views": 2, "trainable": mask})
    _, _, _, cnt, tr = ops.rasterize(*args, views=2)
    vc, va = torch.rand(58, 37, 3, dtype=F64), torch.rand(58, 37, dtype=F64)
    torch.library.opcheck(ops.rasterize_backward.default, (*args, tr, cnt, vc, va, None),
                          {"views": 2, "trainable": mask})
    torch.library.opcheck(ops.rasterize_backward_colors.default,
                          (m2, cn, op, to, ids, 37, 29, 16, 0.99, 1 / 255, 1e-4, cnt, vc),
                          {"views": 2, "trainable": mask})
