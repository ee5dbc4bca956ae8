"""The guidances' convolution layers rewritten for speed with the same sums
(:class:`.model_kernels.ModelKernels` switches them):

- ``subpixel_upsample``: a UNet upsampling layer (nearest 2x, then a 3x3 convolution) as four 2x2
  phase kernels in one convolution on the low-resolution map, interleaved with the bias (the
  phase kernels' taps are sums of the 3x3 taps, rounded once to the model's dtype);
- ``pad_conv_in``: the first convolution of a UNet or VAE encoder (3-8 input channels) on an input
  zero-padded to 16 channels with a zero-padded kernel;
- ``vae_downsample_4x4``: the VAE's padded stride-2 convolutions as unpadded-input 4x4 ones.

Each ``set_*`` function is idempotent and reversible. The derived kernels are instance attributes,
not parameters: state dicts are unchanged.
"""
from __future__ import annotations

import types
from typing import Optional

import torch
import torch.nn.functional as F

from tiger.ops.channel_bias import channel_bias_add, subpixel_interleave
from tiger.utils.lazy import require_diffusers

__all__ = ["padded_conv_in", "set_downsample_4x4", "set_pad_conv_in", "set_subpixel_upsample", "subpixel_weight"]


# -- resampling layers with a derived kernel (sub-pixel upsampling, 4x4 downsampling) -------------
def _plain_3x3(conv: object, stride: int, padding: int) -> bool:
    """Whether ``conv`` is a plain 3x3 ``Conv2d`` (one group, no dilation) with this stride and padding."""
    return (type(conv) is torch.nn.Conv2d and conv.kernel_size == (3, 3) and conv.stride == (stride, stride)
            and conv.padding == (padding, padding) and conv.groups == 1 and conv.dilation == (1, 1))


def _put_kernel(layer: torch.nn.Module, name: str, weight: torch.Tensor, forward) -> None:
    """Give ``layer`` a derived kernel (``layer.<name>``, not a parameter: the state dict is
    unchanged; channels-last when the layer's convolution weight is) and the forward that uses it."""
    if not layer.conv.weight.is_contiguous():  # channels-last models keep their layout
        weight = weight.contiguous(memory_format=torch.channels_last)
    layer.__dict__[name] = weight
    layer.forward = types.MethodType(forward, layer)


def _take_kernel(layer: torch.nn.Module, name: str) -> None:
    """Undo :func:`_put_kernel`: the class's forward again."""
    layer.__dict__.pop("forward", None)
    layer.__dict__.pop(name, None)


# -- sub-pixel upsampling -------------------------------------------------------------------------
# Which 3x3 taps (rows or columns) fall on the two low-resolution pixels a 2x-upsampled output
# pixel of phase a sees: phase 0 sees input rows i-1 (tap 0) and i (taps 1, 2), phase 1 rows i
# (taps 0, 1) and i+1 (tap 2).
_PHASE_TAPS = ((1.0, 0.0, 0.0, 0.0, 1.0, 1.0), (1.0, 1.0, 0.0, 0.0, 0.0, 1.0))


def subpixel_weight(weight: torch.Tensor) -> torch.Tensor:
    """[4·Cout, Cin, 2, 2] kernels of the four output phases (a, b) (channel block 2a + b) of a
    3x3 convolution ``weight`` [Cout, Cin, 3, 3] applied after 2x nearest upsampling; summed in
    float32 (float64 for float64 weights) and rounded once to the weight's dtype."""
    acc = torch.float64 if weight.dtype == torch.float64 else torch.float32
    taps = torch.tensor(_PHASE_TAPS, dtype=acc, device=weight.device).view(2, 2, 3)  # [phase, 2, 3]
    w = weight.detach().to(acc)
    w4 = torch.einsum("aus,bvt,oist->aboiuv", taps, taps, w)  # [2, 2, Cout, Cin, 2, 2]
    return w4.reshape(4 * weight.shape[0], weight.shape[1], 2, 2).to(weight.dtype)


def _subpixel_upsample_forward(self, hidden_states: torch.Tensor, output_size=None, *args: object,
                               out: Optional[torch.Tensor] = None, **kwargs: object) -> torch.Tensor:
    """diffusers 0.42's ``Upsample2D`` (nearest 2x, 3x3 convolution) as four 2x2 convolutions on
    the input: Z = conv(x, W4, padding 1) is [N, 4C, H+1, W+1], and output pixel (2i+a, 2j+b) is
    Z[2a+b block, i+a, j+b] plus the bias (one pass: :func:`tiger.ops.channel_bias.subpixel_interleave`).
    ``out``: a [N, C, 2H, 2W] tensor to write the output into (no gradient), interleaved in place
    when its channels are innermost (a channel slice of a channels-last map: :mod:`.skip_concat`)."""
    _, _, h, w = hidden_states.shape
    conv = self.conv
    if output_size is not None and tuple(output_size) != (2 * h, 2 * w) or \
            (torch.is_grad_enabled() and (conv.weight.requires_grad or hidden_states.requires_grad)):
        y = type(self).forward(self, hidden_states, output_size, *args, **kwargs)
        return y if out is None else out.copy_(y)
    z = F.conv2d(hidden_states, self._tiger_weight_subpixel, None, padding=1)
    bias = None if conv.bias is None else conv.bias.to(z.dtype)
    if out is not None:
        return subpixel_interleave(z, bias, out=out)
    y = subpixel_interleave(z, bias)  # channels-last
    return y if hidden_states.is_contiguous(memory_format=torch.channels_last) and not hidden_states.is_contiguous() \
        else y.contiguous()


def set_subpixel_upsample(unet: torch.nn.Module, on: bool) -> int:
    """The UNet's ``Upsample2D`` layers (nearest 2x, then a plain 3x3 convolution, no norm) as
    per-phase 2x2 convolutions (``on``) or diffusers' own; returns how many run sub-pixel
    afterwards."""
    require_diffusers("the sub-pixel upsampling")
    from diffusers.models.upsampling import Upsample2D

    count = 0
    for m in unet.modules():
        if type(m) is not Upsample2D or not m.use_conv or m.use_conv_transpose or not m.interpolate \
                or m.norm is not None or m.name != "conv":
            continue
        if not _plain_3x3(m.conv, stride=1, padding=1):
            continue
        if on:
            _put_kernel(m, "_tiger_weight_subpixel", subpixel_weight(m.conv.weight), _subpixel_upsample_forward)
            count += 1
        else:
            _take_kernel(m, "_tiger_weight_subpixel")
    return count


# -- zero-padded first convolutions ---------------------------------------------------------------
_PAD_CHANNELS = 16  # cuDNN's tensor-core kernels for 3-8 input channels pad to 8 and run a slow path


def padded_conv_in(conv: torch.nn.Conv2d, x: torch.Tensor, bias: bool = True) -> torch.Tensor:
    """``conv`` (given a padded kernel by :func:`set_pad_conv_in`) on ``x`` zero-padded to the
    kernel's channel count (channels-last); its bias added when ``bias`` (else the caller carries it)."""
    n, c, h, w = x.shape
    weight = conv.__dict__["_tiger_weight_padded"]
    padded = torch.empty((n, weight.shape[1], h, w), dtype=x.dtype, device=x.device,
                         memory_format=torch.channels_last)
    padded[:, c:] = 0
    padded[:, :c] = x
    y = F.conv2d(padded, weight, None, conv.stride, conv.padding, conv.dilation, conv.groups)
    return y if conv.bias is None or not bias else channel_bias_add(y, conv.bias)


def _padded_conv_in_forward(self, x: torch.Tensor) -> torch.Tensor:
    return padded_conv_in(self, x)


def set_pad_conv_in(model: torch.nn.Module, on: bool) -> int:
    """The first convolution of a UNet (``conv_in``) or VAE encoder (``encoder.conv_in``) on an input
    zero-padded to a multiple of 16 channels with a zero-padded kernel (``on``), or as it was;
    returns how many convolutions run padded afterwards."""
    count = 0
    for conv in (getattr(model, "conv_in", None), getattr(getattr(model, "encoder", None), "conv_in", None)):
        if type(conv) is not torch.nn.Conv2d or conv.groups != 1 or conv.in_channels % _PAD_CHANNELS == 0:
            continue
        if not on:
            if conv.__dict__.pop("_tiger_weight_padded", None) is not None:
                before = conv.__dict__.pop("_tiger_forward_before_pad")  # e.g. fused_norms' bias pass
                if before is None:
                    conv.__dict__.pop("forward", None)
                else:
                    conv.forward = before
            continue
        if "_tiger_weight_padded" not in conv.__dict__:
            conv.__dict__["_tiger_forward_before_pad"] = conv.__dict__.get("forward")
        cp = -(-conv.in_channels // _PAD_CHANNELS) * _PAD_CHANNELS
        w = conv.weight.new_zeros(conv.out_channels, cp, *conv.kernel_size)
        w[:, :conv.in_channels] = conv.weight.detach()
        conv.__dict__["_tiger_weight_padded"] = w.contiguous(memory_format=torch.channels_last)
        conv.forward = types.MethodType(_padded_conv_in_forward, conv)
        count += 1
    return count


# -- VAE downsampling -----------------------------------------------------------------------------
def _downsample_4x4_forward(self, hidden_states: torch.Tensor, *args: object, **kwargs: object) -> torch.Tensor:
    conv = self.conv
    if "forward" in conv.__dict__:  # bias_after_conv (fused_norms): the bias by tiger's channel pass
        y = F.conv2d(hidden_states, self._tiger_weight_4x4, None, stride=conv.stride, padding=1)
        return y if conv.bias is None else channel_bias_add(y, conv.bias)
    return F.conv2d(hidden_states, self._tiger_weight_4x4, conv.bias, stride=conv.stride, padding=1)


def set_downsample_4x4(vae: torch.nn.Module, on: bool) -> int:
    """The VAE's padded stride-2 downsampling convolutions as unpadded-input 4x4 convolutions
    (``on``) or diffusers' pad + 3x3 (off); returns how many layers run 4x4 afterwards. Only
    ``Downsample2D`` with a 3x3, stride-2, padding-0 convolution and no norm qualifies (diffusers
    pads those (0, 1, 0, 1))."""
    require_diffusers("the 4x4 VAE downsampling")
    from diffusers.models.downsampling import Downsample2D

    count = 0
    for m in vae.modules():
        if type(m) is not Downsample2D or not m.use_conv or m.padding != 0 or m.norm is not None:
            continue
        conv = m.conv
        if not _plain_3x3(conv, stride=2, padding=0):
            continue
        if on:
            w4 = conv.weight.new_zeros(conv.out_channels, conv.in_channels, 4, 4)
            w4[:, :, 1:, 1:] = conv.weight.detach()
            _put_kernel(m, "_tiger_weight_4x4", w4, _downsample_4x4_forward)
            count += 1
        else:
            _take_kernel(m, "_tiger_weight_4x4")
    return count
