"""``tiger::channel_bias_add``: ``y = x + bias[c]`` for [N, C, H, W] tensors (fake kernels,
autograd, the function). Kernels in ``csrc/channel_bias/``.

A convolution's bias is a per-channel add after the convolution. For channels-last bf16 maps
(the fused diffusion models of :mod:`tiger.edit.guidance.fused_norms`) PyTorch runs that add
through its generic broadcast kernel, about a tenth of an InstructPix2Pix SDS step on an H100;
the CUDA kernel here moves 16-byte vectors instead. A per-sample bias ([N, C]) and a residual fold a
ResNet block's time embedding and shortcut into the same pass. Values are the float sum, rounded
once (identical to ``x + bias`` without a residual). With ``out=`` the same values go into a given
tensor, e.g. a channel slice of a wider channels-last map (the UNet up blocks' skip concatenations
written in place, :mod:`tiger.edit.guidance.skip_concat`); the bias may then be None (a copy).
``tiger::subpixel_interleave_into`` (:func:`subpixel_interleave`) is the same pass with a gather:
the bias pass of a sub-pixel 2x upsampling convolution, whose four phase outputs it interleaves.
"""
from __future__ import annotations

from typing import Optional

import torch

from ._layout import output_format

__all__ = ["channel_bias_add", "subpixel_interleave"]


@torch.library.register_fake("tiger::channel_bias_add")
def _fake(x, bias, residual=None):
    return torch.empty_like(x, memory_format=output_format(x))


@torch.library.register_fake("tiger::channel_bias_add_into")
def _fake_into(x, bias, residual, out):
    torch._check(out.shape == x.shape, lambda: f"tiger.channel_bias_add_into: out must have x's shape "
                                              f"{tuple(x.shape)}, got {tuple(out.shape)}")
    return None


@torch.library.register_fake("tiger::subpixel_interleave_into")
def _fake_interleave(z, bias, out):
    n, c, h2, w2 = out.shape
    torch._check(tuple(z.shape) == (n, 4 * c, h2 // 2 + 1, w2 // 2 + 1),
                 lambda: f"tiger.subpixel_interleave_into: z must be [N, 4C, H+1, W+1] for out {tuple(out.shape)}, "
                         f"got {tuple(z.shape)}")
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


def subpixel_interleave(z: torch.Tensor, bias: Optional[torch.Tensor] = None,
                        out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The four phase outputs of a sub-pixel 2x upsampling convolution interleaved, plus its bias:
    ``y[n, c, 2i+a, 2j+b] = z[n, (2a+b)·C + c, i+a, j+b] + bias[c]`` (one pass; summed in float and
    rounded once). :mod:`tiger.edit.guidance.conv_layers`' upsampling layers.

    Args:
        z: [N, 4C, H+1, W+1] floating point (float32/bfloat16/float16 on CUDA), the convolution of the
            low-resolution map with the four phases' 2x2 kernels (padding 1); channels-last is fastest.
        bias: optional [C], z's dtype and device.
        out: optional [N, C, 2H, 2W] (z's dtype and device, any strides) to write into; fastest on
            CUDA when its rows have the channels innermost (a channels-last map or a channel slice of
            a wider one). No autograd.

    Returns:
        [N, C, 2H, 2W]: ``out`` when given, else a new channels-last tensor.
    """
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (z, bias)):
        raise ValueError("tiger.subpixel_interleave: no autograd; z or bias needs a gradient")
    if out is None:
        n, c4, h1, w1 = z.shape
        out = torch.empty((n, c4 // 4, 2 * (h1 - 1), 2 * (w1 - 1)), dtype=z.dtype, device=z.device,
                          memory_format=torch.channels_last)
    torch.ops.tiger.subpixel_interleave_into(z, bias, out)
    return out
