"""GroupNorm moments taken by the producing pass (ModelKernels.norm_moments,
tiger.edit.guidance.fused_norms.set_norm_moments): the UNets' outputs and the VAE encoder's values
and input gradient are those of the norms' own statistics passes (float64), and the norms that
follow a ResNet block's or a transformer's output pass do take the moments."""
from __future__ import annotations

import pytest
import torch

pytest.importorskip("diffusers")

import tiger.ops.group_norm as gn_ops  # noqa: E402
from tiger.edit.guidance import fused_norms  # noqa: E402
from tiger.edit.guidance import model_kernels as mk  # noqa: E402


def _count_given(monkeypatch) -> list:
    """Every moments_of() that hands moments to a norm appends 1."""
    given = []
    real = gn_ops.moments_of

    def spy(x):
        m = real(x)
        if m is not None:
            given.append(1)
        return m

    monkeypatch.setattr(gn_ops, "moments_of", spy)
    monkeypatch.setattr(fused_norms, "moments_of", spy)
    return given


def _unet_run(unet, unet_inputs):
    x, t, e = unet_inputs(unet, torch.float64)
    with torch.no_grad():
        return unet(x.contiguous(memory_format=torch.channels_last), t, encoder_hidden_states=e).sample


def _vae_run(vae):
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(31), dtype=torch.float64)
    gz = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(32), dtype=torch.float64)
    xx = img.contiguous(memory_format=torch.channels_last).requires_grad_(True)
    z = vae.encode(xx).latent_dist.mean
    (g,) = torch.autograd.grad(z, xx, gz)
    return z.detach(), g


@pytest.mark.parametrize("own_backward", [False, True])
def test_ip2p_models_with_moments_equal_own_statistics_float64(tiny_models, unet_inputs, monkeypatch, own_backward):
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True, dtype=torch.float64)
    unet, vae = models.unet, models.vae
    fused_norms.set_fold_norm_bias(vae, own_backward)
    fused_norms.set_block_backward(vae, own_backward)
    plain = (_unet_run(unet, unet_inputs),) + _vae_run(vae)
    given = _count_given(monkeypatch)
    n_unet = fused_norms.set_norm_moments(unet, True)
    n_vae = fused_norms.set_norm_moments(vae, True)
    n_resnets = sum(1 for m in unet.modules() if type(m).__name__ == "ResnetBlock2D")
    n_transformers = sum(1 for m in unet.modules() if type(m).__name__ == "Transformer2DModel")
    assert n_unet == n_resnets + n_transformers > 0 and n_vae > 0
    unet_out = _unet_run(unet, unet_inputs)
    in_unet = len(given)
    assert in_unet >= n_transformers  # every transformer's norm reads a ResNet block's output
    moments = (unet_out,) + _vae_run(vae)
    assert len(given) > in_unet  # and the encoder's second blocks read their first blocks' outputs
    for a, b in zip(moments, plain):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12), float((a - b).abs().max())
    assert fused_norms.set_norm_moments(unet, False) == 0
    given.clear()
    assert torch.equal(_unet_run(unet, unet_inputs), plain[0]) and given == []


def test_mvdream_unet_linear_projections_with_moments_float64(tiny_models, monkeypatch):
    """MVDream's transformers project linearly: their output pass adds the residual with a zero bias
    to take the moments; the same values."""
    from tiger.edit.guidance.mvdream import load_mvdream

    models = load_mvdream(tiny_models / "mvdream", fused_norms=True, dtype=torch.float64)
    unet = models.unet
    linear = [m for m in unet.modules() if type(m).__name__ == "Transformer2DModel" and m.use_linear_projection]
    if not linear:
        pytest.skip("the tiny MVDream UNet has no linear projections")
    gen = torch.Generator().manual_seed(33)
    c = unet.config
    x = torch.randn(4, c.in_channels, 8, 8, generator=gen, dtype=torch.float64)
    e = torch.randn(4, 77, c.cross_attention_dim, generator=gen, dtype=torch.float64)
    t = torch.tensor([10, 200, 500, 900])
    cams = torch.randn(4, c.projection_class_embeddings_input_dim, generator=gen, dtype=torch.float64)

    def run():
        with torch.no_grad():
            return unet(x.contiguous(memory_format=torch.channels_last), t, encoder_hidden_states=e,
                        class_labels=cams).sample

    plain = run()
    given = _count_given(monkeypatch)
    assert fused_norms.set_norm_moments(unet, True) > len(linear)
    got = run()
    assert len(given) >= len(linear)
    assert torch.allclose(got, plain, rtol=1e-10, atol=1e-12), float((got - plain).abs().max())


def test_auto_follows_the_device(tiny_models):
    """``norm_moments=None`` ("auto"): on for CUDA models with tiger's kernels only."""
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True)
    assert mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels())["norm_moments_producers"] == 0
    got = mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels(norm_moments=True))
    assert got["norm_moments_producers"] > 0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_cuda_default_kernels_take_moments_with_the_same_values(tiny_models, unet_inputs, dtype):
    """On CUDA the default kernels take the moments; the UNet's output and the encoder's values and
    input gradient equal those with norm_moments off bit for bit (the same statistics)."""
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True, dtype=dtype, device="cuda")
    got = mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels())
    assert got["norm_moments_producers"] > 0
    x, t, e = unet_inputs(models.unet, dtype)
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(34)).cuda().to(dtype)
    gz = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(35)).cuda().to(dtype)

    def run():
        with torch.no_grad():
            y = models.unet(x.cuda().contiguous(memory_format=torch.channels_last), t.cuda(),
                            encoder_hidden_states=e.cuda()).sample
        xx = img.contiguous(memory_format=torch.channels_last).requires_grad_(True)
        z = models.vae.encode(xx).latent_dist.mean
        (g,) = torch.autograd.grad(z, xx, gz)
        return y, z.detach(), g

    with torch.backends.cudnn.flags(enabled=True, deterministic=True, allow_tf32=False):
        with_moments = run()
        mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels(norm_moments=False))
        without = run()
    for a, b in zip(with_moments, without):
        assert torch.equal(a, b)
