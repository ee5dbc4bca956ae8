"""``tiger::magnitude_blur`` and ``tiger::masked_logit`` (csrc/featup) against the PyTorch
compositions they replace in the fast FeatUp fit's step (``x.norm(dim=1)``, ``cat`` and
``gaussian_blur(..., padding="reflect")``; ``F.dropout`` and the 1x1 ``conv2d``; channels first, in
float64), values and gradients; gradcheck and opcheck; the CUDA kernels against the CPU kernels;
and the fit's step (``_step_loss``) in its two layouts (``ImplicitConfig.step_layout``)."""
import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

import tiger.ops
from tiger.language.featup import AttentionDownsampler, ImplicitConfig, ImplicitNet, sample_jitter
from tiger.language.featup_fit import _step_loss, jitter_coords, jitter_params, reflect_coords
from tiger.ops.featup import WINDOW_VARIANTS, magnitude_blur, masked_logit
from tiger.testing.cuda_graphs import capture
from tiger.utils.filters import gaussian_blur

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
needs_cuda = pytest.mark.skipif(not CUDA, reason="needs CUDA")
F64 = torch.float64


def reference(x, radius=2, sigma=1.0):
    """(blurred [H, W, C + 1], magnitude [H, W]) of x [H, W, C] through the channels-first ops."""
    chw = x.permute(2, 0, 1)[None]
    mag = chw.norm(dim=1, keepdim=True)
    blurred = gaussian_blur(torch.cat([mag, chw], dim=1), 2 * radius + 1, sigma, padding="reflect")
    return blurred[0].permute(1, 2, 0), mag[0, 0]


def features(h, w, c, seed=0, dtype=F64):
    return torch.randn(h, w, c, generator=torch.Generator().manual_seed(seed), dtype=dtype)


@pytest.mark.parametrize("h,w,c,radius,sigma", [(7, 9, 5, 2, 1.0), (3, 4, 2, 2, 1.0), (20, 13, 6, 2, 1.0),
                                                (11, 6, 3, 1, 0.7), (16, 12, 4, 4, 2.5), (5, 5, 1, 0, 1.0),
                                                (9, 17, 5, 8, 3.0)])
def test_equals_the_channels_first_composition(h, w, c, radius, sigma):
    x = features(h, w, c).requires_grad_()
    x.data[1, 2] = 0  # a zero pixel: the magnitude's gradient is 0 there, as torch.norm's
    blurred, mag = magnitude_blur(x, radius, sigma)
    ref_blurred, ref_mag = reference(x, radius, sigma)
    assert blurred.shape == (h, w, c + 1) and mag.shape == (h, w) and blurred.dtype == mag.dtype == F64
    torch.testing.assert_close(blurred, ref_blurred, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(mag, ref_mag, atol=1e-12, rtol=1e-12)
    gen = torch.Generator().manual_seed(5)
    gb, gm = torch.randn(blurred.shape, generator=gen, dtype=F64), torch.randn(mag.shape, generator=gen, dtype=F64)
    for loss, ref_loss in [((blurred * gb).sum() + (mag * gm).sum(), (ref_blurred * gb).sum() + (ref_mag * gm).sum()),
                           ((blurred * gb).sum(), (ref_blurred * gb).sum()),
                           ((mag * gm).sum(), (ref_mag * gm).sum())]:
        grad, = torch.autograd.grad(loss, x, retain_graph=True)
        ref_grad, = torch.autograd.grad(ref_loss, x, retain_graph=True)
        torch.testing.assert_close(grad, ref_grad, atol=1e-12, rtol=1e-12)


def test_gradcheck():
    x = features(6, 7, 3, seed=1).requires_grad_()
    assert torch.autograd.gradcheck(lambda t: magnitude_blur(t, 2, 1.0), (x,))


def test_opcheck():
    for x in (features(6, 8, 4, seed=2), features(5, 9, 3, seed=3, dtype=torch.float32)):
        torch.library.opcheck(torch.ops.tiger.magnitude_blur, (x.requires_grad_(), 2, 1.0))
    gb = features(6, 8, 5, seed=4)
    x = features(6, 8, 4, seed=2)
    _, mag = magnitude_blur(x)
    torch.library.opcheck(torch.ops.tiger.magnitude_blur_backward, (gb, None, x, mag, 2, 1.0))
    torch.library.opcheck(torch.ops.tiger.magnitude_blur_backward, (gb, mag.clone(), x, mag, 2, 1.0))


def test_bfloat16_features_accumulate_in_float32():
    x = features(9, 10, 7, seed=6).to(torch.bfloat16).requires_grad_()
    blurred, mag = magnitude_blur(x)
    assert blurred.dtype == mag.dtype == torch.float32
    ref_blurred, ref_mag = reference(x.detach().double())
    torch.testing.assert_close(blurred.double(), ref_blurred, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(mag.double(), ref_mag, atol=1e-5, rtol=1e-5)
    gb = torch.randn(blurred.shape, generator=torch.Generator().manual_seed(7))
    grad, = torch.autograd.grad((blurred * gb).sum(), x)
    x64 = x.detach().double().requires_grad_()
    ref_grad, = torch.autograd.grad((reference(x64)[0] * gb.double()).sum(), x64)
    assert grad.dtype == torch.bfloat16
    torch.testing.assert_close(grad.double(), ref_grad, atol=2e-2, rtol=1e-2)


def test_bad_input_names_the_problem():
    with pytest.raises(RuntimeError, match="x must be \\[H, W, C\\]"):
        magnitude_blur(torch.zeros(1, 4, 4, 3))
    with pytest.raises(RuntimeError, match="needs H and W > radius"):
        magnitude_blur(torch.zeros(2, 8, 3))
    with pytest.raises(RuntimeError, match="sigma must be positive"):
        magnitude_blur(torch.zeros(6, 8, 3), 2, 0.0)
    with pytest.raises(RuntimeError, match="float32, float64"):
        magnitude_blur(torch.zeros(6, 8, 3, dtype=torch.int32))


# ------------------------------------------------------------------------------------ masked_logit
def logit_case(h, w, u, seed=0, dtype=F64, dropout=0.2):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(h, w, u, generator=gen, dtype=dtype)
    keep = torch.rand(u, h, w, generator=gen) > dropout
    weight, bias = torch.randn(u, generator=gen, dtype=dtype), torch.randn(1, generator=gen, dtype=dtype)
    return x, keep, 1 / (1 - dropout), weight, bias


def logit_reference(x, keep, scale, weight, bias):
    """The channels-first composition: the dropped-out map's 1x1 convolution."""
    chw = x.permute(2, 0, 1)[None]
    if keep is not None:
        chw = chw * (keep.to(x.dtype) * scale)[None]
    return F.conv2d(chw, weight.view(1, -1, 1, 1), bias)[0, 0]


@pytest.mark.parametrize("h,w,u", [(5, 7, 4), (16, 33, 37), (1, 3, 1), (40, 20, 130)])
@pytest.mark.parametrize("with_keep", [True, False])
def test_masked_logit_equals_the_channels_first_composition(h, w, u, with_keep):
    x, keep, scale, weight, bias = logit_case(h, w, u)
    keep = keep if with_keep else None
    leaves = [t.requires_grad_() for t in (x, weight, bias)]
    out, ref = masked_logit(x, weight, bias, keep, scale), logit_reference(x, keep, scale, weight, bias)
    assert out.shape == (h, w)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=1e-12)
    g = torch.randn(h, w, generator=torch.Generator().manual_seed(3), dtype=F64)
    for a, r in zip(torch.autograd.grad((out * g).sum(), leaves), torch.autograd.grad((ref * g).sum(), leaves)):
        torch.testing.assert_close(a, r, atol=1e-11, rtol=1e-11)


def test_masked_logit_gradcheck_and_opcheck():
    x, keep, scale, weight, bias = logit_case(4, 6, 5, seed=1)
    leaves = [t.requires_grad_() for t in (x, weight, bias)]
    assert torch.autograd.gradcheck(lambda x, w, b: masked_logit(x, w, b, keep, scale), leaves)
    torch.library.opcheck(torch.ops.tiger.masked_logit, (x, keep, scale, weight, bias))
    torch.library.opcheck(torch.ops.tiger.masked_logit, (x, None, 1.0, weight, bias))
    g = torch.randn(4, 6, dtype=F64)
    torch.library.opcheck(torch.ops.tiger.masked_logit_backward, (g, x.detach(), keep, scale, weight.detach(), True))
    torch.library.opcheck(torch.ops.tiger.masked_logit_backward, (g, x.detach(), None, 1.0, weight.detach(), False))


def test_masked_logit_bad_input_names_the_tensor():
    x, keep, scale, weight, bias = logit_case(4, 6, 5)
    with pytest.raises(RuntimeError, match="keep must have shape"):
        masked_logit(x, weight, bias, keep.permute(1, 2, 0), scale)
    with pytest.raises(RuntimeError, match="weight must have shape"):
        masked_logit(x, weight[:4], bias, keep, scale)
    with pytest.raises(RuntimeError, match="keep must be Bool"):
        masked_logit(x, weight, bias, keep.to(x.dtype), scale)
    with pytest.raises(RuntimeError, match="weight must be Double"):
        masked_logit(x, weight.float(), bias, keep, scale)
    with pytest.raises(RuntimeError, match="keep_scale must be finite"):
        masked_logit(x, weight, bias, keep, float("inf"))
    with pytest.raises(RuntimeError, match="grad must be \\[H, W\\]"):
        torch.ops.tiger.masked_logit_backward(torch.zeros(4, 5, dtype=F64), x, keep, scale, weight, True)


# ------------------------------------------------------------------------------------ the fit's step
def _step_case(dropout, dtype):
    gen = torch.Generator().manual_seed(0)
    h, w, k, fh, fw, n_views = 24, 40, 6, 3, 5, 8
    img = torch.rand(1, 3, h, w, generator=gen, dtype=dtype)
    cfg = ImplicitConfig(proj_dim=k, n_freqs=4, kernel_size=9, dropout=dropout, mag_tv_weight=0.05, blur_pin=0.1,
                         precision="fp32")
    net = ImplicitNet(k, cfg.n_freqs, gen, dropout).to(dtype).train()
    down = AttentionDownsampler(k + 1, cfg.kernel_size, gen, dropout).to(dtype).train()
    with torch.random.fork_rng():  # the conv's initial weights come from the global generator
        torch.manual_seed(5)
        outlier = nn.Conv2d(k, 1, 1).to(dtype)
    targets = torch.randn(n_views, k, fh, fw, generator=gen, dtype=dtype)
    params = jitter_params([sample_jitter(h, w, 3, 1.8, True, gen) for _ in range(n_views)], h, w, "cpu").double()
    sy, sx = jitter_coords(params, h, w)
    coord_y, coord_x = reflect_coords(sy, h).to(dtype), reflect_coords(sx, w).to(dtype)
    return cfg, (img, targets, torch.tensor([3, 1, 6]), coord_y, coord_x, net.forward_pixels, down, outlier), \
        [*net.parameters(), *down.parameters(), *outlier.parameters()]


@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("dropout", [0.2, 0.0])
def test_step_layouts_give_the_same_loss_and_gradients(dropout, dtype):
    """``_step_loss`` with ``step_layout="channels_last"`` (tiger::magnitude_blur,
    tiger::masked_logit) = with ``"channels_first"`` (the PyTorch composition): the loss and every
    parameter's gradient, with the same random draws (on the CPU ``F.dropout`` draws its mask as
    the channels-last step does: bernoulli over the channels-first map, in the same order)."""
    cfg, args, leaves = _step_case(dropout, dtype)
    results = []
    for layout in ("channels_last", "channels_first"):
        torch.manual_seed(11)  # the dropout masks: the same draws in the same order
        loss = _step_loss(*args, dataclasses.replace(cfg, step_layout=layout))
        results.append((loss, torch.autograd.grad(loss, leaves, allow_unused=True)))
    (loss, grads), (ref_loss, ref_grads) = results
    assert torch.isfinite(loss) and loss.dtype == dtype
    tol = dict(atol=1e-12, rtol=1e-12) if dtype == F64 else dict(atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(loss, ref_loss, **tol)
    gtol = dict(atol=1e-11, rtol=1e-10) if dtype == F64 else dict(atol=1e-5, rtol=1e-4)
    checked = 0
    for i, (g, r) in enumerate(zip(grads, ref_grads)):
        if r is None:
            assert g is None or not g.any()
            continue
        assert g is not None and g.any(), f"parameter {i}: no gradient through the channels-last step"
        torch.testing.assert_close(g, r, **gtol, msg=lambda m, i=i: f"parameter {i}: {m}")
        checked += 1
    assert checked >= len(leaves) - 1  # every parameter but (at most) an unused one is compared


def test_step_dropout_draws_differ_between_steps():
    """With dropout the channels-last step draws fresh masks: two steps from different seeds give
    different losses (the masks are not a constant), the same seed the same loss."""
    cfg, args, _ = _step_case(0.2, F64)
    losses = []
    for seed in (1, 1, 2):
        torch.manual_seed(seed)
        losses.append(float(_step_loss(*args, cfg).detach()))
    assert losses[0] == losses[1] and losses[0] != losses[2]


def test_step_layout_is_validated():
    with pytest.raises(ValueError, match="step_layout must be 'channels_last' or 'channels_first'"):
        ImplicitConfig(step_layout="nhwc")
    assert ImplicitConfig().step_layout == "channels_last"


# ------------------------------------------------------------------------------------ CUDA
@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float32, F64, torch.bfloat16])
@pytest.mark.parametrize("h,w,c,radius,sigma", [(37, 53, 129, 2, 1.0), (5, 6, 3, 2, 1.0), (64, 112, 128, 2, 1.0),
                                                # other radii: the kernels with the radius at run time
                                                (19, 23, 7, 1, 0.7), (21, 40, 9, 4, 2.5), (9, 17, 5, 8, 3.0)])
def test_cuda_equals_cpu(dtype, h, w, c, radius, sigma):
    x = features(h, w, c, seed=8).to(dtype)
    x[2, 3] = 0
    cpu_blurred, cpu_mag = magnitude_blur(x, radius, sigma)
    blurred, mag = magnitude_blur(x.cuda(), radius, sigma)
    tol = dict(atol=1e-12, rtol=1e-12) if dtype == F64 else dict(atol=2e-5, rtol=2e-5)
    torch.testing.assert_close(blurred.cpu(), cpu_blurred, **tol)
    torch.testing.assert_close(mag.cpu(), cpu_mag, **tol)
    gen = torch.Generator().manual_seed(9)
    gb = torch.randn(cpu_blurred.shape, generator=gen, dtype=cpu_blurred.dtype)
    gm = torch.randn(cpu_mag.shape, generator=gen, dtype=cpu_mag.dtype)
    for grad_m in (gm, None):
        ref = torch.ops.tiger.magnitude_blur_backward(gb, grad_m, x, cpu_mag, radius, sigma)
        out = torch.ops.tiger.magnitude_blur_backward(gb.cuda(), None if grad_m is None else grad_m.cuda(), x.cuda(),
                                                      mag, radius, sigma)
        gtol = tol if dtype != torch.bfloat16 else dict(atol=1e-2, rtol=1e-2)
        torch.testing.assert_close(out.cpu(), ref, **gtol)


@needs_cuda
def test_cuda_is_deterministic_and_graph_capturable():
    x = features(40, 72, 129, seed=10).float().cuda().requires_grad_()
    gb = torch.randn(40, 72, 130, device="cuda")

    def run():
        blurred, mag = magnitude_blur(x)
        return torch.autograd.grad((blurred * gb).sum() + mag.sum(), x)[0]

    first = run()
    assert torch.equal(first, run())
    torch.library.opcheck(torch.ops.tiger.magnitude_blur, (x, 2, 1.0))
    graph, static = capture(run)
    graph.replay()
    torch.cuda.synchronize()
    assert torch.equal(static, first)


@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("h,w,u", [(37, 53, 129), (3, 5, 2), (256, 448, 129)])
@pytest.mark.parametrize("with_keep", [True, False])
def test_masked_logit_cuda_equals_cpu(dtype, h, w, u, with_keep):
    x, keep, scale, weight, bias = logit_case(h, w, u, dtype=dtype)
    keep = keep if with_keep else None
    g = torch.randn(h, w, generator=torch.Generator().manual_seed(4), dtype=dtype)
    cx, ckeep, cw, cb, cg = [t.cuda() if t is not None else None for t in (x, keep, weight, bias, g)]
    tol = dict(atol=1e-11, rtol=1e-11) if dtype == F64 else dict(atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(masked_logit(cx, cw, cb, ckeep, scale).cpu(), masked_logit(x, weight, bias, keep, scale),
                               **tol)
    ref = torch.ops.tiger.masked_logit_backward(g, x, keep, scale, weight, True)
    out = torch.ops.tiger.masked_logit_backward(cg, cx, ckeep, scale, cw, True)
    for name, a, b in zip(("grad x", "grad weight", "grad bias"), out, ref):
        # the weight's gradient sums h * w products: compare relative to its scale
        scaled = dict(atol=tol["atol"] * max(1.0, float(b.abs().max())), rtol=tol["rtol"])
        torch.testing.assert_close(a.cpu(), b, **scaled, msg=lambda m, n=name: f"{n}: {m}")
    again = torch.ops.tiger.masked_logit_backward(cg, cx, ckeep, scale, cw, True)
    assert all(torch.equal(a, b) for a, b in zip(out, again))  # fixed summation order
    torch.library.opcheck(torch.ops.tiger.masked_logit, (cx, ckeep, scale, cw, cb))


def _cuda_case(case):
    cfg, args, leaves = case
    img, targets, idx, coord_y, coord_x, network, down, outlier = args
    net = network.__self__
    for module in (net, down, outlier):
        module.cuda()
    return cfg, (img.cuda(), targets.cuda(), idx.cuda(), coord_y.cuda(), coord_x.cuda(), net.forward_pixels, down,
                 outlier), leaves


def _norm_error(g: torch.Tensor, r: torch.Tensor) -> float:
    """||g - r|| / ||r||, g on any device, in float64."""
    return float((g.cpu().double() - r.double()).norm() / r.double().norm().clamp_min(1e-30))


def _cuda_and_cpu_steps(dtype, changes):
    """The CPU step's (loss, grads) and the CUDA step's for each ``ImplicitConfig`` change in
    ``changes`` (no dropout, no autocast), from the same seeded case."""
    cfg, args, leaves = _step_case(0.0, dtype)
    cpu_loss = _step_loss(*args, cfg)
    cpu = (cpu_loss, torch.autograd.grad(cpu_loss, leaves, allow_unused=True))
    cfg, args, leaves = _cuda_case((cfg, args, leaves))
    cuda = []
    for change in changes:
        loss = _step_loss(*args, dataclasses.replace(cfg, **change))
        cuda.append((loss, torch.autograd.grad(loss, leaves, allow_unused=True)))
    return cpu, cuda


@needs_cuda
def test_cuda_step_layouts_agree_and_equal_the_cpu_step():
    """Without dropout, the CUDA step gives the CPU step's loss and gradients in both layouts, in
    float64 (in float32 the Fourier phases' gradient, a sum of sines over every pixel, differed
    between devices by up to 3e-2 of its norm on an H100: rounding, not the layouts)."""
    (cpu_loss, cpu_grads), cuda = _cuda_and_cpu_steps(F64, [dict(step_layout=lo)
                                                            for lo in ("channels_last", "channels_first")])
    for layout, (loss, grads) in zip(("channels_last", "channels_first"), cuda):
        torch.testing.assert_close(loss.cpu(), cpu_loss, atol=1e-12, rtol=1e-10)
        for i, (g, r) in enumerate(zip(grads, cpu_grads)):
            if r is not None:
                assert _norm_error(g, r) <= 1e-9, f"{layout} parameter {i}: {_norm_error(g, r):.2e}"


@needs_cuda
@pytest.mark.parametrize("variant", WINDOW_VARIANTS)
def test_cuda_step_with_each_attention_variant_equals_the_cpu_step(variant):
    """``ImplicitConfig.attention_variant`` reaches the attention op: without dropout the CUDA
    step with every kernel variant gives the CPU step's loss and gradients in float64.
    ``staged_tiles_bf16`` takes float32 features and reads them as bfloat16: its float32 step is
    held to the CUDA baseline step's loss (1e-2 relative) and gradient directions (cosine >= 0.99)."""
    bf16 = variant == "staged_tiles_bf16"
    if not bf16:
        (cpu_loss, cpu_grads), [(loss, grads)] = _cuda_and_cpu_steps(F64, [dict(attention_variant=variant)])
        torch.testing.assert_close(loss.cpu(), cpu_loss, atol=1e-12, rtol=1e-10)
        for i, (g, r) in enumerate(zip(grads, cpu_grads)):
            if r is not None:
                assert _norm_error(g, r) <= 1e-9, f"{variant} parameter {i}: {_norm_error(g, r):.2e}"
        return
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        _, [(base_loss, base_grads), (loss, grads)] = _cuda_and_cpu_steps(
            torch.float32, [dict(attention_variant="baseline"), dict(attention_variant=variant)])
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old
    torch.testing.assert_close(loss, base_loss, atol=1e-5, rtol=1e-2)
    for i, (g, r) in enumerate(zip(grads, base_grads)):
        if r is not None and r.any():
            cos = F.cosine_similarity(g.flatten().double(), r.flatten().double(), dim=0)
            assert cos >= 0.99, f"parameter {i}: gradient cosine {float(cos)}"


def test_attention_variant_is_validated():
    with pytest.raises(ValueError, match="attention_variant must be one of"):
        ImplicitConfig(attention_variant="fastest")
    assert {ImplicitConfig(attention_variant=v).attention_variant for v in WINDOW_VARIANTS} == set(WINDOW_VARIANTS)


@needs_cuda
def test_cuda_channels_last_step_with_dropout_replays_from_a_graph():
    """With dropout the channels-last step (bool mask drawn on the device) is captured in a CUDA
    graph; every replay draws fresh masks: finite losses that differ between replays, and finite
    gradients."""
    cfg, args, leaves = _cuda_case(_step_case(0.2, torch.float32))

    def step():
        loss = _step_loss(*args, cfg)
        return loss.detach(), torch.autograd.grad(loss, leaves, allow_unused=True)

    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(2):
            step()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        static_loss, static_grads = step()
    losses = []
    for _ in range(3):
        graph.replay()
        losses.append(float(static_loss))
        assert all(g is None or bool(torch.isfinite(g).all()) for g in static_grads)
    assert all(math.isfinite(v) for v in losses) and len(set(losses)) == 3, losses
