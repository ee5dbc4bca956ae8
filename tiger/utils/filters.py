"""Image filters shared across the package: one Gaussian blur (SSIM, FeatUp) and one mask dilation
(edit locality, deletion holes)."""
from __future__ import annotations

from functools import lru_cache

import torch
import torch.nn.functional as F

__all__ = ["gaussian_blur", "gaussian_taps", "dilate"]


@lru_cache(maxsize=8)
def gaussian_taps(size: int, sigma: float) -> torch.Tensor:
    """[size] float64 normalised taps exp(-d²/2σ²) of the 1-D window (d in pixels from the centre)."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


@lru_cache(maxsize=16)
def _taps_on(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """:func:`gaussian_taps` on a device, made once: no host-to-device copy per blur (which a
    CUDA-graph capture would refuse)."""
    return gaussian_taps(size, sigma).to(dtype=dtype, device=device)


@lru_cache(maxsize=16)
def _band(n: int, size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """[n, n] matrix M with (M @ x) = the 1-D Gaussian filter of x with zero padding."""
    g = gaussian_taps(size, sigma)
    M = torch.zeros(n, n, dtype=torch.float64)
    for i in range(size):
        off = i - size // 2
        if abs(off) < n:
            M += torch.diag(torch.full((n - abs(off),), float(g[i]), dtype=torch.float64), off)
    return M.to(dtype=dtype, device=device)


_METHODS = ("conv", "depthwise", "matmul", "shift")


def gaussian_blur(x: torch.Tensor, window_size: int = 11, sigma: float = 1.5,
                  method: str = "auto", padding: str = "zeros") -> torch.Tensor:
    """Separable Gaussian filter of [B, C, H, W] ("same" size), taps exp(-d²/2σ²) normalised.

    ``padding``: ``"zeros"`` (SSIM's convention) or ``"reflect"`` (FeatUp's). ``method``:
    ``"conv"`` (conv2d over B·C single-channel images), ``"depthwise"`` (conv2d with one group
    per channel), ``"matmul"`` (products with banded [H, H] and [W, W] matrices; zero padding
    only), ``"shift"`` (sum of shifted slices) or ``"auto"`` (depthwise: the fastest on the CPU
    and on the H100 from 64 px to 1080p, ``benchmarks/recon_ssim.py``). All compute the same sums.

    With zero padding the filter is a symmetric linear map (symmetric taps, symmetric band), so
    its backward is the same filter applied to the incoming gradient: one forward pass instead
    of cuDNN's data-gradient convolution (the costliest kernel of a 1080p training step).
    """
    if x.dim() != 4:
        raise ValueError(f"tiger: gaussian_blur takes [B, C, H, W], got {list(x.shape)}")
    if padding not in ("zeros", "reflect"):
        raise ValueError(f"tiger: gaussian_blur padding must be 'zeros' or 'reflect', got '{padding}'")
    if method == "auto":
        method = "depthwise"
    if method not in _METHODS:
        raise ValueError(f"tiger: gaussian_blur method must be auto, {', '.join(_METHODS)}, got {method}")
    if method == "matmul" and padding != "zeros":
        raise ValueError("tiger: gaussian_blur method 'matmul' implements zero padding only")
    if padding == "zeros" and x.requires_grad:
        return _SelfAdjointBlur.apply(x, window_size, float(sigma), method)
    return _blur(x, window_size, float(sigma), method, padding)


def _blur(x: torch.Tensor, window_size: int, sigma: float, method: str, padding: str) -> torch.Tensor:
    B, C, H, W = x.shape
    if method == "matmul":
        bh = _band(H, window_size, sigma, x.dtype, x.device)
        bw = _band(W, window_size, sigma, x.dtype, x.device)
        return bh @ (x @ bw)   # both bands are symmetric
    g = _taps_on(window_size, sigma, x.dtype, x.device)
    pad = window_size // 2
    if method == "depthwise":  # zero padding inside conv2d (no padded copy); reflect padded first
        zeros = padding == "zeros"
        src = x if zeros else F.pad(x, (pad, pad, pad, pad), mode="reflect")
        y = F.conv2d(src, g.view(1, 1, 1, -1).expand(C, 1, 1, -1), padding=(0, pad) if zeros else 0, groups=C)
        return F.conv2d(y, g.view(1, 1, -1, 1).expand(C, 1, -1, 1), padding=(pad, 0) if zeros else 0, groups=C)
    xp = F.pad(x, (pad, pad, pad, pad), mode="constant" if padding == "zeros" else "reflect")
    if method == "conv":
        y = xp.reshape(B * C, 1, H + 2 * pad, W + 2 * pad)
        y = F.conv2d(y, g.view(1, 1, 1, -1))
        return F.conv2d(y, g.view(1, 1, -1, 1)).reshape(B, C, H, W)
    rows = sum(g[i] * xp[..., i:i + W] for i in range(window_size))
    return sum(g[i] * rows[..., i:i + H, :] for i in range(window_size))


class _SelfAdjointBlur(torch.autograd.Function):
    """Zero-padded Gaussian filter whose backward is itself (see :func:`gaussian_blur`)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, window_size: int, sigma: float, method: str) -> torch.Tensor:
        ctx.args = (window_size, sigma, method)
        return _blur(x, window_size, sigma, method, "zeros")

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return _blur(grad.contiguous(), *ctx.args, "zeros"), None, None, None


def dilate(mask: torch.Tensor, radius: int, shape: str = "disk") -> torch.Tensor:
    """Grow bool masks [..., H, W] by ``radius`` pixels (0: unchanged copy).

    Args:
        mask: [..., H, W] bool (any float is read as ``> 0.5``).
        radius: pixels, >= 0.
        shape: ``"disk"`` (pixels within Euclidean distance ``radius``) or ``"square"``
            (a (2 radius + 1)^2 max filter: Chebyshev distance).
    Returns:
        [..., H, W] bool.
    """
    if radius < 0:
        raise ValueError(f"tiger.utils.filters.dilate: radius must be >= 0, got {radius}")
    if shape not in ("disk", "square"):
        raise ValueError(f"tiger.utils.filters.dilate: shape must be 'disk' or 'square', got {shape!r}")
    if mask.dim() < 2:
        raise ValueError(f"tiger.utils.filters.dilate: mask must be [..., H, W], got {list(mask.shape)}")
    m = mask.bool() if mask.dtype == torch.bool else mask > 0.5
    if radius == 0 or m.numel() == 0:
        return m.clone()
    lead, (h, w) = m.shape[:-2], m.shape[-2:]
    x = m.reshape(-1, 1, h, w).float()
    if shape == "square":
        y = F.max_pool2d(x, kernel_size=2 * radius + 1, stride=1, padding=radius)
    else:
        r = torch.arange(-radius, radius + 1, device=m.device, dtype=torch.float32)
        disk = ((r[:, None] ** 2 + r[None, :] ** 2) <= radius * radius + 1e-6).float()
        y = F.conv2d(x, disk[None, None], padding=radius)
    return (y > 0.5).reshape(*lead, h, w)
