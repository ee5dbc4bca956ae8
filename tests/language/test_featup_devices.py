"""The implicit FeatUp fit on every device: its tensors (PCA mean and basis, targets, network) live
on the image's device, and on CUDA the fit follows the CPU fit (every random number but the
dropout masks is drawn from one CPU generator; with ``dropout=0`` there are none; ``precision="fp32"``
keeps the fast fit out of bf16 autocast on CUDA)."""
import pytest
import torch
import torch.nn.functional as F

import tiger.ops
from tiger.language.featup import ImplicitConfig, ImplicitUpsampler, _pca_basis, _project

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
needs_cuda = pytest.mark.skipif(not CUDA, reason="needs CUDA")

TINY = ImplicitConfig(steps=6, n_views=6, pca_batch=6, proj_dim=5, kernel_size=5, jitters_per_step=2,
                      n_freqs=4, dropout=0.0, precision="fp32")


def image(h=24, w=32, seed=0):
    return torch.rand(3, h, w, generator=torch.Generator().manual_seed(seed))


class PooledColour(torch.nn.Module):
    """A 'backbone' with weights: 8 channels of colour mixed per pixel and average-pooled 4x."""

    def __init__(self):
        super().__init__()
        self.mix = torch.nn.Parameter(torch.randn(8, 3, generator=torch.Generator().manual_seed(1)))

    def forward(self, images):
        return F.avg_pool2d(torch.einsum("dc,bchw->bdhw", self.mix, images), 4)


def test_pca_basis_and_projection_stay_on_the_views_device():
    views = torch.randn(4, 8, 3, 5, generator=torch.Generator().manual_seed(0))
    mean, basis = _pca_basis(views, 3)
    assert mean.device == views.device and basis.device == views.device
    assert mean.dtype == basis.dtype == torch.float32 and basis.shape == (8, 3)
    coeffs = _project(views, mean, basis)
    rows = views.permute(0, 2, 3, 1).reshape(-1, 8).double()
    ref = (rows - rows.mean(0)) @ basis.double()
    assert torch.allclose(coeffs.permute(0, 2, 3, 1).reshape(-1, 3).double(), ref, atol=1e-5)


def test_fit_without_dropout_on_cpu():
    up = ImplicitUpsampler.fit(image(), PooledColour(), TINY)
    out = up((12, 16))
    assert out.shape == (8, 12, 16) and torch.isfinite(out).all()
    assert up.mean.device.type == "cpu" and len(up.history) == TINY.steps


@pytest.fixture
def exact_cuda_math():
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


@needs_cuda
def test_cuda_fit_equals_cpu_fit(exact_cuda_math):
    img = image()
    cpu = ImplicitUpsampler.fit(img, PooledColour(), TINY)
    gpu = ImplicitUpsampler.fit(img.cuda(), PooledColour().cuda(), TINY)
    assert gpu.mean.device.type == "cuda" and gpu.basis.device.type == "cuda"
    # Reductions run in another order on each device; six optimizer steps grow that to ~3e-4
    # relative in the loss (measured on an H100), so the tolerance is 2e-3.
    assert torch.allclose(torch.tensor(gpu.history), torch.tensor(cpu.history), rtol=2e-3, atol=1e-5)
    # Adam's first steps move each weight by about lr * sign(gradient): where a gradient is near
    # zero the devices' rounding picks the sign, so the maps agree in direction, not digit for digit
    # (on an H100: max abs difference 0.17 on values of ~1.4).
    a, b = cpu((24, 32)), gpu((24, 32)).cpu()
    cos = F.cosine_similarity(a.reshape(a.shape[0], -1), b.reshape(b.shape[0], -1), dim=0)
    assert cos.mean() > 0.99 and cos.min() > 0.9, (cos.mean(), cos.min())


@needs_cuda
def test_cuda_fit_with_dropout_runs_and_is_deterministic():
    import dataclasses

    cfg = dataclasses.replace(TINY, dropout=0.2)
    img, net = image().cuda(), PooledColour().cuda()
    first = ImplicitUpsampler.fit(img, net, cfg)()
    again = ImplicitUpsampler.fit(img, net, cfg)()
    assert first.device.type == "cuda" and torch.isfinite(first).all()
    # the same dropout masks; CUDA's atomic adds (interpolation backward) may round differently
    assert torch.allclose(first, again, rtol=1e-3, atol=1e-3), (first - again).abs().max()


@needs_cuda
def test_extract_features_implicit_cuda_equals_cpu(tiny_models, tmp_path, exact_cuda_math):
    from tiger.language.extract import FeatureConfig, extract_features
    from tiger.language.maskclip import MaskCLIP

    cfg = FeatureConfig(upsampler="implicit", clip_long_side=64, output_long_side=32, pca_dim=4, use_sam=False,
                        implicit=TINY)
    imgs = [image(40, 56, seed=k) for k in range(2)]
    results = {}
    for dev in ("cpu", "cuda"):
        clip = MaskCLIP.from_pretrained(tiny_models / "clip-vit-base-patch16", device=dev)
        results[dev] = extract_features(imgs, tmp_path / dev, clip=clip, config=cfg, progress=False)
    for name in results["cpu"].names:
        a, va = results["cpu"].load(name)
        b, vb = results["cuda"].load(name)
        assert torch.equal(va, vb)
        cos = F.cosine_similarity(a.float().reshape(-1, 4), b.float().reshape(-1, 4), dim=1)
        # The PCA to 4 dimensions magnifies the devices' rounding where a pixel's feature is small:
        # on an H100 the mean cosine was 0.9995 and single pixels down to 0.75.
        assert cos.mean() > 0.999 and torch.quantile(cos, 0.01) > 0.99, (cos.mean(), cos.min())
