"""tiger::group_norm against an explicit float64 GroupNorm(+SiLU) written here (values, input and
parameter gradients), torch's GroupNorm as a second witness, gradcheck/opcheck, layouts, dtypes,
large-mean accuracy and clear errors; on CUDA the kernels against the CPU op and the reference."""
import pytest
import torch
import torch.nn.functional as F

import tiger  # noqa: F401
from tiger.ops.group_norm import GroupNormSiLU, group_norm, group_norm_input_grad, group_norm_with_stats
from tiger.testing.cuda_graphs import capture

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
F64 = torch.float64
CL = torch.channels_last
LOW = {torch.bfloat16: 3e-2, torch.float16: 4e-3, torch.float32: 2e-5, F64: 1e-12}


def reference(x, groups, w, b, eps, silu):
    """y = act((x − μ_ng)/√(σ²_ng + ε)·w_c + b_c), μ and the biased σ² over each (n, group), in float64."""
    n, c, h, wd = x.shape
    xg = x.to(F64).reshape(n, groups, (c // groups) * h * wd)
    mu = xg.sum(-1, keepdim=True) / xg.shape[-1]
    var = ((xg - mu) ** 2).sum(-1, keepdim=True) / xg.shape[-1]
    z = ((xg - mu) / torch.sqrt(var + eps)).reshape(n, c, h, wd)
    if w is not None:
        z = z * w.to(F64)[None, :, None, None]
    if b is not None:
        z = z + b.to(F64)[None, :, None, None]
    return z / (1 + torch.exp(-z)) if silu else z


def make(n=2, c=8, h=5, w=6, dtype=F64, seed=0, layout=None, mean=0.0, scale=1.0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    x = (mean + scale * torch.randn(n, c, h, w, generator=g, dtype=F64)).to(device=device, dtype=dtype)
    wt = (1 + 0.5 * torch.randn(c, generator=g, dtype=F64)).to(device=device, dtype=dtype)
    bs = (0.3 * torch.randn(c, generator=g, dtype=F64)).to(device=device, dtype=dtype)
    if layout == "cl":
        x = x.contiguous(memory_format=CL)
    return x, wt, bs


def is_cl(t):
    return t.is_contiguous(memory_format=CL) and not t.is_contiguous()


@pytest.mark.parametrize("dtype", [F64, torch.float32, torch.bfloat16, torch.float16])
@pytest.mark.parametrize("layout", ["nchw", "cl"])
@pytest.mark.parametrize("silu", [False, True])
def test_values_match_reference(dtype, layout, silu):
    x, w, b = make(dtype=dtype, layout=layout)
    y = group_norm(x, 4, w, b, 1e-5, silu)
    assert y.dtype == dtype and is_cl(y) == (layout == "cl") and y.is_contiguous(memory_format=CL if layout == "cl" else torch.contiguous_format)
    ref = reference(x, 4, w, b, 1e-5, silu)
    torch.testing.assert_close(y.to(F64), ref, atol=LOW[dtype], rtol=LOW[dtype])
    witness = F.group_norm(x.to(F64), 4, w.to(F64), b.to(F64), 1e-5)
    torch.testing.assert_close(ref, F.silu(witness) if silu else witness, atol=1e-12, rtol=1e-12)


def test_float32_params_with_half_input_and_no_affine():
    x, w, b = make(dtype=torch.bfloat16, layout="cl")
    y = group_norm(x, 2, w.float(), b.float(), 1e-6, True)
    torch.testing.assert_close(y.to(F64), reference(x, 2, w.float(), b.float(), 1e-6, True), atol=3e-2, rtol=3e-2)
    y0 = group_norm(x.float(), 2, None, None, 1e-6, False)
    torch.testing.assert_close(y0.to(F64), reference(x.float(), 2, None, None, 1e-6, False), atol=2e-5, rtol=2e-5)


@pytest.mark.parametrize("layout", ["nchw", "cl"])
@pytest.mark.parametrize("silu", [False, True])
def test_gradients_match_reference(layout, silu):
    x, w, b = make(layout=layout, seed=3)
    leaves = [t.clone().requires_grad_() for t in (x, w, b)]
    ref_leaves = [t.clone().requires_grad_() for t in (x, w, b)]
    gy = torch.randn(x.shape, dtype=F64, generator=torch.Generator().manual_seed(9))
    (group_norm(leaves[0], 4, leaves[1], leaves[2], 1e-5, silu) * gy).sum().backward()
    (reference(ref_leaves[0], 4, ref_leaves[1], ref_leaves[2], 1e-5, silu) * gy).sum().backward()
    for a, r in zip(leaves, ref_leaves):
        torch.testing.assert_close(a.grad, r.grad, atol=1e-10, rtol=1e-10)
    assert is_cl(leaves[0].grad) == (layout == "cl")


@pytest.mark.parametrize("layout", ["nchw", "cl"])
def test_gradcheck_and_opcheck(layout):
    x, w, b = make(n=2, c=6, h=3, w=4, layout=layout, seed=1)
    for silu in (False, True):
        args = [t.clone().requires_grad_() for t in (x, w, b)]
        assert torch.autograd.gradcheck(lambda a, ww, bb: group_norm(a, 3, ww, bb, 1e-5, silu), args)
    assert torch.autograd.gradcheck(lambda a: group_norm(a, 2, None, None, 1e-5, True), (x.clone().requires_grad_(),))
    torch.library.opcheck(torch.ops.tiger.group_norm, (x, w, b, 3, 1e-5, True))
    torch.library.opcheck(torch.ops.tiger.group_norm, (x.float(), w.float(), None, 2, 1e-5, False))
    torch.library.opcheck(torch.ops.tiger.group_norm, (x.float().requires_grad_(), None, None, 3, 1e-5, True))


@pytest.mark.parametrize("layout", ["nchw", "cl"])
@pytest.mark.parametrize("per_sample", [False, True])
def test_input_bias_equals_norm_of_the_sum(layout, per_sample):
    """input_bias: the same values and gradients as the norm of x + bias (float64), the bias's
    gradient included; gradcheck and opcheck with it."""
    x, w, b = make(n=2, c=8, h=4, w=5, layout=layout, seed=11, mean=3.0)
    g = torch.Generator().manual_seed(12)
    ib = torch.randn((2, 8) if per_sample else (8,), generator=g, dtype=F64) * 5
    ib_map = ib[:, :, None, None] if per_sample else ib[None, :, None, None]
    gy = torch.randn(x.shape, dtype=F64, generator=g)
    for silu in (False, True):
        xa, iba = x.clone().requires_grad_(), ib.clone().requires_grad_()
        xr, ibr = x.clone().requires_grad_(), ib.clone().requires_grad_()
        y = group_norm(xa, 4, w, b, 1e-5, silu, input_bias=iba)
        ref = reference(xr + (ibr[:, :, None, None] if per_sample else ibr[None, :, None, None]), 4, w, b, 1e-5, silu)
        torch.testing.assert_close(y, ref, atol=1e-12, rtol=1e-12)
        assert is_cl(y) == (layout == "cl")
        (y * gy).sum().backward()
        (ref * gy).sum().backward()
        torch.testing.assert_close(xa.grad, xr.grad, atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(iba.grad, ibr.grad, atol=1e-10, rtol=1e-10)
    assert torch.autograd.gradcheck(lambda a, c: group_norm(a, 4, w, b, 1e-5, True, input_bias=c),
                                    (x.clone().requires_grad_(), ib.clone().requires_grad_()))
    torch.library.opcheck(torch.ops.tiger.group_norm, (x, w, b, 4, 1e-5, True, ib))
    torch.testing.assert_close(group_norm(x.float(), 4, w.float(), b.float(), 1e-5, True, ib.float()).double(),
                               reference(x + ib_map, 4, w, b, 1e-5, True), atol=2e-5, rtol=2e-5)
    with pytest.raises(RuntimeError, match=r"input_bias must be \[C\] = \[8\] or \[N, C\]"):
        group_norm(x, 4, w, b, 1e-5, True, input_bias=torch.zeros(3, dtype=F64))


def _strided_biases(n: int, c: int, device: str, seed: int) -> list[tuple[str, torch.Tensor]]:
    """input_bias views read in place (no copy): a column slice of a wider [N, C'] matrix, a [C]
    row (row stride 0) and a [1, C] row expanded to [N, C] (row stride 0)."""
    g = torch.Generator().manual_seed(seed)
    wide = (torch.randn(n, c + 24, generator=g) * 3).to(device)
    row = (torch.randn(c, generator=g) * 3).to(device)
    return [("slice", wide[:, 16:16 + c]), ("channel", row), ("expanded", row[None].expand(n, -1))]


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if CUDA else []))
@pytest.mark.parametrize("layout", ["nchw", "cl"])
def test_strided_input_bias_equals_its_contiguous_copy(device, layout):
    """A strided input bias (what the UNets' stacked time biases hand the norms) gives exactly the
    values and gradients of its contiguous copy, on the CPU and on CUDA (the one-launch forward's
    maps and the three-kernel walk's), forward and backward."""
    shapes = [(2, 8, 5, 6, 4)] if device == "cpu" else [(2, 128, 8, 8, 32), (2, 320, 40, 40, 32)]
    dtypes = [F64] if device == "cpu" else [torch.float32, torch.bfloat16]
    for (n, c, h, w_, groups), dtype in [(s, d) for s in shapes for d in dtypes]:
        x, w, b = make(n, c, h, w_, dtype=dtype, layout=layout, seed=c, mean=1.0, device=device)
        gy = torch.randn(x.shape, generator=torch.Generator().manual_seed(5), dtype=F64).to(device)
        for name, ib in _strided_biases(n, c, device, seed=c + 1):
            for silu in (False, True):
                outs = []
                for bias in (ib, ib.contiguous()):
                    xa = x.clone().requires_grad_()
                    y = group_norm(xa, groups, w, b, 1e-6, silu, input_bias=bias)
                    (y.to(F64) * gy).sum().backward()
                    outs.append((y.detach(), xa.grad))
                assert torch.equal(outs[0][0], outs[1][0]), (name, dtype, silu)
                assert torch.equal(outs[0][1], outs[1][1]), (name, dtype, silu)
                ref = reference(x.to(F64) + ib.to(F64).expand(n, c)[:, :, None, None], groups, w.to(F64),
                                b.to(F64), 1e-6, silu)
                tol = LOW[dtype] if dtype != torch.float32 else 1e-4
                torch.testing.assert_close(outs[0][0].to(F64), ref, atol=tol, rtol=tol)


@pytest.mark.parametrize("layout", ["nchw", "cl"])
@pytest.mark.parametrize("dtype", [F64, torch.bfloat16])
def test_input_grad_adds_the_residual_gradient_before_rounding(layout, dtype):
    x, w, b = make(dtype=dtype, layout=layout, seed=3)
    ib = torch.randn(2, 8, generator=torch.Generator().manual_seed(4), dtype=F64)
    gy = torch.randn(x.shape, generator=torch.Generator().manual_seed(5), dtype=F64).to(dtype)
    res = torch.randn(x.shape, generator=torch.Generator().manual_seed(6), dtype=F64).to(dtype)
    y, mean, rstd = group_norm_with_stats(x, 4, w, b, 1e-5, True, ib)
    torch.testing.assert_close(y, group_norm(x, 4, w, b, 1e-5, True, ib), atol=0, rtol=0)
    xr = x.to(F64).detach().requires_grad_()
    (gx,) = torch.autograd.grad(reference(xr + ib[:, :, None, None], 4, w, b, 1e-5, True), xr, gy.to(F64))
    got = group_norm_input_grad(gy, x, 4, mean, rstd, w, b, True, ib, residual_grad=res)
    assert got.dtype == dtype and is_cl(got) == (layout == "cl")
    # one rounding of dx + residual (float64: exact to its rounding)
    tol = 1e-12 if dtype == F64 else 2.0 ** -8
    scale = (gx + res.to(F64)).abs().max()
    torch.testing.assert_close(got.to(F64) / scale, (gx + res.to(F64)) / scale, atol=tol, rtol=tol)
    plain = group_norm_input_grad(gy, x, 4, mean, rstd, w, b, True, ib)
    if dtype == F64:
        torch.testing.assert_close(got, plain + res, atol=1e-12, rtol=0)
    with pytest.raises(RuntimeError, match="residual_grad must have x's shape"):
        group_norm_input_grad(gy, x, 4, mean, rstd, w, b, True, ib, residual_grad=res[:1])


def test_large_mean_input_is_accurate():
    x, w, b = make(mean=1000.0, scale=1e-2, dtype=torch.float32, layout="cl", seed=2)
    y = group_norm(x, 4, w, b, 1e-6, True)
    torch.testing.assert_close(y.to(F64), reference(x, 4, w, b, 1e-6, True), atol=1e-4, rtol=1e-4)


def test_parameter_gradients_only_when_needed():
    x, w, b = make(dtype=torch.float32)
    ops = torch.ops.tiger
    y, mean, rstd = ops.group_norm(x, w, b, 4, 1e-5, True)
    gx, gw, gb = ops.group_norm_backward(torch.ones_like(y), x, w, b, mean, rstd, 4, True, False)
    assert gw.numel() == 0 and gb.numel() == 0 and gx.shape == x.shape
    xl = x.clone().requires_grad_()
    group_norm(xl, 4, w, b, 1e-5, True).sum().backward()  # frozen affine: dx only
    assert xl.grad is not None and w.grad is None


def test_module_matches_nn_group_norm_and_shares_parameters():
    gn = torch.nn.GroupNorm(4, 8, eps=1e-6).double()
    with torch.no_grad():
        gn.weight.normal_()
        gn.bias.normal_()
    m = GroupNormSiLU.from_group_norm(gn, silu=True)
    assert m.weight is gn.weight and m.bias is gn.bias
    assert list(m.state_dict()) == list(gn.state_dict())
    x, _, _ = make(seed=4)
    torch.testing.assert_close(m(x), F.silu(gn(x)), atol=1e-12, rtol=1e-12)
    tokens = torch.randn(2, 7, 8, dtype=F64)  # [N, L, C] as diffusers' attention blocks hold them
    out = m(tokens.transpose(1, 2))
    torch.testing.assert_close(out, F.silu(gn(tokens.transpose(1, 2))), atol=1e-12, rtol=1e-12)
    fresh = GroupNormSiLU(4, 8, affine=False)
    assert fresh.weight is None and "silu=False" in repr(fresh)


def test_bad_inputs_name_the_problem():
    x, w, b = make(dtype=torch.float32)
    with pytest.raises(RuntimeError, match="C = 8 channels of x are not divisible by num_groups = 3"):
        group_norm(x, 3, w, b)
    with pytest.raises(RuntimeError, match=r"weight must be \[C\] = \[8\]"):
        group_norm(x, 4, w[:5], b)
    with pytest.raises(RuntimeError, match=r"bias must be \[C\] = \[8\]"):
        group_norm(x, 4, w, b[None])
    with pytest.raises(RuntimeError, match="x must be float32, bfloat16 or float16"):
        group_norm(x.long(), 4)
    with pytest.raises(RuntimeError, match=r"x must be \[N, C, H, W\], got \[2, 8, 30\]"):
        group_norm(x.flatten(2), 4)
    with pytest.raises(RuntimeError, match="weight must have x's dtype"):
        group_norm(x.bfloat16(), 4, w.half(), None)
    with pytest.raises(RuntimeError, match="eps must be finite"):
        group_norm(x, 4, eps=-1.0)
    y, mean, rstd = torch.ops.tiger.group_norm(x, w, b, 4, 1e-5, False)
    with pytest.raises(RuntimeError, match=r"mean must be \[N, G\] = \[2, 4\]"):
        torch.ops.tiger.group_norm_backward(y, x, w, b, mean[:, :2], rstd, 4, False, False)
    with pytest.raises(ValueError, match="num_channels=6 is not divisible by num_groups=4"):
        GroupNormSiLU(4, 6)


# ---- CUDA ------------------------------------------------------------------------------------
# Shapes: D = 4 (VAE's 128 channels / 32), D = 10 (UNet's 320 / 32), a scalar path (C = 30 is no
# multiple of the 16-byte vector; H·W = 35 neither), and one large enough for several chunks. On
# compute capability 9.0 channels-last maps go to the one-launch forward where a block's registers
# hold them (group_norm_small_cuda.cu): 8x8 and 6x5 maps with two and four groups a block; 40x40
# at D = 10, 96x80 and D = 60 (15 vectors a block row, over its limit of 8) take the three-kernel
# forward; 1920 channels are 240 vectors, four column passes of blocks of their own (grid z) in
# the three-kernel forward and in the backward.
CUDA_SHAPES = [(2, 128, 8, 8, 32), (3, 320, 6, 5, 32), (2, 30, 5, 7, 3), (1, 64, 96, 80, 8),
               (2, 320, 40, 40, 32), (1, 1920, 8, 8, 32)]


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
@pytest.mark.parametrize("layout", ["nchw", "cl"])
@pytest.mark.parametrize("shape", CUDA_SHAPES)
def test_cuda_matches_cpu_and_reference(dtype, layout, shape):
    n, c, h, w_, groups = shape
    x, w, b = make(n, c, h, w_, dtype=dtype, layout=layout, seed=c)
    gy = torch.randn(x.shape, generator=torch.Generator().manual_seed(5)).to(dtype)
    for silu in (False, True):
        outs = {}
        for dev in ("cpu", "cuda"):
            leaves = [t.to(dev).clone().requires_grad_() for t in (x, w, b)]
            y = group_norm(leaves[0], groups, leaves[1], leaves[2], 1e-6, silu)
            (y.float() * gy.to(dev).float()).sum().backward()
            assert is_cl(y) == (layout == "cl") and is_cl(leaves[0].grad) == (layout == "cl")
            outs[dev] = [t.detach().cpu().to(F64) for t in (y, leaves[0].grad, leaves[1].grad, leaves[2].grad)]
        tol = LOW[dtype] if dtype != torch.float32 else 1e-4
        ref = reference(x, groups, w, b, 1e-6, silu)
        torch.testing.assert_close(outs["cuda"][0], ref, atol=tol, rtol=tol)
        for a, r in zip(outs["cuda"], outs["cpu"]):  # dx, dw, db against the float64-accumulating CPU op
            scale = r.abs().max().clamp_min(1.0)
            torch.testing.assert_close(a / scale, r / scale, atol=tol * 2, rtol=tol * 2)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
@pytest.mark.parametrize("layout", ["nchw", "cl"])
@pytest.mark.parametrize("hw", [64, 16])  # 16x16 channels-last: the one-launch forward (compute capability 9.0)
def test_cuda_large_mean_and_determinism(layout, hw):
    x, w, b = make(4, 128, hw, hw, dtype=torch.float32, layout=layout, mean=1000.0, scale=1e-2, seed=7)
    xc, wc, bc = x.cuda(), w.cuda(), b.cuda()
    y, mean, rstd = torch.ops.tiger.group_norm(xc, wc, bc, 32, 1e-6, True)
    xg = x.to(F64).reshape(4, 32, -1)
    ref_mean, ref_std = xg.mean(-1), xg.std(-1, unbiased=False)  # σ ≈ 1e-2 under a mean of 1000
    torch.testing.assert_close(mean.cpu().to(F64), ref_mean, atol=0, rtol=1e-7)
    torch.testing.assert_close(rstd.cpu().to(F64), 1 / torch.sqrt(ref_std ** 2 + 1e-6), atol=0, rtol=1e-4)
    # y: the float32 mean is off by up to half an ulp of 1000 (3e-5 = 3e-3 σ): that, not the
    # variance, bounds y's error (a one-pass sum of squares would have lost σ² entirely).
    torch.testing.assert_close(y.cpu().to(F64), reference(x, 32, w, b, 1e-6, True), atol=1e-2, rtol=1e-2)
    y2 = group_norm(xc, 32, wc, bc, 1e-6, True)
    assert torch.equal(y, y2)
    a = xc.clone().requires_grad_()
    group_norm(a, 32, wc, bc, 1e-6, True).sum().backward()
    g1 = a.grad.clone()
    a.grad = None
    group_norm(a, 32, wc, bc, 1e-6, True).sum().backward()
    assert torch.equal(g1, a.grad)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("layout", ["nchw", "cl"])
@pytest.mark.parametrize("shape", CUDA_SHAPES)
def test_cuda_input_bias_matches_cpu(dtype, layout, shape):
    n, c, h, w_, groups = shape
    x, w, b = make(n, c, h, w_, dtype=dtype, layout=layout, seed=c + 1, mean=2.0)
    ib = torch.randn(n, c, generator=torch.Generator().manual_seed(c)) * 3
    gy = torch.randn(x.shape, generator=torch.Generator().manual_seed(6)).to(dtype)
    for silu in (False, True):
        outs = {}
        for dev in ("cpu", "cuda"):
            xa, iba = x.to(dev).clone().requires_grad_(), ib.to(dev).clone().requires_grad_()
            y = group_norm(xa, groups, w.to(dev), b.to(dev), 1e-6, silu, input_bias=iba)
            (y.float() * gy.to(dev).float()).sum().backward()
            assert is_cl(y) == (layout == "cl")
            outs[dev] = [t.detach().cpu().to(F64) for t in (y, xa.grad, iba.grad)]
        tol = LOW[dtype] if dtype != torch.float32 else 1e-4
        ref = reference(x.to(F64) + ib.to(F64)[:, :, None, None], groups, w, b, 1e-6, silu)
        torch.testing.assert_close(outs["cuda"][0], ref, atol=tol, rtol=tol)
        for a, r in zip(outs["cuda"], outs["cpu"]):
            scale = r.abs().max().clamp_min(1.0)
            torch.testing.assert_close(a / scale, r / scale, atol=tol * 2, rtol=tol * 2)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("layout", ["nchw", "cl"])
@pytest.mark.parametrize("shape", CUDA_SHAPES)
def test_cuda_residual_grad_matches_cpu(dtype, layout, shape):
    n, c, h, w_, groups = shape
    x, w, b = make(n, c, h, w_, dtype=dtype, layout=layout, seed=c + 2)
    gy = torch.randn(x.shape, generator=torch.Generator().manual_seed(7)).to(dtype)
    res = torch.randn(x.shape, generator=torch.Generator().manual_seed(8)).to(dtype)
    outs = {}
    for dev in ("cpu", "cuda"):
        xa = x.to(dev)
        _, mean, rstd = group_norm_with_stats(xa, groups, w.to(dev), b.to(dev), 1e-6, True)
        with_res = group_norm_input_grad(gy.to(dev), xa, groups, mean, rstd, w.to(dev), b.to(dev), True,
                                         residual_grad=res.to(dev))
        without = group_norm_input_grad(gy.to(dev), xa, groups, mean, rstd, w.to(dev), b.to(dev), True)
        assert is_cl(with_res) == (layout == "cl")
        outs[dev] = (with_res.cpu().to(F64), without.cpu().to(F64))
    tol = LOW[dtype] if dtype != torch.float32 else 1e-4
    for a, r in zip(outs["cuda"], outs["cpu"]):
        scale = r.abs().max().clamp_min(1.0)
        torch.testing.assert_close(a / scale, r / scale, atol=tol * 2, rtol=tol * 2)
    # the residual is added before the one rounding: within a rounding of the unfused sum
    fused, plain = outs["cuda"]
    unfused = plain + res.to(F64)
    scale = unfused.abs().max().clamp_min(1.0)
    tol = 2 * LOW[dtype] if dtype != torch.float32 else 1e-6
    torch.testing.assert_close(fused / scale, unfused / scale, atol=tol, rtol=0)


# Channels-last maps whose input gradient runs in one launch on an H100 (launch_backward_small: a
# block per (sample, channel block), at least 3/4 of the SMs' worth of blocks): 1, 2 and 4 groups
# a block, a block row of 1-5 vectors (255 threads), a large mean.
ONE_LAUNCH_BACKWARD_SHAPES = [(4, 512, 8, 8, 32), (8, 128, 9, 9, 32), (16, 320, 5, 5, 32), (4, 256, 12, 10, 32)]


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
@pytest.mark.parametrize("shape", ONE_LAUNCH_BACKWARD_SHAPES)
def test_cuda_one_launch_input_grad_matches_float64(dtype, shape):
    """The input gradient alone (no parameter gradients: the one-launch kernel on these maps) against
    float64 autograd, with and without SiLU, a strided input bias and a residual gradient; the
    three-kernel backward (asked for parameter gradients too) gives the same dx to rounding;
    repeated calls are bit-identical."""
    n, c, h, w_, groups = shape
    x, w, b = make(n, c, h, w_, dtype=dtype, layout="cl", seed=c + h, mean=4.0, device="cuda")
    gen = torch.Generator().manual_seed(c)
    gy = torch.randn(x.shape, generator=gen).to("cuda", dtype).contiguous(memory_format=CL)
    res = torch.randn(x.shape, generator=gen).to("cuda", dtype).contiguous(memory_format=CL)
    ib = (torch.randn(n, c + 8, generator=gen) * 2).cuda()[:, 8:]
    for silu in (False, True):
        for bias, residual in ((None, None), (ib, res)):
            y, mean, rstd = group_norm_with_stats(x, groups, w, b, 1e-6, silu, bias)
            dx = group_norm_input_grad(gy, x, groups, mean, rstd, w, b, silu, bias, residual)
            assert is_cl(dx) and dx.dtype == dtype
            assert torch.equal(dx, group_norm_input_grad(gy, x, groups, mean, rstd, w, b, silu, bias, residual))
            x64 = x.to(F64).requires_grad_()
            shifted = x64 if bias is None else x64 + bias.to(F64)[:, :, None, None]
            (ref,) = torch.autograd.grad(reference(shifted, groups, w, b, 1e-6, silu), x64, gy.to(F64))
            if residual is not None:
                ref = ref + residual.to(F64)
            scale = ref.abs().max().clamp_min(1.0)
            tol = {torch.float32: 1e-4, torch.bfloat16: 3e-2, torch.float16: 4e-3}[dtype]
            torch.testing.assert_close(dx.to(F64) / scale, ref / scale, atol=tol, rtol=tol)
            walk = torch.ops.tiger.group_norm_backward(gy, x, w, b, mean, rstd, groups, silu, True, bias, residual)[0]
            torch.testing.assert_close(dx.to(F64) / scale, walk.to(F64) / scale, atol=tol, rtol=tol)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
def test_cuda_unaligned_views_and_opcheck():
    x, w, b = make(2, 16, 8, 8, dtype=torch.bfloat16, layout="cl", seed=8)
    flat = torch.cat([torch.zeros(1, dtype=x.dtype), x.permute(0, 2, 3, 1).reshape(-1)]).cuda()
    xv = flat[1:].view(2, 8, 8, 16).permute(0, 3, 1, 2)  # channels-last, 2-byte offset: scalar path
    assert is_cl(xv) and xv.data_ptr() % 16 != 0
    y = group_norm(xv, 4, w.cuda(), b.cuda(), 1e-6, True)
    torch.testing.assert_close(y.cpu().to(F64), reference(x, 4, w, b, 1e-6, True), atol=3e-2, rtol=3e-2)
    torch.library.opcheck(torch.ops.tiger.group_norm, (x.cuda().float().requires_grad_(), w.cuda().float(), b.cuda().float(), 4, 1e-5, True))


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
def test_cuda_graph_capture_and_replay():
    x, w, b = make(4, 128, 32, 32, dtype=torch.bfloat16, layout="cl", seed=11)
    xc, wc, bc = x.cuda(), w.cuda(), b.cuda()
    gy = torch.randn(x.shape, device="cuda", dtype=x.dtype).contiguous(memory_format=CL)

    def step(inp):
        leaf = inp.detach().requires_grad_()
        y = group_norm(leaf, 32, wc, bc, 1e-6, True)
        (gx,) = torch.autograd.grad(y, leaf, gy)
        return y.detach(), gx

    static_x = xc.clone()
    graph, (static_y, static_gx) = capture(lambda: step(static_x), warmup=2)
    for seed in (1, 2):
        new = torch.randn(x.shape, generator=torch.Generator().manual_seed(seed)).to(x.dtype).cuda()
        static_x.copy_(new.contiguous(memory_format=CL))
        graph.replay()
        want_y, want_gx = step(static_x)
        assert torch.equal(static_y, want_y) and torch.equal(static_gx, want_gx)


def test_walk_grid_constants_are_the_measured_ones():
    """csrc/group_norm/group_norm.h plans the walks' grids: the forward for 4 blocks per SM, the
    backward for 2 blocks per SM in 2 waves, the fastest of the variants measured on the H100 on
    the VAE's largest input gradient (benchmarks/gpu/results/group_norm_backward_occupancy_variants_h100.txt,
    V<blocks><waves>). A change there must be re-measured."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    header = (root / "csrc/group_norm/group_norm.h").read_text()
    consts = {k: int(v) for k, v in re.findall(r"constexpr int (k\w+) = (\d+);", header)}
    assert (consts["kForwardBlocksPerSm"], consts["kBackwardBlocksPerSm"], consts["kBackwardWaves"]) == (4, 2, 2)
    raw = (root / "benchmarks/gpu/results/group_norm_backward_occupancy_variants_h100.txt").read_text()
    tags = next(l for l in raw.splitlines() if l.startswith("shape | pass |")).split(" | ")[2:]
    row = next(l for l in raw.splitlines() if l.startswith("4x128x512x512 | bwd |")).split(" | ")[2:]
    times = dict(zip(tags, map(float, row)))
    kept = f"V{consts['kBackwardBlocksPerSm']}{consts['kBackwardWaves']}"
    assert min(times, key=times.get) == kept, times


def test_one_launch_input_grad_constants_are_the_measured_ones():
    """csrc/group_norm/group_norm_small_cuda.cu runs the one-launch input gradient in 512-thread
    blocks on maps whose x and dy fit 36 MiB: of the variants measured on the H100
    (benchmarks/gpu/results/group_norm_one_launch_input_grad_h100.txt, second call: t256 = 256
    threads, variant72 = 512 threads admitting 72 MiB, final = the kept constants), 512 threads is
    the faster at 4x512x64², and the 72 MiB bound made 4x256x128² (64 MiB) slower. A change there
    must be re-measured."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    src = (root / "csrc/group_norm/group_norm_small_cuda.cu").read_text()
    assert int(re.search(r"constexpr int kBackwardThreads = (\d+);", src).group(1)) == 512
    assert int(re.search(r"kSmallBackwardMaxBytes = int64_t\((\d+)\) << 20;", src).group(1)) == 36
    assert 4 * 256 * 128 * 128 * 2 * 2 > 36 << 20 >= 4 * 512 * 64 * 64 * 2 * 2  # bf16 x + dy
    raw = (root / "benchmarks/gpu/results/group_norm_one_launch_input_grad_h100.txt").read_text()
    second = raw[raw.index("# call 5"):]
    times = {(tag, shape): float(us) for tag, shape, us in
             re.findall(r"^(t256|variant72|final) (\S+) bwd ([\d.]+) us$", second, re.M)}
    assert times[("final", "4x512x64x64")] < times[("t256", "4x512x64x64")]
    assert times[("variant72", "4x256x128x128")] > times[("final", "4x256x128x128")]

