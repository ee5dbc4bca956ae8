"""``tiger::adaptive_conv`` (FeatUp's joint bilateral upsampler convolution): fake kernel,
autograd and Python entry point. Formula in ``csrc/jbu/jbu.h``."""
from __future__ import annotations

import torch

__all__ = ["adaptive_conv"]


@torch.library.register_fake("tiger::adaptive_conv")
def _fake(input, filters):
    b, h, w = filters.shape[:3]
    return input.new_empty((b, input.shape[1], h, w))


@torch.library.register_fake("tiger::adaptive_conv_backward")
def _fake_backward(grad_out, input, filters, need_input, need_filters):
    return input.new_empty(input.shape), filters.new_empty(filters.shape)


def _setup_context(ctx, inputs, output):
    input, filters = inputs
    ctx.save_for_backward(input, filters)


def _backward(ctx, grad_out):
    input, filters = ctx.saved_tensors
    need_input, need_filters = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
    if not (need_input or need_filters):
        return None, None
    gi, gf = torch.ops.tiger.adaptive_conv_backward(
        grad_out.contiguous(), input, filters, need_input, need_filters
    )
    return (gi if need_input else None), (gf if need_filters else None)


torch.library.register_autograd("tiger::adaptive_conv", _backward, setup_context=_setup_context)


def adaptive_conv(input: torch.Tensor, filters: torch.Tensor) -> torch.Tensor:
    """Per-pixel K x K convolution shared across channels.

    Args:
        input: [B, C, H + K - 1, W + K - 1] padded source (float32/float64).
        filters: [B, H, W, K, K] one kernel per output pixel.

    Returns:
        [B, C, H, W]: ``out[b, c, y, x] = sum_ij input[b, c, y+i, x+j] * filters[b, y, x, i, j]``.
    """
    return torch.ops.tiger.adaptive_conv(input, filters)
