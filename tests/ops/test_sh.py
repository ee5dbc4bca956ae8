"""tiger::sh_to_color: float64 reference, gradcheck, visibility mask, opcheck, the public function."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.sh import sh_to_color
from tiger.render.reference import sh_to_color_ref

from ..render.devices import DEVICES
from .opargs import F64, ops


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
def test_public_function_is_the_op(device):
    dirs = torch.randn(5, 3, dtype=F64, device=device)
    coeffs = torch.randn(5, 9, 3, dtype=F64, device=device)
    vis = torch.tensor([True, True, False, True, True], device=device)
    assert torch.equal(sh_to_color(dirs, coeffs, 2, vis), ops.sh_to_color(dirs, coeffs, 2, vis))
