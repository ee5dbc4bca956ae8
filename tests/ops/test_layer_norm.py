"""tiger::layer_norm_rows against LayerNorm computed here in float64 (values rounded once, layouts,
gradients), gradcheck/opcheck and clear errors; on CUDA every kernel path (16-byte vectors kept
in registers, rows re-read when longer than the registers hold, scalar rows, misaligned storage),
with and without an input bias, against that reference within one rounding of the dtype."""
import pytest
import torch
import torch.nn.functional as F

import tiger  # noqa: F401
from tiger.ops.layer_norm import layer_norm_rows

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()


def reference(x, w, b, eps, input_bias=None):
    """float64 LayerNorm (two passes) of x (+ input_bias), not rounded; and the size of its terms
    (|u| + |mean|)·rstd·|w| + |b| per element (what the float32 statistics' error scales with:
    u - mean loses the mean's rounding)."""
    xd = x.double() if input_bias is None else x.double() + input_bias.double()
    mean = xd.mean(-1, keepdim=True)
    var = (xd - mean).square().mean(-1, keepdim=True)
    rstd = 1 / torch.sqrt(var + eps)
    y = (xd - mean) * rstd * w.double()
    scale = (xd.abs() + mean.abs()) * rstd * w.double().abs()
    if b is not None:
        y, scale = y + b.double(), scale + b.double().abs()
    return y, scale


def ulp(dtype):
    return {torch.float32: 2.0 ** -23, torch.float16: 2.0 ** -10, torch.bfloat16: 2.0 ** -7,
            torch.float64: 2.0 ** -52}[dtype]


def assert_one_rounding(y, ref_scale, dtype):
    """|y - ref| within one rounding of ref to dtype (half an ulp; a subnormal's spacing near 0)
    plus the float32 statistics' error (relative 1e-5 of the terms' size; 1e-12 for float64)."""
    ref, scale = ref_scale
    err = (y.double() - ref).abs()
    stats = 1e-12 if dtype == torch.float64 else 1e-5
    subnormal = torch.finfo(dtype).tiny * ulp(dtype)  # the spacing below the normal range (fp16: 6e-8)
    bound = ref.abs() * ulp(dtype) * 0.5 + scale * stats + subnormal
    excess = float((err - bound).max())
    assert excess <= 0, f"max error {float(err.max()):.3g}, worst excess {excess:.3g}"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.bfloat16])
@pytest.mark.parametrize("bias", [True, False])
def test_cpu_values(dtype, bias):
    g = torch.Generator().manual_seed(0)
    x = (torch.randn(3, 5, 40, generator=g, dtype=torch.float64) * 3 + 2).to(dtype)
    w = torch.randn(40, generator=g, dtype=torch.float64).to(dtype)
    b = torch.randn(40, generator=g, dtype=torch.float64).to(dtype) if bias else None
    y = layer_norm_rows(x, w, b, 1e-5)
    assert y.dtype == dtype and y.shape == x.shape and y.is_contiguous()
    assert_one_rounding(y, reference(x, w, b, 1e-5), dtype)
    if dtype == torch.float64:
        torch.testing.assert_close(y, F.layer_norm(x, (40,), w, b, 1e-5), atol=1e-13, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.bfloat16])
def test_cpu_input_bias(dtype):
    """``input_bias`` normalises x + input_bias: against the float64 reference, and in float64
    against LayerNorm of the materialised sum."""
    g = torch.Generator().manual_seed(4)
    x = (torch.randn(3, 5, 40, generator=g, dtype=torch.float64) * 3).to(dtype)
    w, b, ib = (torch.randn(40, generator=g, dtype=torch.float64).to(dtype) for _ in range(3))
    ib = ib * 4 + 1  # an offset the row's own statistics would not hide
    y = layer_norm_rows(x, w, b, 1e-5, input_bias=ib)
    assert_one_rounding(y, reference(x, w, b, 1e-5, ib), dtype)
    if dtype == torch.float64:
        torch.testing.assert_close(y, F.layer_norm(x + ib, (40,), w, b, 1e-5), atol=1e-13, rtol=0)
        assert not torch.allclose(y, layer_norm_rows(x, w, b, 1e-5))


def test_cpu_input_bias_gradients():
    g = torch.Generator().manual_seed(5)
    args = [torch.randn(*s, generator=g, dtype=torch.float64).requires_grad_() for s in ((4, 12), (12,), (12,), (12,))]
    fn = lambda x, w, b, ib: layer_norm_rows(x, w, b, 1e-3, input_bias=ib)  # noqa: E731
    assert torch.autograd.gradcheck(fn, args)
    gy = torch.randn(4, 12, generator=g, dtype=torch.float64)
    ours = torch.autograd.grad(fn(*args), args, gy)
    theirs = torch.autograd.grad(F.layer_norm(args[0] + args[3], (12,), args[1], args[2], 1e-3), args, gy)
    for a, t in zip(ours, theirs):
        torch.testing.assert_close(a, t, atol=1e-12, rtol=0)


def test_cpu_strided_input_and_gradients():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(4, 12, 2, generator=g, dtype=torch.float64)[..., 0]  # not contiguous
    w = torch.randn(12, generator=g, dtype=torch.float64)
    b = torch.randn(12, generator=g, dtype=torch.float64)
    torch.testing.assert_close(layer_norm_rows(x, w, b), reference(x, w, b, 1e-5)[0], atol=1e-13, rtol=0)
    args = [t.detach().clone().requires_grad_() for t in (x.contiguous(), w, b)]
    assert torch.autograd.gradcheck(lambda a, c, d: layer_norm_rows(a, c, d, 1e-3), args)
    assert torch.autograd.gradcheck(lambda a, c: layer_norm_rows(a, c, None, 1e-3), args[:2])
    gy = torch.randn(4, 12, generator=g, dtype=torch.float64)
    ours = torch.autograd.grad(layer_norm_rows(*args, 1e-5), args, gy)
    theirs = torch.autograd.grad(F.layer_norm(args[0], (12,), args[1], args[2], 1e-5), args, gy)
    for a, t in zip(ours, theirs):
        torch.testing.assert_close(a, t, atol=1e-12, rtol=0)


def test_opcheck():
    x = torch.randn(3, 8, requires_grad=True)
    w, b = torch.randn(8, requires_grad=True), torch.randn(8, requires_grad=True)
    torch.library.opcheck(torch.ops.tiger.layer_norm_rows, (x, w, b, 1e-5))
    torch.library.opcheck(torch.ops.tiger.layer_norm_rows, (x, w, None, 1e-5))
    torch.library.opcheck(torch.ops.tiger.layer_norm_rows, (x, w, b, 1e-5, torch.randn(8, requires_grad=True)))


def test_constant_rows_give_the_bias():
    x = torch.full((2, 16), 3.25)
    w, b = torch.randn(16), torch.randn(16)
    torch.testing.assert_close(layer_norm_rows(x, w, b), b.expand(2, 16), atol=0, rtol=0)


def test_errors_name_the_problem():
    x = torch.zeros(2, 3)
    with pytest.raises(RuntimeError, match=r"weight must be \[C\] = \[3\]"):
        layer_norm_rows(x, torch.ones(4))
    with pytest.raises(RuntimeError, match=r"bias must be \[C\] = \[3\]"):
        layer_norm_rows(x, torch.ones(3), torch.zeros(2))
    with pytest.raises(RuntimeError, match="weight has dtype"):
        layer_norm_rows(x, torch.ones(3, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="must not be empty"):
        layer_norm_rows(torch.zeros(2, 0), torch.ones(0))
    with pytest.raises(RuntimeError, match=r"input_bias must be \[C\] = \[3\]"):
        layer_norm_rows(x, torch.ones(3), None, 1e-5, input_bias=torch.zeros(3, 1))
    with pytest.raises(RuntimeError, match="input_bias has dtype"):
        layer_norm_rows(x, torch.ones(3), None, 1e-5, input_bias=torch.zeros(3, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="eps must be >= 0"):
        layer_norm_rows(x, torch.ones(3), None, -1.0)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32, torch.float64])
@pytest.mark.parametrize("shape,case", [((12, 256, 320), "vectors"), ((3, 5, 1280), "vectors"), ((7, 4096), "re-read"),
                                        ((33, 13), "scalar"), ((5, 320), "misaligned"), ((1, 8), "vectors"),
                                        ((1000, 40), "vectors"), ((9, 512), "vectors")])
@pytest.mark.parametrize("bias,input_bias", [(True, False), (False, False), (True, True)])
def test_cuda_against_float64(dtype, shape, case, bias, input_bias):
    g = torch.Generator().manual_seed(2)
    C = shape[-1]
    x = torch.randn(*shape, generator=g, dtype=torch.float64) * 2 + 0.5
    w = torch.randn(C, generator=g, dtype=torch.float64)
    b = torch.randn(C, generator=g, dtype=torch.float64) if bias else None
    ib = torch.randn(C, generator=g, dtype=torch.float64) * 3 if input_bias else None
    x, w = x.to(dtype).cuda(), w.to(dtype).cuda()
    b = None if b is None else b.to(dtype).cuda()
    ib = None if ib is None else ib.to(dtype).cuda()
    if case == "misaligned":  # storage offset of one element: the scalar path
        buf = torch.empty(x.numel() + 1, dtype=dtype, device="cuda")
        buf[1:] = x.flatten()
        x = buf[1:].view(shape)
    y = layer_norm_rows(x, w, b, 1e-5, input_bias=ib)
    assert y.dtype == dtype and y.shape == x.shape
    assert torch.isfinite(y).all()
    cpu = lambda t: None if t is None else t.cpu()  # noqa: E731
    assert_one_rounding(y.cpu(), reference(x.cpu(), w.cpu(), cpu(b), 1e-5, cpu(ib)), dtype)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
def test_cuda_graph_replay_and_torch_agreement():
    g = torch.Generator(device="cuda").manual_seed(3)
    x = torch.randn(12, 4096, 320, device="cuda", generator=g).bfloat16()
    w = torch.randn(320, device="cuda", generator=g).bfloat16()
    b = torch.randn(320, device="cuda", generator=g).bfloat16()
    eager = layer_norm_rows(x, w, b)
    graph = torch.cuda.CUDAGraph()
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        layer_norm_rows(x, w, b)
        with torch.cuda.graph(graph, stream=s):
            out = layer_norm_rows(x, w, b)
    torch.cuda.current_stream().wait_stream(s)
    graph.replay()
    torch.cuda.synchronize()
    assert torch.equal(out, eager)
    ref = F.layer_norm(x.float(), (320,), w.float(), b.float(), 1e-5)
    # both round to bf16 once: at most one bf16 ulp (2^-7 relative) apart, plus float32 noise
    assert bool(((eager.float() - ref).abs() <= ref.abs() * 2.0 ** -7 + 1e-4).all())
