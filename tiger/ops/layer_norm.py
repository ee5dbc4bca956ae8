"""``tiger::layer_norm_rows``: LayerNorm over the last dimension (fake kernel, autograd, the
function). Kernels in ``csrc/layer_norm/``.

The guidances' UNets normalise every transformer block's tokens three times (rows of 320 to 1280
channels). PyTorch's CUDA LayerNorm runs a block of 128 threads per row, most of them idle on such
short rows; the CUDA kernel here gives a row to a group of lanes of one warp and keeps it in
registers. Same statistics (mean, biased variance, two passes in float), rounded once.
``input_bias`` normalises ``x + input_bias`` without writing that sum: the fused transformer
blocks (``tiger/edit/guidance/transformer_blocks.py``) carry their attention outputs' biases that
way instead of adding them to the residual stream in a pass of their own.
"""
from __future__ import annotations

from typing import Optional

import torch

__all__ = ["layer_norm_rows"]


@torch.library.register_fake("tiger::layer_norm_rows")
def _fake(x, weight, bias, eps, input_bias=None):
    return torch.empty_like(x, memory_format=torch.contiguous_format)


def _setup_context(ctx, inputs, output):
    x, weight, bias, eps, input_bias = inputs
    ctx.save_for_backward(x, weight, input_bias)
    ctx.eps = eps
    ctx.has_bias = bias is not None
    ctx.has_input_bias = input_bias is not None


def _backward(ctx, grad_y):
    """The LayerNorm gradient in float (float64 for float64), from the saved input: with
    u = x + input_bias, x̂ = (u - μ)·r, g = grad_y·w: du = r·(g - mean(g) - x̂·mean(g·x̂)) (the
    gradient of x, and summed over rows that of input_bias), dw = Σ grad_y·x̂, db = Σ grad_y."""
    x, weight, input_bias = ctx.saved_tensors
    acc = torch.float64 if x.dtype == torch.float64 else torch.float32
    xf, gy = x.to(acc), grad_y.to(acc)
    if input_bias is not None:
        xf = xf + input_bias.to(acc)
    mean = xf.mean(-1, keepdim=True)
    rstd = ((xf - mean).square().mean(-1, keepdim=True) + ctx.eps).rsqrt()
    xhat = (xf - mean) * rstd
    rows = tuple(range(x.dim() - 1))
    gx = gw = gb = gib = None
    if ctx.needs_input_grad[0] or (ctx.has_input_bias and ctx.needs_input_grad[4]):
        g = gy * weight.to(acc)
        du = rstd * (g - g.mean(-1, keepdim=True) - xhat * (g * xhat).mean(-1, keepdim=True))
        gx = du.to(x.dtype) if ctx.needs_input_grad[0] else None
        if ctx.has_input_bias and ctx.needs_input_grad[4]:
            gib = du.sum(rows).to(input_bias.dtype)
    if ctx.needs_input_grad[1]:
        gw = (gy * xhat).sum(rows).to(weight.dtype)
    if ctx.has_bias and ctx.needs_input_grad[2]:
        gb = gy.sum(rows).to(weight.dtype)
    return gx, gw, gb, None, gib


torch.library.register_autograd("tiger::layer_norm_rows", _backward, setup_context=_setup_context)


def layer_norm_rows(x: torch.Tensor, weight: torch.Tensor, bias: Optional[torch.Tensor] = None,
                    eps: float = 1e-5, input_bias: Optional[torch.Tensor] = None) -> torch.Tensor:
    """LayerNorm over the last dimension, as ``torch.nn.functional.layer_norm(x, (C,), weight, bias, eps)``
    (of ``x + input_bias`` when given).

    Args:
        x: [..., C] floating point (float32/float64/bfloat16/float16 on CUDA), any layout (made
            contiguous).
        weight: [C], x's dtype and device.
        bias: [C] or None.
        eps: added to the variance.
        input_bias: [C] or None, x's dtype: a per-channel vector added to every row (in float)
            before the statistics; the sum is never written.

    Returns:
        [..., C] contiguous, x's dtype: ``(u - mean) / sqrt(var + eps) * weight + bias`` per row
        of ``u = x + input_bias`` (``x`` without it), mean and biased variance computed in float
        (float64 for float64) in two passes, rounded once.

    Example:
        >>> y = layer_norm_rows(torch.tensor([[1.0, 3.0]]), torch.ones(2), torch.zeros(2), eps=0.0)
        >>> y.tolist()
        [[-1.0, 1.0]]
    """
    return torch.ops.tiger.layer_norm_rows(x, weight, bias, float(eps), input_bias)
