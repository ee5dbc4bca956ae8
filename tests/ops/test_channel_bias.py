"""tiger::channel_bias_add against the sum computed here in float64 and rounded once (values,
layouts, gradients), gradcheck/opcheck, clear errors; on CUDA every kernel path (vectorised
NCHW/NHWC, scalar shapes, misaligned storage) bit-exact against that rounding."""
import pytest
import torch

import tiger  # noqa: F401
from tiger.ops.channel_bias import channel_bias_add

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
CL = torch.channels_last


def rounded_sum(x, b):
    """x + b[c] exactly (float64 holds the sum of two float32/bf16/fp16 values), rounded once."""
    return (x.double() + b.double()[None, :, None, None]).to(x.dtype)


@pytest.mark.parametrize("layout", ["nchw", "cl", "strided"])
def test_cpu_values_layout_and_gradients(layout):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 6, 5, 3, generator=g, dtype=torch.float64)
    if layout == "cl":
        x = x.contiguous(memory_format=CL)
    elif layout == "strided":
        x = torch.randn(2, 6, 5, 6, generator=g, dtype=torch.float64)[..., ::2]
    b = torch.randn(6, generator=g, dtype=torch.float64)
    y = channel_bias_add(x, b)
    torch.testing.assert_close(y, rounded_sum(x, b), atol=0, rtol=0)
    assert y.is_contiguous(memory_format=CL) == (layout == "cl") and (layout == "cl" or y.is_contiguous())
    xr, br = x.detach().requires_grad_(), b.detach().requires_grad_()
    assert torch.autograd.gradcheck(channel_bias_add, (xr, br))
    gy = torch.randn(y.shape, generator=g, dtype=torch.float64)
    gx, gb = torch.autograd.grad(channel_bias_add(xr, br), (xr, br), gy)
    torch.testing.assert_close(gx, gy)
    torch.testing.assert_close(gb, gy.sum((0, 2, 3)))  # d/db_c = Σ over n, h, w


def test_opcheck():
    x = torch.randn(2, 4, 3, 3, requires_grad=True)
    torch.library.opcheck(torch.ops.tiger.channel_bias_add, (x, torch.randn(4, requires_grad=True)))


def test_errors_name_the_problem():
    x = torch.zeros(1, 3, 2, 2)
    with pytest.raises(RuntimeError, match=r"bias must be \[C\] = \[3\]"):
        channel_bias_add(x, torch.zeros(4))
    with pytest.raises(RuntimeError, match="x must be \\[N, C, H, W\\]"):
        channel_bias_add(torch.zeros(3, 2, 2), torch.zeros(3))
    with pytest.raises(RuntimeError, match="bias has dtype"):
        channel_bias_add(x, torch.zeros(3, dtype=torch.float64))


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32])
@pytest.mark.parametrize("shape,layout", [((4, 128, 16, 16), "cl"), ((2, 4, 5, 7), "cl"), ((3, 3, 8, 8), "nchw"),
                                          ((2, 5, 3, 5), "nchw"), ((2, 320, 4, 4), "misaligned")])
def test_cuda_bit_exact(dtype, shape, layout):
    g = torch.Generator().manual_seed(1)
    n = torch.Size(shape).numel()
    if layout == "misaligned":  # storage offset of one element: the scalar kernel
        x = torch.randn(n + 1, generator=g).to(dtype).cuda()[1:].view(shape)
    else:
        x = torch.randn(shape, generator=g).to(dtype).cuda()
        x = x.contiguous(memory_format=CL) if layout == "cl" else x
    b = torch.randn(shape[1], generator=g).to(dtype).cuda()
    y = channel_bias_add(x, b)
    assert torch.equal(y, rounded_sum(x, b)) and torch.equal(y, x + b[None, :, None, None])
    assert y.is_contiguous(memory_format=CL) == (layout == "cl" and x.shape[2] * x.shape[3] > 1)
    assert torch.isfinite(y).all()
