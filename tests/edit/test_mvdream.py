"""MVDream SDS on a tiny random model loaded from its original LDM .pt: reconstruction-form and plain
SDS gradients against an independent computation, the diffusers folder giving the same gradient,
lazy loading, dtypes at both ends of the t range, and clear errors."""
import json
import shutil

import pytest
import torch
import torch.nn.functional as F

from tiger.edit.guidance import ViewBatch
from tiger.edit.guidance.mvdream import MVDreamGuidance, load_mvdream
from tiger.edit.guidance.ldm_checkpoint import convert_ldm_checkpoint
from tiger.edit.guidance.mvdream_cameras import mvdream_cameras
from tiger.testing.random_models import mvdream_ldm_config
from tiger.models import ENV_VAR, ModelNotFoundError

diffusers = pytest.importorskip("diffusers")
transformers = pytest.importorskip("transformers")

S = 16  # MVDream's 256 scaled down for the tiny model


@pytest.fixture(scope="module")
def models(tiny_models):
    return load_mvdream(tiny_models / "mvdream" / "sd-v2.1-base-4view.pt")


def _views(ring_cameras):
    return ViewBatch(cameras=ring_cameras(center=(1.0, 0.0, 0.5)), originals=torch.rand(4, 3, 16, 16),
                     object_center=torch.tensor([1.0, 0.0, 0.5]))


def _reference(models, renders, views, t, noise, vae_noise, recon):
    # written from MVDream-threestudio's guidance: one t, [text; negative] branches, scale 50
    vae, unet = models.vae, models.unet
    p = mvdream_ldm_config("tiny")["model"]["params"]
    betas = torch.linspace(p["linear_start"] ** 0.5, p["linear_end"] ** 0.5, 1000, dtype=torch.float64) ** 2
    acp = torch.cumprod(1 - betas, 0).to(renders.dtype)
    x = renders.clone().requires_grad_(True)
    post = vae.encode(F.interpolate(x, (S, S), mode="bilinear", align_corners=False) * 2 - 1).latent_dist
    z = (post.mean + post.std * vae_noise) * vae.config.scaling_factor
    with torch.no_grad():
        tok = models.prompts.tokenizer(["a fox", "ugly"], padding="max_length", max_length=77, return_tensors="pt")
        emb = models.prompts.text_encoder(tok.input_ids).last_hidden_state.to(renders.dtype)
        a = acp[t]
        z_t = a.sqrt() * z + (1 - a).sqrt() * noise
        cams = mvdream_cameras(views.cameras, views.object_center).to(renders.dtype)
        out = unet(torch.cat([z_t, z_t]), t.repeat(8), encoder_hidden_states=emb.repeat_interleave(4, 0),
                   class_labels=cams.repeat(2, 1)).sample
        e_text, e_unc = out.chunk(2)
        eps = e_unc + 50.0 * (e_text - e_unc)
    if recon:
        x0 = (z_t - (1 - a).sqrt() * eps) / a.sqrt()
        x0_text = (z_t - (1 - a).sqrt() * e_text) / a.sqrt()
        factor = (x0_text.view(-1, 4, *x0.shape[1:]).std([1, 2, 3, 4], keepdim=True) + 1e-8) / (
            x0.view(-1, 4, *x0.shape[1:]).std([1, 2, 3, 4], keepdim=True) + 1e-8)
        x0 = 0.5 * x0 * factor.squeeze(1).repeat_interleave(4, dim=0) + 0.5 * x0
        loss = 0.5 * F.mse_loss(z, x0.detach(), reduction="sum") / 4
    else:
        grad = (1 - a) * (eps - noise)
        loss = 0.5 * F.mse_loss(z, (z - grad).detach(), reduction="sum") / 4
    loss.backward()
    return x.grad


@pytest.fixture(scope="module")
def models64(tiny_models):
    return load_mvdream(tiny_models / "mvdream" / "sd-v2.1-base-4view.pt", dtype=torch.float64)


@pytest.mark.parametrize("recon", [True, False])
def test_sds_gradient_matches_independent_computation(models64, ring_cameras, recon):
    # float64 models: guidance scale 50 multiplies the branches' difference, and with it the
    # float32 rounding of convolutions whose results depend on the batch size (the guidance runs
    # the branches' shared prefix on 4 rows, the reference on 8); what is left is the guidance's
    # CFG in float32 (its noise predictions are taken to float32), ~6e-7 of the largest entry
    g = MVDreamGuidance(models64, "a fox", negative_prompt="ugly", image_size=S, recon=recon, keep_text_encoder=True)
    torch.manual_seed(2)
    renders, views = torch.rand(4, 3, 24, 24, dtype=torch.float64), _views(ring_cameras)
    t = torch.tensor([150])
    noise, vae_noise = (torch.randn(4, 4, S // 2, S // 2, dtype=torch.float64) for _ in range(2))
    got, _ = g.grad(renders, views, t=t, noise=noise, vae_noise=vae_noise)
    want = _reference(models64, renders, views, t, noise, vae_noise, recon)
    assert torch.allclose(got, want, rtol=1e-5, atol=2e-6 * float(want.abs().max())), float((got - want).abs().max())


def test_diffusers_folder_gives_the_same_gradient(models, tiny_models, ring_cameras, tmp_path):
    folder = tmp_path / "mvdream-diffusers"
    models.unet.save_pretrained(str(folder / "unet"))
    # the loaded VAE is encoder-only: write the full one (and the text tower) from the conversion
    comp = convert_ldm_checkpoint(torch.load(tiny_models / "mvdream" / "sd-v2.1-base-4view.pt", weights_only=True),
                                  mvdream_ldm_config("tiny"))
    full_vae = diffusers.AutoencoderKL(**comp.vae_config)
    full_vae.load_state_dict(comp.vae_state)
    full_vae.save_pretrained(str(folder / "vae"))
    text = transformers.CLIPTextModel(transformers.CLIPTextConfig(**comp.text_config))
    text.load_state_dict(comp.text_state, strict=False)
    text.save_pretrained(str(folder / "text_encoder"))
    shutil.copytree(tiny_models / "mvdream" / "tokenizer", folder / "tokenizer")
    (folder / "scheduler").mkdir()
    (folder / "scheduler" / "scheduler_config.json").write_text(json.dumps(
        {"beta_start": 0.00085, "beta_end": 0.012, "beta_schedule": "scaled_linear", "num_train_timesteps": 1000}))
    other = load_mvdream(folder)
    args = dict(t=torch.tensor([100]), noise=torch.randn(4, 4, S // 2, S // 2), vae_noise=torch.randn(4, 4, S // 2, S // 2))
    renders, views = torch.rand(4, 3, 16, 16), _views(ring_cameras)
    a, _ = MVDreamGuidance(models, "a fox", image_size=S, keep_text_encoder=True).grad(renders, views, **args)
    b, _ = MVDreamGuidance(other, "a fox", image_size=S).grad(renders, views, **args)
    assert torch.allclose(a, b, rtol=1e-5, atol=1e-7)


def test_lazy_loading_and_release(tiny_models, ring_cameras, monkeypatch, tmp_path):
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    with pytest.raises(ModelNotFoundError) as err:  # resolved at construction, loaded later
        MVDreamGuidance.from_registry("a fox")
    for part in ("MVDream/MVDream", "sd-v2.1-base-4view.pt", "unet/config.json", str(tmp_path)):
        assert part in str(err.value)
    monkeypatch.setenv(ENV_VAR, str(tiny_models))
    g = MVDreamGuidance.from_registry("a fox", image_size=S)
    assert not g.loaded  # λ2 = 0 runs never pay for MVDream
    out, _ = g.grad(torch.rand(4, 3, 16, 16), _views(ring_cameras))
    assert g.loaded and out.shape == (4, 3, 16, 16)
    g.release()
    assert not g.loaded


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_gradients_finite_at_both_ends_of_t(tiny_models, ring_cameras, dtype):
    m = load_mvdream(tiny_models / "mvdream", dtype=dtype)
    g = MVDreamGuidance(m, "a fox", image_size=S)
    lo, hi = m.schedule.step_range(g.t_range)
    assert (lo, hi) == (20, 200)
    for t in (lo, hi):
        out, _ = g.grad(torch.rand(4, 3, 16, 16), _views(ring_cameras), t=torch.tensor([t]))
        assert bool(torch.isfinite(out).all()) and float(out.abs().max()) > 0


def test_bad_inputs_named(models, ring_cameras):
    g = MVDreamGuidance(models, "a fox", image_size=S, keep_text_encoder=True)
    views = _views(ring_cameras)
    with pytest.raises(ValueError, match="exactly 4 views"):
        g.grad(torch.rand(3, 3, 16, 16), views)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        g.grad(torch.rand(4, 3, 16, 16) - 2.0, views)
    inf = torch.rand(4, 3, 16, 16)
    inf[3, 0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="renders contain NaN or Inf"):
        g.grad(inf, views)
    with pytest.raises(ValueError, match=r"\[V, 3, H, W\]"):
        g.grad(torch.rand(4, 16, 16), views)
    with pytest.raises(ValueError, match="object_center"):
        g.grad(torch.rand(4, 3, 16, 16), ViewBatch(cameras=views.cameras, originals=views.originals))


def test_camera_conditions_cached_by_view_ids(models, ring_cameras):
    """Pooled camera sets keep their conditions (the same values as the uncached conversion); other
    ids, another object centre or a reset convert again."""
    g = MVDreamGuidance(models, "a fox", image_size=S)
    cams = ring_cameras(center=(1.0, 0.0, 0.5))
    center = torch.tensor([1.0, 0.0, 0.5])
    pooled = ViewBatch(cameras=cams, originals=torch.rand(4, 3, 16, 16), object_center=center,
                       view_ids=torch.arange(8, 12))
    first = g.camera_conditions(pooled)
    assert torch.equal(first, mvdream_cameras(cams, center))
    assert g.camera_conditions(pooled) is first  # cached
    moved = ViewBatch(cameras=cams, originals=pooled.originals, object_center=center + 1, view_ids=pooled.view_ids)
    assert torch.equal(g.camera_conditions(moved), mvdream_cameras(cams, center + 1))
    other = ring_cameras(center=(0.0, 1.0, 0.5))
    renamed = ViewBatch(cameras=other, originals=pooled.originals, object_center=center, view_ids=torch.arange(4))
    assert torch.equal(g.camera_conditions(renamed), mvdream_cameras(other, center))
    g.reset_caches()
    assert g.camera_conditions(pooled) is not first
    fresh = ViewBatch(cameras=cams, originals=pooled.originals, object_center=center)
    assert g.camera_conditions(fresh) is not g.camera_conditions(fresh)  # no ids: nothing cached


def test_text_tower_built_without_random_init_equals_the_loaded_reference(tiny_models):
    """The .pt's text tower is built on the meta device and given the checkpoint's tensors (no
    random init); its outputs and position ids are those of a randomly initialised CLIPTextModel
    that loads the same state dict."""
    comp = convert_ldm_checkpoint(torch.load(tiny_models / "mvdream" / "sd-v2.1-base-4view.pt", weights_only=True),
                                  mvdream_ldm_config("tiny"))
    ref = transformers.CLIPTextModel(transformers.CLIPTextConfig(**comp.text_config))
    ref.load_state_dict(comp.text_state, strict=False)
    got = load_mvdream(tiny_models / "mvdream" / "sd-v2.1-base-4view.pt").prompts.text_encoder
    ids = torch.randint(0, comp.text_config["vocab_size"], (2, 77), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        assert torch.equal(got(ids).last_hidden_state, ref.eval()(ids).last_hidden_state)
    ids_of = lambda m: dict(m.named_buffers())  # noqa: E731
    assert [n for n in ids_of(got) if n.endswith("position_ids")]
    for n, b in ids_of(ref).items():
        assert torch.equal(ids_of(got)[n], b)
    assert not any(t.is_meta for t in list(got.parameters()) + list(got.buffers()))
