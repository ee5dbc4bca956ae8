"""Fused GroupNorm(+SiLU) and channels-last memory for the guidances' frozen diffusers models.

On an H100 a bf16 SDS step of InstructPix2Pix spends about a quarter of its time converting
NCHW conv inputs to NHWC and back (cuDNN) and in GroupNorm. Channels-last models avoid the
conversions, but torch's CUDA GroupNorm has no channels-last kernel (it copies to NCHW and
returns NCHW), so :func:`fuse_group_norms` swaps the models' GroupNorms for
:class:`tiger.ops.group_norm.GroupNormSiLU` (channels-last in, channels-last out, the SiLU that
follows fused in) and :func:`apply_fused_norms` then converts the module to channels-last. By
default (on CUDA) the VAEs and the UNets are converted (:func:`fused_norms_default` has the
figures).

What is replaced (diffusers 0.42, read from its ``forward`` methods):

- ``ResnetBlock2D``: ``norm1`` and ``norm2``, each followed by ``nonlinearity``. When that is
  SiLU and ``time_embedding_norm == "default"`` (norm2 directly followed by the activation), both
  norms fuse the SiLU and ``nonlinearity`` becomes the identity; its third use, the time
  embedding ``time_emb_proj(nonlinearity(temb))``, keeps its SiLU by turning ``time_emb_proj``
  into :class:`SiLUThenLinear` (same parameters); without resampling and with an output scale
  factor of 1 (and plain convolutions) the block adds conv1's bias with its time embedding, and
  conv2's bias with the shortcut, in one pass each (:func:`tiger.ops.channel_bias.channel_bias_add`
  with a per-sample bias and a residual). Otherwise the norms are replaced without SiLU and
  ``nonlinearity`` stays.
- ``Encoder`` / ``Decoder`` / ``UNet2DConditionModel``: ``conv_norm_out`` followed by ``conv_act``
  (used nowhere else): SiLU fused, ``conv_act`` the identity.
- ``Attention.group_norm`` and ``Transformer2DModel.norm``: no SiLU. A continuous-input
  ``Transformer2DModel`` also gets an output method without diffusers' ``.contiguous()``, which
  otherwise turns every transformer block's output (and the residual sum) back to NCHW, and
  whose 1x1-convolution ``proj_out`` adds its bias and the residual in one pass.
"""
from __future__ import annotations

import logging
import types
from typing import Optional

import torch
import torch.nn.functional as F

from tiger.ops.channel_bias import channel_bias_add
from tiger.ops.group_norm import GroupNormSiLU, group_norm_input_grad, group_norm_with_stats

from tiger.utils.lazy import require_diffusers

logger = logging.getLogger(__name__)

# A folded block's shared time-embedding biases (:class:`.time_bias.StackedTimeBias`), if any.
TIME_BIAS_KEY = "_tiger_time_biases"

__all__ = ["SiLUThenLinear", "fuse_group_norms", "bias_after_conv", "apply_fused_norms", "fused_norms_default",
           "folds_norm_bias", "set_fold_norm_bias", "set_block_backward", "TIME_BIAS_KEY"]


class SiLUThenLinear(torch.nn.Linear):
    """``linear(silu(x))``: a fused ResnetBlock2D's time-embedding projection, whose SiLU used to
    come from the block's ``nonlinearity`` (now the identity). Parameters keep the names
    ``weight`` [out, in] and ``bias`` [out], so state dicts are unchanged."""

    @classmethod
    def from_linear(cls, linear: torch.nn.Linear) -> "SiLUThenLinear":
        m = cls.__new__(cls)
        torch.nn.Module.__init__(m)
        m.in_features, m.out_features = linear.in_features, linear.out_features
        m.weight, m.bias = linear.weight, linear.bias
        m.train(linear.training)
        return m

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(F.silu(x), self.weight, self.bias)


def _fused(gn: torch.nn.Module, silu: bool) -> Optional[GroupNormSiLU]:
    return GroupNormSiLU.from_group_norm(gn, silu) if type(gn) is torch.nn.GroupNorm else None


def _fuse_resnet(block) -> int:
    n1, n2 = _fused(block.norm1, False), _fused(block.norm2, False)
    if n1 is None or n2 is None:  # already fused, or not a plain GroupNorm
        return 0
    silu = type(block.nonlinearity) is torch.nn.SiLU and block.time_embedding_norm == "default"
    n1.silu = n2.silu = silu
    block.norm1, block.norm2 = n1, n2
    if silu:
        if block.time_emb_proj is not None and not block.skip_time_act:
            block.time_emb_proj = SiLUThenLinear.from_linear(block.time_emb_proj)
        block.nonlinearity = torch.nn.Identity()
        if (block.upsample is None and block.downsample is None and block.output_scale_factor == 1.0
                and _folds_adds(block)):
            block.forward = types.MethodType(_resnet_forward_folded, block)
    return 2


def _conv_then_add(conv: torch.nn.Conv2d, x: torch.Tensor, extra_bias: Optional[torch.Tensor] = None,
                   residual: Optional[torch.Tensor] = None, out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``conv(x) + extra_bias + residual`` with the convolution's bias, ``extra_bias`` ([N, C] or
    [C]) and ``residual`` added by one :func:`channel_bias_add` pass after a bias-free convolution;
    written into ``out`` when given (no gradient: :mod:`.skip_concat`)."""
    y = conv._conv_forward(x, conv.weight, None)
    bias = conv.bias
    if extra_bias is not None:
        bias = extra_bias if bias is None else extra_bias + bias
    if bias is None and residual is None:
        return y if out is None else out.copy_(y)
    if bias is None and out is None:
        bias = y.new_zeros(y.shape[1])
    if bias is not None and bias.dim() == 2 and bias.shape[0] != y.shape[0]:  # a [1, C] time embedding for the batch
        bias = bias.expand(y.shape[0], -1)
    return channel_bias_add(y, None if bias is None else bias.to(y.dtype), residual, out=out)


def _resnet_forward_folded(self, input_tensor: torch.Tensor, temb: Optional[torch.Tensor],
                             *args: object, input_bias: Optional[torch.Tensor] = None,
                             out: Optional[torch.Tensor] = None, **kwargs: object) -> torch.Tensor:
    """A fused ``ResnetBlock2D`` (SiLUs inside the norms, ``time_embedding_norm == "default"``,
    no resampling, ``output_scale_factor == 1``): diffusers 0.42's computation with the adds
    folded into the convolutions' bias passes: ``conv1``'s bias and the time embedding as one
    [N, C] bias, ``conv2``'s bias (plus ``conv_shortcut``'s) and the shortcut in one pass
    (:func:`_conv_then_add`), and no division by a scale factor of 1: two full-size passes and
    allocations fewer per block. Same values (the sums rounded once).

    ``input_bias`` [C] (model dtype): a bias the producing convolution has not added to
    ``input_tensor`` (:mod:`.encoder_bias`); the block computes on ``input_tensor + input_bias``
    by adding it inside norm1 and to the shortcut's bias (through a 1x1 shortcut convolution:
    ``W_sc·input_bias``, a per-channel constant). ``out``: a tensor of the output's shape to write
    the output into (no gradient; :mod:`.skip_concat`)."""
    fold = self.__dict__.get("_tiger_fold_norm_bias", False)
    stacked = self.__dict__.get(TIME_BIAS_KEY) if fold and temb is not None else None
    ib2 = None if stacked is None else stacked.input_bias(self, temb, input_tensor.shape[0])  # .time_bias
    temb_bias = None
    if ib2 is None and self.time_emb_proj is not None and temb is not None:
        temb_bias = self.time_emb_proj(temb)  # its SiLU: SiLUThenLinear or skip_time_act
    ib1 = None if input_bias is None else _norm_input_bias(input_bias, None, input_tensor.shape[0])
    if fold:  # conv1's bias and temb added inside norm2
        if (ib2 is None and self.__dict__.get("_tiger_block_backward", False)
                and _block_backward_applies(self, input_tensor, temb_bias)):
            y = _FoldedBlock.apply(input_tensor, self, ib1)
            return y if out is None else out.copy_(y)
        h = self.conv1._conv_forward(self.norm1(input_tensor, input_bias=ib1), self.conv1.weight, None)
        if ib2 is None:
            ib2 = _norm_input_bias(self.conv1.bias, temb_bias, h.shape[0])
        h = self.dropout(self.norm2(h, input_bias=ib2))
    else:
        h = _conv_then_add(self.conv1, self.norm1(input_tensor, input_bias=ib1), temb_bias)
        h = self.dropout(self.norm2(h))
    if self.conv_shortcut is None:
        return _conv_then_add(self.conv2, h, input_bias, input_tensor, out=out)
    sc = self.conv_shortcut
    shortcut = sc._conv_forward(input_tensor, sc.weight, None)
    return _conv_then_add(self.conv2, h, _shortcut_bias(sc, input_bias), shortcut, out=out)


def _shortcut_bias(sc: torch.nn.Conv2d, input_bias: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
    """The 1x1 shortcut convolution's bias plus its weights times ``input_bias`` (the constant
    ``sc(x + input_bias) − sc(x)``), summed in float32 (float64 for float64) and rounded once."""
    if input_bias is None:
        return sc.bias
    acc = torch.float64 if sc.weight.dtype == torch.float64 else torch.float32
    carried = sc.weight.reshape(sc.out_channels, sc.in_channels).to(acc) @ input_bias.to(acc)
    if sc.bias is not None:
        carried = carried + sc.bias.to(acc)
    return carried.to(sc.weight.dtype)


def _norm_input_bias(conv_bias: Optional[torch.Tensor], temb_bias: Optional[torch.Tensor],
                     n: int) -> Optional[torch.Tensor]:
    """conv1's bias [C] plus the time embedding [N, C] (or [1, C]) in float32 (float64 for a
    float64 model), for norm2's ``input_bias``; None when there is neither."""
    ref = temb_bias if temb_bias is not None else conv_bias
    if ref is None:
        return None
    acc = torch.float64 if ref.dtype == torch.float64 else torch.float32
    if temb_bias is None:
        return conv_bias.to(acc)
    b = temb_bias.to(acc)
    if b.shape[0] != n:
        b = b.expand(n, -1)
    return b if conv_bias is None else b + conv_bias.to(acc)


def _block_backward_applies(block, x: torch.Tensor, temb_bias: Optional[torch.Tensor]) -> bool:
    """Whether :class:`_FoldedBlock` may run ``block`` on ``x``: a gradient to x only (frozen
    block, eval mode), no time embedding, no shortcut convolution, fused SiLU norms."""
    return (torch.is_grad_enabled() and x.requires_grad and temb_bias is None and block.conv_shortcut is None
            and not block.training and type(block.norm1) is GroupNormSiLU and type(block.norm2) is GroupNormSiLU
            and not any(p.requires_grad for p in block.parameters()))


def _input_grad(conv: torch.nn.Conv2d, grad_out: torch.Tensor, like_input: torch.Tensor) -> torch.Tensor:
    """dL/d(input) of a bias-free ``conv`` (weights frozen), as autograd's convolution backward
    computes it; ``like_input`` gives the input's shape and layout (its values are not read)."""
    return torch.ops.aten.convolution_backward(grad_out, like_input, conv.weight, None, conv.stride, conv.padding,
                                               conv.dilation, False, [0, 0], conv.groups, (True, False, False))[0]


class _FoldedBlock(torch.autograd.Function):
    """A folded ``ResnetBlock2D`` (no time embedding, no shortcut convolution) whose backward is
    written out for a gradient to its input only: the same convolution and GroupNorm backward
    kernels autograd runs, except that the shortcut's gradient is added inside norm1's backward
    (:func:`tiger.ops.group_norm.group_norm_input_grad`'s ``residual_grad``) instead of by a
    separate sum, and only x and conv1's output are kept for it (autograd also keeps both norms'
    outputs, the convolutions' inputs). The VAE encoder's blocks under SDS."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, block, ib1: Optional[torch.Tensor] = None) -> torch.Tensor:
        # ib1: norm1's input bias (a producer's carried bias, float32), also added with the shortcut
        n1, n2, conv1, conv2 = block.norm1, block.norm2, block.conv1, block.conv2
        h1, mean1, rstd1 = group_norm_with_stats(x, n1.num_groups, n1.weight, n1.bias, n1.eps, n1.silu, ib1)
        c1 = conv1._conv_forward(h1, conv1.weight, None)
        ib = _norm_input_bias(conv1.bias, None, c1.shape[0])
        h2, mean2, rstd2 = group_norm_with_stats(c1, n2.num_groups, n2.weight, n2.bias, n2.eps, n2.silu, ib)
        c2 = conv2._conv_forward(block.dropout(h2), conv2.weight, None)
        bias = conv2.bias if conv2.bias is not None else c2.new_zeros(c2.shape[1])
        if ib1 is not None:
            bias = bias.to(ib1.dtype) + ib1
        ctx.save_for_backward(x, c1, mean1, rstd1, mean2, rstd2, ib, ib1)
        ctx.block = block
        return channel_bias_add(c2, bias.to(c2.dtype), x)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        x, c1, mean1, rstd1, mean2, rstd2, ib, ib1 = ctx.saved_tensors
        b = ctx.block
        n1, n2 = b.norm1, b.norm2
        dh2 = _input_grad(b.conv2, grad_out, c1)  # norm2's output has conv1's output's shape and layout
        dc1 = group_norm_input_grad(dh2, c1, n2.num_groups, mean2, rstd2, n2.weight, n2.bias, n2.silu, ib)
        dh1 = _input_grad(b.conv1, dc1, x)
        dx = group_norm_input_grad(dh1, x, n1.num_groups, mean1, rstd1, n1.weight, n1.bias, n1.silu, ib1,
                                   residual_grad=grad_out)
        return dx, None, None


def set_block_backward(module: torch.nn.Module, on: bool) -> int:
    """In every folded ``ResnetBlock2D`` of ``module`` that folds its norm bias
    (:func:`set_fold_norm_bias`), run the block through :class:`_FoldedBlock` when only its input
    needs a gradient (``on``), or through autograd (off). Returns how many blocks have it on
    (the time-embedded and shortcut-convolution blocks keep autograd when they run)."""
    require_diffusers("the ResNet blocks' own backward")
    from diffusers.models.resnet import ResnetBlock2D

    count = 0
    for m in module.modules():
        if type(m) is ResnetBlock2D:
            here = bool(on) and m.__dict__.get("_tiger_fold_norm_bias", False)
            m.__dict__["_tiger_block_backward"] = here
            count += here
    return count


def set_fold_norm_bias(module: torch.nn.Module, on: bool) -> int:
    """In every folded ``ResnetBlock2D`` of ``module`` (:func:`fuse_group_norms` made its forward
    :func:`_resnet_forward_folded`), add conv1's bias and the time embedding inside norm2
    (``GroupNormSiLU``'s ``input_bias``: the biased map is never written, one full read and write
    fewer per block) when ``on``, or in conv1's bias pass (off). Returns how many blocks fold."""
    require_diffusers("folding conv biases into GroupNorm")
    from diffusers.models.resnet import ResnetBlock2D

    count = 0
    for m in module.modules():
        if type(m) is not ResnetBlock2D or m.__dict__.get("forward") is None:
            continue
        if getattr(m.forward, "__func__", None) is not _resnet_forward_folded or type(m.norm2) is not GroupNormSiLU:
            continue
        m.__dict__["_tiger_fold_norm_bias"] = bool(on)
        count += bool(on)
    return count


def folds_norm_bias(module: torch.nn.Module) -> bool:
    """Whether ``module`` is a folded ``ResnetBlock2D`` adding conv1's bias and its time embedding
    inside norm2 (:func:`set_fold_norm_bias` on)."""
    return (module.__dict__.get("_tiger_fold_norm_bias", False)
            and getattr(module.__dict__.get("forward"), "__func__", None) is _resnet_forward_folded)


def _folds_adds(block) -> bool:
    """Whether :func:`_resnet_forward_folded` may run ``block``: plain convolutions (a subclass
    may do more in its forward)."""
    convs = (block.conv1, block.conv2) + (() if block.conv_shortcut is None else (block.conv_shortcut,))
    return all(type(c) is torch.nn.Conv2d for c in convs)


def _fuse_norm_out(module) -> int:
    norm = getattr(module, "conv_norm_out", None)
    act = getattr(module, "conv_act", None)
    if norm is None or type(norm) is not torch.nn.GroupNorm:
        return 0
    silu = type(act) is torch.nn.SiLU
    module.conv_norm_out = GroupNormSiLU.from_group_norm(norm, silu)
    if silu:
        module.conv_act = torch.nn.Identity()
    return 1


def _continuous_output_keep_layout(self, hidden_states, residual, batch_size, height, width, inner_dim,
                                   out_bias: Optional[torch.Tensor] = None, out: Optional[torch.Tensor] = None):
    """``Transformer2DModel._get_output_for_continuous_inputs`` of diffusers 0.42 without its
    ``.contiguous()``: the [B, H·W, C] tokens viewed as a [B, C, H, W] map are channels-last, so
    the output (and the residual sum) stay channels-last; a 1x1-convolution projection adds its
    bias and the residual in one pass (:func:`_conv_then_add`), a linear one gets the residual in
    place into its fresh output (a linear layer's backward keeps no output). Same values.
    ``out_bias`` [C_out]: used instead of the projection's bias (a linear ``proj_out``, layer or
    1x1 convolution: the fused transformers' carried biases, :mod:`.transformer_blocks`).
    ``out``: a tensor of the output's shape to write the output into (no gradient; :mod:`.skip_concat`)."""
    po = self.proj_out
    if not self.use_linear_projection:
        hidden_states = hidden_states.reshape(batch_size, height, width, inner_dim).permute(0, 3, 1, 2)
        if type(po) is torch.nn.Conv2d:  # bias and residual in one pass
            if out_bias is None:
                return _conv_then_add(po, hidden_states, None, residual, out=out)
            y = po._conv_forward(hidden_states, po.weight, None)
            return channel_bias_add(y, out_bias.to(y.dtype), residual, out=out)
        hidden_states = po(hidden_states)
    else:
        hidden_states = po(hidden_states) if out_bias is None else F.linear(hidden_states, po.weight, out_bias)
        hidden_states = hidden_states.reshape(batch_size, height, width, inner_dim).permute(0, 3, 1, 2)
    return hidden_states.add_(residual) if out is None else torch.add(hidden_states, residual, out=out)


def _conv_then_channel_bias(self, x: torch.Tensor) -> torch.Tensor:
    return channel_bias_add(self._conv_forward(x, self.weight, None), self.bias)


def bias_after_conv(module: torch.nn.Module) -> int:
    """Make every ``torch.nn.Conv2d`` with a bias inside ``module`` add it with
    :func:`tiger.ops.channel_bias.channel_bias_add` after a bias-free convolution (PyTorch adds
    it through its generic broadcast kernel, slow on channels-last maps). Same values;
    idempotent; returns how many convolutions changed."""
    count = 0
    for m in module.modules():
        if type(m) is torch.nn.Conv2d and m.bias is not None and "forward" not in m.__dict__:
            m.forward = types.MethodType(_conv_then_channel_bias, m)
            count += 1
    return count


def fuse_group_norms(module: torch.nn.Module) -> int:
    """Replace the GroupNorms of diffusers blocks inside ``module`` by fused
    :class:`GroupNormSiLU` modules (module docstring: which ones, and how the SiLUs move).
    Idempotent; parameters are shared, not copied. Returns how many norms were replaced."""
    diffusers = require_diffusers("fusing GroupNorm + SiLU")
    from diffusers.models.attention_processor import Attention
    from diffusers.models.autoencoders.vae import Decoder, Encoder
    from diffusers.models.resnet import ResnetBlock2D
    from diffusers.models.transformers.transformer_2d import Transformer2DModel

    count = 0
    for m in list(module.modules()):
        if type(m) is ResnetBlock2D:
            count += _fuse_resnet(m)
        elif type(m) in (Encoder, Decoder) or isinstance(m, diffusers.UNet2DConditionModel):
            count += _fuse_norm_out(m)
        elif isinstance(m, Attention) and type(m.group_norm) is torch.nn.GroupNorm:
            m.group_norm = GroupNormSiLU.from_group_norm(m.group_norm, False)
            count += 1
        elif type(m) is Transformer2DModel and m.is_input_continuous and type(m.norm) is torch.nn.GroupNorm:
            m.norm = GroupNormSiLU.from_group_norm(m.norm, False)
            m._get_output_for_continuous_inputs = types.MethodType(_continuous_output_keep_layout, m)
            count += 1
    return count


def fused_norms_default(module: torch.nn.Module) -> bool:
    """The default of ``fused_norms=None``: on for the diffusion models (``AutoencoderKL`` and
    ``UNet2DConditionModel``) on CUDA with tiger's CUDA kernels built, off otherwise (text encoders,
    the CPU, where the op is the slow reference implementation).

    Measured in bf16 with full-size random weights (``benchmarks/guidance.py``), one graphed
    4-view InstructPix2Pix step 84.4 ms (torch's GroupNorm) -> 68.1 ms (VAE fused) -> 60.6 ms
    (VAE and UNet fused; the UNet's eager passes 38.6 -> 31.2 ms), MVDream 25.1 -> 21.0 -> 18.6 ms
    on an H200; on the H100 with everything of this module 59.6 and 17.3 ms (figures and commands in
    docs/BENCHMARKS.md). (Before the transformer blocks kept channels-last, the fused UNet was the
    slower one.)"""
    from tiger.ops import cuda_enabled

    p = next(module.parameters(), None)
    if p is None or p.device.type != "cuda" or not cuda_enabled():
        return False
    d = require_diffusers("fusing GroupNorm + SiLU")
    return isinstance(module, (d.AutoencoderKL, d.UNet2DConditionModel))


def apply_fused_norms(module: torch.nn.Module, enabled: Optional[bool] = None) -> int:
    """:func:`fuse_group_norms` and :func:`bias_after_conv`, then ``module`` to channels-last memory; ``enabled=None``:
    :func:`fused_norms_default`. Returns the number of fused norms (0 when not enabled)."""
    if enabled is None:
        enabled = fused_norms_default(module)
    if not enabled:
        return 0
    p = next(module.parameters(), None)
    if p is not None and p.device.type == "cuda":
        from tiger.ops import cuda_enabled

        if not cuda_enabled():
            raise ValueError("tiger.edit: fused_norms=True on CUDA needs tiger built with its CUDA kernels "
                             "(tiger.ops.cuda_enabled() is False); rebuild with nvcc or pass fused_norms=False")
    count = fuse_group_norms(module)
    bias_after_conv(module)
    torch.nn.Module.to(module, memory_format=torch.channels_last)
    logger.info("fused %d GroupNorms of %s; channels-last", count, type(module).__name__)
    return count
