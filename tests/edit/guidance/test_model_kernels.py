"""The guidances' model kernels (tiger.edit.guidance.model_kernels, tiger.ops.fp8_rows) against
independent references: row-wise e4m3 quantisation against a nearest-value search over the 256
e4m3 codes, the GEGLU against diffusers' chunk + gelu + multiply (float64), FP8 linears against
float64 linears with the error bound of two e4m3 roundings; the fused feed-forward, the row
LayerNorm, the folded norm biases and the VAE blocks' own backward against diffusers' modules and
autograd (float64); the guidances' settings. The convolution layers: test_conv_layers.py; the lean
attention and the fused transformer blocks: test_transformer_blocks.py. The FP8
matmul itself (torch._scaled_mm) needs a Hopper/Ada GPU: tests/edit/guidance/test_model_kernels_cuda.py."""
import pytest
import torch
import torch.nn.functional as F

from tiger.edit.guidance import ViewBatch
from tiger.edit.guidance import model_kernels as mk
from tiger.edit.guidance import fused_norms
from tiger.ops.fp8_rows import E4M3_MAX, dequantize_rows, geglu, quantize_rows_fp8

diffusers = pytest.importorskip("diffusers")

U = 2.0 ** -4          # e4m3's unit roundoff (3 mantissa bits): |round(v) - v| <= U·|v| for normal v
SUBNORMAL_STEP = 2.0 ** -9  # e4m3's smallest positive value (its subnormal spacing)


def _e4m3_codes():
    """(finite values, codes) of all float8_e4m3fn bit patterns, as float64."""
    codes = torch.arange(256, dtype=torch.uint8)
    vals = codes.view(torch.float8_e4m3fn).double()
    keep = torch.isfinite(vals)
    return vals[keep], codes[keep]


def _nearest_e4m3(v: torch.Tensor) -> torch.Tensor:
    """float64 values rounded to the nearest e4m3 value, ties to the even code (independent of
    torch's cast): a search over all codes."""
    vals, codes = _e4m3_codes()
    d = (v.reshape(-1, 1) - vals.reshape(1, -1)).abs()
    best = d.min(dim=1, keepdim=True).values
    tied = d == best
    even = (codes % 2 == 0).reshape(1, -1) & tied
    pick = torch.where(even.any(dim=1, keepdim=True), even, tied).float().argmax(dim=1)
    return vals[pick].reshape(v.shape)


def _geglu_reference(x: torch.Tensor) -> torch.Tensor:
    """diffusers' GEGLU after its projection, in x's dtype."""
    a, g = x.chunk(2, dim=-1)
    return a * F.gelu(g)


def _cos_rel(a, b):
    a, b = a.double().flatten(), b.double().flatten()
    return float(a @ b / (a.norm() * b.norm())), float((a - b).norm() / b.norm())


# -- quantisation --------------------------------------------------------------------------------
def test_quantize_rows_matches_nearest_e4m3_search():
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(6, 48, generator=gen, dtype=torch.float64) * torch.logspace(-3, 2, 6, dtype=torch.float64)[:, None]
    x[2] = 0.0  # an all-zero row: scale 1, zeros
    x[3, 5] = -1e-7  # far below the row's amax: underflows to the subnormals / zero
    q, scale = quantize_rows_fp8(x)
    assert q.dtype == torch.float8_e4m3fn and q.shape == x.shape and scale.shape == (6, 1)
    amax = x.abs().amax(dim=1, keepdim=True)
    want_scale = torch.where(amax > 0, amax / E4M3_MAX, torch.ones_like(amax))
    assert torch.allclose(scale.double(), want_scale, rtol=1e-7, atol=0)
    inv = torch.where(amax > 0, E4M3_MAX / amax, torch.ones_like(amax))
    assert torch.equal(q.double(), _nearest_e4m3(x * inv))
    assert torch.equal(q[2].double(), torch.zeros(48, dtype=torch.float64)) and scale[2].item() == 1.0
    # every row's largest magnitude lands on ±448 exactly
    assert torch.equal(q.double().abs().amax(dim=1)[[0, 1, 3, 4, 5]], torch.full((5,), 448.0, dtype=torch.float64))
    # the dequantisation error bound of one e4m3 rounding
    err = (dequantize_rows(q, scale).double() - x).abs()
    assert bool((err <= U * x.abs() + SUBNORMAL_STEP / 2 * scale.double() * (1 + 1e-6)).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
def test_quantize_rows_reduced_types_equal_float64_path(dtype):
    x = torch.randn(5, 32, generator=torch.Generator().manual_seed(1)).to(dtype)
    q, scale = quantize_rows_fp8(x)
    amax = x.double().abs().amax(dim=1, keepdim=True)
    inv = (torch.full_like(amax, E4M3_MAX).float() / amax.float()).double()  # the float32 factor the op uses
    assert torch.equal(q.double(), _nearest_e4m3((x.float().double() * inv).float().double()))
    assert torch.equal(scale, (amax.float() / torch.full_like(amax, E4M3_MAX).float()))


def test_quantize_rows_geglu_equals_quantized_geglu():
    x = torch.randn(4, 64, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    q, scale = quantize_rows_fp8(x, geglu=True)
    q_ref, scale_ref = quantize_rows_fp8(_geglu_reference(x))
    assert q.shape == (4, 32)
    assert torch.equal(q.double(), q_ref.double()) and torch.equal(scale, scale_ref)


def test_quantize_rows_bad_input_names_the_problem():
    with pytest.raises(RuntimeError, match=r"x must be \[M, K\]"):
        quantize_rows_fp8(torch.zeros(2, 3, 4))
    with pytest.raises(RuntimeError, match="even number of columns"):
        quantize_rows_fp8(torch.zeros(2, 5), geglu=True)


# -- GEGLU ---------------------------------------------------------------------------------------
def test_geglu_equals_diffusers_composition_float64_and_rounds_once():
    x = torch.randn(3, 5, 40, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    ref = _geglu_reference(x)
    assert torch.allclose(geglu(x), ref, rtol=1e-13, atol=1e-15)
    y16 = geglu(x.to(torch.bfloat16))
    ref16 = _geglu_reference(x.to(torch.bfloat16).double())  # exact math on the rounded input
    # one rounding to bfloat16 (8 significant bits): unit roundoff 2^-8
    assert bool(((y16.double() - ref16).abs() <= 2.0 ** -8 * ref16.abs() * (1 + 1e-6) + 1e-30).all())


def test_geglu_backward_gradcheck():
    x = torch.randn(2, 3, 8, generator=torch.Generator().manual_seed(4), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(geglu, (x,))


# -- FP8 linear layers (emulated on the CPU) -------------------------------------------------------
def _two_rounding_bound(x: torch.Tensor, w: torch.Tensor, xs: torch.Tensor, ws: torch.Tensor) -> torch.Tensor:
    """|ŷ − y| bound for ŷ = Σ x̂·ŵ with x̂, ŵ each one e4m3 rounding of x, w (scales xs per row,
    ws per output channel): each product's error ≤ (2U + U²)|x||w| plus the subnormal floor."""
    floor_x, floor_w = SUBNORMAL_STEP / 2 * xs, SUBNORMAL_STEP / 2 * ws
    return ((2 * U + U * U) * (x.abs() @ w.abs().t()) + floor_x * (w.abs().sum(1) * (1 + U))[None, :]
            + (x.abs().sum(1, keepdim=True) * (1 + U)) * floor_w[None, :] + floor_x * floor_w * x.shape[1])


def test_fp8_linear_emulated_within_two_e4m3_roundings():
    gen = torch.Generator().manual_seed(5)
    lin = torch.nn.Linear(64, 32).double()
    with torch.no_grad():
        lin.weight.copy_(torch.randn(32, 64, generator=gen, dtype=torch.float64) * 0.1)
    x = torch.randn(2, 7, 64, generator=gen, dtype=torch.float64)
    layer = mk.Fp8Linear(lin, emulate=True)
    with torch.no_grad():
        y, ref = layer(x), lin(x)
    x2 = x.reshape(-1, 64)
    xs = x2.abs().amax(1, keepdim=True) / E4M3_MAX
    ws = lin.weight.abs().amax(1) / E4M3_MAX
    bound = _two_rounding_bound(x2, lin.weight.detach(), xs, ws).reshape(2, 7, 32)
    # + the float32 accumulation of the emulation (K = 64 terms)
    bound = bound + 64 * 2.0 ** -23 * (x.abs() @ lin.weight.abs().t()).detach()
    assert y.shape == (2, 7, 32)
    assert bool(((y - ref).abs() <= bound).all())
    assert float((y - ref).norm() / ref.norm()) > 1e-4  # it did quantise


def test_fp8_conv1x1_on_channels_last_map_equals_linear_on_pixels():
    gen = torch.Generator().manual_seed(6)
    conv = torch.nn.Conv2d(32, 48, 1).double()
    x = torch.randn(2, 32, 5, 3, generator=gen, dtype=torch.float64).contiguous(memory_format=torch.channels_last)
    lin = torch.nn.Linear(32, 48).double()
    with torch.no_grad():
        lin.weight.copy_(conv.weight.reshape(48, 32))
        lin.bias.copy_(conv.bias)
        y = mk.Fp8Linear(conv, emulate=True)(x)
        y_lin = mk.Fp8Linear(lin, emulate=True)(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)
    assert y.shape == (2, 48, 5, 3) and y.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(y, y_lin)


def test_fp8_linear_refuses_bad_shapes_and_gradients():
    with pytest.raises(ValueError, match="divisible by 16"):
        mk.Fp8Linear(torch.nn.Linear(20, 32), emulate=True)
    with pytest.raises(ValueError, match="1x1 convolution"):
        mk.Fp8Linear(torch.nn.Conv2d(16, 16, 3), emulate=True)
    layer = mk.Fp8Linear(torch.nn.Linear(16, 16), emulate=True)
    with pytest.raises(RuntimeError, match="forward-only"):
        layer(torch.randn(2, 16, requires_grad=True))


# -- on the tiny UNets ----------------------------------------------------------------------------
def _expected_fp8_layers(unet) -> int:
    """Linear layers inside the transformer models, plus their 1x1-convolution projections."""
    from diffusers.models.transformers.transformer_2d import Transformer2DModel

    n = 0
    for tr in unet.modules():
        if type(tr) is Transformer2DModel:
            n += sum(1 for m in tr.modules() if type(m) is torch.nn.Linear)
            n += sum(1 for name in ("proj_in", "proj_out") if type(getattr(tr, name)) is torch.nn.Conv2d)
    return n


def test_fp8_unet_converts_every_transformer_matmul_and_restores(tiny_ip2p, monkeypatch, unet_inputs):
    unet = tiny_ip2p.unet
    x, t, e = unet_inputs(unet)
    expected = _expected_fp8_layers(unet)
    with torch.no_grad():
        y0 = unet(x, t, encoder_hidden_states=e).sample
        assert mk.set_matmul_precision(unet, "fp8", emulate=True) == expected > 0
        assert mk.set_matmul_precision(unet, "fp8", emulate=True) == expected  # idempotent
        assert mk.set_fused_geglu(unet, True) > 0
        calls = []
        real = mk.quantize_rows_fp8
        monkeypatch.setattr(mk, "quantize_rows_fp8", lambda x, geglu=False: calls.append(geglu) or real(x, geglu))
        y1 = unet(x, t, encoder_hidden_states=e).sample
        monkeypatch.undo()
        cos, rel = _cos_rel(y1, y0)
        assert cos > 0.99 and 1e-4 < rel < 0.2, (cos, rel)
        # per transformer block: proj_in, q/k/v once, out, q, k/v once, out, ff proj, GEGLU+quantise, proj_out
        n_tr = sum(1 for m in unet.modules() if type(m).__name__ == "Transformer2DModel")
        assert len(calls) == 9 * n_tr and sum(calls) == n_tr
        assert mk.set_matmul_precision(unet, "model") == 0
        mk.set_fused_geglu(unet, False)
        assert not any(isinstance(m, mk.Fp8Linear) for m in unet.modules())
        assert torch.equal(unet(x, t, encoder_hidden_states=e).sample, y0)


def test_fp8_refused_on_cpu_with_reason(tiny_ip2p):
    with pytest.raises(ValueError, match="matmul_precision='fp8' is not available: .*CUDA GPU with FP8"):
        mk.set_matmul_precision(tiny_ip2p.unet, "fp8")
    with pytest.raises(ValueError, match="matmul_precision must be one of"):
        mk.ModelKernels(matmul_precision="int8")
    with pytest.raises(ValueError, match="fp8_fast_accum"):
        mk.ModelKernels(fp8_fast_accum=True)


def test_row_layer_norm_unet_equals_diffusers_float64(tiny_ip2p, unet_inputs):
    unet = tiny_ip2p.unet.double()
    x, t, e = unet_inputs(unet, torch.float64)
    norms = [m for m in unet.modules() if type(m) is torch.nn.LayerNorm]
    with torch.no_grad():
        y0 = unet(x, t, encoder_hidden_states=e).sample
        assert mk.set_row_layer_norm(unet, True) == len(norms) > 0  # three per transformer block
        assert mk.set_row_layer_norm(unet, True) == len(norms)  # idempotent
        calls = []
        real = mk.layer_norm_rows
        mk.layer_norm_rows = lambda *a: calls.append(a[0].shape) or real(*a)
        try:
            y1 = unet(x, t, encoder_hidden_states=e).sample
        finally:
            mk.layer_norm_rows = real
        assert len(calls) == len(norms)
    assert mk.set_row_layer_norm(unet, False) == 0
    assert not any("forward" in m.__dict__ for m in norms)
    assert torch.allclose(y1, y0, rtol=1e-10, atol=1e-12)


def test_fused_geglu_unet_equals_diffusers_float64(tiny_ip2p, unet_inputs):
    unet = tiny_ip2p.unet.double()
    x, t, e = unet_inputs(unet, torch.float64)
    with torch.no_grad():
        y0 = unet(x, t, encoder_hidden_states=e).sample
        assert mk.set_fused_geglu(unet, True) == sum(1 for m in unet.modules() if type(m).__name__ == "FeedForward")
        y1 = unet(x, t, encoder_hidden_states=e).sample
    mk.set_fused_geglu(unet, False)
    assert torch.allclose(y1, y0, rtol=1e-10, atol=1e-12)


def test_fold_norm_bias_equals_separate_bias_pass_float64(tiny_models, unet_inputs):
    """conv1's bias and the time embedding added inside norm2 (tiger's GroupNorm input_bias) give
    the UNet's output and the VAE encoder's values and input gradient of the separate pass."""
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True, dtype=torch.float64)
    unet, vae = models.unet, models.vae
    x, t, e = unet_inputs(unet, torch.float64)
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(10), dtype=torch.float64)

    def run():
        with torch.no_grad():
            y = unet(x.contiguous(memory_format=torch.channels_last), t, encoder_hidden_states=e).sample
        xx = img.contiguous(memory_format=torch.channels_last).requires_grad_(True)
        z = vae.encode(xx).latent_dist.mean
        (g,) = torch.autograd.grad((z * z).sum(), xx)
        return y, z.detach(), g

    plain = run()
    n_blocks = sum(1 for m in list(unet.modules()) + list(vae.modules()) if type(m).__name__ == "ResnetBlock2D")
    assert fused_norms.set_fold_norm_bias(unet, True) + fused_norms.set_fold_norm_bias(vae, True) == n_blocks > 0
    folded = run()
    fused_norms.set_fold_norm_bias(unet, False)
    fused_norms.set_fold_norm_bias(vae, False)
    for a, b in zip(folded, plain):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)
    assert torch.equal(run()[0], plain[0])


def test_block_backward_equals_autograd_float64(tiny_models):
    """The VAE encoder's ResNet blocks with their own backward (the shortcut's gradient added
    inside norm1's backward) give autograd's values and input gradient; blocks with a shortcut
    convolution keep autograd; without a gradient to the input nothing changes."""
    from diffusers.models.resnet import ResnetBlock2D

    from tiger.edit.guidance.ip2p import load_ip2p

    vae = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True, dtype=torch.float64).vae
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    gz = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(12), dtype=torch.float64)
    calls = []
    real = fused_norms._FoldedBlock.apply
    fused_norms._FoldedBlock.apply = lambda *a: calls.append(1) or real(*a)

    def run():
        xx = img.contiguous(memory_format=torch.channels_last).requires_grad_(True)
        dist = vae.encode(xx).latent_dist
        z = dist.mean + dist.std * gz
        (g,) = torch.autograd.grad(z, xx, gz)
        return z.detach(), g

    try:
        assert fused_norms.set_fold_norm_bias(vae, True) > 0
        plain = run()
        blocks = [m for m in vae.modules() if type(m) is ResnetBlock2D]
        assert fused_norms.set_block_backward(vae, True) == len(blocks)
        own = run()
        assert len(calls) == sum(1 for m in blocks if m.conv_shortcut is None) > 0
        with torch.no_grad():
            vae.encode(img)  # no gradient needed: autograd's path
        assert len(calls) == sum(1 for m in blocks if m.conv_shortcut is None)
    finally:
        fused_norms._FoldedBlock.apply = real
        fused_norms.set_block_backward(vae, False)
        fused_norms.set_fold_norm_bias(vae, False)
    for a, b in zip(own, plain):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12), float((a - b).abs().max())


def test_guidance_records_and_applies_kernels(tiny_models, ring_cameras):
    from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p
    from tiger.edit.guidance.mvdream import MVDreamGuidance

    grads = []
    gen = torch.Generator().manual_seed(9)
    renders, originals = torch.rand(4, 3, 16, 16, generator=gen), torch.rand(4, 3, 16, 16, generator=gen)
    noise, vae_noise = torch.randn(4, 4, 8, 8, generator=gen), torch.randn(4, 4, 8, 8, generator=gen)
    t = torch.tensor([20, 60, 120, 180])
    views = ViewBatch(cameras=ring_cameras(size=(16, 16)), originals=originals, object_center=torch.zeros(3))
    for kernels in (None, mk.ModelKernels(fused_geglu=True, vae_downsample_4x4=True, fused_transformer=True)):
        models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=False)
        g = InstructPix2PixGuidance(models, "make it red", short_side=16, kernels=kernels)
        on = kernels is not None
        assert any("forward" in m.__dict__ for m in models.unet.modules() if type(m).__name__ == "FeedForward") == on
        assert g.settings()["kernels"] == {"matmul_precision": "model", "fp8_fast_accum": False,
                                           "fused_geglu": True if on else "auto",
                                           "vae_downsample_4x4": True if on else "auto", "fold_norm_bias": "auto",
                                           "row_layer_norm": "auto", "subpixel_upsample": "auto",
                                           "lean_attention": "auto", "block_backward": "auto",
                                           "pad_conv_in": "auto", "fused_transformer": True if on else "auto",
                                           "carry_conv_bias": "auto", "branch_prefix": "auto",
                                           "stacked_time_bias": "auto", "cached_text_kv": "auto",
                                           "skip_concat": "auto", "row_softmax": "auto",
                                           "head40_attention": "auto"}
        grads.append(g.grad(renders, views, t=t, noise=noise, vae_noise=vae_noise)[0])
    cos, rel = _cos_rel(grads[1], grads[0])
    assert cos > 1 - 1e-9 and rel < 1e-5, (cos, rel)
    mv = MVDreamGuidance(lambda: None, "a fox", kernels=mk.ModelKernels(fused_geglu=False))
    assert mv.settings()["kernels"]["fused_geglu"] is False  # recorded before loading


def test_row_layer_norm_and_subpixel_follow_the_device(tiny_ip2p):
    # None ("auto"): on for CUDA models only; True puts them on CPU models too (the reference ops)
    unet, vae = tiny_ip2p.unet, tiny_ip2p.vae
    got = mk.apply_model_kernels(unet, vae, mk.ModelKernels())
    assert (got["row_layer_norms"], got["subpixel_upsamples"]) == (0, 0)
    got = mk.apply_model_kernels(unet, vae, mk.ModelKernels(row_layer_norm=True, subpixel_upsample=True))
    assert got["row_layer_norms"] == sum(1 for m in unet.modules() if type(m) is torch.nn.LayerNorm) > 0
    assert got["subpixel_upsamples"] == sum(1 for m in unet.modules() if type(m).__name__ == "Upsample2D") > 0
    mk.apply_model_kernels(unet, vae, mk.ModelKernels(row_layer_norm=False, subpixel_upsample=False))




def test_kernels_from_spec_sets_named_fields_and_names_bad_items():
    k = mk.ModelKernels.from_spec("stacked_time_bias=off, cached_text_kv=on,fused_geglu=auto,matmul_precision=fp8")
    assert (k.stacked_time_bias, k.cached_text_kv, k.fused_geglu, k.matmul_precision) == (False, True, None, "fp8")
    assert mk.ModelKernels.from_spec("") == mk.ModelKernels()
    with pytest.raises(ValueError, match="field=on\\|off\\|auto.*got 'no_such=on'"):
        mk.ModelKernels.from_spec("no_such=on")
    with pytest.raises(ValueError, match="got 'branch_prefix=yes'"):
        mk.ModelKernels.from_spec("branch_prefix=yes")
    with pytest.raises(ValueError, match="matmul_precision must be one of"):
        mk.ModelKernels.from_spec("matmul_precision=int4")


def test_model_kernels_defaults_resolve_the_new_switches(tiny_models):
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True, dtype=torch.float64)
    got = mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels(fold_norm_bias=True))
    resnets = sum(1 for m in models.unet.modules()
                  if type(m).__name__ == "ResnetBlock2D" and m.time_emb_proj is not None)
    cross = sum(1 for m in models.unet.modules() if type(m).__name__ == "Attention" and m.is_cross_attention)
    # defaults: stacked time biases wherever the norms fold them, cached text keys/values everywhere
    assert got["stacked_time_bias_blocks"] == resnets > 0 and got["cached_text_kv_layers"] == cross > 0
    got = mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels(fold_norm_bias=False))
    assert got["stacked_time_bias_blocks"] == 0 and got["cached_text_kv_layers"] == cross
