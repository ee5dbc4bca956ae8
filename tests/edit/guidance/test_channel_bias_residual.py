"""tiger::channel_bias_add with a per-sample [N, C] bias and a residual (the folded ResNet adds of
the guidances' diffusion models): values against the float32 sum rounded once, layouts,
gradients (gradcheck), opcheck, clear errors; on CUDA every kernel path bit-exact against that
rounding."""
import pytest
import torch

import tiger  # noqa: F401
from tiger.ops.channel_bias import channel_bias_add

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
CL = torch.channels_last


def rounded_sum(x, b, r=None):
    """(x + b[(n,) c]) + r summed in float32 (float64 for float64 input), left to right, then
    rounded once to x's dtype: the op's contract on both devices."""
    acc = torch.float64 if x.dtype == torch.float64 else torch.float32
    bb = b.to(acc)[:, :, None, None] if b.dim() == 2 else b.to(acc)[None, :, None, None]
    s = x.to(acc) + bb
    if r is not None:
        s = s + r.to(acc)
    return s.to(x.dtype)


@pytest.mark.parametrize("layout", ["nchw", "cl", "strided"])
@pytest.mark.parametrize("per_sample", [False, True])
@pytest.mark.parametrize("with_residual", [False, True])
def test_cpu_values_layout_and_gradients(layout, per_sample, with_residual):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 6, 5, 3, generator=g, dtype=torch.float64)
    if layout == "cl":
        x = x.contiguous(memory_format=CL)
    elif layout == "strided":
        x = torch.randn(2, 6, 5, 6, generator=g, dtype=torch.float64)[..., ::2]
    b = torch.randn((2, 6) if per_sample else (6,), generator=g, dtype=torch.float64)
    r = torch.randn(2, 6, 5, 3, generator=g, dtype=torch.float64) if with_residual else None
    y = channel_bias_add(x, b, r)
    torch.testing.assert_close(y, rounded_sum(x, b, r), atol=0, rtol=0)
    assert y.is_contiguous(memory_format=CL) == (layout == "cl") and (layout == "cl" or y.is_contiguous())
    args = [x.detach().requires_grad_(), b.detach().requires_grad_()]
    if r is not None:
        args.append(r.detach().requires_grad_())
    assert torch.autograd.gradcheck(channel_bias_add, tuple(args))
    gy = torch.randn(y.shape, generator=g, dtype=torch.float64)
    grads = torch.autograd.grad(channel_bias_add(*args), args, gy)
    torch.testing.assert_close(grads[0], gy)
    torch.testing.assert_close(grads[1], gy.sum((2, 3)) if per_sample else gy.sum((0, 2, 3)))
    if r is not None:
        torch.testing.assert_close(grads[2], gy)


def test_cpu_bfloat16_rounds_once():
    g = torch.Generator().manual_seed(4)
    x = torch.randn(2, 8, 4, 4, generator=g).to(torch.bfloat16)
    b = torch.randn(2, 8, generator=g).to(torch.bfloat16)
    r = (1000 * torch.randn(2, 8, 4, 4, generator=g)).to(torch.bfloat16)
    assert torch.equal(channel_bias_add(x, b, r), rounded_sum(x, b, r))


def test_opcheck():
    x = torch.randn(2, 4, 3, 3, requires_grad=True)
    torch.library.opcheck(torch.ops.tiger.channel_bias_add, (x, torch.randn(2, 4, requires_grad=True),
                                                             torch.randn(2, 4, 3, 3, requires_grad=True)))
    torch.library.opcheck(torch.ops.tiger.channel_bias_add, (x, torch.randn(4, requires_grad=True), None))


def test_errors_name_the_problem():
    x = torch.zeros(2, 3, 2, 2)
    with pytest.raises(RuntimeError, match=r"bias must be \[C\] = \[3\] or \[N, C\] = \[2, 3\]"):
        channel_bias_add(x, torch.zeros(3, 3))
    with pytest.raises(RuntimeError, match=r"residual must have x's shape \[2, 3, 2, 2\]"):
        channel_bias_add(x, torch.zeros(3), torch.zeros(2, 3, 2, 1))
    with pytest.raises(RuntimeError, match="residual has dtype"):
        channel_bias_add(x, torch.zeros(3), torch.zeros(2, 3, 2, 2, dtype=torch.float64))


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32])
@pytest.mark.parametrize("shape,layout", [((4, 128, 16, 16), "cl"), ((2, 4, 5, 7), "cl"), ((3, 3, 8, 8), "nchw"),
                                          ((2, 5, 3, 5), "nchw"), ((2, 320, 4, 4), "misaligned")])
@pytest.mark.parametrize("per_sample,with_residual", [(True, False), (False, True), (True, True)])
def test_cuda_bit_exact(dtype, shape, layout, per_sample, with_residual):
    g = torch.Generator().manual_seed(1)
    n = torch.Size(shape).numel()

    def make():
        if layout == "misaligned":  # storage offset of one element: the scalar kernel
            return torch.randn(n + 1, generator=g).to(dtype).cuda()[1:].view(shape)
        t = torch.randn(shape, generator=g).to(dtype).cuda()
        return t.contiguous(memory_format=CL) if layout == "cl" else t

    x = make()
    r = make() if with_residual else None
    b = torch.randn((shape[0], shape[1]) if per_sample else (shape[1],), generator=g).to(dtype).cuda()
    y = channel_bias_add(x, b, r)
    assert torch.equal(y, rounded_sum(x, b, r))
    assert y.is_contiguous(memory_format=CL) == (layout == "cl" and x.shape[2] * x.shape[3] > 1)
    if r is not None:  # a residual in the other layout is copied to x's first, same values
        other = r.contiguous() if layout == "cl" else r.contiguous(memory_format=CL)
        assert torch.equal(channel_bias_add(x, b, other), y)
