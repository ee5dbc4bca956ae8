"""MVDream's multi-view self-attention as a diffusers attention processor.

MVDream's ``BasicTransformerBlock3D`` runs its self-attention (``attn1``) over the tokens of all
F views of one sample jointly: ``(b·f, l, c) → (b, f·l, c)`` before the attention and back after.
Norms, residuals, cross-attention and the feed-forward act per token, so reshaping only inside
``attn1`` reproduces the block exactly. The batch must hold groups of F consecutive views.
"""
from __future__ import annotations

from typing import Optional

import torch

from tiger.utils.lazy import require_diffusers


class MultiViewAttnProcessor:
    """Self-attention over ``num_views`` consecutive batch entries jointly (SDPA inside)."""

    def __init__(self, num_views: int) -> None:
        if num_views < 1:
            raise ValueError(f"tiger.edit.mvdream: num_views must be >= 1, got {num_views}")
        self.num_views = int(num_views)
        diffusers = require_diffusers("MVDream's multi-view attention")
        self.inner = diffusers.models.attention_processor.AttnProcessor2_0()

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states: Optional[torch.Tensor] = None,
                 attention_mask: Optional[torch.Tensor] = None, temb: Optional[torch.Tensor] = None,
                 *args, **kwargs) -> torch.Tensor:
        if encoder_hidden_states is not None:
            raise ValueError("tiger.edit.mvdream: the multi-view processor is for self-attention (attn1) only")
        if hidden_states.ndim != 3:
            raise ValueError(f"tiger.edit.mvdream: expected tokens [b*f, l, c], got {list(hidden_states.shape)}")
        bf, l, c = hidden_states.shape
        f = self.num_views
        if bf % f != 0:
            raise ValueError(f"tiger.edit.mvdream: batch {bf} is not a multiple of num_views={f}")
        joint = hidden_states.reshape(bf // f, f * l, c)
        out = self.inner(attn, joint, None, attention_mask, temb, *args, **kwargs)
        return out.reshape(bf, l, c)


def install_multiview_attention(unet: torch.nn.Module, num_views: int) -> int:
    """Put :class:`MultiViewAttnProcessor` on every self-attention (``attn1``) of ``unet``, the
    default SDPA processor elsewhere. Returns the number of multi-view layers."""
    diffusers = require_diffusers("MVDream's multi-view attention")
    default = diffusers.models.attention_processor.AttnProcessor2_0()
    processors = {}
    count = 0
    for name in unet.attn_processors:
        if name.endswith("attn1.processor"):
            processors[name] = MultiViewAttnProcessor(num_views)
            count += 1
        else:
            processors[name] = default
    unet.set_attn_processor(processors)
    return count
