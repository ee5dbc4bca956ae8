"""Photometric losses and image metrics: L1, SSIM (INRIA/Wang et al.), PSNR."""
from __future__ import annotations

from typing import Optional

import torch

from tiger.ops.ssim import fused_ssim
from tiger.utils.filters import gaussian_blur, gaussian_taps

__all__ = ["ssim_map", "ssim", "l1", "photometric_loss", "psnr", "psnr_tensor", "SSIM_C1", "SSIM_C2"]

SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def _to_bchw(img: torch.Tensor, name: str) -> torch.Tensor:
    if img.ndim == 3:
        return img.permute(2, 0, 1)[None]
    if img.ndim == 4:
        return img
    raise ValueError(f"tiger.recon: {name} must be [H, W, C] or [B, C, H, W], got {list(img.shape)}")


def ssim_map(img1: torch.Tensor, img2: torch.Tensor, window_size: int = 11,
             sigma: float = 1.5, fused: Optional[bool] = None) -> torch.Tensor:
    """Per-pixel SSIM of two images with a Gaussian window (size 11, sigma 1.5).

    Args:
        img1, img2: [H, W, C] or [B, C, H, W], values in [0, 1] (C1, C2 assume range 1).
        fused: use the fused kernels (:func:`tiger.ops.ssim.fused_ssim`); None: whenever they
            apply (float32/float64, an odd window of at most 11 taps, ``img2`` not requiring
            grad). False: tensor ops (the reference, and the path for the other cases).
    Returns:
        [B, C, H, W] SSIM map; borders use zero padding (as INRIA's training loss), so
        ``ssim_map(...).mean()`` is INRIA's ``ssim``.
    """
    a, b = _to_bchw(img1, "img1"), _to_bchw(img2, "img2")
    if a.shape != b.shape:
        raise ValueError(f"tiger.recon: ssim inputs differ in shape: {list(a.shape)} vs {list(b.shape)}")
    fusable = (a.dtype in (torch.float32, torch.float64) and b.dtype == a.dtype and window_size % 2 == 1
               and window_size <= 11 and not b.requires_grad)
    if fused and not fusable:
        raise ValueError("tiger.recon: ssim_map(fused=True) needs float32/float64 images of one dtype, an odd "
                         f"window of at most 11 taps and img2 without grad (got {a.dtype}/{b.dtype}, "
                         f"window {window_size}, img2.requires_grad={b.requires_grad})")
    if fusable and fused is not False:
        taps = gaussian_taps(window_size, float(sigma)).tolist()
        return fused_ssim(a, b.to(a.device), taps, SSIM_C1, SSIM_C2)
    C = a.shape[1]
    # the five local moments in one filtering pass
    m = gaussian_blur(torch.cat([a, b, a * a, b * b, a * b], 1), window_size, sigma)
    mu1, mu2, e11, e22, e12 = m.split(C, 1)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1, s2, s12 = e11 - mu1_sq, e22 - mu2_sq, e12 - mu12
    return ((2 * mu12 + SSIM_C1) * (2 * s12 + SSIM_C2)) / ((mu1_sq + mu2_sq + SSIM_C1) * (s1 + s2 + SSIM_C2))


def ssim(img1: torch.Tensor, img2: torch.Tensor, window_size: int = 11, sigma: float = 1.5,
         mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Mean SSIM (scalar tensor, differentiable) of [H, W, C] images, over the pixels where
    ``mask`` [H, W] is True (default all); see :func:`ssim_map`."""
    m = ssim_map(img1, img2, window_size, sigma)
    return m.mean() if mask is None else m[0].permute(1, 2, 0)[mask.to(m.device)].mean()


def l1(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    return (img1 - img2).abs().mean()


def photometric_loss(render: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """3DGS loss ``(1 - λ) L1 + λ (1 - SSIM)`` on [H, W, 3] images (λ = 0.2)."""
    loss = (1.0 - lambda_dssim) * l1(render, target)
    if lambda_dssim:
        loss = loss + lambda_dssim * (1.0 - ssim(render, target))
    return loss


def psnr(img1: torch.Tensor, img2: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    """PSNR in dB of [H, W, C] images in [0, 1] (both clamped to [0, 1] first), over the
    pixels where ``mask`` [H, W] is True (default all); ``inf`` for identical images."""
    return float(psnr_tensor(img1, img2, mask))


def psnr_tensor(img1: torch.Tensor, img2: torch.Tensor, mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """:func:`psnr` as a 0-d float64 tensor on the images' device, computed without a read-back
    to the host (a training loop can log it later without stalling the GPU)."""
    err = (img1.detach().clamp(0, 1) - img2.detach().clamp(0, 1)) ** 2
    mse = (err.mean() if mask is None else err[mask.to(err.device)].mean()).double()
    return -10.0 * torch.log10(mse)   # log10(0) = -inf: identical images give +inf
