"""The rewritten convolution layers (tiger.edit.guidance.conv_layers) against diffusers' layers in
float64: sub-pixel upsampling (every 3x3 tap's phase position, layer and UNet), the 4x4 VAE
downsampling, and the zero-padded first convolutions (UNet output, latents, input gradient)."""
import pytest
import torch

from tiger.edit.guidance import conv_layers as cl


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("bias", [True, False])
def test_subpixel_upsample_equals_nearest_then_conv_float64(channels_last, bias):
    from diffusers.models.upsampling import Upsample2D

    g = torch.Generator().manual_seed(4)
    m = Upsample2D(6, use_conv=True, out_channels=5, bias=bias).double()
    x = torch.randn(2, 6, 5, 7, generator=g, dtype=torch.float64)
    if channels_last:
        m, x = m.to(memory_format=torch.channels_last), x.contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        y0 = m(x)
        assert cl.set_subpixel_upsample(m, True) == 1
        y1, y2 = m(x), m(x, output_size=(10, 14))
        odd = m(x, output_size=(11, 14))  # not 2x: diffusers' own computation
        assert cl.set_subpixel_upsample(m, False) == 0 and "forward" not in m.__dict__
        assert torch.equal(odd, m(x, output_size=(11, 14)))
    torch.testing.assert_close(y1, y0, atol=1e-13, rtol=0)
    torch.testing.assert_close(y2, y0, atol=1e-13, rtol=0)
    assert y1.is_contiguous(memory_format=torch.channels_last) == channels_last


def test_subpixel_weight_taps():
    # one 3x3 tap at a time: phase (a, b) sees it at 2x2 position (row of tap s in phase a, col of t in b)
    where = {0: {0: 0, 1: 1, 2: 1}, 1: {0: 0, 1: 0, 2: 1}}
    for s_ in range(3):
        for t_ in range(3):
            w = torch.zeros(1, 1, 3, 3, dtype=torch.float64)
            w[0, 0, s_, t_] = 1.0
            w4 = cl.subpixel_weight(w)
            for a in (0, 1):
                for b in (0, 1):
                    expect = torch.zeros(2, 2, dtype=torch.float64)
                    expect[where[a][s_], where[b][t_]] = 1.0
                    assert torch.equal(w4[2 * a + b, 0], expect), (s_, t_, a, b)


def test_subpixel_upsample_unet_equals_diffusers_float64(tiny_ip2p, unet_inputs):
    unet = tiny_ip2p.unet.double()
    x, t, e = unet_inputs(unet, torch.float64)
    ups = sum(1 for m in unet.modules() if type(m).__name__ == "Upsample2D")
    with torch.no_grad():
        y0 = unet(x, t, encoder_hidden_states=e).sample
        assert cl.set_subpixel_upsample(unet, True) == ups > 0
        y1 = unet(x, t, encoder_hidden_states=e).sample
    cl.set_subpixel_upsample(unet, False)
    assert torch.allclose(y1, y0, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("fused_norms", [False, True])
def test_downsample_4x4_vae_equals_padded_3x3_float64(tiny_models, fused_norms):
    from tiger.edit.guidance.ip2p import load_ip2p

    vae = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=fused_norms, dtype=torch.float64).vae
    x = torch.rand(2, 3, 16, 12, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    if fused_norms:
        x = x.contiguous(memory_format=torch.channels_last)

    def encode_and_grad():
        xx = x.clone().requires_grad_(True)
        z = vae.encode(xx).latent_dist.mean
        (g,) = torch.autograd.grad((z * torch.linspace(-1, 1, z.numel(), dtype=z.dtype).reshape(z.shape)).sum(), xx)
        return z.detach(), g

    z0, g0 = encode_and_grad()
    n_down = sum(1 for m in vae.modules() if type(m).__name__ == "Downsample2D")
    assert cl.set_downsample_4x4(vae, True) == n_down > 0
    z1, g1 = encode_and_grad()
    assert cl.set_downsample_4x4(vae, False) == 0
    z2, _ = encode_and_grad()
    # the same sums in another order (plus products with zero weights): float64 rounding only
    assert torch.allclose(z1, z0, rtol=1e-12, atol=1e-13) and torch.allclose(g1, g0, rtol=1e-12, atol=1e-13)
    assert torch.equal(z2, z0)


def test_pad_conv_in_gives_the_same_sums_float64(tiny_ip2p, unet_inputs):
    unet, vae = tiny_ip2p.unet.double(), tiny_ip2p.vae.double()
    x, t, e = unet_inputs(unet, torch.float64)
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(13), dtype=torch.float64)

    def run():
        with torch.no_grad():
            y = unet(x, t, encoder_hidden_states=e).sample
        xx = img.clone().requires_grad_(True)
        z = vae.encode(xx).latent_dist.mean
        (g,) = torch.autograd.grad((z * z).sum(), xx)
        return y, z.detach(), g

    plain = run()
    forwards = [m.__dict__.get("forward") for m in (unet.conv_in, vae.encoder.conv_in)]
    assert cl.set_pad_conv_in(unet, True) + cl.set_pad_conv_in(vae, True) == 2
    assert unet.conv_in.__dict__["_tiger_weight_padded"].shape[1] == 16
    padded = run()
    assert cl.set_pad_conv_in(unet, False) + cl.set_pad_conv_in(vae, False) == 0
    assert [m.__dict__.get("forward") for m in (unet.conv_in, vae.encoder.conv_in)] == forwards
    for a, b in zip(padded, plain):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)
    assert torch.equal(run()[0], plain[0])
