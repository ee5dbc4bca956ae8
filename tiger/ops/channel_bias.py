"""``tiger::channel_bias_add``: ``y = x + bias[c]`` for [N, C, H, W] tensors (fake kernel,
autograd, the function). Kernels in ``csrc/channel_bias/``.

A convolution's bias is a per-channel add after the convolution. For channels-last bf16 maps
(the fused diffusion models of :mod:`tiger.edit.guidance.fused_norms`) PyTorch runs that add
through its generic broadcast kernel, about a tenth of an InstructPix2Pix SDS step on an H100;
the CUDA kernel here moves 16-byte vectors instead. A per-sample bias ([N, C]) and a residual fold a
ResNet block's time embedding and shortcut into the same pass. Values are the float sum, rounded
once (identical to ``x + bias`` without a residual). With ``out=`` the same values go into a given
tensor, e.g. a channel slice of a wider channels-last map (the UNet up blocks' skip concatenations
written in place, :mod:`tiger.edit.guidance.skip_concat`); the bias may then be None (a copy).
"""
from __future__ import annotations

from typing import Optional

import torch

from ._layout import output_format

__all__ = ["channel_bias_add"]


@torch.library.register_fake("tiger::channel_bias_add")
def _fake(x, bias, residual=None):
    return torch.empty_like(x, memory_format=output_format(x))


@torch.library.register_fake("tiger::channel_bias_add_into")
def _fake_into(x, bias, residual, out):
    torch._check(out.shape == x.shape, lambda: f"tiger.channel_bias_add_into: out must have x's shape "
                                              f"{tuple(x.shape)}, got {tuple(out.shape)}")
    return None


def _setup_context(ctx, inputs, output):
    ctx.bias_dtype = inputs[1].dtype
    ctx.per_sample = inputs[1].dim() == 2


def _backward(ctx, grad_y):
    need_x, need_b, need_r = (tuple(ctx.needs_input_grad) + (False,))[:3]  # residual may be left out
    acc = torch.float64 if grad_y.dtype == torch.float64 else torch.float32  # reduced types sum in float32
    gb = None
    if need_b:
        gb = grad_y.sum(dim=(2, 3) if ctx.per_sample else (0, 2, 3), dtype=acc).to(ctx.bias_dtype)
    grads = ((grad_y if need_x else None), gb, (grad_y if need_r else None))
    return grads[:len(ctx.needs_input_grad)]


torch.library.register_autograd("tiger::channel_bias_add", _backward, setup_context=_setup_context)


def channel_bias_add(x: torch.Tensor, bias: Optional[torch.Tensor], residual: Optional[torch.Tensor] = None,
                     out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``x + bias`` broadcast over channels (and, for a [N, C] bias, per sample), plus ``residual``.

    Args:
        x: [N, C, H, W] floating point (float32/bfloat16/float16 on CUDA), channels-last or NCHW.
        bias: [C], or [N, C] (a convolution's bias plus a per-sample term such as a ResNet block's
            time embedding); x's dtype and device.
            None only with ``out`` (then a copy of x, plus the residual).
        residual: optional [N, C, H, W] added in the same pass (x's dtype and device, any layout).
        out: optional [N, C, H, W] tensor (x's dtype and device, any strides, not overlapping x or
            the residual) to write the result into and return; fastest on CUDA when its rows are
            ``stride(3) >= C`` elements apart with the channels innermost (a channel slice of a
            channels-last map). No autograd: refused when x, bias or residual needs a gradient.

    Returns:
        [N, C, H, W] ``x[n, c, h, w] + bias[(n,) c] (+ residual[n, c, h, w])`` in x's dtype, summed
        in float and rounded once; channels-last when x is; ``out`` when given.

    Example:
        >>> x = torch.zeros(1, 2, 1, 2)
        >>> channel_bias_add(x, torch.tensor([1.0, -1.0])).flatten().tolist()
        [1.0, 1.0, -1.0, -1.0]
    """
    if out is None:
        if bias is None:
            raise ValueError("tiger.channel_bias_add: bias is None; only a call with out= may leave it out")
        return torch.ops.tiger.channel_bias_add(x, bias, residual)
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (x, bias, residual)):
        raise ValueError("tiger.channel_bias_add: out= has no autograd; x, bias or residual needs a gradient "
                         "(call it under torch.no_grad() or without out=)")
    torch.ops.tiger.channel_bias_add_into(x, bias, residual, out)
    return out
