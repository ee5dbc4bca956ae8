"""tiger::project_gaussians: float64 reference, gradcheck, opcheck, the public function."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.projection import project_gaussians
from tiger.render.reference import project_ref

from ..render.devices import DEVICES
from .opargs import F64, _projection_args, ops


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
def test_public_function_is_the_op(device):
    m, q, s, o, V, K, w, h = _projection_args(device=device)
    got = project_gaussians(m, q, s, o, V, K, w, h, eps2d=0.3, near=0.01, far=1e10,
                            alpha_threshold=1 / 255, antialiased=True)
    want = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, True)
    assert all(torch.equal(a, b) for a, b in zip(got, want))
