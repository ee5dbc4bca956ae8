"""tiger::sh_to_color: float64 reference, gradcheck, visibility mask, opcheck, the public function."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.sh import sh_to_color
from tiger.render.reference import sh_to_color_ref

from ..render.devices import CUDA_SKIP, DEVICES
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


_STAGED_SCRIPT = r"""
import sys, torch
import tiger
from tiger.ops.sh import sh_to_color
out = {}
for n, k, degree in ((1000, 16, 3), (130, 16, 1), (64, 9, 2), (5, 4, 1)):
    g = torch.Generator().manual_seed(n + k)
    dirs = torch.randn(n, 3, generator=g).cuda().requires_grad_()
    coeffs = torch.randn(n, k, 3, generator=g).cuda().requires_grad_()
    vis = (torch.rand(n, generator=g) > 0.3).cuda()
    y = sh_to_color(dirs, coeffs, degree, vis)
    y.backward(torch.randn(n, 3, generator=g).cuda())
    out[(n, k, degree)] = (y.detach().cpu(), dirs.grad.cpu(), coeffs.grad.cpu())
torch.save(out, sys.argv[1])
"""


@pytest.mark.cuda
@CUDA_SKIP
def test_cuda_staged_rows_match_plain_kernel_and_reference(tmp_path):
    """TIGER_SH_STAGED=1 (coefficient rows through shared memory) against the plain kernels (bit for
    bit: the same arithmetic on the same values) and the float64 reference; block-boundary sizes,
    unused stored bases and invisible Gaussians included."""
    import os
    import subprocess
    import sys

    runs = {}
    for staged in ("0", "1"):
        path = tmp_path / f"staged{staged}.pt"
        env = {**os.environ, "TIGER_SH_STAGED": staged}
        subprocess.run([sys.executable, "-c", _STAGED_SCRIPT, str(path)], check=True, env=env)
        runs[staged] = torch.load(path)
    for key, got in runs["1"].items():
        for a, b in zip(got, runs["0"][key]):
            assert torch.equal(a, b), key
        n, k, degree = key
        g = torch.Generator().manual_seed(n + k)
        dirs = torch.randn(n, 3, generator=g).to(F64).requires_grad_()  # the script's float32 draws
        coeffs = torch.randn(n, k, 3, generator=g).to(F64).requires_grad_()
        vis = torch.rand(n, generator=g) > 0.3
        ref = sh_to_color_ref(dirs, coeffs, degree) * vis[:, None]
        ref.backward(torch.randn(n, 3, generator=g).to(F64))
        for a, r in zip(got, (ref.detach(), dirs.grad, coeffs.grad)):
            torch.testing.assert_close(a.double(), r, atol=2e-5, rtol=2e-5)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_split_rows_equal_joined_rows(device, dtype):
    """coeffs + rest (a scene's DC band and a strided slice of its higher bands, read in place on
    CUDA in float32) give the values and gradients of the joined [N, K, 3] tensor, bit for bit."""
    g = torch.Generator().manual_seed(11)
    n = 300  # several 64-row blocks and a ragged last one
    dirs = torch.randn(n, 3, generator=g, dtype=F64).to(device, dtype)
    dc = torch.randn(n, 3, generator=g, dtype=F64).to(device, dtype)
    rest_all = torch.randn(n, 15, 3, generator=g, dtype=F64).to(device, dtype)
    vis = (torch.rand(n, generator=g) > 0.2).to(device)
    vc = torch.randn(n, 3, generator=g, dtype=F64).to(device, dtype)
    for degree in (0, 1, 2, 3):
        k1 = (degree + 1) ** 2 - 1
        d0, r0 = dc.clone().requires_grad_(), rest_all.clone().requires_grad_()
        rest = r0[:, :k1] if degree else None           # strided rows for degree < 3
        got = sh_to_color(dirs, d0[:, None], degree, vis, rest)
        got.backward(vc)
        d1, r1 = dc.clone().requires_grad_(), rest_all.clone().requires_grad_()
        joined = torch.cat([d1[:, None], r1[:, :k1]], 1)
        want = sh_to_color(dirs, joined, degree, vis)
        want.backward(vc)
        assert torch.equal(got, want), degree
        assert torch.equal(d0.grad, d1.grad), degree
        if degree:
            assert torch.equal(r0.grad, r1.grad), degree


def test_split_rows_errors_and_opcheck():
    dirs, dc, rest = torch.randn(4, 3, dtype=F64), torch.randn(4, 1, 3, dtype=F64), torch.randn(4, 2, 3, dtype=F64)
    with pytest.raises(RuntimeError, match=r"coeffs \+ rest hold 3 SH coefficients per Gaussian but degree 1 needs 4"):
        sh_to_color(dirs, dc, 1, None, rest)
    with pytest.raises(RuntimeError, match="rest must have shape"):
        sh_to_color(dirs, dc, 1, None, torch.randn(3, 3, 3, dtype=F64))
    rest = torch.randn(4, 3, 3, dtype=F64, requires_grad=True)
    torch.library.opcheck(ops.sh_to_color.default, (dirs, dc.requires_grad_(), 1, None, rest))
