"""``tiger::jittered_window_attention`` (FeatUp's attention downsampler over jittered copies of
one feature map, without materialising the copies): fake kernels, autograd and the Python entry
point. Formula in ``csrc/featup/featup.h``."""
from __future__ import annotations

import torch

__all__ = ["jittered_window_attention"]


@torch.library.register_fake("tiger::jittered_window_attention")
def _fake(features, logit_map, coord_y, coord_x, w, b, mask, stride_h, stride_w):
    torch._check(features.dim() == 3, lambda: f"features must be [H, W, C], got {tuple(features.shape)}")
    torch._check(mask.dim() == 3, lambda: f"mask must be [J, FH, FW], got {tuple(mask.shape)}")
    torch._check(w.dim() == 2, lambda: f"w must be [K, K], got {tuple(w.shape)}")
    j, fh, fw = mask.shape
    return features.new_empty((j, fh, fw, features.shape[2])), features.new_empty((j, fh, fw, w.shape[0] * w.shape[1]))


@torch.library.register_fake("tiger::jittered_window_attention_backward")
def _fake_backward(grad_out, features, logit_map, coord_y, coord_x, w, b, mask, attn, stride_h, stride_w):
    torch._check(grad_out.shape[-1] == features.shape[-1], lambda: "grad_out must be [J, FH, FW, C]")
    return (features.new_empty(features.shape), logit_map.new_empty(logit_map.shape), w.new_empty(w.shape),
            b.new_empty(b.shape))


def _setup_context(ctx, inputs, output):
    features, logit_map, coord_y, coord_x, w, b, mask, stride_h, stride_w = inputs
    ctx.save_for_backward(features, logit_map, coord_y, coord_x, w, b, mask, output[1])
    ctx.strides = (stride_h, stride_w)
    ctx.mark_non_differentiable(output[1])


def _backward(ctx, grad_out, _grad_attn):
    features, logit_map, coord_y, coord_x, w, b, mask, attn = ctx.saved_tensors
    needs = ctx.needs_input_grad
    if grad_out is None or not (needs[0] or needs[1] or needs[4] or needs[5]):
        return (None,) * 9
    gf, gl, gw, gb = torch.ops.tiger.jittered_window_attention_backward(
        grad_out.contiguous(), features, logit_map, coord_y, coord_x, w, b, mask, attn, *ctx.strides)
    return (gf if needs[0] else None, gl if needs[1] else None, None, None, gw if needs[4] else None,
            gb if needs[5] else None, None, None, None)


torch.library.register_autograd("tiger::jittered_window_attention", _backward, setup_context=_setup_context)


def jittered_window_attention(features: torch.Tensor, logit_map: torch.Tensor, coord_y: torch.Tensor,
                              coord_x: torch.Tensor, w: torch.Tensor, b: torch.Tensor, mask: torch.Tensor,
                              stride: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """FeatUp's attention downsampler over J jittered copies of one map (float32/float64).

    Args:
        features: [H, W, C] the blurred high-resolution features, channels last.
        logit_map: [H, W] the attention logit of every source pixel.
        coord_y: [J, Ho] source row (pixels, in [0, H-1]: reflect beforehand) of each row of copy j.
        coord_x: [J, Wo] source column of each column of copy j.
        w, b: [K, K] logit scale and bias of the window softmax.
        mask: [J, FH, FW] logit multiplier per copy and cell (FeatUp's logit dropout; ones for none).
        stride: (rows, columns) between the windows of neighbouring cells.

    Returns:
        (out [J, FH, FW, C], attn [J, FH, FW, K*K]): the softmax-weighted window sums of the
        bilinearly resampled copies, and the softmax weights (not differentiable). ``out`` is
        differentiable in ``features``, ``logit_map``, ``w`` and ``b``.
    """
    return torch.ops.tiger.jittered_window_attention(features, logit_map, coord_y, coord_x, w, b, mask,
                                                     int(stride[0]), int(stride[1]))
