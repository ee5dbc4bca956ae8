"""InstructPix2Pix SDS on a tiny random model loaded through the real loader: the gradient against an
independent computation (diffusers' own scheduler, one UNet call per branch, autograd of the SDS
loss), condition caching, dtypes at both ends of the t range, and clear errors."""
import pytest
import torch
import torch.nn.functional as F

from tiger.edit.guidance import ViewBatch
from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p
from tiger.models import ENV_VAR, ModelNotFoundError

diffusers = pytest.importorskip("diffusers")

V, H, W = 4, 12, 16


@pytest.fixture(scope="module")
def models(tiny_models):
    return load_ip2p(tiny_models / "instruct-pix2pix")


def _views(ring_cameras, originals, ids=True):
    return ViewBatch(cameras=ring_cameras(size=(W, H)), originals=originals,
                     view_ids=torch.arange(V) if ids else None, object_center=torch.zeros(3))


def test_registry_resolution_and_missing_error(tiny_models, tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_VAR, str(tiny_models))
    g = InstructPix2PixGuidance.from_registry("make it red", short_side=H)
    assert g.models.unet.config.in_channels == 8
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    with pytest.raises(ModelNotFoundError) as err:
        load_ip2p()
    for part in ("timbrooks/instruct-pix2pix", "unet/config.json", "scheduler/scheduler_config.json", str(tmp_path)):
        assert part in str(err.value)


def test_sds_gradient_matches_independent_computation(models, tiny_models, ring_cameras):
    g = InstructPix2PixGuidance(models, "make it red", short_side=H, keep_text_encoder=True)
    torch.manual_seed(1)
    renders, originals = torch.rand(V, 3, H, W), torch.rand(V, 3, H, W)
    rh, rw = g.resolution(H, W)
    assert (rh, rw) == (12, 16)  # shorter side 12, multiples of the tiny VAE's factor 2
    lat = (V, 4, rh // 2, rw // 2)
    t = torch.tensor([20, 60, 140, 200])
    noise, vae_noise = torch.randn(lat), torch.randn(lat)
    got, info = g.grad(renders, _views(ring_cameras, originals), t=t, noise=noise, vae_noise=vae_noise)

    # reference: diffusers' DDPM scheduler from the model's scheduler config, one UNet call per branch
    sched = diffusers.DDPMScheduler.from_pretrained(str(tiny_models / "instruct-pix2pix"), subfolder="scheduler")
    vae, unet, sf = models.vae, models.unet, models.vae.config.scaling_factor
    x = renders.clone().requires_grad_(True)
    post = vae.encode(F.interpolate(x, (rh, rw), mode="bilinear", align_corners=False) * 2 - 1).latent_dist
    z = (post.mean + post.std * vae_noise) * sf
    with torch.no_grad():
        cond = vae.encode(originals * 2 - 1).latent_dist.mode()
        tok = models.prompts.tokenizer(["make it red", ""], padding="max_length", max_length=77, return_tensors="pt")
        emb = models.prompts.text_encoder(tok.input_ids).last_hidden_state
        z_t = sched.add_noise(z, noise, t)
        run = lambda c, e: unet(torch.cat([z_t, c], 1), t, encoder_hidden_states=e.expand(V, -1, -1)).sample  # noqa: E731
        e_text, e_img, e_unc = run(cond, emb[0:1]), run(cond, emb[1:2]), run(torch.zeros_like(cond), emb[1:2])
        eps = e_unc + 7.5 * (e_text - e_img) + 1.5 * (e_img - e_unc)
        w = (1 - sched.alphas_cumprod[t]).view(-1, 1, 1, 1)
        grad = w * (eps - noise)
    loss = 0.5 * F.mse_loss(z, (z - grad).detach(), reduction="sum") / V
    loss.backward()
    assert torch.allclose(got, x.grad, rtol=1e-4, atol=1e-5 * float(x.grad.abs().max())), float((got - x.grad).abs().max())
    assert torch.equal(info.t, t)


def test_condition_latents_cached_per_camera(models, ring_cameras):
    g = InstructPix2PixGuidance(models, "make it red", short_side=H)
    originals = torch.rand(V, 3, H, W)
    a = g.condition_latents(originals, (H, W), torch.arange(V))
    b = g.condition_latents(torch.rand(V, 3, H, W), (H, W), torch.arange(V))  # same cameras: cached
    assert torch.equal(a, b) and len(g._cond_cache) == V
    c = g.condition_latents(originals, (H, W), None)  # no ids: computed, equal to the cached values
    assert torch.allclose(a, c, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_gradients_finite_at_both_ends_of_t(tiny_models, ring_cameras, dtype):
    m = load_ip2p(tiny_models / "instruct-pix2pix", dtype=dtype)
    g = InstructPix2PixGuidance(m, "make it red", short_side=H)
    lo, hi = m.schedule.step_range(g.t_range)
    renders, views = torch.rand(V, 3, H, W), _views(ring_cameras, torch.rand(V, 3, H, W))
    for t in (lo, hi):
        out, _ = g.grad(renders, views, t=torch.full((V,), t))
        assert out.dtype == torch.float32 and bool(torch.isfinite(out).all()) and float(out.abs().max()) > 0


def test_bad_inputs_named(models, ring_cameras):
    g = InstructPix2PixGuidance(models, "make it red", short_side=H)
    views = _views(ring_cameras, torch.rand(V, 3, H, W))
    with pytest.raises(ValueError, match=r"\[V, 3, H, W\]"):
        g.grad(torch.rand(V, 4, H, W), views)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        g.grad(torch.rand(V, 3, H, W) + 1.0, views)
    nan = torch.rand(V, 3, H, W)
    nan[1, 2, 3, 4] = float("nan")
    with pytest.raises(ValueError, match="ip2p: renders contain NaN or Inf"):
        g.grad(nan, views)
    with pytest.raises(ValueError, match="originals"):
        g.grad(torch.rand(V, 3, H + 2, W), views)
    with pytest.raises(ValueError, match="noise"):
        g.grad(torch.rand(V, 3, H, W), views, noise=torch.zeros(1))
    with pytest.raises(ValueError, match="t_range"):
        InstructPix2PixGuidance(models, "x", t_range=(0.5, 0.2))


def test_matmul_vae_attention_keeps_encoder_output_and_gradient(tiny_models):
    """The VAE's attention switched from SDPA to plain matmul + softmax (speed: see
    ``matmul_vae_attention``) computes the same latents and the same input gradient."""
    from diffusers.models.attention_processor import Attention, AttnProcessor

    from tiger.edit.guidance.diffusers_models import encode_latents, latent_shape, matmul_vae_attention

    vae = load_ip2p(tiny_models / "instruct-pix2pix").vae
    attn = [m for m in vae.modules() if isinstance(m, Attention)]
    assert attn and not any(isinstance(m.processor, AttnProcessor) for m in attn)
    torch.manual_seed(0)
    x = torch.rand(2, 3, 32, 32, dtype=torch.float64)
    vae = vae.double()
    noise = torch.randn(latent_shape(vae, 2, (32, 32)), dtype=torch.float64)

    def run():
        xr = x.clone().requires_grad_(True)
        z = encode_latents(vae, xr, noise)
        (g,) = torch.autograd.grad((z * torch.linspace(-1, 1, z.numel(), dtype=z.dtype).view_as(z)).sum(), xr)
        return z.detach(), g

    z0, g0 = run()
    assert matmul_vae_attention(vae) == len(attn)
    assert all(isinstance(m.processor, AttnProcessor) for m in attn)
    z1, g1 = run()
    # diffusers' plain processor takes the softmax in float32 (upcast_softmax), SDPA in float64 here
    assert torch.allclose(z0, z1, rtol=1e-5, atol=1e-6 * float(z0.abs().max()))
    assert torch.allclose(g0, g1, rtol=1e-5, atol=1e-6 * float(g0.abs().max()))
