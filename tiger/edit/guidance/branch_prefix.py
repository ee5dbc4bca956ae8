"""Classifier-free-guidance branches that agree up to the first cross-attention, computed once
(:class:`~tiger.edit.guidance.model_kernels.ModelKernels` field ``branch_prefix``).

InstructPix2Pix's UNet call stacks three branches of V rows each: (instruction, image),
("", image) and ("", no image). The first two get the same noisy latents, image condition and
timestep, so they are equal row for row until text enters: the first cross-attention, inside the
first transformer block of the first down block. Before it run ``conv_in``, the time embedding,
the first ResNet block and the first transformer's GroupNorm, ``proj_in`` and self-attention: at
64² latents the self-attention alone is a third of a millisecond for 12 rows on an H100.

With a :class:`BranchShare` set on the UNet (:func:`shared_branches`, by the guidance around its
call), the first down block runs its first ResNet block and its first transformer's
self-attention half on the rows that differ (2V), copies the shared rows back in before the
cross-attention (:func:`tiger.edit.guidance.transformer_blocks.fused_cross_feed_forward`), and
carries on with all 3V rows. ``conv_in`` and the time embedding still run on all rows (the
skip connection keeps ``conv_in``'s full output; both are small). The same operations on the same
values, so the same result up to the batch-size-dependent choices of the convolution and matmul
libraries. A first transformer block that does not run fused gets all rows after ``proj_in``
(only the ResNet block, norm and ``proj_in`` are shared then); anything else the shared path does
not handle (gradients, training mode, masks, extra residuals, no share set) falls back to
diffusers' forward with all rows.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator, Optional

import torch

from .forward_switch import switch_forward
from .transformer_blocks import fused_blocks_output, fused_derived, fused_self_attention

__all__ = ["BranchShare", "set_branch_prefix", "shared_branches"]

_SHARE = "_tiger_branch_share"


@dataclass(frozen=True)
class BranchShare:
    """Rows ``[start, start + length)`` of a batch equal rows ``[start - length, start)`` up to the
    first cross-attention (InstructPix2Pix: ``start = length = V``)."""

    start: int
    length: int

    def __post_init__(self) -> None:
        if self.length <= 0 or self.start < self.length:
            raise ValueError(f"tiger.edit: BranchShare needs 0 < length <= start, got start={self.start}, "
                             f"length={self.length}")

    def compact(self, x: torch.Tensor) -> torch.Tensor:
        """[B, ...] -> [B - length, ...]: the duplicate rows dropped."""
        return torch.cat([x[:self.start], x[self.start + self.length:]])

    def expand(self, x: torch.Tensor) -> torch.Tensor:
        """[B - length, ...] -> [B, ...]: the duplicate rows copied back in."""
        return torch.cat([x[:self.start], x[self.start - self.length:self.start], x[self.start:]])


def _first_down_block(unet: torch.nn.Module) -> Optional[torch.nn.Module]:
    blocks = getattr(unet, "down_blocks", None)
    if not blocks:
        return None
    block = blocks[0]
    if getattr(block, "resnets", None) is None or getattr(block, "attentions", None) is None:
        return None
    return block


def set_branch_prefix(unet: torch.nn.Module, on: bool) -> int:
    """Give the UNet's first down block (a cross-attention block) the shared-prefix forward
    (``on``) or diffusers' again; returns 1 if it has it afterwards, else 0."""
    block = _first_down_block(unet)
    if block is None:
        return 0
    return switch_forward(block, lambda m: m is block, _shared_down_block_forward, on)


@contextlib.contextmanager
def shared_branches(unet: torch.nn.Module, share: Optional[BranchShare]) -> Iterator[None]:
    """Within the block, calls of ``unet`` may compute the rows ``share`` names once (no effect
    unless :func:`set_branch_prefix` is on, or with ``share=None``)."""
    block = _first_down_block(unet)
    if block is None or share is None:
        yield
        return
    block.__dict__[_SHARE] = share
    try:
        yield
    finally:
        block.__dict__.pop(_SHARE, None)


def _transformer_shared(tr, h: torch.Tensor, encoder_hidden_states: torch.Tensor, share: BranchShare) -> torch.Tensor:
    """A ``Transformer2DModel`` (diffusers' plain continuous-input forward) on the compact rows
    ``h`` [B', C, H, W]: norm and ``proj_in`` on B' rows, then the first block's self-attention
    half too when it runs fused, the rest on all B rows (``encoder_hidden_states`` [B, T, D])."""
    if not getattr(tr, "is_input_continuous", False) or tr.training:
        return tr(share.expand(h), encoder_hidden_states=encoder_hidden_states, return_dict=False)[0]
    _, _, height, width = h.shape
    x, inner = tr._operate_on_continuous_inputs(h)
    x = x.contiguous()  # a view already on channels-last maps (CUDA); the fused half needs [B, L, C] rows
    blocks = list(tr.transformer_blocks)
    d = fused_derived(blocks[0], x, encoder_hidden_states) if blocks else None
    if d is not None:
        x = fused_self_attention(blocks[0], d, x)
    return fused_blocks_output(tr, share.expand(x), share.expand(h), encoder_hidden_states, height, width, inner,
                               first_half_done=d is not None)


def _shared_down_block_forward(self, hidden_states: torch.Tensor, temb: Optional[torch.Tensor] = None,
                               encoder_hidden_states: Optional[torch.Tensor] = None, attention_mask=None,
                               cross_attention_kwargs=None, encoder_attention_mask=None,
                               additional_residuals=None):
    """``CrossAttnDownBlock2D.forward`` with its first ResNet block and its first transformer's
    self-attention on the rows a :class:`BranchShare` leaves (module docstring)."""
    share: Optional[BranchShare] = self.__dict__.get(_SHARE)
    plain = (share is not None and temb is not None and encoder_hidden_states is not None and attention_mask is None
             and not cross_attention_kwargs and encoder_attention_mask is None and additional_residuals is None
             and not torch.is_grad_enabled() and not self.training and len(self.resnets) == len(self.attentions) > 0
             and hidden_states.shape[0] == encoder_hidden_states.shape[0] == temb.shape[0]
             and hidden_states.shape[0] >= share.start + share.length)
    if not plain:
        return type(self).forward(self, hidden_states, temb, encoder_hidden_states, attention_mask,
                                  cross_attention_kwargs, encoder_attention_mask, additional_residuals)
    h = self.resnets[0](share.compact(hidden_states), share.compact(temb))
    h = _transformer_shared(self.attentions[0], h, encoder_hidden_states, share)
    output_states = (h,)
    for resnet, attn in zip(self.resnets[1:], self.attentions[1:]):
        h = resnet(h, temb)
        h = attn(h, encoder_hidden_states=encoder_hidden_states, return_dict=False)[0]
        output_states = output_states + (h,)
    if self.downsamplers is not None:
        for downsampler in self.downsamplers:
            h = downsampler(h)
        output_states = output_states + (h,)
    return h, output_states
