"""The VAE encoder with its producer convolutions' biases carried into the next ResNet block.

In diffusers' ``Encoder`` the first convolution (``conv_in``) and each ``DownEncoderBlock2D``'s
downsampling convolution feed exactly one consumer, the next block's first ``ResnetBlock2D``,
which reads the map twice: through ``norm1`` and as its shortcut. Their biases are per-channel
constants, so instead of a pass that adds them to the whole map (at 512² and 128 channels, a read
and a write of 268 MB for 4 images) the bias-free map goes on with the bias beside it: ``norm1``
adds it inside the GroupNorm (tiger's ``input_bias``) and the block's output pass adds it with
conv2's bias and the shortcut (through a 1x1 shortcut convolution ``W_sc·b``, also a constant).
Convolutions pad their *inputs*, so a convolution's output bias is exactly a constant on its
whole output map: same sums, the added map rounded once less.

Only the encoder's own wiring is rewritten (:func:`set_carry_conv_bias`); a block that cannot take
the bias (not a fused, folded ``ResnetBlock2D``) gets the map with the bias added first. The UNet's
``conv_in`` and downsampler outputs are also its skip connections, read again by the up blocks, so
they keep their bias pass.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from tiger.ops.channel_bias import channel_bias_add
from tiger.ops.group_norm import GroupNormSiLU
from tiger.utils.lazy import require_diffusers

from .conv_layers import padded_conv_in
from .forward_switch import switch_forward
from .fused_norms import _resnet_forward_folded

__all__ = ["set_carry_conv_bias"]

_Carried = tuple[torch.Tensor, Optional[torch.Tensor]]  # (bias-free map, the bias it still needs)


def _with_bias(x: torch.Tensor, bias: Optional[torch.Tensor]) -> torch.Tensor:
    return x if bias is None else channel_bias_add(x, bias.to(x.dtype))


def _conv_in(conv: torch.nn.Module, x: torch.Tensor) -> _Carried:
    """The encoder's first convolution without its bias (zero-padded input channels if
    :func:`.conv_layers.set_pad_conv_in` put them on); any other layer runs as it is."""
    if type(conv) is not torch.nn.Conv2d:
        return conv(x), None
    if "_tiger_weight_padded" in conv.__dict__:
        return padded_conv_in(conv, x, bias=False), conv.bias
    return conv._conv_forward(x, conv.weight, None), conv.bias


def _downsample(layer: torch.nn.Module, x: torch.Tensor) -> _Carried:
    """A ``Downsample2D`` (diffusers 0.42: zero-pad (0, 1, 0, 1), 3x3 stride-2 convolution; or the
    4x4 form of :func:`.conv_layers.set_downsample_4x4`) without its bias."""
    from diffusers.models.downsampling import Downsample2D

    conv = getattr(layer, "conv", None)
    if type(layer) is not Downsample2D or type(conv) is not torch.nn.Conv2d or layer.norm is not None \
            or not layer.use_conv or layer.padding != 0:
        return layer(x), None
    if "_tiger_weight_4x4" in layer.__dict__:
        return F.conv2d(x, layer._tiger_weight_4x4, None, stride=conv.stride, padding=1), conv.bias
    return conv._conv_forward(F.pad(x, (0, 1, 0, 1), mode="constant", value=0), conv.weight, None), conv.bias


def _takes_bias(block: torch.nn.Module) -> bool:
    """Whether ``block`` runs :func:`.fused_norms._resnet_forward_folded` with a fused norm1."""
    fwd = block.__dict__.get("forward")
    return getattr(fwd, "__func__", None) is _resnet_forward_folded and type(block.norm1) is GroupNormSiLU


def _resnet(block: torch.nn.Module, x: torch.Tensor, bias: Optional[torch.Tensor]) -> torch.Tensor:
    if bias is not None and _takes_bias(block):
        return _resnet_forward_folded(block, x, None, input_bias=bias)
    return block(_with_bias(x, bias), temb=None)


def _encoder_forward_carried(self, sample: torch.Tensor) -> torch.Tensor:
    """diffusers 0.42's ``Encoder.forward`` with the biases of ``conv_in`` and of the
    downsamplers carried into the next ResNet block (module docstring)."""
    from diffusers.models.unets.unet_2d_blocks import DownEncoderBlock2D

    if torch.is_grad_enabled() and self.gradient_checkpointing:
        return type(self).forward(self, sample)
    x, bias = _conv_in(self.conv_in, sample)
    for block in self.down_blocks:
        if type(block) is not DownEncoderBlock2D:
            x, bias = block(_with_bias(x, bias)), None
            continue
        for resnet in block.resnets:
            x, bias = _resnet(resnet, x, bias), None
        for layer in block.downsamplers or ():
            x, bias = _downsample(layer, _with_bias(x, bias))
    x = self.mid_block(_with_bias(x, bias))
    return self.conv_out(self.conv_act(self.conv_norm_out(x)))


def set_carry_conv_bias(vae: torch.nn.Module, on: bool) -> int:
    """Run every diffusers ``Encoder`` inside ``vae`` with its first convolution's and its
    downsamplers' biases carried into the next ResNet block (``on``; module docstring) or as
    diffusers does; returns how many encoders carry them afterwards."""
    require_diffusers("carrying the VAE encoder's convolution biases")
    from diffusers.models.autoencoders.vae import Encoder

    return switch_forward(vae, lambda m: type(m) is Encoder, _encoder_forward_carried, on)
