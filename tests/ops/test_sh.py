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


def _sh_with_grads(dirs, coeffs, degree, vis, v_colors, staged: bool):
    d, c = dirs.clone().requires_grad_(), coeffs.clone().requires_grad_()
    y = sh_to_color(d, c, degree, vis, _staged=staged)
    y.backward(v_colors)
    return y.detach(), d.grad, c.grad


@pytest.mark.cuda
@CUDA_SKIP
@pytest.mark.parametrize("n, k, degree", [(1000, 16, 3), (130, 16, 1), (64, 9, 2), (5, 4, 1)])
def test_cuda_staged_rows_match_plain_kernel_and_reference(n, k, degree):
    """The staged kernels (coefficient rows through shared memory, the default) against the plain
    ones (_staged=False; bit for bit: the same arithmetic on the same values) and the float64
    reference; block-boundary sizes, unused stored bases and invisible Gaussians included."""
    g = torch.Generator().manual_seed(n + k)
    dirs = torch.randn(n, 3, generator=g)
    coeffs = torch.randn(n, k, 3, generator=g)
    vis = torch.rand(n, generator=g) > 0.3
    v_colors = torch.randn(n, 3, generator=g)
    on_gpu = [t.cuda() for t in (dirs, coeffs, vis, v_colors)]
    staged = _sh_with_grads(*on_gpu[:2], degree, *on_gpu[2:], staged=True)
    plain = _sh_with_grads(*on_gpu[:2], degree, *on_gpu[2:], staged=False)
    for a, b in zip(staged, plain):
        assert torch.equal(a, b)
    d64, c64 = dirs.to(F64).requires_grad_(), coeffs.to(F64).requires_grad_()
    ref = sh_to_color_ref(d64, c64, degree) * vis[:, None]
    ref.backward(v_colors.to(F64))
    for a, r in zip(staged, (ref.detach(), d64.grad, c64.grad)):
        torch.testing.assert_close(a.double().cpu(), r, atol=2e-5, rtol=2e-5)


@pytest.mark.parametrize("device", DEVICES)
def test_staged_choice_reaches_the_backward_op(device):
    """sh_to_color's _staged is an argument of the forward op that its autograd formula hands to
    the backward op (read off the dispatched calls); the CPU has one kernel, same values."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class ArgLog(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.calls = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            kwargs = kwargs or {}  # trailing arguments equal to their defaults are left out
            full = list(args) + [kwargs.get(a.name, a.default_value)
                                 for a in func._schema.arguments[len(args):]]
            self.calls.append((str(func), tuple(full)))
            return func(*args, **kwargs)

    g = torch.Generator().manual_seed(3)
    dirs, coeffs = torch.randn(9, 3, generator=g), torch.randn(9, 9, 3, generator=g)
    vis, v_colors = torch.rand(9, generator=g) > 0.2, torch.randn(9, 3, generator=g)
    ins = [t.to(device) for t in (dirs, coeffs, vis, v_colors)]
    runs = []
    for staged in (True, False):
        log = ArgLog()
        with log:
            runs.append(_sh_with_grads(*ins[:2], 2, *ins[2:], staged=staged))
        backward = [a for n, a in log.calls if n == "tiger.sh_to_color_backward.default"]
        assert len(backward) == 1 and backward[0][-2] is staged  # then trainable
    if device == "cpu":
        assert all(torch.equal(a, b) for a, b in zip(*runs))
    torch.library.opcheck(ops.sh_to_color.default, (ins[0], ins[1], 2, ins[2], None, False))


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
