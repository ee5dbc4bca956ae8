"""The VAE encoder with its convolution biases carried into the next ResNet block
(tiger.edit.guidance.encoder_bias) against diffusers' encoder, in float64."""
from __future__ import annotations

import pytest
import torch

pytest.importorskip("diffusers")

from tiger.edit.guidance import conv_layers, encoder_bias, fused_norms  # noqa: E402


def _vae(tiny_models, fused: bool):
    from tiger.edit.guidance.ip2p import load_ip2p

    return load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=fused, dtype=torch.float64).vae


def _encode_and_grad(vae):
    """Posterior mean and std of a fixed image and the input gradient of a fixed latent sample."""
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(21), dtype=torch.float64)
    gz = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(22), dtype=torch.float64)
    x = img.contiguous(memory_format=torch.channels_last).requires_grad_(True)
    dist = vae.encode(x).latent_dist
    z = dist.mean + dist.std * gz
    (g,) = torch.autograd.grad(z, x, gz)
    return dist.mean.detach(), dist.std.detach(), g


def _count_materialised(monkeypatch) -> list:
    calls = []
    real = encoder_bias.channel_bias_add
    monkeypatch.setattr(encoder_bias, "channel_bias_add", lambda *a: calls.append(1) or real(*a))
    return calls


@pytest.mark.parametrize("fold, own_backward, resampling", [(False, False, False), (True, False, True),
                                                            (True, True, False), (True, True, True)])
def test_carried_biases_equal_diffusers_encoder(tiny_models, monkeypatch, fold, own_backward, resampling):
    """Every ResNet block that follows conv_in or a downsampler takes the bias (none is added to
    a map in a pass of its own) and the encoder's values and input gradient are diffusers'; with
    and without norm2's folded bias, the blocks' own backward, the padded conv_in and the 4x4
    downsampling."""
    vae = _vae(tiny_models, fused=True)
    fused_norms.set_fold_norm_bias(vae, fold)
    if own_backward:
        assert fused_norms.set_block_backward(vae, True) > 0
    assert conv_layers.set_pad_conv_in(vae, resampling) == int(resampling)
    conv_layers.set_downsample_4x4(vae, resampling)
    reference = _encode_and_grad(vae)
    calls = _count_materialised(monkeypatch)
    assert encoder_bias.set_carry_conv_bias(vae, True) == 1
    carried = _encode_and_grad(vae)
    assert calls == []  # conv_in's and the downsamplers' biases all went into ResNet blocks
    for a, b in zip(carried, reference):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12), float((a - b).abs().max())
    assert encoder_bias.set_carry_conv_bias(vae, False) == 0
    assert "forward" not in vae.encoder.__dict__
    assert torch.equal(_encode_and_grad(vae)[0], reference[0])


def test_blocks_that_cannot_take_the_bias_get_it_added(tiny_models, monkeypatch):
    """diffusers' own ResNet blocks (no fused norms): the bias is added to the map first; the
    same values."""
    vae = _vae(tiny_models, fused=False)
    reference = _encode_and_grad(vae)
    calls = _count_materialised(monkeypatch)
    encoder_bias.set_carry_conv_bias(vae, True)
    carried = _encode_and_grad(vae)
    n_producers = 1 + sum(1 for m in vae.encoder.down_blocks if m.downsamplers is not None)
    assert len(calls) == n_producers > 1
    for a, b in zip(carried, reference):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)


def test_shortcut_convolution_carries_its_constant(tiny_models):
    """A block with a 1x1 shortcut convolution on x + b equals the block on x with the shortcut's
    bias raised by W_sc·b (and norm1's input bias b)."""
    from diffusers.models.resnet import ResnetBlock2D

    vae = _vae(tiny_models, fused=True)
    fused_norms.set_fold_norm_bias(vae, True)
    block = next((m for m in vae.modules() if type(m) is ResnetBlock2D and m.conv_shortcut is not None), None)
    if block is None:
        pytest.skip("the tiny VAE has no block with a shortcut convolution")
    c = block.in_channels
    x = torch.randn(2, c, 6, 6, generator=torch.Generator().manual_seed(23), dtype=torch.float64)
    b = torch.randn(c, generator=torch.Generator().manual_seed(24), dtype=torch.float64)
    x = x.contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        expected = block(x + b.view(1, -1, 1, 1), temb=None)
        got = fused_norms._resnet_forward_folded(block, x, None, input_bias=b)
    assert torch.allclose(got, expected, rtol=1e-10, atol=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_cuda_default_kernels_carry_the_biases(tiny_models, dtype):
    """On CUDA the default kernels carry the biases (tiger's GroupNorm input bias, the blocks'
    own backward, padded conv_in, 4x4 downsampling); the encoder's values and input gradient
    match the encoder without the carry: float32 to float32 rounding, bfloat16 within its own."""
    from tiger.edit.guidance import model_kernels as mk
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True, dtype=dtype, device="cuda")
    got = mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels())
    assert got["carry_conv_bias_encoders"] == 1 and got["block_backward_blocks"] > 0
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(25)).cuda().to(dtype)
    gz = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(26)).cuda().to(dtype)

    def run():
        x = img.contiguous(memory_format=torch.channels_last).requires_grad_(True)
        z = models.vae.encode(x).latent_dist.mean
        (g,) = torch.autograd.grad(z, x, gz)
        return z.detach().double(), g.double()

    with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):  # float32 convolutions, not TF32
        carried = run()
        encoder_bias.set_carry_conv_bias(models.vae, False)
        plain = run()
    tol = 1e-5 if dtype == torch.float32 else 3e-2
    for a, b in zip(carried, plain):
        assert float((a - b).norm() / b.norm()) < tol


def test_auto_follows_the_device(tiny_models):
    """``carry_conv_bias=None`` ("auto") carries the biases only for CUDA VAEs with tiger's kernels
    (the CUDA test above); on the CPU it stays diffusers' encoder unless asked for."""
    from tiger.edit.guidance import model_kernels as mk
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=False)
    assert mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels())["carry_conv_bias_encoders"] == 0
    assert "forward" not in models.vae.encoder.__dict__
    got = mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels(carry_conv_bias=True))
    assert got["carry_conv_bias_encoders"] == 1
