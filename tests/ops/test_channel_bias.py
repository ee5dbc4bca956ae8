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


def _wide_slice(shape, extra, dtype, device="cpu", offset=0):
    """A [N, C, H, W] channel slice (channels offset .. offset + C) of a channels-last map with C + extra channels."""
    n, c, h, w = shape
    wide = torch.full((n, c + extra, h, w), float("nan"), dtype=dtype, device=device).contiguous(memory_format=CL)
    return wide, wide[:, offset:offset + c]


@pytest.mark.parametrize("bias_kind", ["channel", "sample", "none"])
@pytest.mark.parametrize("residual", [False, True])
def test_into_a_channel_slice_writes_the_same_values_and_nothing_else(bias_kind, residual):
    g = torch.Generator().manual_seed(2)
    x = torch.randn(2, 6, 3, 4, generator=g, dtype=torch.float64).contiguous(memory_format=CL)
    b = {"channel": torch.randn(6, generator=g, dtype=torch.float64),
         "sample": torch.randn(2, 6, generator=g, dtype=torch.float64), "none": None}[bias_kind]
    r = torch.randn(2, 6, 3, 4, generator=g, dtype=torch.float64) if residual else None
    wide, out = _wide_slice(x.shape, 5, torch.float64, offset=3)
    assert channel_bias_add(x, b, r, out=out) is out
    ref = x + (0 if b is None else b.view(-1, 6, 1, 1) if b.dim() == 1 else b[:, :, None, None])
    ref = ref + (0 if r is None else r)
    torch.testing.assert_close(out, ref, atol=0, rtol=0)
    assert wide[:, :3].isnan().all() and wide[:, 9:].isnan().all()  # the other channels untouched


def test_into_rounds_once_like_the_op_and_takes_any_output_layout():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(2, 8, 5, 3, generator=g).to(torch.bfloat16)
    b = torch.randn(8, generator=g).to(torch.bfloat16)
    r = torch.randn(2, 8, 5, 3, generator=g).to(torch.bfloat16)
    ref = channel_bias_add(x, b, r)
    for out in (torch.empty_like(x), torch.empty(2, 8, 5, 6, dtype=torch.bfloat16)[..., ::2],
                _wide_slice(x.shape, 8, torch.bfloat16, offset=8)[1]):
        assert torch.equal(channel_bias_add(x, b, r, out=out), ref)


def test_into_refuses_autograd_and_wrong_outputs():
    x = torch.zeros(1, 3, 2, 2, requires_grad=True)
    with pytest.raises(ValueError, match="out= has no autograd"):
        channel_bias_add(x, torch.zeros(3), out=torch.empty(1, 3, 2, 2))
    with torch.no_grad():
        channel_bias_add(x, torch.ones(3), out=torch.empty(1, 3, 2, 2))
    with pytest.raises(RuntimeError, match=r"out must have x's shape \[1, 3, 2, 2\]"):
        channel_bias_add(x.detach(), torch.zeros(3), out=torch.empty(1, 4, 2, 2))
    with pytest.raises(RuntimeError, match="out has dtype"):
        channel_bias_add(x.detach(), torch.zeros(3), out=torch.empty(1, 3, 2, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="bias is None"):
        channel_bias_add(x.detach(), None)


def test_opcheck_into():
    x = torch.randn(2, 4, 3, 3).contiguous(memory_format=CL)
    out = _wide_slice(x.shape, 4, torch.float32)[1]
    torch.library.opcheck(torch.ops.tiger.channel_bias_add_into, (x, torch.randn(4), None, out))
    torch.library.opcheck(torch.ops.tiger.channel_bias_add_into, (x, None, torch.randn(2, 4, 3, 3), out))


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32])
@pytest.mark.parametrize("case", ["vector", "odd_rows", "odd_offset", "nchw_out", "no_bias", "nchw_x"])
def test_cuda_into_bit_exact(dtype, case):
    g = torch.Generator().manual_seed(4)
    shape = (3, 16 if case != "odd_rows" else 5, 4, 6)
    x = torch.randn(shape, generator=g).to(dtype).cuda()
    x = x if case == "nchw_x" else x.contiguous(memory_format=CL)
    b = None if case == "no_bias" else torch.randn(shape[1], generator=g).to(dtype).cuda()
    r = torch.randn(shape, generator=g).to(dtype).cuda()
    if case == "nchw_out":
        wide, out = None, torch.empty(shape, dtype=dtype, device="cuda")
    else:  # rows of 32 (21) elements, slices at channel 8 (16-byte aligned) or 3: the vector (scalar) kernel
        wide, out = _wide_slice(shape, 16, dtype, "cuda", offset=3 if case == "odd_offset" else 8)
    ref = channel_bias_add(x, b if b is not None else torch.zeros_like(x[0, :, 0, 0]), r)
    assert torch.equal(channel_bias_add(x, b, r, out=out), ref)
    if wide is not None:
        o = 3 if case == "odd_offset" else 8
        assert wide[:, :o].isnan().all() and wide[:, o + shape[1]:].isnan().all()


def interleave_reference(z: torch.Tensor, bias) -> torch.Tensor:
    """y[n, c, 2i+a, 2j+b] = z[n, (2a+b)C + c, i+a, j+b] + bias[c] by explicit indexing, float64."""
    n, c4, h1, w1 = z.shape
    c, h, w = c4 // 4, h1 - 1, w1 - 1
    y = torch.empty(n, c, 2 * h, 2 * w, dtype=torch.float64)
    zd = z.double()
    for a in (0, 1):
        for b in (0, 1):
            y[:, :, a::2, b::2] = zd[:, (2 * a + b) * c:(2 * a + b + 1) * c, a:a + h, b:b + w]
    return y if bias is None else y + bias.double()[None, :, None, None]


@pytest.mark.parametrize("with_bias", [True, False])
def test_subpixel_interleave_cpu_and_into_a_slice(with_bias):
    from tiger.ops.channel_bias import subpixel_interleave

    g = torch.Generator().manual_seed(5)
    z = torch.randn(2, 4 * 6, 4, 5, generator=g).to(torch.bfloat16).contiguous(memory_format=CL)
    b = torch.randn(6, generator=g).to(torch.bfloat16) if with_bias else None
    want = interleave_reference(z, b).to(torch.bfloat16)  # one rounding of the exact sum
    y = subpixel_interleave(z, b)
    assert torch.equal(y, want) and y.is_contiguous(memory_format=CL) and y.shape == (2, 6, 6, 8)
    wide, out = _wide_slice((2, 6, 6, 8), 10, torch.bfloat16, offset=4)
    assert subpixel_interleave(z, b, out=out) is out and torch.equal(out, want)
    assert wide[:, :4].isnan().all() and wide[:, 10:].isnan().all()
    with pytest.raises(RuntimeError, match=r"z must be \[N, 4C, H\+1, W\+1\] = \[2, 24, 4, 5\]"):
        subpixel_interleave(z[:, :, :3], b, out=torch.empty(2, 6, 6, 8, dtype=torch.bfloat16))
    torch.library.opcheck(torch.ops.tiger.subpixel_interleave_into, (z, b, out))


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32])
@pytest.mark.parametrize("case", ["vector", "slice", "odd_channels", "no_bias", "nchw_z"])
def test_cuda_subpixel_interleave_bit_exact(dtype, case):
    from tiger.ops.channel_bias import subpixel_interleave

    g = torch.Generator().manual_seed(6)
    c = 5 if case == "odd_channels" else 16
    z = torch.randn(3, 4 * c, 9, 7, generator=g).to(dtype)
    b = None if case == "no_bias" else torch.randn(c, generator=g).to(dtype)
    want = interleave_reference(z, b).to(dtype)
    zc = z.cuda() if case == "nchw_z" else z.cuda().contiguous(memory_format=CL)
    bc = None if b is None else b.cuda()
    if case == "slice":
        wide, out = _wide_slice((3, c, 16, 12), 16, dtype, "cuda", offset=8)
        subpixel_interleave(zc, bc, out=out)
        assert wide[:, :8].isnan().all() and wide[:, 8 + c:].isnan().all()
        y = out
    else:
        y = subpixel_interleave(zc, bc)
    assert torch.equal(y.cpu(), want)
