"""Each rendering op on its own: references, gradcheck (float64), opcheck."""
from __future__ import annotations

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import tiger
from tiger.render.reference import project_ref, sh_to_color_ref

from .devices import DEVICES
from .scenes import camera, random_scene

F64 = torch.float64
ops = torch.ops.tiger


def _projection_args(n=6, w=24, h=20, seed=0, dtype=F64, device="cpu"):
    m, q, s, o, _ = random_scene(n, 1, dtype=dtype, seed=seed, scale_range=(0.1, 0.4),
                                 opacity_range=(0.3, 0.9))
    V, K = camera(w, h, dtype=dtype)
    return (*[t.to(device) for t in (m, q, s, o, V, K)], w, h)


def _raster_args(n=8, c=4, w=20, h=18, seed=0, dtype=F64, device="cpu"):
    m, q, s, o, V, K, w, h = _projection_args(n, w, h, seed, dtype, device)
    m2, cn, d, op, r = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
    col = torch.rand(n, c, dtype=dtype, generator=torch.Generator().manual_seed(seed)).to(device)
    bg = torch.rand(c, dtype=dtype, generator=torch.Generator().manual_seed(seed + 1)).to(device)
    to, ids = ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255)
    return m2, cn, op, col, d, bg, to, ids, w, h


@pytest.mark.parametrize("device", DEVICES)
class TestProjection:
    def test_matches_reference(self, device):
        m, q, s, o, V, K, w, h = _projection_args(300, 64, 48, seed=1, device=device)
        for aa in (False, True):
            m2, cn, d, op, r = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10,
                                                     1 / 255, aa)
            ref = project_ref(m, q, s, o, V, K, w, h, antialiased=aa)
            vis = r[:, 0] > 0
            assert bool((vis <= ref["valid"]).all())
            for a, b in ((m2, ref["means2d"]), (cn, ref["conics"]), (d, ref["depths"]),
                         (op, ref["opacities"])):
                assert torch.allclose(a[vis], b[vis], rtol=1e-12, atol=1e-12)

    @pytest.mark.parametrize("antialiased", [False, True])
    def test_gradcheck(self, antialiased, device):
        m, q, s, o, V, K, w, h = _projection_args(device=device)
        def f(m, q, s, o, V, K):
            out = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, antialiased)
            return out[:4]
        ins = [t.clone().requires_grad_() for t in (m, q, s, o, V, K)]
        assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-7, rtol=1e-5)

    def test_gradcheck_frustum_clamp(self, device):
        # Gaussians far off-axis exercise the clamped branch of the Jacobian.
        m, q, s, o, V, K, w, h = _projection_args(device=device)
        m = m.clone()
        m[:3, 0] += torch.tensor([2.5, -2.6, 2.7], dtype=F64, device=device)
        def f(m, s, K):
            return ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1e-6, False)[1]
        ins = [t.clone().requires_grad_() for t in (m, s, K)]
        assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-7, rtol=1e-5)

    def test_opcheck(self, device):
        args = _projection_args(5, device=device)
        torch.library.opcheck(ops.project_gaussians.default,
                              (*args, 0.3, 0.01, 1e10, 1 / 255, True))
        m, q, s, o, V, K, w, h = args
        r = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)[4]
        g = [torch.randn(5, 2, dtype=F64), torch.randn(5, 3, dtype=F64), torch.randn(5, dtype=F64),
             torch.randn(5, dtype=F64)]
        g = [t.to(device) for t in g]
        torch.library.opcheck(ops.project_gaussians_backward.default,
                              (m, q, s, o, V, K, r, w, h, 0.3, False, *g, True))


@pytest.mark.parametrize("device", DEVICES)
class TestSphericalHarmonics:
    @pytest.mark.parametrize("degree", [0, 1, 2, 3])
    def test_matches_reference_and_gradcheck(self, degree, device):
        g = torch.Generator().manual_seed(degree)
        dirs = (torch.randn(20, 3, generator=g, dtype=F64) * 3).to(device)
        coeffs = torch.randn(20, 16, 3, generator=g, dtype=F64).to(device)
        out = ops.sh_to_color(dirs, coeffs, degree, None)
        assert torch.allclose(out, sh_to_color_ref(dirs, coeffs, degree), atol=1e-13)
        ins = [dirs.clone().requires_grad_(), coeffs.clone().requires_grad_()]
        assert torch.autograd.gradcheck(lambda d, c: ops.sh_to_color(d, c, degree, None), ins)

    def test_visible_mask_skips(self, device):
        dirs = torch.randn(4, 3, dtype=F64, device=device)
        coeffs = torch.randn(4, 4, 3, dtype=F64, device=device)
        vis = torch.tensor([True, False, True, False], device=device)
        out = ops.sh_to_color(dirs, coeffs, 1, vis)
        assert bool((out[~vis] == 0).all())
        assert torch.allclose(out[vis], sh_to_color_ref(dirs, coeffs, 1)[vis])

    def test_opcheck(self, device):
        dirs = torch.randn(6, 3, dtype=F64, device=device)
        coeffs = torch.randn(6, 9, 3, dtype=F64, device=device)
        torch.library.opcheck(ops.sh_to_color.default, (dirs, coeffs, 2, None))
        torch.library.opcheck(ops.sh_to_color_backward.default,
                              (dirs, coeffs, 2, None, torch.randn(6, 3, dtype=F64, device=device)))


@pytest.mark.parametrize("device", DEVICES)
class TestBinning:
    @pytest.mark.parametrize("dtype", [F64, torch.float32])
    def test_lists_match_brute_force(self, device, dtype):
        m, q, s, o, V, K, w, h = _projection_args(200, 70, 50, seed=4, dtype=dtype, device=device)
        m2, cn, d, op, r = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
        to, ids = ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255)
        tiles_x = (w + 15) // 16
        m2, cn, d, op, r, to, ids = [t.cpu() for t in (m2, cn, d, op, r, to, ids)]
        m2, cn, d, op = m2.double(), cn.double(), d.double(), op.double()
        ys, xs = torch.meshgrid(torch.arange(h, dtype=F64), torch.arange(w, dtype=F64), indexing="ij")
        for t in range(to.numel() - 1):
            tx, ty = t % tiles_x, t // tiles_x
            lst = ids[to[t]:to[t + 1]].long()
            # front to back
            assert bool((d[lst][1:] >= d[lst][:-1]).all())
            # every Gaussian reaching alpha >= 1/255 at a pixel of this tile is listed
            px = xs[ty * 16:(ty + 1) * 16, tx * 16:(tx + 1) * 16].reshape(-1) + 0.5
            py = ys[ty * 16:(ty + 1) * 16, tx * 16:(tx + 1) * 16].reshape(-1) + 0.5
            dx = px[:, None] - m2[:, 0]
            dy = py[:, None] - m2[:, 1]
            qf = cn[:, 0] * dx * dx + 2 * cn[:, 1] * dx * dy + cn[:, 2] * dy * dy
            touches = ((op * torch.exp(-0.5 * qf)) >= 1 / 255).any(0) & (r[:, 0] > 0)
            need = set(torch.nonzero(touches).flatten().tolist())
            assert need <= set(lst.tolist())

    def test_opcheck(self, device):
        m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
        r = torch.ones(m2.shape[0], 2, dtype=torch.int32, device=device) * 4
        torch.library.opcheck(ops.bin_gaussians.default, (m2, cn, op, d, r, w, h, 16, 1 / 255),
                              test_utils=("test_schema", "test_faketensor"))


@pytest.mark.parametrize("device", DEVICES)
class TestRasterize:
    def test_gradcheck(self, device):
        m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
        def f(m2, cn, op, col, d, bg):
            c, a, dep, _, _ = ops.rasterize(m2, cn, op, col, d, bg, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
            return c, a, dep
        ins = [t.clone().requires_grad_() for t in (m2, cn, op, col, d, bg)]
        assert torch.autograd.gradcheck(f, ins, eps=1e-7, atol=1e-6, rtol=1e-5)

    def test_gradcheck_end_to_end_every_input(self, device):
        w, h = 18, 14
        m, q, s, o, col = random_scene(7, 3, seed=12, scale_range=(0.1, 0.3))
        V, K = camera(w, h)
        bg = torch.rand(3, dtype=F64)
        m, q, s, o, col, V, K, bg = [t.to(device) for t in (m, q, s, o, col, V, K, bg)]
        def f(*t):
            out = tiger.rasterize_gaussians(*t[:7], w, h, background=t[7])
            return out["color"], out["alpha"], out["depth"]
        ins = [t.clone().requires_grad_() for t in (m, q, s, o, col, V, K, bg)]
        assert torch.autograd.gradcheck(f, ins, eps=1e-7, atol=1e-6, rtol=1e-4)

    def test_opcheck(self, device):
        m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
        args = (m2, cn, op, col, d, bg, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
        torch.library.opcheck(ops.rasterize.default, args)
        c, a, dep, cnt, tr = ops.rasterize(*args)
        vc, va, vd = torch.randn_like(c), torch.randn_like(a), torch.randn_like(dep)
        torch.library.opcheck(ops.rasterize_backward.default, (*args, tr, cnt, vc, va, vd))
        torch.library.opcheck(ops.rasterize_backward_colors.default,
                              (m2, cn, op, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4, cnt, vc))


class _OpLog(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.names: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.names.append(str(func))
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("device", DEVICES)
def test_features_only_backward_skips_geometry_and_matches_full(device):
    w, h = 40, 30
    m, q, s, o, col = random_scene(300, 64, seed=21)
    V, K = camera(w, h)
    m, q, s, o, col, V, K = [t.to(device) for t in (m, q, s, o, col, V, K)]
    wgt = torch.randn(h, w, 64, dtype=F64).to(device)
    c1 = col.clone().requires_grad_()
    out = tiger.rasterize_gaussians(m, q, s, o, c1, V, K, w, h)
    log = _OpLog()
    with log:
        (out["color"] * wgt).sum().backward()
    assert any("rasterize_backward_colors" in n for n in log.names)
    assert not any("rasterize_backward.default" in n or "project_gaussians_backward" in n
                   for n in log.names)
    # Same colour gradient as the full backward (geometry also requiring grad).
    c2 = col.clone().requires_grad_()
    m2 = m.clone().requires_grad_()
    out2 = tiger.rasterize_gaussians(m2, q, s, o, c2, V, K, w, h)
    (out2["color"] * wgt).sum().backward()
    assert float((c1.grad - c2.grad).abs().max()) <= 1e-10 * float(c2.grad.abs().max())
