"""SSIM against an independent SciPy implementation; PSNR; the position learning rate."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from tiger.recon import expon_lr, psnr, ssim, ssim_map
from tiger.recon.losses import photometric_loss
from tiger.utils.filters import gaussian_blur


def ssim_scipy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Wang et al.'s SSIM with an 11-tap Gaussian window (sigma 1.5), zero padding, per
    channel of [H, W, C] float64 images in [0, 1]."""
    f = lambda x: gaussian_filter(x, sigma=1.5, mode="constant", cval=0.0, truncate=5 / 1.5)  # noqa: E731
    out = np.empty_like(a)
    for c in range(a.shape[2]):
        x, y = a[..., c], b[..., c]
        mx, my = f(x), f(y)
        sxx, syy, sxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        out[..., c] = (2 * mx * my + c1) * (2 * sxy + c2) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return out


@pytest.mark.parametrize("shape", [(37, 53, 3), (8, 9, 1), (64, 64, 3)])
def test_ssim_matches_scipy_reference(shape):
    rng = np.random.default_rng(0)
    a = rng.uniform(size=shape)
    b = np.clip(a + rng.normal(scale=0.1, size=shape), 0, 1)
    ref = ssim_scipy(a, b)
    got = ssim_map(torch.from_numpy(a), torch.from_numpy(b))[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    # float32 (the training dtype) stays close
    got32 = float(ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float()))
    assert got32 == pytest.approx(ref.mean(), abs=1e-5)


def test_blur_methods_agree_and_ssim_properties():
    x = torch.rand(2, 5, 20, 17, dtype=torch.float64)
    ref = gaussian_blur(x, method="conv")
    for m in ("depthwise", "shift", "matmul", "auto"):
        torch.testing.assert_close(gaussian_blur(x, method=m), ref, rtol=0, atol=1e-14)
    a = torch.rand(16, 16, 3, requires_grad=True)
    assert float(ssim(a.detach(), a.detach())) == pytest.approx(1.0, abs=1e-6)
    photometric_loss(a, torch.rand(16, 16, 3)).backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


def test_psnr():
    a = torch.zeros(4, 4, 3)
    b = torch.full((4, 4, 3), 0.1)
    assert psnr(a, b) == pytest.approx(20.0)
    assert psnr(a, a) == math.inf


def test_position_lr_schedule_is_log_linear():
    assert expon_lr(0, 1.6e-4, 1.6e-6, 30000) == pytest.approx(1.6e-4)
    assert expon_lr(30000, 1.6e-4, 1.6e-6, 30000) == pytest.approx(1.6e-6)
    assert expon_lr(15000, 1.6e-4, 1.6e-6, 30000) == pytest.approx(1.6e-5)       # geometric mean
    assert expon_lr(60000, 1.6e-4, 1.6e-6, 30000) == pytest.approx(1.6e-6)       # clamped
    assert expon_lr(0, 1.0, 0.1, 100, delay_steps=10, delay_mult=0.01) == pytest.approx(0.01)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_ssim_on_cuda_matches_cpu():
    a, b = torch.rand(2, 3, 70, 90, dtype=torch.float64).unbind(0)
    cpu = ssim_map(a, b)
    gpu = ssim_map(a.cuda(), b.cuda())   # fused kernels on both devices
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=0, atol=1e-12)


def test_scaled_schedule_is_inria_at_30k_and_sane_when_short():
    from tiger.recon import ReconConfig

    assert ReconConfig.scaled(30_000).to_dict() == ReconConfig().to_dict()
    short = ReconConfig.scaled(600)
    assert short.densify_from >= 100 and short.densify_interval >= 50
    assert short.densify_from + short.densify_interval <= short.densify_until <= 600
    assert ReconConfig.from_dict(short.to_dict()) == short


def test_ssim_map_defaults_to_the_fused_kernels_where_they_apply():
    """Default path: the fused op (float images, 11-tap window, a target without grad); the
    tensor-op reference otherwise (a target that needs a gradient), with the same values."""
    a = torch.rand(1, 3, 20, 24, dtype=torch.float64, requires_grad=True)
    b = torch.rand(1, 3, 20, 24, dtype=torch.float64)
    fused = ssim_map(a, b)
    assert "fused_ssim" in type(fused.grad_fn).__name__
    ref = ssim_map(a, b.requires_grad_())
    assert "fused_ssim" not in type(ref.grad_fn).__name__
    torch.testing.assert_close(fused, ref, rtol=0, atol=1e-12)
