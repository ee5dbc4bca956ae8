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
