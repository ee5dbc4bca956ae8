"""``tiger::jittered_window_attention`` (csrc/featup) against the PyTorch composition it replaces in
the fast FeatUp fit: ``apply_jitters`` (grid_sample with reflection) then ``window_attention``
(the downsampler's windows and softmax), in float64 on the CPU, values and gradients; and the CUDA
kernels against the CPU kernels."""
import pytest
import torch

import tiger.ops
from tiger.language.featup import AttentionDownsampler, sample_jitter
from tiger.language.featup_fit import (apply_jitters, fused_window_attention, jitter_coords, jitter_grid,
                                       jitter_params, reflect_coords, window_attention, window_geometry)
from tiger.ops.featup import WINDOW_VARIANTS, jittered_window_attention
from tiger.testing.cuda_graphs import capture

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
needs_cuda = pytest.mark.skipif(not CUDA, reason="needs CUDA")
F64 = torch.float64


def case(h, w, size, kernel, jitters=6, channels=5, seed=0, dtype=F64, max_pad=None):
    """Blurred features [1, C, h, w], logit map [1, 1, h, w], jitter params [J, 7], a downsampler
    and a 0/1 logit mask [J, fh, fw], all from one seed."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(1, channels, h, w, generator=gen, dtype=dtype)
    logit_map = torch.randn(1, 1, h, w, generator=gen, dtype=dtype)
    pad = max_pad if max_pad is not None else max(1, min(h, w) // 6)
    params = jitter_params([sample_jitter(h, w, pad, 1.8, True, gen) for _ in range(jitters)], h, w, "cpu").to(dtype)
    down = AttentionDownsampler(channels, kernel, gen).to(dtype)
    mask = (torch.rand(jitters, *size, generator=gen) > 0.2).to(dtype)
    return x, logit_map, params, down, mask


def reference(x, logit_map, params, down, mask, size):
    h, w = x.shape[-2:]
    sampled = apply_jitters(torch.cat([logit_map, x], dim=1), jitter_grid(params, h, w))
    return window_attention(down, sampled[:, :1], sampled[:, 1:], size, mask)


def fused(x, logit_map, params, down, mask, size):
    h, w = x.shape[-2:]
    sy, sx = jitter_coords(params, h, w)
    return fused_window_attention(down, logit_map[0, 0], x[0].permute(1, 2, 0), reflect_coords(sy, h),
                                  reflect_coords(sx, w), size, mask)


GEOMETRIES = [((40, 72), (5, 9), 11), ((33, 47), (8, 14), 7), ((64, 112), (4, 7), 29), ((24, 30), (3, 4), 9)]


@pytest.mark.parametrize("hw,size,kernel", GEOMETRIES)
def test_fused_equals_the_jitter_and_window_composition(hw, size, kernel):
    x, logit_map, params, down, mask = case(*hw, size, kernel, jitters=8)
    assert (params[:, 1] > 1).any() and (params[:, 4] > 0.5).any()  # zoomed and flipped copies
    for t in (x, logit_map):
        t.requires_grad_()
    ref = reference(x, logit_map, params, down, mask, size)
    out = fused(x, logit_map, params, down, mask, size)
    assert out.shape == ref.shape == (8, x.shape[1], *size)
    torch.testing.assert_close(out, ref, atol=1e-10, rtol=1e-10)
    g = torch.randn(ref.shape, generator=torch.Generator().manual_seed(9), dtype=F64)
    leaves = (x, logit_map, down.w, down.b)
    ref_grads = torch.autograd.grad((ref * g).sum(), leaves)
    grads = torch.autograd.grad((out * g).sum(), leaves)
    for name, a, r in zip(("features", "logit_map", "w", "b"), grads, ref_grads):
        torch.testing.assert_close(a, r, atol=1e-9, rtol=1e-9, msg=lambda m, n=name: f"grad {n}: {m}")


def test_reflected_coordinates_read_what_grid_sample_reads():
    """Coordinates far outside the image (several reflections) give grid_sample's reflection."""
    h, w = 7, 9
    x = torch.randn(1, 1, h, w, dtype=F64, generator=torch.Generator().manual_seed(2))
    sy = torch.linspace(-20.3, 25.7, 41, dtype=F64)
    sx = torch.linspace(-17.1, 30.2, 37, dtype=F64)
    grid = torch.stack(torch.broadcast_tensors((2 * sx / (w - 1) - 1).view(1, -1), (2 * sy / (h - 1) - 1).view(-1, 1)),
                       -1)[None]
    ref = torch.nn.functional.grid_sample(x, grid, mode="bilinear", padding_mode="reflection", align_corners=True)
    ry, rx = reflect_coords(sy, h), reflect_coords(sx, w)
    assert ry.min() >= 0 and ry.max() <= h - 1 and rx.min() >= 0 and rx.max() <= w - 1
    ident = torch.stack(torch.broadcast_tensors((2 * rx / (w - 1) - 1).view(1, -1), (2 * ry / (h - 1) - 1).view(-1, 1)),
                        -1)[None]
    direct = torch.nn.functional.grid_sample(x, ident, mode="bilinear", padding_mode="zeros", align_corners=True)
    torch.testing.assert_close(direct, ref, atol=1e-12, rtol=0)


def op_args(h=6, w=7, c=3, j=2, size=(2, 2), k=3, stride=(2, 3), seed=0, dtype=F64, device="cpu"):
    gen = torch.Generator().manual_seed(seed)
    F = torch.randn(h, w, c, generator=gen, dtype=dtype)
    L = torch.randn(h, w, generator=gen, dtype=dtype)
    # monotone rows/columns one pixel apart at most (a zoom >= 1), off the integers (gradcheck)
    cy = (torch.rand(j, 1, generator=gen, dtype=dtype) * 0.5 + torch.arange(h, dtype=dtype) * 0.8).clamp(max=h - 1)
    cx = (torch.rand(j, 1, generator=gen, dtype=dtype) * 0.5 + torch.arange(w, dtype=dtype) * 0.9).clamp(max=w - 1)
    wk = 1 + 0.3 * torch.randn(k, k, generator=gen, dtype=dtype)
    bk = 0.3 * torch.randn(k, k, generator=gen, dtype=dtype)
    mask = (torch.rand(j, *size, generator=gen) > 0.3).to(dtype)
    return [t.to(device) for t in (F, L, cy, cx, wk, bk, mask)] + [stride]


def test_gradcheck_and_opcheck():
    F, L, cy, cx, wk, bk, mask, stride = op_args()
    for t in (F, L, wk, bk):
        t.requires_grad_()
    fn = lambda F, L, wk, bk: jittered_window_attention(F, L, cy, cx, wk, bk, mask, stride)[0]  # noqa: E731
    assert torch.autograd.gradcheck(fn, (F, L, wk, bk))
    torch.library.opcheck(torch.ops.tiger.jittered_window_attention,
                          (F.detach(), L.detach(), cy, cx, wk.detach(), bk.detach(), mask, *stride))
    torch.library.opcheck(torch.ops.tiger.jittered_window_attention, (F, L, cy, cx, wk, bk, mask, *stride))


@pytest.mark.parametrize("variant", WINDOW_VARIANTS)
def test_cpu_computes_every_variant_as_the_reference(variant):
    """The CPU kernels are the reference of every CUDA variant: the name is checked, the result
    is the baseline's; the variant reaches the backward (opcheck runs it through autograd)."""
    F, L, cy, cx, wk, bk, mask, stride = op_args()
    base = jittered_window_attention(F, L, cy, cx, wk, bk, mask, stride)
    out = jittered_window_attention(F, L, cy, cx, wk, bk, mask, stride, variant)
    for a, b in zip(out, base):
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    for t in (F, L, wk, bk):
        t.requires_grad_()
    torch.library.opcheck(torch.ops.tiger.jittered_window_attention, (F, L, cy, cx, wk, bk, mask, *stride, variant))


def test_unknown_variant_names_the_choices():
    F, L, cy, cx, wk, bk, mask, stride = op_args()
    with pytest.raises(RuntimeError, match="variant must be one of 'baseline', 'shared_scatter', 'pixel_dots', "
                                           "'staged_tiles', 'staged_tiles_bf16', got 'fast'"):
        jittered_window_attention(F, L, cy, cx, wk, bk, mask, stride, "fast")
    g = torch.ones(2, 2, 2, 3, dtype=F64)
    attn = torch.full((2, 2, 2, 9), 1 / 9, dtype=F64)
    with pytest.raises(RuntimeError, match="variant must be one of"):
        torch.ops.tiger.jittered_window_attention_backward(g, F, L, cy, cx, wk, bk, mask, attn, *stride, "fast")


def test_attention_rows_sum_to_one_and_mask_zero_is_the_bias_softmax():
    F, L, cy, cx, wk, bk, mask, stride = op_args(j=3)
    mask = torch.zeros_like(mask)
    _, attn = jittered_window_attention(F, L, cy, cx, wk, bk, mask, stride)
    torch.testing.assert_close(attn.sum(-1), torch.ones(attn.shape[:-1], dtype=F64))
    torch.testing.assert_close(attn, torch.softmax(bk.flatten(), 0).expand_as(attn))


def test_bad_inputs_name_the_tensor():
    F, L, cy, cx, wk, bk, mask, stride = op_args()
    with pytest.raises(RuntimeError, match="features must be \\[H, W, C\\]"):
        jittered_window_attention(F[0], L, cy, cx, wk, bk, mask, stride)
    with pytest.raises(RuntimeError, match="logit_map must be \\[H, W\\]"):
        jittered_window_attention(F, L[1:], cy, cx, wk, bk, mask, stride)
    with pytest.raises(RuntimeError, match="coord_x must be \\[J, Wo\\]"):
        jittered_window_attention(F, L, cy, cx[:1], wk, bk, mask, stride)
    with pytest.raises(RuntimeError, match="b must be \\[K, K\\]"):
        jittered_window_attention(F, L, cy, cx, wk, bk[:2], mask, stride)
    with pytest.raises(RuntimeError, match="must fit the jittered copy"):
        jittered_window_attention(F, L, cy, cx, wk, bk, mask, (4, 4))
    with pytest.raises(RuntimeError, match="mask \\(Float\\) must have the dtype of features"):
        jittered_window_attention(F, L, cy, cx, wk, bk, mask.float(), stride)


# ----------------------------------------------------------------------------- CUDA
def _both(args, device):
    F, L, cy, cx, wk, bk, mask, stride = [a.to(device) if torch.is_tensor(a) else a for a in args]
    leaves = [t.clone().requires_grad_() for t in (F, L, wk, bk)]
    out, attn = jittered_window_attention(leaves[0], leaves[1], cy, cx, leaves[2], leaves[3], mask, stride)
    # drawn in float64 and rounded: float32 and float64 draws of one seed are different numbers
    g = torch.randn(out.shape, generator=torch.Generator().manual_seed(4), dtype=F64).to(out.dtype).to(device)
    grads = torch.autograd.grad((out * g).sum(), leaves)
    return [t.detach().cpu() for t in (out, attn, *grads)]


@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("shape", [dict(), dict(h=13, w=17, c=37, j=3, size=(3, 4), k=5, stride=(4, 4)),
                                   dict(h=40, w=64, c=129, j=4, size=(3, 5), k=11, stride=(9, 11))])
def test_cuda_equals_cpu(dtype, shape):
    args = op_args(dtype=dtype, **shape)
    cpu, gpu = _both(args, "cpu"), _both(args, "cuda")
    tol = dict(atol=1e-10, rtol=1e-10) if dtype == F64 else dict(atol=1e-4, rtol=1e-3)
    for name, a, b in zip(("out", "attn", "grad features", "grad logit_map", "grad w", "grad b"), gpu, cpu):
        torch.testing.assert_close(a, b, **tol, msg=lambda m, n=name: f"{n}: {m}")


@needs_cuda
def test_cuda_fused_equals_cpu_reference_at_the_fit_geometry():
    """FeatUp's geometry (kernel 29, stride 15, zoomed, flipped and reflected copies, 129 channels)
    on CUDA against the float64 CPU composition."""
    hw, size, kernel = (128, 224), (8, 14), 29
    x, logit_map, params, down, mask = case(*hw, size, kernel, jitters=6, channels=129, max_pad=17)
    assert window_geometry(*hw, size, kernel)[1:3] == (14, 15)
    ref = reference(x, logit_map, params, down, mask, size)
    dev = torch.device("cuda")
    out = fused(x.float().to(dev), logit_map.float().to(dev), params.to(dev), down.float().to(dev), mask.to(dev), size)
    torch.testing.assert_close(out.cpu().double(), ref, atol=1e-4, rtol=1e-4)


@needs_cuda
def test_cuda_footprint_past_the_tile_gives_nan():
    """A copy that skips source pixels (zoom < 1) exceeds the CUDA tile: NaN, never a wrong number."""
    F, L, cy, cx, wk, bk, mask, stride = op_args(h=20, w=20, size=(2, 2), k=3, stride=(2, 2), dtype=torch.float32)
    cy = (torch.arange(20.0) * 4).clamp(max=19).expand(2, 20).contiguous()
    out, _ = jittered_window_attention(*(t.cuda() for t in (F, L, cy, cx, wk, bk, mask)), stride)
    assert out[:, 0].isnan().all() and out[:, 1].isnan().all()


@needs_cuda
def test_cuda_graph_fit_equals_the_eager_fit():
    """The fit step replayed from one CUDA graph = the same steps run eagerly (float32, no dropout:
    no random numbers; the same view picks, drawn up front)."""
    import dataclasses

    import torch.nn.functional as F

    from tiger.language.featup import ImplicitConfig, ImplicitUpsampler

    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        img = torch.rand(3, 48, 80, generator=torch.Generator().manual_seed(0)).cuda()
        backbone = lambda x: F.avg_pool2d(x.repeat(1, 4, 1, 1), 8)  # noqa: E731
        cfg = ImplicitConfig(steps=12, n_views=16, pca_batch=16, proj_dim=8, kernel_size=11, jitters_per_step=4,
                             n_freqs=6, dropout=0.0, precision="fp32")
        graphed = ImplicitUpsampler.fit(img, backbone, cfg)
        eager = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(cfg, cuda_graph=False))
        # the logit map's gradient is summed with atomics (order-dependent rounding), which NAdam's
        # first steps can amplify where gradients are near zero: losses to rounding, maps in direction
        torch.testing.assert_close(torch.tensor(graphed.history), torch.tensor(eager.history), rtol=2e-3, atol=1e-5)
        cos = F.cosine_similarity(graphed(), eager(), dim=0)
        assert cos.mean() >= 0.999 and cos.min() > 0.99, (cos.mean(), cos.min())
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


# ----------------------------------------------------------------------------- CUDA kernel variants
def _run(args, device, variant="baseline", bf16_features=False):
    """out, attn and the four gradients of <out, g> (g seeded) of the op on ``device``; features
    rounded to bfloat16 first when ``bf16_features`` (the CPU reference of staged_tiles_bf16)."""
    F, L, cy, cx, wk, bk, mask, stride = [a.to(device) if torch.is_tensor(a) else a for a in args]
    if bf16_features:
        F = F.to(torch.bfloat16).to(F.dtype)
    leaves = [t.clone().requires_grad_() for t in (F, L, wk, bk)]
    out, attn = jittered_window_attention(leaves[0], leaves[1], cy, cx, leaves[2], leaves[3], mask, stride, variant)
    # drawn in float64 and rounded: float32 and float64 draws of one seed are different numbers
    g = torch.randn(out.shape, generator=torch.Generator().manual_seed(4), dtype=F64).to(out.dtype).to(device)
    grads = torch.autograd.grad((out * g).sum(), leaves)
    return [t.detach().cpu() for t in (out, attn, *grads)]


NAMES = ("out", "attn", "grad features", "grad logit_map", "grad w", "grad b")
VARIANT_SHAPES = [dict(), dict(h=13, w=17, c=37, j=3, size=(3, 4), k=5, stride=(4, 4)),
                  dict(h=40, w=64, c=129, j=4, size=(3, 5), k=11, stride=(9, 11)),
                  dict(h=23, w=41, c=64, j=3, size=(2, 3), k=9, stride=(7, 13)),  # even C, odd sizes
                  dict(h=70, w=75, c=33, j=2, size=(3, 2), k=29, stride=(15, 20))]  # K = 29, 32-pixel tiles


@needs_cuda
@pytest.mark.parametrize("variant", WINDOW_VARIANTS)
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("shape", VARIANT_SHAPES)
def test_cuda_variant_equals_cpu(variant, dtype, shape):
    """Every variant, forward and backward, against the CPU kernels (staged_tiles_bf16: against the
    CPU kernels on the features rounded to bfloat16; float32 only)."""
    if variant == "staged_tiles_bf16" and dtype == F64:
        pytest.skip("staged_tiles_bf16 takes float32 features")
    args = op_args(dtype=dtype, **shape)
    bf16 = variant == "staged_tiles_bf16"
    cpu, gpu = _run(args, "cpu", bf16_features=bf16), _run(args, "cuda", variant)
    tol = dict(atol=1e-10, rtol=1e-10) if dtype == F64 else dict(atol=1e-4, rtol=1e-3)
    for name, a, b in zip(NAMES, gpu, cpu):
        torch.testing.assert_close(a, b, **tol, msg=lambda m, n=name: f"{variant} {n}: {m}")


def _fit_args(h, w, size, jitters, channels=129, kernel=29, seed=0):
    """The fit's geometry: FeatUp jitters (reflect pad, zoom up to 1.8, flips) of an [h, w, C] map
    onto size cells with kernel 29, as op arguments (float64, CPU)."""
    from tiger.language.featup import sample_jitter

    gen = torch.Generator().manual_seed(seed)
    k, sh, sw, _, _ = window_geometry(h, w, size, kernel)
    max_pad = min(int(round(30 * min(h, w) / 224)), min(h, w) - 1)
    params = jitter_params([sample_jitter(h, w, max_pad, 1.8, True, gen) for _ in range(jitters)], h, w, "cpu")
    sy, sx = jitter_coords(params.double(), h, w)
    F = torch.randn(h, w, channels, generator=gen, dtype=F64)
    L = torch.randn(h, w, generator=gen, dtype=F64)
    wk = 1 + 0.3 * torch.randn(k, k, generator=gen, dtype=F64)
    bk = 0.3 * torch.randn(k, k, generator=gen, dtype=F64)
    mask = (torch.rand(jitters, *size, generator=gen) > 0.2).double()
    return [F, L, reflect_coords(sy, h), reflect_coords(sx, w), wk, bk, mask, (sh, sw)]


@needs_cuda
@pytest.mark.parametrize("variant", WINDOW_VARIANTS)
def test_cuda_variant_equals_float64_cpu_at_the_fit_geometry(variant):
    """Half the fit's resolution (128 x 224, 8 x 14 cells, kernel 29, 129 channels, 6 jitters) in
    float32 on CUDA against the float64 CPU op (bf16: on the bfloat16-rounded features)."""
    args = _fit_args(128, 224, (8, 14), 6)
    bf16 = variant == "staged_tiles_bf16"
    cpu = _run(args, "cpu", bf16_features=bf16)
    f32 = [a.float() if torch.is_tensor(a) else a for a in args]
    gpu = _run(f32, "cuda", variant)
    for name, a, b in zip(NAMES, gpu, cpu):
        torch.testing.assert_close(a.double(), b, atol=2e-4, rtol=1e-3, msg=lambda m, n=name: f"{variant} {n}: {m}")


@needs_cuda
@pytest.mark.parametrize("variant", [v for v in WINDOW_VARIANTS if v != "baseline"])
def test_cuda_variant_equals_baseline_at_the_full_fit_geometry(variant):
    """The fit's 256 x 448 map, 16 x 28 cells, 10 jitters, float32: each variant against the
    baseline kernels (float rounding; staged_tiles_bf16 against the baseline on the bf16-rounded
    features)."""
    args = [a.float() if torch.is_tensor(a) else a for a in _fit_args(256, 448, (16, 28), 10)]
    base = _run(args, "cuda", "baseline", bf16_features=variant == "staged_tiles_bf16")
    new = _run(args, "cuda", variant)
    for name, a, b in zip(NAMES, new, base):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-3, msg=lambda m, n=name: f"{variant} {n}: {m}")


@needs_cuda
@pytest.mark.parametrize("variant", WINDOW_VARIANTS)
@pytest.mark.parametrize("axis", ["rows", "columns"])
def test_cuda_variant_footprint_past_the_tile_gives_the_baselines_nan(variant, axis):
    """A copy that skips source pixels overflows the tile: every variant gives NaN exactly where
    the baseline does (outputs and gradients), never a wrong number. Rows: every cell overflows;
    columns: only the cells reading copy columns 10-12 (l = 5: a forward group with both kinds)."""
    F, L, cy, cx, wk, bk, mask, stride = op_args(h=20, w=20, c=7, size=(2, 8), k=3, stride=(2, 2),
                                                  dtype=torch.float32)
    if axis == "rows":
        cy = (torch.arange(20.0) * 4).clamp(max=19).expand(2, 20).contiguous()
    else:
        x = torch.arange(20.0)
        cx = torch.where(x < 10, 0.9 * x, 8.1 + 3 * (x - 9)).clamp(max=19).expand(2, 20).contiguous()
    args = [F, L, cy, cx, wk, bk, mask, stride]
    # staged_tiles_bf16 against the baseline on the bfloat16-rounded features (its own reference)
    base = _run(args, "cuda", "baseline", bf16_features=variant == "staged_tiles_bf16")
    new = _run(args, "cuda", variant)
    assert base[0][:, :, 5].isnan().all() and (axis == "rows") == bool(base[0][:, :, 0].isnan().any())
    for name, a, b in zip(NAMES, new, base):
        assert torch.equal(a.isnan(), b.isnan()), name
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-3, equal_nan=True, msg=lambda m, n=name: f"{n}: {m}")


@needs_cuda
def test_cuda_variant_limits_name_the_problem():
    F, L, cy, cx, wk, bk, mask, stride = op_args(dtype=F64, device="cuda")
    with pytest.raises(RuntimeError, match="'staged_tiles_bf16' takes float32 features"):
        jittered_window_attention(F, L, cy, cx, wk, bk, mask, stride, "staged_tiles_bf16")
    F, L, cy, cx, wk, bk, mask, stride = op_args(c=10240, dtype=torch.float32, device="cuda")
    with pytest.raises(RuntimeError, match="variant 'pixel_dots' .* at most 10239 channels"):
        jittered_window_attention(F, L, cy, cx, wk, bk, mask, stride, "pixel_dots")


@needs_cuda
@pytest.mark.parametrize("variant", WINDOW_VARIANTS)
def test_cuda_variant_opcheck(variant):
    F, L, cy, cx, wk, bk, mask, stride = op_args(h=13, w=17, c=37, j=3, size=(3, 4), k=5, stride=(4, 4),
                                                  dtype=torch.float32, device="cuda")
    for t in (F, L, wk, bk):
        t.requires_grad_()
    # the logit map's gradient is summed with float atomics: run-to-run rounding, not bitwise
    torch.library.opcheck(torch.ops.tiger.jittered_window_attention, (F, L, cy, cx, wk, bk, mask, *stride, variant),
                          atol=1e-5, rtol=1e-4)


@needs_cuda
@pytest.mark.parametrize("variant", WINDOW_VARIANTS)
def test_cuda_variant_replays_from_a_cuda_graph(variant):
    """Forward + backward captured in a CUDA graph (as the fit runs its step) = the eager call."""
    args = [a.float().cuda() if torch.is_tensor(a) else a for a in _fit_args(64, 112, (4, 7), 4)]
    F, L, cy, cx, wk, bk, mask, stride = args
    leaves = [t.clone().requires_grad_() for t in (F, L, wk, bk)]
    g = torch.randn(4, 4, 7, F.shape[2], generator=torch.Generator().manual_seed(1)).cuda()

    def step():
        out, _ = jittered_window_attention(leaves[0], leaves[1], cy, cx, leaves[2], leaves[3], mask, stride, variant)
        return [out, *torch.autograd.grad((out * g).sum(), leaves)]

    # detached: a kept autograd graph keeps its AccumulateGrad nodes on the default stream, which
    # breaks the capture ('legacy stream depend on a capturing blocking stream', H100)
    eager = [t.detach().clone() for t in step()]
    graph, captured = capture(step)
    graph.replay()
    torch.cuda.synchronize()
    for name, a, b in zip(("out", "grad features", "grad logit_map", "grad w", "grad b"), captured, eager):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4, msg=lambda m, n=name: f"{variant} {n}: {m}")
