"""``tiger::channel_bias_add``: ``y = x + bias[c]`` for [N, C, H, W] tensors (fake kernel,
autograd, the function). Kernels in ``csrc/channel_bias/``.

A convolution's bias is a per-channel add after the convolution. For channels-last bf16 maps
(the fused diffusion models of :mod:`tiger.edit.guidance.fused_norms`) PyTorch runs that add
through its generic broadcast kernel, about a tenth of an InstructPix2Pix SDS step on an H100;
the CUDA kernel here moves 16-byte vectors instead. Values are identical to ``x + bias`` (float
arithmetic, one rounding).
"""
from __future__ import annotations

import torch

from ._layout import output_format

__all__ = ["channel_bias_add"]


@torch.library.register_fake("tiger::channel_bias_add")
def _fake(x, bias):
    return torch.empty_like(x, memory_format=output_format(x))


def _setup_context(ctx, inputs, output):
    ctx.bias_dtype = inputs[1].dtype


def _backward(ctx, grad_y):
    need_x, need_b = ctx.needs_input_grad[:2]
    acc = torch.float64 if grad_y.dtype == torch.float64 else torch.float32  # reduced types sum in float32
    gb = grad_y.sum(dim=(0, 2, 3), dtype=acc).to(ctx.bias_dtype) if need_b else None
    return (grad_y if need_x else None), gb


torch.library.register_autograd("tiger::channel_bias_add", _backward, setup_context=_setup_context)


def channel_bias_add(x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``x + bias`` broadcast over channels.

    Args:
        x: [N, C, H, W] floating point (float32/bfloat16/float16 on CUDA), channels-last or NCHW.
        bias: [C], x's dtype and device.

    Returns:
        [N, C, H, W] ``x[n, c, h, w] + bias[c]`` in x's dtype; channels-last when x is.

    Example:
        >>> x = torch.zeros(1, 2, 1, 2)
        >>> channel_bias_add(x, torch.tensor([1.0, -1.0])).flatten().tolist()
        [1.0, 1.0, -1.0, -1.0]
    """
    return torch.ops.tiger.channel_bias_add(x, bias)
