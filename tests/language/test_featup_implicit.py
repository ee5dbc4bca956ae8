"""FeatUp's implicit upsampler recovers a known high-resolution feature field from jittered
low-resolution views of a synthetic image better than bilinear upsampling."""
import torch
import torch.nn.functional as F

from tiger.language.featup import ImplicitConfig, ImplicitUpsampler, Jitter, upsample_features

H = W = 32
POOL = 8


def scene():
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    img = torch.empty(3, H, W)
    img[:] = torch.tensor([0.2, 0.3, 0.8])[:, None, None]
    disc = (yy - 13.3) ** 2 + (xx - 18.7) ** 2 <= 9.5**2
    img[:, disc] = torch.tensor([0.9, 0.5, 0.1])[:, None]
    box = (yy > 20) & (xx < 12)
    img[:, box] = torch.tensor([0.1, 0.9, 0.3])[:, None]
    return img


MIX = torch.randn(6, 3, generator=torch.Generator().manual_seed(0))


def field(images):
    """The ground-truth pixel-level features: a fixed linear map of colour (sharp at edges)."""
    return torch.einsum("dc,bchw->bdhw", MIX, images)


def backbone(images):
    """A low-resolution 'backbone': the field averaged over 8x8 patches (like a ViT's tokens)."""
    return F.avg_pool2d(field(images), POOL)


def test_implicit_beats_bilinear():
    img = scene()
    truth = field(img[None])[0]
    bilinear = upsample_features(img, backbone, (H, W), "bilinear")
    cfg = ImplicitConfig(steps=120, n_views=32, pca_batch=32, kernel_size=11, jitters_per_step=3)
    up = ImplicitUpsampler.fit(img, backbone, cfg)
    pred = up((H, W))
    err_implicit = (pred - truth).square().mean().item()
    err_bilinear = (bilinear - truth).square().mean().item()
    assert pred.shape == truth.shape
    assert err_implicit < 0.5 * err_bilinear, (err_implicit, err_bilinear)
    assert up.history[-1] < up.history[0]
    # resolution-free: evaluating at another size stays close to the field there
    big = up((2 * H, 2 * W))
    truth_big = field(F.interpolate(img[None], size=(2 * H, 2 * W), mode="bilinear", antialias=True))[0]
    assert (big - truth_big).square().mean().item() < err_bilinear


def test_jitter_is_one_transform_for_image_and_features():
    x = torch.arange(2 * 8 * 10, dtype=torch.float32).reshape(1, 2, 8, 10)
    j = Jitter(pad=2, zoom=1.0, y=1, x=3, flip=True)
    out = j.apply(x)
    ref = torch.flip(F.pad(x, [2] * 4, mode="reflect")[..., 1:9, 3:13], [3])
    assert torch.equal(out, ref)


def test_fit_is_deterministic_and_leaves_global_rng_alone():
    img = scene()
    cfg = ImplicitConfig(steps=3, n_views=4, pca_batch=4, kernel_size=5, jitters_per_step=2)
    torch.manual_seed(123)
    expected_next = torch.rand(1)
    torch.manual_seed(123)
    a = ImplicitUpsampler.fit(img, backbone, cfg)()
    assert torch.equal(torch.rand(1), expected_next)
    b = ImplicitUpsampler.fit(img, backbone, cfg)()
    assert torch.equal(a, b)


# ----------------------------------------------------------------------------- the fast fit
import dataclasses  # noqa: E402

import pytest  # noqa: E402

import tiger.ops  # noqa: E402
from tiger.language.featup import AttentionDownsampler, sample_jitter  # noqa: E402
from tiger.language.featup_fit import apply_jitters, jitter_grid, jitter_params, window_attention  # noqa: E402
from tiger.utils.filters import gaussian_blur  # noqa: E402

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
needs_cuda = pytest.mark.skipif(not CUDA, reason="needs CUDA")


def test_jitter_grid_reads_what_jitter_apply_reads():
    """One grid_sample per batch of jitters = FeatUp's pad/zoom/crop/flip, zoomed or not, flipped or not."""
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(1, 4, 30, 52, generator=gen, dtype=torch.float64)
    jitters = [sample_jitter(30, 52, 6, 1.8, True, gen) for _ in range(64)]
    assert any(j.zoom > 1 for j in jitters) and any(j.zoom == 1 for j in jitters) and any(j.flip for j in jitters)
    grid = jitter_grid(jitter_params(jitters, 30, 52, x.device), 30, 52).double()
    fast = apply_jitters(x, grid)
    ref = torch.cat([j.apply(x) for j in jitters])
    assert torch.allclose(fast, ref, atol=1e-4), (fast - ref).abs().max()  # float32 grid coordinates


@pytest.mark.parametrize("hw,size,kernel", [((40, 72), (5, 9), 11), ((40, 72), (3, 4), 11), ((33, 47), (8, 14), 7),
                                            ((64, 112), (4, 7), 29)])
def test_window_attention_equals_the_downsampler(hw, size, kernel):
    """Logits on one channel + fold/avg-pool window sums = the reference's unfold-patches downsampler."""
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(3, 5, *hw, generator=gen, dtype=torch.float64)
    down = AttentionDownsampler(5, kernel, gen).double().eval()
    ref = down(x, size)
    blurred = gaussian_blur(x, 5, 1.0, padding="reflect")
    lin = down.attention[1]
    logit_map = F.conv2d(blurred, lin.weight.view(1, -1, 1, 1), lin.bias)
    out = window_attention(down, logit_map, blurred, size)
    assert out.shape == ref.shape
    assert torch.allclose(out, ref, atol=1e-10), (out - ref).abs().max()


class PatchBackbone(torch.nn.Module):
    """A ViT-like stand-in: 8x8 patches embedded to 48 channels, a 3x3 token mixer, GELU."""

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(5)
        self.embed = torch.nn.Parameter(torch.randn(48, 3, 8, 8, generator=g) / 8)
        self.mix = torch.nn.Parameter(torch.randn(48, 48, 3, 3, generator=g) / 20)

    def forward(self, images):
        tokens = F.conv2d(images, self.embed, stride=8)
        return tokens + F.gelu(F.conv2d(tokens, self.mix, padding=1))


def _photo(h, w):
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.stack([0.3 + 0.4 * xx, 0.2 + 0.5 * yy, 0.6 - 0.3 * xx * yy])
    img[:, (yy - 0.4) ** 2 + (xx - 0.6) ** 2 < 0.06] = torch.tensor([0.9, 0.2, 0.1])[:, None]
    img[:, (yy > 0.7) & (xx < 0.3)] = torch.tensor([0.1, 0.8, 0.4])[:, None]
    return img


FIT = ImplicitConfig(steps=60, n_views=40, pca_batch=40, proj_dim=16, kernel_size=11, jitters_per_step=4)


def test_fast_fit_gives_the_reference_fit():
    """The default (fast) fit's upsampled map against the reference loop's, same seed: per-pixel
    cosine similarity mean >= 0.99 (dropout on, as by default; the masks differ by construction)."""
    img, backbone = _photo(48, 80), PatchBackbone()
    fast = ImplicitUpsampler.fit(img, backbone, FIT)((96, 160))
    ref = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(FIT, method="reference"))((96, 160))
    cos = F.cosine_similarity(fast, ref, dim=0)
    assert cos.mean() >= 0.99 and torch.quantile(cos.flatten(), 0.01) >= 0.95, (cos.mean(), cos.min())


def test_config_names_a_bad_method_or_precision():
    with pytest.raises(ValueError, match="method"):
        ImplicitConfig(method="quick")
    with pytest.raises(ValueError, match="precision"):
        ImplicitConfig(precision="fp16")


@needs_cuda
def test_fast_fit_on_cuda_equals_cpu():
    """float32 on CUDA without TF32 and without dropout follows the CPU fit: the first losses to
    rounding, the maps in direction (NAdam's first steps follow the sign of near-zero gradients,
    which rounding picks: see test_featup_devices.py); the default bf16 fit stays within the fit's
    tolerance (per-pixel cosine mean >= 0.99) of the CPU fit."""
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        img, backbone = _photo(48, 80), PatchBackbone()
        cfg = dataclasses.replace(FIT, dropout=0.0, precision="fp32")
        cpu = ImplicitUpsampler.fit(img, backbone, cfg)
        gpu = ImplicitUpsampler.fit(img.cuda(), backbone.cuda(), cfg)
        assert gpu.mean.device.type == "cuda"
        assert torch.allclose(torch.tensor(gpu.history[:6]), torch.tensor(cpu.history[:6]), rtol=2e-3, atol=1e-5)
        a, b = cpu((96, 160)), gpu((96, 160)).cpu()
        cos = F.cosine_similarity(a, b, dim=0)
        assert cos.mean() >= 0.99 and cos.min() > 0.9, (cos.mean(), cos.min())
        bf16 = ImplicitUpsampler.fit(img.cuda(), backbone.cuda(), dataclasses.replace(cfg, precision="bf16"))
        cos = F.cosine_similarity(a, bf16((96, 160)).cpu(), dim=0)
        assert cos.mean() >= 0.99, cos.mean()
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def test_network_channels_last_equals_the_convolutions():
    """The fast fit's per-pixel MLP form of the implicit network = its 1x1-convolution form."""
    from tiger.language.featup import ImplicitNet

    gen = torch.Generator().manual_seed(7)
    net = ImplicitNet(12, n_freqs=6, generator=gen).double()
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=gen, dtype=p.dtype))
    img = torch.rand(2, 3, 9, 14, generator=gen, dtype=torch.float64)
    net.eval()
    torch.testing.assert_close(net.forward_pixels(img), net(img), atol=1e-12, rtol=1e-12)
    net.train()  # channel dropout: every channel of an image kept or dropped whole, kept ones scaled
    torch.manual_seed(0)
    out = net.forward_pixels(img)
    assert out.shape == (2, 12, 9, 14)
    net.net[1].p = net.net[4].p = 0.0
    torch.testing.assert_close(net.forward_pixels(img), net(img), atol=1e-12, rtol=1e-12)


def test_compiled_network_fit_equals_the_plain_fit():
    """``compile_network`` (torch.compile of the channels-last network) changes no result."""
    img, backbone = _photo(32, 48), PatchBackbone()
    cfg = ImplicitConfig(steps=4, n_views=8, pca_batch=8, proj_dim=8, kernel_size=7, jitters_per_step=2, n_freqs=5,
                         dropout=0.0, precision="fp32")
    plain = ImplicitUpsampler.fit(img, backbone, cfg)
    compiled = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(cfg, compile_network=True))
    torch.testing.assert_close(torch.tensor(compiled.history), torch.tensor(plain.history), rtol=1e-4, atol=1e-6)
    # maps in direction: NAdam's first steps amplify rounding where gradients are near zero
    cos = F.cosine_similarity(compiled(), plain(), dim=0)
    assert cos.mean() >= 0.999 and cos.min() >= 0.98, (cos.mean(), cos.min())


STOP = dataclasses.replace(FIT, steps=12, check_every=3, min_steps=6, dropout=0.0)


def test_stopping_check_measures_the_maps_change():
    """Each stopping check's reported change equals 1 - the mean per-pixel cosine similarity
    between the maps of two fits run to that check's step and to the previous check's (same
    seed: the same trajectory), at the fitting resolution; with stop_change=0 every step runs."""
    img, backbone = _photo(48, 80), PatchBackbone()
    full = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(STOP, stop_change=0.0))
    assert len(full.history) == STOP.steps and full.checks == []
    watched = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(STOP, stop_change=1e-12))
    assert [s for s, _ in watched.checks] == [6, 9]  # first map at step 3, compared from step 6 on
    for step, change in watched.checks:
        a = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(STOP, steps=step - 3, stop_change=0.0))()
        b = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(STOP, steps=step, stop_change=0.0))()
        expected = 1.0 - float(F.cosine_similarity(a.flatten(1), b.flatten(1), dim=0).mean())
        assert abs(change - expected) <= 1e-4 * max(expected, 1e-3), (step, change, expected)


def test_fit_stops_once_the_map_settles_and_featurises_only_picked_views():
    img, backbone = _photo(48, 80), PatchBackbone()
    loose = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(STOP, stop_change=0.999,
                                                                     n_views=400, pca_batch=8))
    assert len(loose.history) == STOP.min_steps  # any change passes: stops at the first allowed check
    assert loose.checks[-1][0] == STOP.min_steps and loose.checks[-1][1] < 0.999
    # 8 PCA views plus at most 6 steps x 4 picks, of 400
    assert 8 < loose.views_featurised <= 8 + STOP.min_steps * STOP.jitters_per_step
    with pytest.raises(ValueError, match="stop_change"):
        ImplicitConfig(stop_change=1.0)
