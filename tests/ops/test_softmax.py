"""tiger::softmax_rows against softmax computed here in float64 (values, gradients, gradcheck,
opcheck, errors); on CUDA every kernel variant (1-8 vectors a thread, float32/bf16/fp16) and the
fallback shapes against the float64 reference within one rounding of the output, against torch's
softmax, and with no NaN/Inf on peaked and -inf-masked rows."""
import pytest
import torch

import tiger  # noqa: F401
from tiger.ops.softmax import softmax_rows

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()


def reference(x: torch.Tensor) -> torch.Tensor:
    """Softmax in float64 from its definition: exp(x - max) / sum."""
    d = x.double()
    e = (d - d.amax(-1, keepdim=True)).exp()
    return e / e.sum(-1, keepdim=True)


def reference_backward(y: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """y * (g - <g, y>) per row in float64 (the Jacobian-vector product of softmax)."""
    y, g = y.double(), g.double()
    return y * (g - (g * y).sum(-1, keepdim=True))


def test_cpu_values_gradients_and_checks():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 5, 7, generator=g, dtype=torch.float64) * 4
    y = softmax_rows(x)
    torch.testing.assert_close(y, reference(x), rtol=1e-14, atol=1e-16)
    xr = x.clone().requires_grad_()
    assert torch.autograd.gradcheck(softmax_rows, (xr,))
    gy = torch.randn(x.shape, generator=g, dtype=torch.float64)
    (gx,) = torch.autograd.grad(softmax_rows(xr), xr, gy)
    torch.testing.assert_close(gx, reference_backward(y, gy), rtol=1e-12, atol=1e-15)
    torch.library.opcheck(torch.ops.tiger.softmax_rows, (torch.randn(2, 3, 8, requires_grad=True),))
    torch.library.opcheck(torch.ops.tiger.softmax_rows_backward, (torch.rand(2, 8), torch.randn(2, 8)))


def test_errors_name_the_problem():
    with pytest.raises(RuntimeError, match="x must be a floating-point tensor"):
        softmax_rows(torch.zeros(2, 3, dtype=torch.int64))
    with pytest.raises(RuntimeError, match=r"grad_y must have y's shape \[2, 3\]"):
        torch.ops.tiger.softmax_rows_backward(torch.rand(2, 3), torch.rand(2, 4))


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32])
@pytest.mark.parametrize("length", [8, 1024, 4096, 6144, 16384, 12, 40000])  # 12 / 40000: torch's fallback
def test_cuda_within_one_rounding_of_float64(dtype, length):
    g = torch.Generator().manual_seed(length)
    rows = 37 if length <= 16384 else 3
    x = (torch.randn(rows, length, generator=g) * 6).to(dtype).cuda()
    x[0, : length // 2] = float("-inf")  # a masked half
    x[1] = 0
    x[1, 3] = 40  # peaked: one value near 1, the rest underflow
    y = softmax_rows(x)
    ref = reference(x.cpu())
    # the output's rounding, float32 arithmetic (expf, a tree of sums: 64 float32 ulps) and one subnormal step
    fi, f32 = torch.finfo(dtype), torch.finfo(torch.float32).eps
    step = fi.smallest_normal * fi.eps
    assert torch.isfinite(y).all()
    assert ((y.cpu().double() - ref).abs() <= (fi.eps + 64 * f32) * ref + step).all()
    torch.testing.assert_close(y, torch.softmax(x, -1), rtol=2 * fi.eps + 64 * f32, atol=2 * step)
    gy = torch.randn(rows, length, generator=g).to(dtype).cuda()
    xr = x.clone().requires_grad_()
    (gx,) = torch.autograd.grad(softmax_rows(xr), xr, gy)
    yd, gd = y.cpu().double(), gy.cpu().double()
    want = reference_backward(yd, gd)
    dot_err = 64 * f32 * (yd * gd).abs().sum(-1, keepdim=True)  # float32 error of <grad, y>
    bound = fi.eps * want.abs() + yd * dot_err + step
    if length == 40000 or length == 12 and dtype != torch.float32:  # torch's fallback rounds grad * y first
        bound = bound + fi.eps * (yd * gd).abs()
    assert torch.isfinite(gx).all()
    assert ((gx.cpu().double() - want).abs() <= bound).all()


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
def test_cuda_misaligned_and_strided_inputs_take_the_fallback_or_a_copy():
    base = torch.randn(4 * 64 + 1, device="cuda", dtype=torch.bfloat16)
    x = base[1:].view(4, 64)  # 2-byte offset: not 16-byte aligned
    torch.testing.assert_close(softmax_rows(x), torch.softmax(x, -1), rtol=0, atol=0)
    t = torch.randn(64, 4, device="cuda", dtype=torch.bfloat16).t()  # strided: copied contiguous first
    torch.testing.assert_close(softmax_rows(t), torch.softmax(t.contiguous(), -1), rtol=2 ** -7, atol=1e-7)
