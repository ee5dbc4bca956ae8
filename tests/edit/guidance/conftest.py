import pytest
import torch

from tiger.edit.guidance import ViewBatch


@pytest.fixture
def ip2p_step_inputs(ring_cameras):
    """A builder ``(device, t=None) -> (renders, views, draws)`` of one 16-px InstructPix2Pix
    guidance step's inputs: 4 renders [4, 3, 16, 16] and originals in [0, 1] on the camera ring,
    and ``draws`` (t [4], noise and vae_noise [4, 4, 8, 8]) for ``guidance.grad``. Drawn from
    torch's global generator in this order: originals, renders, t (unless given), noise, vae_noise."""

    def make(device: str = "cuda", t=None):
        views = ViewBatch(cameras=ring_cameras(size=(16, 16)), originals=torch.rand(4, 3, 16, 16, device=device),
                          object_center=torch.zeros(3))
        renders = torch.rand(4, 3, 16, 16, device=device)
        t = torch.randint(20, 201, (4,), device=device) if t is None else torch.tensor(t, device=device)
        draws = dict(t=t, noise=torch.randn(4, 4, 8, 8, device=device),
                     vae_noise=torch.randn(4, 4, 8, 8, device=device))
        return renders, views, draws

    return make


@pytest.fixture
def tiny_ip2p(tiny_models):
    """The tiny InstructPix2Pix models (float32, CPU, diffusers' own norms)."""
    from tiger.edit.guidance.ip2p import load_ip2p

    return load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=False)


@pytest.fixture
def unet_inputs():
    """A builder ``(unet, dtype=float32) -> (x, t, encoder_hidden_states)`` of one fixed UNet call
    on 3 samples of 8x8 latents."""

    def make(unet, dtype=torch.float32):
        gen = torch.Generator().manual_seed(7)
        c = unet.config
        x = torch.randn(3, c.in_channels, 8, 8, generator=gen).to(dtype)
        e = torch.randn(3, 77, c.cross_attention_dim, generator=gen).to(dtype)
        return x, torch.tensor([10, 200, 900]), e

    return make


@pytest.fixture
def mvdream_unet64(tiny_models):
    """The tiny MVDream UNet (multi-view self-attention) in float64, eval mode, diffusers' own
    norms, with the lean attention."""
    from tiger.edit.guidance import transformer_blocks as tb
    from tiger.edit.guidance.mvdream import load_mvdream

    unet = load_mvdream(tiny_models / "mvdream", fused_norms=False).unet.double().eval()
    tb.set_lean_attention(unet, True)
    return unet


@pytest.fixture
def mvdream_inputs():
    """A builder ``(unet, views=4, dtype=float64) -> (latents, t, text, cameras)`` of one fixed
    2-branch call of MVDream's UNet on 2·views rows, rows [views, 2·views) repeating rows
    [0, views) except for the text."""

    def make(unet, views: int = 4, dtype=torch.float64):
        gen = torch.Generator().manual_seed(5)
        c = unet.config
        z = torch.randn(views, c.in_channels, 8, 8, generator=gen, dtype=dtype)
        text = torch.randn(2, 77, c.cross_attention_dim, generator=gen, dtype=dtype)
        cams = torch.randn(views, c.projection_class_embeddings_input_dim, generator=gen, dtype=dtype)
        emb = torch.cat([text[:1].expand(views, -1, -1), text[1:].expand(views, -1, -1)])
        return torch.cat([z, z]), torch.full((2 * views,), 300), emb, torch.cat([cams, cams])

    return make
