"""The guidances' speed changes keep the SDS gradient: tiny random InstructPix2Pix and MVDream
through the real loaders, with tiger's fused models (fused norms, folded bias/time-embedding/
shortcut adds, channels-last) against diffusers' plain modules, on fixed noise and t (float32:
cosine ~1, relative error ~1e-6); the VAE attention's one-pass softmax against diffusers'
upcast softmax (float32 identical, bfloat16 within its rounding)."""
import pytest
import torch

from tiger.edit.guidance import ViewBatch
from tiger.edit.guidance.diffusers_models import _attention_probs_one_pass
from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p
from tiger.edit.guidance.mvdream import MVDreamGuidance, load_mvdream

diffusers = pytest.importorskip("diffusers")


def _cosine_and_rel(a, b):
    a, b = a.double().flatten(), b.double().flatten()
    return float(a @ b / (a.norm() * b.norm())), float((a - b).norm() / b.norm())


def _spy_folded_calls():
    """Calls of channel_bias_add with a residual or a per-sample bias during the next forwards."""
    calls = []
    import tiger.edit.guidance.fused_norms as fn

    real = fn.channel_bias_add

    def spy(x, bias, residual=None, out=None):
        calls.append(residual is not None or bias is not None and bias.dim() == 2)
        return real(x, bias, residual, out=out)

    fn.channel_bias_add = spy
    return calls, lambda: setattr(fn, "channel_bias_add", real)


def test_ip2p_sds_gradient_fused_equals_plain(tiny_models, ring_cameras):
    grads = []
    for fused in (False, True):
        models = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=fused)
        g = InstructPix2PixGuidance(models, "make it red", short_side=16)
        gen = torch.Generator().manual_seed(0)
        renders, originals = torch.rand(4, 3, 16, 16, generator=gen), torch.rand(4, 3, 16, 16, generator=gen)
        views = ViewBatch(cameras=ring_cameras(size=(16, 16)), originals=originals, object_center=torch.zeros(3))
        shape = (4, 4, 8, 8)
        t = torch.tensor([20, 60, 120, 180])
        noise, vae_noise = torch.randn(shape, generator=gen), torch.randn(shape, generator=gen)
        calls, restore = _spy_folded_calls()
        try:
            out, _ = g.grad(renders, views, t=t, noise=noise, vae_noise=vae_noise)
        finally:
            restore()
        assert any(calls) == fused  # the folded adds ran in the fused models only
        grads.append(out)
    cos, rel = _cosine_and_rel(grads[1], grads[0])
    assert cos > 1 - 1e-9 and rel < 1e-5, (cos, rel)


@pytest.mark.parametrize("recon", [True, False])
def test_mvdream_sds_gradient_fused_equals_plain(tiny_models, ring_cameras, recon):
    grads = []
    for fused in (False, True):
        models = load_mvdream(tiny_models / "mvdream" / "sd-v2.1-base-4view.pt", fused_norms=fused)
        g = MVDreamGuidance(models, "a fox", image_size=16, recon=recon)
        gen = torch.Generator().manual_seed(1)
        renders = torch.rand(4, 3, 16, 16, generator=gen)
        views = ViewBatch(cameras=ring_cameras(center=(1.0, 0.0, 0.5)), originals=torch.rand(4, 3, 16, 16),
                          object_center=torch.tensor([1.0, 0.0, 0.5]))
        f = 2 ** (len(models.vae.config.block_out_channels) - 1)
        shape = (4, models.vae.config.latent_channels, 16 // f, 16 // f)
        noise, vae_noise = torch.randn(shape, generator=gen), torch.randn(shape, generator=gen)
        out, _ = g.grad(renders, views, t=torch.tensor([150]), noise=noise, vae_noise=vae_noise)
        grads.append(out)
    cos, rel = _cosine_and_rel(grads[1], grads[0])
    assert cos > 1 - 1e-9 and rel < 1e-5, (cos, rel)


def _vae_like_attention(dtype):
    from diffusers.models.attention_processor import Attention

    torch.manual_seed(0)
    return Attention(64, heads=1, dim_head=64, upcast_softmax=True, residual_connection=True, bias=True,
                     norm_num_groups=8, _from_deprecated_attn_block=True).to(dtype).eval()


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_vae_attention_probs_one_pass_match_upcast(dtype):
    from diffusers.models.attention_processor import Attention

    attn = _vae_like_attention(dtype)
    gen = torch.Generator().manual_seed(2)
    q = (3 * torch.randn(2, 50, 64, generator=gen)).to(dtype)
    k = torch.randn(2, 50, 64, generator=gen).to(dtype)
    want = Attention.get_attention_scores(attn, q, k)  # diffusers: float32 upcast, then back to dtype
    got = _attention_probs_one_pass(attn, q, k)
    assert got.dtype == want.dtype == dtype
    if dtype == torch.float32:
        torch.testing.assert_close(got, want, atol=1e-7, rtol=1e-6)
    else:  # at most one bfloat16 rounding step apart
        assert ((got.float() - want.float()).abs() <= 2 ** -8 * want.float().abs() + 1e-6).all()
    mask = torch.zeros(2, 50, 50, dtype=dtype)
    mask[:, :, :5] = -1e4
    torch.testing.assert_close(_attention_probs_one_pass(attn, q, k, mask).float(),
                               Attention.get_attention_scores(attn, q, k, mask).float(),
                               atol=1e-6 if dtype == torch.float32 else 4e-3, rtol=0)


def test_folded_resnet_add_matches_separate_adds():
    """_conv_then_add: conv bias + [N, C] extra bias + residual, against the three separate adds."""
    from tiger.edit.guidance.fused_norms import _conv_then_add

    torch.manual_seed(3)
    conv = torch.nn.Conv2d(6, 8, 3, padding=1)
    x, r = torch.randn(2, 6, 5, 5), torch.randn(2, 8, 5, 5)
    extra = torch.randn(2, 8)
    want = conv(x) + extra[:, :, None, None] + r
    torch.testing.assert_close(_conv_then_add(conv, x, extra, r), want, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(_conv_then_add(conv, x, extra[:1]), conv(x) + extra[:1, :, None, None])
    plain = torch.nn.Conv2d(6, 8, 3, padding=1, bias=False)
    plain.weight = conv.weight
    torch.testing.assert_close(_conv_then_add(plain, x, None, r), plain(x) + r)
    assert torch.equal(_conv_then_add(plain, x), plain(x))


def test_ip2p_fresh_views_encode_the_condition_in_the_step(tiny_models, ring_cameras):
    """Views without camera ids run ``fresh_step`` (the condition encoded inside the step, one CUDA
    graph on the device): the same gradient as the cached path with ids, and nothing cached."""
    models = load_ip2p(tiny_models / "instruct-pix2pix")
    g = InstructPix2PixGuidance(models, "make it red", short_side=16)
    gen = torch.Generator().manual_seed(5)
    renders, originals = torch.rand(4, 3, 16, 16, generator=gen), torch.rand(4, 3, 16, 16, generator=gen)
    draws = dict(t=torch.tensor([25, 70, 110, 160]), noise=torch.randn(4, 4, 8, 8, generator=gen),
                 vae_noise=torch.randn(4, 4, 8, 8, generator=gen))
    cams = ring_cameras(size=(16, 16))
    fresh, _ = g.grad(renders, ViewBatch(cameras=cams, originals=originals, object_center=torch.zeros(3)), **draws)
    assert not g._cond_cache
    pooled, _ = g.grad(renders, ViewBatch(cameras=cams, originals=originals, view_ids=torch.arange(4),
                                          object_center=torch.zeros(3)), **draws)
    assert len(g._cond_cache) == 4
    cos, rel = _cosine_and_rel(fresh, pooled)  # float32 sums in another order: ~1e-7
    assert cos > 1 - 1e-9 and rel < 1e-5, (cos, rel)
    size = g.resolution(16, 16)
    want = g.step(renders, g.condition_latents(originals, size), draws["t"], draws["noise"], draws["vae_noise"])
    cos, rel = _cosine_and_rel(g.fresh_step(renders, originals, draws["t"], draws["noise"], draws["vae_noise"]), want)
    assert cos > 1 - 1e-9 and rel < 1e-5, (cos, rel)
