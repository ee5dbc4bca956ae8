"""``tiger::channel_bias_add_moments`` and ``group_norm(..., moments=)``: the sum is
channel_bias_add's, the moments are the float64 moments of the stored sum, and a GroupNorm given
them equals the GroupNorm that takes its own statistics (CPU: to float rounding; CUDA: bit for bit,
the same walk); attached moments follow the tensor's version."""
from __future__ import annotations

import pytest
import torch

from tiger.ops import cuda_enabled
from tiger.ops.channel_bias import channel_bias_add
from tiger.ops.group_norm import attach_moments, channel_bias_add_moments, group_norm, group_norm_with_stats, moments_of


def _inputs(shape=(2, 8, 5, 6), dtype=torch.float32, layout="nchw", per_sample=True, residual=True, device="cpu",
            mean=10.0, seed=0):
    gen = torch.Generator().manual_seed(seed)
    n, c = shape[:2]
    x = (torch.randn(shape, generator=gen, dtype=torch.float64) * 3 + mean).to(dtype).to(device)
    if layout == "nhwc":
        x = x.contiguous(memory_format=torch.channels_last)
    b = torch.randn((n, c) if per_sample else (c,), generator=gen, dtype=torch.float64).to(dtype).to(device)
    r = torch.randn(shape, generator=gen, dtype=torch.float64).to(dtype).to(device) if residual else None
    return x, b, r


def _reference_moments(y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per (n, c): mean of y - y[n, c, 0, 0] and the sum of squared deviations, float64."""
    yd = y.double().flatten(2)
    rel = yd - yd[:, :, :1]
    mu = rel.mean(dim=2)
    return mu, ((rel - mu[:, :, None]) ** 2).sum(dim=2)


@pytest.mark.parametrize("layout", ["nchw", "nhwc"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.bfloat16])
@pytest.mark.parametrize("per_sample, residual", [(True, True), (False, False)])
def test_cpu_sum_is_channel_bias_add_and_moments_are_its_moments(layout, dtype, per_sample, residual):
    x, b, r = _inputs(dtype=dtype, layout=layout, per_sample=per_sample, residual=residual)
    y, m = channel_bias_add_moments(x, b, r)
    assert torch.equal(y, channel_bias_add(x, b, r))
    assert y.is_contiguous(memory_format=torch.channels_last) == (layout == "nhwc")
    n, c = x.shape[:2]
    assert m.shape == ((2, n, 1, c) if layout == "nhwc" else (2, n, c, 1, 1))
    assert m.dtype == (torch.float64 if dtype == torch.float64 else torch.float32)
    mu, m2 = _reference_moments(y)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    assert torch.allclose(m[0].reshape(n, c).double(), mu, rtol=tol, atol=tol)
    assert torch.allclose(m[1].reshape(n, c).double(), m2, rtol=tol, atol=tol)


@pytest.mark.parametrize("layout", ["nchw", "nhwc"])
@pytest.mark.parametrize("silu", [False, True])
def test_cpu_group_norm_given_moments_equals_its_own_statistics(layout, silu):
    x, b, r = _inputs(dtype=torch.float64, layout=layout)
    y, m = channel_bias_add_moments(x, b, r)
    w = torch.randn(8, dtype=torch.float64)
    bb = torch.randn(8, dtype=torch.float64)
    ib = torch.randn(2, 8, dtype=torch.float64)
    for input_bias in (None, ib):
        own = group_norm_with_stats(y, 4, w, bb, 1e-5, silu, input_bias)
        given = group_norm_with_stats(y, 4, w, bb, 1e-5, silu, input_bias, m)
        for a, e in zip(given, own):
            assert torch.allclose(a, e, rtol=1e-11, atol=1e-12), float((a - e).abs().max())


def test_cpu_group_norm_reads_moments_of_several_chunks_and_lanes():
    """Moments as the CUDA walk lays them out (K chunks; NCHW rows of V lanes) give the group
    statistics: built here by hand from float64 sums."""
    y = torch.randn(2, 4, 4, 6, dtype=torch.float64) * 2 + 5
    n, c, hw = 2, 4, 24

    def partials(vals: torch.Tensor, shift: torch.Tensor, counts: list[int]):
        out_m, out_m2, start = [], [], 0
        for k in counts:
            part = vals[..., start:start + k] - shift[..., None]
            mu = part.mean(dim=-1)
            out_m.append(mu)
            out_m2.append(((part - mu[..., None]) ** 2).sum(dim=-1))
            start += k
        return torch.stack(out_m, dim=-1), torch.stack(out_m2, dim=-1)

    flat = y.flatten(2)  # [N, C, HW]
    shift = flat[..., 0]
    # channels-last: 3 chunks of ceil(24 / 3) = 8 pixels -> [2, N, K, C]
    pm, pm2 = partials(flat, shift, [8, 8, 8])
    nhwc = torch.stack([pm.permute(0, 2, 1), pm2.permute(0, 2, 1)]).contiguous()
    # NCHW, V = 2 lanes: rows of 2 pixels (12 rows), K = 5 chunks of ceil(12 / 5) = 3 rows (last: 0 rows? no: 3,3,3,3)
    lanes = flat.reshape(n, c, 12, 2).transpose(2, 3)  # [N, C, V, rows]
    lm, lm2 = partials(lanes, shift[..., None].expand(n, c, 2), [3, 3, 3, 3])
    nchw = torch.stack([lm.permute(0, 1, 3, 2), lm2.permute(0, 1, 3, 2)]).contiguous()  # [2, N, C, K, V]
    own = group_norm_with_stats(y, 2)
    for moments in (nhwc, nchw):
        given = group_norm_with_stats(y, 2, moments=moments)
        for a, e in zip(given, own):
            assert torch.allclose(a, e, rtol=1e-11, atol=1e-12)


def test_gradients_are_channel_bias_adds():
    x, b, r = _inputs(dtype=torch.float64, shape=(2, 3, 3, 2))
    for args in ((x, b, r), (x, b)):
        leaves = [a.detach().clone().requires_grad_(True) for a in args]
        torch.autograd.gradcheck(lambda *a: channel_bias_add_moments(*a)[0], leaves)
        y, m = channel_bias_add_moments(*leaves)
        assert not m.requires_grad


def test_opcheck():
    x, b, r = _inputs(dtype=torch.float32, shape=(2, 4, 3, 3), layout="nhwc")
    torch.library.opcheck(torch.ops.tiger.channel_bias_add_moments, (x, b, r))
    y, m = channel_bias_add_moments(x, b, r)
    torch.library.opcheck(torch.ops.tiger.group_norm, (y, None, None, 2, 1e-5, True, None, m))


def test_bad_moments_name_the_problem():
    x, b, r = _inputs(shape=(2, 8, 4, 4))
    y, m = channel_bias_add_moments(x, b, r)
    with pytest.raises(RuntimeError, match="moments .* do not belong to x"):
        group_norm(y[:1], 4, moments=m)
    with pytest.raises(RuntimeError, match="moments must have dtype"):
        group_norm(y, 4, moments=m.double())
    with pytest.raises(RuntimeError, match="moments must be \\[2, N, K, C\\]"):
        group_norm(y, 4, moments=m.flatten())
    with pytest.raises(RuntimeError, match="non-empty chunks"):
        group_norm(y, 4, moments=torch.zeros(2, 2, 17, 8))
    with pytest.raises(RuntimeError, match="bias must be \\[C\\]"):
        channel_bias_add_moments(x, b[:, :3])


def test_attached_moments_follow_the_tensor_version():
    x, b, r = _inputs()
    y, m = channel_bias_add_moments(x, b, r)
    assert attach_moments(y, m) is y and moments_of(y) is m
    assert moments_of(y[:1]) is None and moments_of(y.view_as(y)) is None  # views carry nothing
    y.add_(1.0)
    assert moments_of(y) is None  # changed since


# -- CUDA: the same walk as group_norm's statistics pass, so the same bits ---------------------
cuda = pytest.mark.skipif(not (torch.cuda.is_available() and cuda_enabled()), reason="needs CUDA kernels")


@pytest.mark.cuda
@cuda
@pytest.mark.parametrize("layout", ["nchw", "nhwc"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
@pytest.mark.parametrize("shape", [(2, 64, 16, 16), (4, 320, 8, 8), (1, 24, 5, 7), (3, 1280, 2, 2)])
def test_cuda_sum_and_norm_equal_the_separate_passes_bit_for_bit(layout, dtype, shape):
    for per_sample, residual in ((True, True), (False, False)):
        x, b, r = _inputs(shape=shape, dtype=dtype, layout=layout, per_sample=per_sample, residual=residual,
                          device="cuda", mean=3.0)
        y, m = channel_bias_add_moments(x, b, r)
        assert torch.equal(y, channel_bias_add(x, b, r))
        assert y.is_contiguous(memory_format=torch.channels_last) == (layout == "nhwc")
        w = torch.randn(shape[1], device="cuda", dtype=dtype)
        for silu in (False, True):
            own = group_norm_with_stats(y, shape[1] // 8 if shape[1] % 8 == 0 else 1, w, w, 1e-6, silu)
            given = group_norm_with_stats(y, shape[1] // 8 if shape[1] % 8 == 0 else 1, w, w, 1e-6, silu, None, m)
            for a, e in zip(given, own):
                assert torch.equal(a, e)
        # the statistics from the CUDA moments are y's, as float64 sums on the CPU give them
        yd = y.cpu().double()
        ref = group_norm_with_stats(yd, 1, moments=channel_bias_add_moments(yd, yd.new_zeros(shape[1]))[1])
        got = group_norm_with_stats(y, 1, moments=m)
        for a, e in zip(got[1:], ref[1:]):
            assert torch.allclose(a.double().cpu(), e, rtol=1e-5, atol=1e-6)


@pytest.mark.cuda
@cuda
def test_cuda_unaligned_inputs_and_graph_capture():
    x, b, r = _inputs(shape=(2, 16, 9, 9), layout="nchw", device="cuda")
    xs = torch.empty(x.numel() + 1, device="cuda")[1:].view_as(x).copy_(x)  # 4-byte aligned only
    y, m = channel_bias_add_moments(xs, b, r)
    assert m.shape[-1] == 1 and torch.equal(y, channel_bias_add(x, b, r))
    assert torch.equal(group_norm(y, 4, moments=m), group_norm(y, 4))
    torch.library.opcheck(torch.ops.tiger.channel_bias_add_moments, (x, b, r))
    static = x.clone()
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        for _ in range(2):  # warm-up before the capture
            group_norm(*channel_bias_add_moments(static, b, r)[:1], 4)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g):
            ys, ms = channel_bias_add_moments(static, b, r)
            out = group_norm(ys, 4, moments=ms)
    torch.cuda.current_stream().wait_stream(stream)
    static.copy_(x * 2)
    g.replay()
    torch.cuda.synchronize()
    y2 = channel_bias_add(x * 2, b, r)
    assert torch.equal(out, group_norm(y2, 4))
