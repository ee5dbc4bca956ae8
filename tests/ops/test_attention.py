"""tiger::attention_rows against softmax attention written out here in float64 (CPU: every shape;
CUDA: the head-dim-40 Hopper kernel in every schedule and CTA size, strided q/k/v views, peaked
and flat softmaxes, lengths that 64·warpgroups does not divide, its error no larger than cuDNN's SDPA
on the same bf16 inputs), the reference paths the CUDA op takes for other shapes, opcheck, clear
errors."""
import pytest
import torch
import torch.nn.functional as F

import tiger  # noqa: F401
from tiger.ops.attention import SCHEDULES, attention_rows

VARIANTS = [(k, w) for k, ws in SCHEDULES.items() for w in ws]

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
HOPPER = CUDA and torch.cuda.get_device_capability() == (9, 0)


def attention64(q, k, v, batch, heads, scale=None):
    """The definition in float64: per (sequence, head), softmax(q kᵀ · scale) v."""
    n, width = q.shape
    L, D = n // batch, width // heads
    scale = D ** -0.5 if scale is None else scale
    out = torch.empty(n, width, dtype=torch.float64, device=q.device)  # float64 on q's device
    q, k, v = (t.detach().double() for t in (q, k, v))
    for b in range(batch):
        rows = slice(b * L, (b + 1) * L)
        for h in range(heads):
            cols = slice(h * D, (h + 1) * D)
            s = q[rows, cols] @ k[rows, cols].T * scale
            w = torch.exp(s - s.max(dim=1, keepdim=True).values)
            out[rows, cols] = (w / w.sum(dim=1, keepdim=True)) @ v[rows, cols]
    return out


def sdpa_rows(q, k, v, batch, heads):
    """The peer on the same rows: torch's F.scaled_dot_product_attention (cuDNN's on an H100), as
    the guidances' transformer blocks call it."""
    view = [t.unflatten(1, (heads, -1)).unflatten(0, (batch, -1)).transpose(1, 2) for t in (q, k, v)]
    return F.scaled_dot_product_attention(*view).transpose(1, 2).reshape(q.shape[0], -1)


def stacked_qkv(batch, L, heads, D, dtype, device, gen, spread=1.0):
    """q, k, v as the strided column blocks of one [batch·L, 3·heads·D] matmul output."""
    qkv = (torch.randn(batch * L, 3 * heads * D, generator=gen, dtype=torch.float64) * spread).to(dtype).to(device)
    w = heads * D
    return qkv[:, :w], qkv[:, w:2 * w], qkv[:, 2 * w:]


@pytest.mark.parametrize("batch,L,heads,D", [(1, 5, 1, 3), (2, 7, 3, 4), (3, 16, 2, 40)])
@pytest.mark.parametrize("scale", [None, 0.3])
def test_cpu_matches_the_definition(batch, L, heads, D, scale):
    g = torch.Generator().manual_seed(batch * 100 + L)
    q, k, v = stacked_qkv(batch, L, heads, D, torch.float64, "cpu", g)
    out = attention_rows(q, k, v, batch, heads, scale)
    assert out.shape == q.shape and out.is_contiguous() and out.dtype == torch.float64
    torch.testing.assert_close(out, attention64(q, k, v, batch, heads, scale), rtol=1e-12, atol=1e-12)


def test_cpu_bfloat16_rounds_the_float32_result_once():
    g = torch.Generator().manual_seed(3)
    q, k, v = stacked_qkv(2, 9, 2, 8, torch.bfloat16, "cpu", g)
    out = attention_rows(q, k, v, 2, 2)
    ref = attention64(q, k, v, 2, 2)
    assert out.dtype == torch.bfloat16
    assert ((out.double() - ref).abs() <= ref.abs() * 2 ** -8 + 1e-6).all()  # float32 math, one bf16 rounding


def test_opcheck():
    g = torch.Generator().manual_seed(4)
    q, k, v = stacked_qkv(2, 6, 2, 4, torch.float32, "cpu", g)
    torch.library.opcheck(torch.ops.tiger.attention_rows, (q, k, v, 2, 2), {"scale": None, "schedule": "producer", "warpgroups": 3},
                          test_utils=("test_schema", "test_faketensor"))


def test_errors_name_the_problem():
    q = torch.zeros(8, 6)
    with pytest.raises(RuntimeError, match=r"k must have q's shape \[8, 6\]"):
        attention_rows(q, torch.zeros(4, 6), q, 1, 2)
    with pytest.raises(RuntimeError, match="not a multiple of heads = 4"):
        attention_rows(q, q, q, 1, 4)
    with pytest.raises(RuntimeError, match="not a multiple of batch = 3"):
        attention_rows(q, q, q, 3, 2)
    with pytest.raises(RuntimeError, match="v has dtype"):
        attention_rows(q, q, q.double(), 1, 2)
    with pytest.raises(ValueError, match=r"\(schedule, warpgroups\) must be one of"):
        attention_rows(q, q, q, 1, 2, warpgroups=4)  # the producer schedule takes 2-3
    with pytest.raises(RuntimeError, match="the lockstep schedule takes 1-4 warpgroups, got 5"):
        torch.ops.tiger.attention_rows(q, q, q, 1, 2, None, "lockstep", 5)
    with pytest.raises(RuntimeError, match="forward only"):
        attention_rows(q.requires_grad_(), q, q, 1, 2)


needs_hopper = pytest.mark.skipif(not HOPPER, reason="needs an H100-class GPU (compute capability 9.0) and "
                                                     "tiger built with CUDA")


@pytest.mark.cuda
@needs_hopper
@pytest.mark.parametrize("schedule,warpgroups", VARIANTS)
@pytest.mark.parametrize("batch,L,heads,spread", [(1, 128, 1, 1.0), (2, 256, 3, 1.0), (3, 384, 2, 4.0),
                                                  (12, 4096, 8, 1.0), (2, 1024, 8, 6.0)])
def test_hopper_kernel_as_close_as_cudnn(schedule, warpgroups, batch, L, heads, spread):
    """bf16 inputs: the kernel's error against the float64 definition is no larger than cuDNN's
    SDPA's (1.25x, plus a bf16 rounding's worth) on the same inputs; spread 4-6 makes the
    softmax peaked (scores of tens), which exercises the running maximum."""
    g = torch.Generator().manual_seed(batch * 1000 + L)
    q, k, v = stacked_qkv(batch, L, heads, 40, torch.bfloat16, "cuda", g, spread)
    with torch.no_grad():
        out = attention_rows(q, k, v, batch, heads, schedule=schedule, warpgroups=warpgroups)
        sdpa = sdpa_rows(q, k, v, batch, heads)
    torch.cuda.synchronize()
    assert torch.isfinite(out).all()
    ref = attention64(q, k, v, batch, heads)
    err, err_sdpa = ((o.double() - ref).norm() / ref.norm() for o in (out, sdpa))
    worst = (out.double() - ref).abs().max()
    assert err <= 1.25 * err_sdpa + 2 ** -9, (err, err_sdpa)
    assert worst <= 4 * 2 ** -8 * ref.abs().max(), worst


@pytest.mark.cuda
@needs_hopper
def test_hopper_kernel_in_a_cuda_graph_and_every_tiling_agrees():
    g = torch.Generator().manual_seed(5)
    q, k, v = stacked_qkv(4, 512, 8, 40, torch.bfloat16, "cuda", g)
    with torch.no_grad():
        eager = {kw: attention_rows(q, k, v, 4, 8, None, *kw) for kw in VARIANTS}
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.stream(side):
            attention_rows(q, k, v, 4, 8)
            with torch.cuda.graph(graph, stream=side):
                out = attention_rows(q, k, v, 4, 8)
        torch.cuda.current_stream().wait_stream(side)
        graph.replay()
    torch.cuda.synchronize()
    torch.testing.assert_close(out, eager[("producer", 3)], rtol=0, atol=0)  # deterministic
    for kw in VARIANTS:  # within a schedule a row's products and sums do not depend on the rows it shares a CTA with
        first = next(other for other in VARIANTS if other[0] == kw[0])
        torch.testing.assert_close(eager[kw], eager[first], rtol=0, atol=0)
    # across schedules only a quarter of the exponentials differ (a cubic on the FMA pipes in the
    # producer schedule, the SFU in the lockstep one): within the output's bf16 rounding
    torch.testing.assert_close(eager[("lockstep", 1)], out, rtol=2 ** -7, atol=2 ** -9)
    assert (eager[("lockstep", 1)] != out).any()  # the two schedules are not the same code path


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
@pytest.mark.parametrize("case", ["head_dim_64", "float32", "length_100", "misaligned_rows"])
def test_cuda_shapes_the_kernel_does_not_take_run_the_reference(case):
    g = torch.Generator().manual_seed(6)
    D, dtype, L = (64 if case == "head_dim_64" else 40), (torch.float32 if case == "float32" else torch.bfloat16), \
        (100 if case == "length_100" else 128)
    q, k, v = stacked_qkv(2, L, 2, D, dtype, "cuda", g)
    if case == "misaligned_rows":  # a row stride of 3·80 + 4 elements: rows not 16-byte aligned
        wide = torch.zeros(2 * L, 3 * 80 + 4, dtype=dtype, device="cuda")
        wide[:, :240] = torch.cat([q, k, v], 1)
        q, k, v = wide[:, :80], wide[:, 80:160], wide[:, 160:240]
    with torch.no_grad():
        out = attention_rows(q, k, v, 2, 2)
    cpu = attention_rows(q.cpu(), k.cpu(), v.cpu(), 2, 2)
    torch.testing.assert_close(out.cpu(), cpu, rtol=1e-2 if dtype == torch.bfloat16 else 1e-5,
                               atol=1e-2 if dtype == torch.bfloat16 else 1e-5)
