"""The UNet up blocks' skip concatenations written in place (``ModelKernels.skip_concat``).

Each ResNet block of a diffusers up block (``UpBlock2D``, ``CrossAttnUpBlock2D``) starts from
``torch.cat([hidden, skip], dim=1)``: a pass that reads both maps and writes the wide one (about
0.45 ms of an InstructPix2Pix UNet call on an H100, ``guidance_roofline_h100.txt``). Here the
wide map is allocated before ``hidden`` exists, and the layer that produces ``hidden`` writes its
output straight into the wide map's first channels: the previous ResNet block's output pass
(:func:`.fused_norms._resnet_forward_folded`), the transformer's ``proj_out`` pass
(:func:`.transformer_blocks._fused_transformer_forward`) or the previous up block's sub-pixel
upsampler (:func:`.conv_layers._subpixel_upsample_forward`, handed to the next block through a
:class:`_Handoff`). Only the skip is copied in, by tiger's channel pass with strided rows
(:func:`tiger.ops.channel_bias.channel_bias_add` with ``out=``). A producer without an ``out``
writes its own output and it is copied in (the cat's cost). The same kernels write the same numbers
to another place: the UNet's output is unchanged bit for bit. Forward without gradients only (the
guidances' UNet calls); with gradients, FreeU or an upsampling size other than 2x the blocks run
diffusers' forward.
"""
from __future__ import annotations

import types
from typing import Any, Callable, Optional, Sequence

import torch

from tiger.ops.channel_bias import channel_bias_add
from tiger.utils.lazy import require_diffusers

from .conv_layers import _subpixel_upsample_forward
from .fused_norms import _resnet_forward_folded
from .transformer_blocks import _fused_transformer_forward

__all__ = ["set_skip_concat"]

_HANDOFF = "_tiger_skip_concat"  # an up block's shared _Handoff: the switch is on
_NEXT_SKIP = "_tiger_next_skip_channels"  # channels of the next up block's first skip (blocks with an upsampler)
_WRITES_INTO = (_resnet_forward_folded, _fused_transformer_forward, _subpixel_upsample_forward)


class _Handoff:
    """The wide map an up block's upsampler wrote its output into, kept for the next up block's
    first ResNet block (the UNet's forward passes only the output view from block to block).
    Identity, not shape, decides whether the next block's input is that view."""

    def __init__(self) -> None:
        self.view: Optional[torch.Tensor] = None
        self.wide: Optional[torch.Tensor] = None

    def put(self, view: torch.Tensor, wide: torch.Tensor) -> None:
        self.view, self.wide = view, wide

    def take(self, hidden: torch.Tensor) -> Optional[torch.Tensor]:
        wide = self.wide if self.view is hidden else None
        self.view = self.wide = None
        return wide


def _writes_into(module: torch.nn.Module) -> bool:
    return getattr(module.__dict__.get("forward"), "__func__", None) in _WRITES_INTO


def _channels_last(x: torch.Tensor) -> bool:
    return x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()


def _wide(like: torch.Tensor, skip: torch.Tensor, channels: int, channels_last: bool) -> torch.Tensor:
    """An empty [N, channels, H, W] map (``skip``'s size) in ``like``'s dtype and device."""
    n, _, h, w = skip.shape
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    return torch.empty((n, channels, h, w), dtype=like.dtype, device=like.device, memory_format=fmt)


def _produce(module: torch.nn.Module, call: Callable[..., Any], like: torch.Tensor, channels: int,
             nxt: Optional[torch.Tensor]) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """``module``'s output (``call()``, ``channels`` channels, ``like``'s layout) and, when a skip
    ``nxt`` follows, the wide map whose first channels hold it: written there by ``module``
    (``call(out=...)``) or copied in. The wide map takes torch.cat's layout rule (channels-last
    when both parts are), so the next block sees what it would have seen."""
    if nxt is None:
        return call(), None
    if _writes_into(module):
        wide = _wide(like, nxt, channels + nxt.shape[1], _channels_last(like) and _channels_last(nxt))
        return call(out=wide[:, :channels]), wide
    y = call()
    wide = _wide(y, nxt, y.shape[1] + nxt.shape[1], _channels_last(y) and _channels_last(nxt))
    return channel_bias_add(y, None, out=wide[:, :y.shape[1]]), wide


def _runs_here(block: torch.nn.Module, hidden: torch.Tensor) -> bool:
    freeu = all(getattr(block, k, None) for k in ("s1", "s2", "b1", "b2"))
    grad = torch.is_grad_enabled() and (hidden.requires_grad or any(p.requires_grad for p in block.parameters()))
    return _HANDOFF in block.__dict__ and not freeu and not grad and hidden.dim() == 4


def _up_block(block: torch.nn.Module, hidden: torch.Tensor, skips: Sequence[torch.Tensor],
              temb: Optional[torch.Tensor], attention_kwargs: Optional[dict],
              upsample_size: Optional[Sequence[int]]) -> torch.Tensor:
    """diffusers 0.42's up-block forward (``attention_kwargs`` None: ``UpBlock2D``) with every
    concatenation's hidden half written by its producer (module docstring)."""
    handoff: _Handoff = block.__dict__[_HANDOFF]
    wide = handoff.take(hidden)
    attentions = getattr(block, "attentions", None) if attention_kwargs is not None else None
    n = len(block.resnets)
    for i, resnet in enumerate(block.resnets):
        skip = skips[-1 - i]
        c = hidden.shape[1]
        if wide is not None and wide.shape[1] == c + skip.shape[1] and wide.shape[2:] == skip.shape[2:]:
            channel_bias_add(skip, None, out=wide[:, c:])
            x = wide
        else:
            x = torch.cat([hidden, skip], dim=1)
        nxt = skips[-2 - i] if i + 1 < n else None
        if attentions is None:
            hidden, wide = _produce(resnet, lambda **o: resnet(x, temb, **o), x, resnet.out_channels, nxt)
        else:
            r = resnet(x, temb)
            attn = attentions[i]
            hidden, wide = _produce(attn, lambda **o: attn(r, return_dict=False, **attention_kwargs, **o)[0],
                                    r, r.shape[1], nxt)
    if block.upsamplers is None:
        return hidden
    for k, up in enumerate(block.upsamplers):
        extra = block.__dict__.get(_NEXT_SKIP) if k == len(block.upsamplers) - 1 else None
        batch, _, h, w = hidden.shape
        c = getattr(up, "out_channels", None)
        doubled = upsample_size is None or tuple(upsample_size) == (2 * h, 2 * w)
        if extra and c and doubled and _writes_into(up) and _channels_last(hidden):
            wide = torch.empty((batch, c + extra, 2 * h, 2 * w), dtype=hidden.dtype, device=hidden.device,
                               memory_format=torch.channels_last)  # the sub-pixel output's layout
            hidden = up(hidden, upsample_size, out=wide[:, :c])
            handoff.put(hidden, wide)
        else:
            hidden = up(hidden, upsample_size)
    return hidden


def _up_block_forward(self, hidden_states: torch.Tensor, res_hidden_states_tuple: tuple[torch.Tensor, ...],
                      temb: Optional[torch.Tensor] = None, upsample_size: Optional[int] = None, *args: object,
                      **kwargs: object) -> torch.Tensor:
    """``UpBlock2D.forward`` with the skip concatenations written in place, when it applies."""
    if args or kwargs or not _runs_here(self, hidden_states):
        return type(self).forward(self, hidden_states, res_hidden_states_tuple, temb, upsample_size, *args, **kwargs)
    return _up_block(self, hidden_states, res_hidden_states_tuple, temb, None, upsample_size)


def _cross_attn_up_block_forward(self, hidden_states: torch.Tensor, res_hidden_states_tuple: tuple[torch.Tensor, ...],
                                 temb: Optional[torch.Tensor] = None,
                                 encoder_hidden_states: Optional[torch.Tensor] = None,
                                 cross_attention_kwargs: Optional[dict] = None, upsample_size: Optional[int] = None,
                                 attention_mask: Optional[torch.Tensor] = None,
                                 encoder_attention_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``CrossAttnUpBlock2D.forward`` with the skip concatenations written in place, when it applies."""
    if not _runs_here(self, hidden_states):
        return type(self).forward(self, hidden_states, res_hidden_states_tuple, temb, encoder_hidden_states,
                                  cross_attention_kwargs, upsample_size, attention_mask, encoder_attention_mask)
    attention_kwargs = {"encoder_hidden_states": encoder_hidden_states, "cross_attention_kwargs": cross_attention_kwargs,
                        "attention_mask": attention_mask, "encoder_attention_mask": encoder_attention_mask}
    return _up_block(self, hidden_states, res_hidden_states_tuple, temb, attention_kwargs, upsample_size)


def set_skip_concat(unet: torch.nn.Module, on: bool) -> int:
    """The UNet's up blocks with their skip concatenations written in place (``on``) or diffusers'
    forward; returns how many up blocks run in place afterwards."""
    require_diffusers("the in-place skip concatenations")
    from diffusers.models.unets.unet_2d_blocks import CrossAttnUpBlock2D, UpBlock2D

    forwards = {UpBlock2D: _up_block_forward, CrossAttnUpBlock2D: _cross_attn_up_block_forward}
    blocks = list(getattr(unet, "up_blocks", ()))
    handoff = _Handoff()
    count = 0
    for i, block in enumerate(blocks):
        forward = forwards.get(type(block))
        if not on or forward is None:
            if _HANDOFF in block.__dict__:
                for key in ("forward", _HANDOFF, _NEXT_SKIP):
                    block.__dict__.pop(key, None)
            continue
        block.forward = types.MethodType(forward, block)
        block.__dict__[_HANDOFF] = handoff
        block.__dict__.pop(_NEXT_SKIP, None)
        nxt = blocks[i + 1] if i + 1 < len(blocks) else None
        ups = block.upsamplers
        if nxt is not None and ups is not None and len(nxt.resnets) and hasattr(ups[-1], "out_channels"):
            block.__dict__[_NEXT_SKIP] = nxt.resnets[0].in_channels - ups[-1].out_channels
        count += 1
    return count
