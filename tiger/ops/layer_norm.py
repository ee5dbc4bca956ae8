"""``tiger::layer_norm_rows``: LayerNorm over the last dimension (fake kernel, autograd, the
function). Kernels in ``csrc/layer_norm/``.

The guidances' UNets normalise every transformer block's tokens three times (rows of 320 to 1280
channels). PyTorch's CUDA LayerNorm runs a block of 128 threads per row, most of them idle on such
short rows; the CUDA kernel here gives a row to a group of lanes of one warp and keeps it in
registers. Same statistics (mean, biased variance, two passes in float), rounded once.
"""
from __future__ import annotations

from typing import Optional

import torch

__all__ = ["layer_norm_rows"]


@torch.library.register_fake("tiger::layer_norm_rows")
def _fake(x, weight, bias, eps):
    return torch.empty_like(x, memory_format=torch.contiguous_format)


def _setup_context(ctx, inputs, output):
    x, weight, bias, eps = inputs
    ctx.save_for_backward(x, weight)
    ctx.eps = eps
    ctx.has_bias = bias is not None


def _backward(ctx, grad_y):
    """The LayerNorm gradient in float (float64 for float64), from the saved input: with
    x̂ = (x - μ)·r, g = grad_y·w: dx = r·(g - mean(g) - x̂·mean(g·x̂)), dw = Σ grad_y·x̂, db = Σ grad_y."""
    x, weight = ctx.saved_tensors
    acc = torch.float64 if x.dtype == torch.float64 else torch.float32
    xf, gy = x.to(acc), grad_y.to(acc)
    mean = xf.mean(-1, keepdim=True)
    rstd = ((xf - mean).square().mean(-1, keepdim=True) + ctx.eps).rsqrt()
    xhat = (xf - mean) * rstd
    rows = tuple(range(x.dim() - 1))
    gx = gw = gb = None
    if ctx.needs_input_grad[0]:
        g = gy * weight.to(acc)
        gx = (rstd * (g - g.mean(-1, keepdim=True) - xhat * (g * xhat).mean(-1, keepdim=True))).to(x.dtype)
    if ctx.needs_input_grad[1]:
        gw = (gy * xhat).sum(rows).to(weight.dtype)
    if ctx.has_bias and ctx.needs_input_grad[2]:
        gb = gy.sum(rows).to(weight.dtype)
    return gx, gw, gb, None


torch.library.register_autograd("tiger::layer_norm_rows", _backward, setup_context=_setup_context)


def layer_norm_rows(x: torch.Tensor, weight: torch.Tensor, bias: Optional[torch.Tensor] = None,
                    eps: float = 1e-5) -> torch.Tensor:
    """LayerNorm over the last dimension, as ``torch.nn.functional.layer_norm(x, (C,), weight, bias, eps)``.

    Args:
        x: [..., C] floating point (float32/float64/bfloat16/float16 on CUDA), any layout (made
            contiguous).
        weight: [C], x's dtype and device.
        bias: [C] or None.
        eps: added to the variance.

    Returns:
        [..., C] contiguous, x's dtype: ``(x - mean) / sqrt(var + eps) * weight + bias`` per row,
        mean and biased variance computed in float (float64 for float64) in two passes, rounded once.

    Example:
        >>> y = layer_norm_rows(torch.tensor([[1.0, 3.0]]), torch.ones(2), torch.zeros(2), eps=0.0)
        >>> y.tolist()
        [[-1.0, 1.0]]
    """
    return torch.ops.tiger.layer_norm_rows(x, weight, bias, float(eps))
