"""``tiger::fused_ssim``: the SSIM map of two images and its gradient for the first, one kernel
each (fake kernels, autograd, the function). Kernels in ``csrc/ssim/``, the per-pixel formula
and its derivatives in ``csrc/ssim/ssim_math.h``.

The 3DGS loss's D-SSIM term, written with tensor ops, filters five moment maps (x, y, x², y², xy)
with the 11-tap window, combines them in ~15 elementwise kernels and runs all of that backwards
again: at 1080p on an H100 a tenth of a training step. Here the forward applies the window once
from shared memory and writes the map and three derivative maps (d SSIM / d mu1, d e11, d e12);
the backward multiplies them by the incoming gradient, applies the window again and finishes
``d/dx = g*(G dmu1) + 2 x g*(G de11) + y g*(G de12)``. The second image is the fixed target: it
gets no gradient (``tiger.recon.losses.ssim_map`` takes the tensor-op path when it needs one).
"""
from __future__ import annotations

from typing import Sequence

import torch

__all__ = ["fused_ssim"]


@torch.library.register_fake("tiger::fused_ssim")
def _fake(img1, img2, taps, c1, c2):
    return torch.empty_like(img1, memory_format=torch.contiguous_format), img1.new_empty((3, *img1.shape))


@torch.library.register_fake("tiger::fused_ssim_backward")
def _fake_backward(grad, img1, img2, dmoments, taps):
    return torch.empty_like(img1, memory_format=torch.contiguous_format)


def _setup_context(ctx, inputs, output):
    img1, img2, taps, _c1, _c2 = inputs
    ctx.save_for_backward(img1, img2, output[1])
    ctx.taps = taps
    ctx.mark_non_differentiable(output[1])


def _backward(ctx, grad_map, _grad_dmoments):
    if ctx.needs_input_grad[1]:
        raise RuntimeError("tiger.fused_ssim: no gradient for img2 (the fixed target); use "
                           "tiger.recon.losses.ssim_map, which falls back to tensor ops for it")
    if grad_map is None or not ctx.needs_input_grad[0]:
        return None, None, None, None, None
    img1, img2, dmoments = ctx.saved_tensors
    return torch.ops.tiger.fused_ssim_backward(grad_map, img1, img2, dmoments, ctx.taps), None, None, None, None


torch.library.register_autograd("tiger::fused_ssim", _backward, setup_context=_setup_context)


def fused_ssim(img1: torch.Tensor, img2: torch.Tensor, taps: Sequence[float], c1: float, c2: float) -> torch.Tensor:
    """Per-pixel SSIM with a separable window, differentiable in ``img1``.

    Args:
        img1: [B, C, H, W] float32/float64 (the rendering; gets a gradient).
        img2: [B, C, H, W] like img1 (the target; must not require grad).
        taps: the normalised 1-D window, an odd number of weights (at most 11), applied along
            rows and columns with zero padding (3DGS: 11 Gaussian taps, sigma 1.5).
        c1, c2: SSIM's stabilising constants ((0.01 L)², (0.03 L)² for value range L).

    Returns:
        [B, C, H, W] SSIM map (contiguous).

    Example:
        >>> x = torch.rand(1, 1, 8, 8)
        >>> bool(torch.allclose(fused_ssim(x, x, [0.25, 0.5, 0.25], 1e-4, 9e-4), torch.ones(1, 1, 8, 8)))
        True
    """
    return torch.ops.tiger.fused_ssim(img1, img2, [float(t) for t in taps], float(c1), float(c2))[0]
