"""How the guidances' frozen UNets and VAEs compute, beyond :mod:`.fused_norms`
(:class:`ModelKernels`): FP8 matmuls, the fused GEGLU and the row LayerNorm here; the lean
attention and the fused transformer blocks in :mod:`.transformer_blocks`; the rewritten
convolution layers (sub-pixel upsampling, padded first convolutions, 4x4 downsampling) in
:mod:`.conv_layers`.

- ``matmul_precision="fp8"`` (opt-in): the UNet's transformer-block linear layers (attention
  q/k/v/out projections, the feed-forward's GEGLU projection and output, the transformers'
  ``proj_in``/``proj_out``, linear or 1x1 convolution) run as ``torch._scaled_mm`` on
  float8_e4m3fn operands: weights quantised once per output channel when applied, activations
  per row (token) on every call by :func:`tiger.ops.fp8_rows.quantize_rows_fp8` (scale on the
  device: no host sync, CUDA-graph capturable), bfloat16 output with the bias added by the
  matmul. q, k and v of one attention quantise their shared input once; the feed-forward
  quantises its GEGLU output as it computes it. The VAEs stay in the model's dtype (the SDS
  gradient back-propagates through the encoder). Needs bfloat16 models on a GPU with FP8
  tensor cores (compute capability >= 8.9); elsewhere :func:`set_matmul_precision` refuses,
  except with ``emulate=True`` (tests: the same quantisation, the product in float32).
- ``fused_geglu``: diffusers' ``FeedForward`` with a GEGLU computes ``a·gelu(g)`` in one pass
  (:func:`tiger.ops.fp8_rows.geglu`) instead of chunk + gelu + multiply.
- ``row_layer_norm``: the UNet's LayerNorms (three per transformer block) by
  :func:`tiger.ops.layer_norm.layer_norm_rows`, whose CUDA kernel gives each row of 320-1280
  channels to a few lanes of one warp, instead of PyTorch's block of 128 threads per row.
- ``fold_norm_bias``: in the fused ResNet blocks (:mod:`.fused_norms`), conv1's bias and the
  time embedding are added inside norm2 (tiger's GroupNorm ``input_bias``) instead of in a pass
  of their own: the biased map is never written (one full read and write fewer per block,
  forward; the backward recomputes the sum from conv1's output).
- ``subpixel_upsample``: the UNet's upsampling layers (2x nearest upsampling, then a 3x3
  convolution) as one 2x2 convolution per output phase on the low-resolution map: pixel (2i+a,
  2j+b) of the output sees, through the nearest upsampling, a 2x2 window of the input whose taps
  are sums of the 3x3 kernel's taps (rows {0}, {1, 2} for a = 0; {0, 1}, {2} for a = 1; columns
  alike). The four phases run as one convolution with 4x the output channels and are interleaved
  with the bias added: 32 instead of 72 multiply-adds per output pixel and channel pair, and no
  upsampled copy of the input. Same sums, except that the combined taps are rounded once to the
  model's dtype.
- ``lean_attention``: the UNet's attention layers without the steps diffusers' SDPA processor
  takes for features these models do not use; in particular without dividing every attention
  output by ``rescale_output_factor`` = 1 (one full pass per layer). The same operations
  otherwise, so the same values; any layer with a mask, a norm, a residual or another factor
  keeps diffusers' processor.
- ``fused_transformer``: the UNet's plain transformer blocks (self-attention, cross-attention,
  GEGLU feed-forward) without their three residual adds: the residual stream is the output
  matmuls' accumulator, the attention outputs' biases are carried into the next LayerNorm
  (``input_bias``) and added by the feed-forward's output matmul through an extra input column,
  and q/k/v come from one matmul (:mod:`.transformer_blocks`). Same sums, rounded once less.
- ``block_backward``: the VAE encoder's ResNet blocks without a shortcut convolution run their
  own backward when only their input needs a gradient (SDS): the kernels autograd runs, except
  that the shortcut's gradient is added inside norm1's backward pass (no separate sum: two map
  passes fewer per block) and the norms' outputs are not kept. Needs ``fold_norm_bias``.
- ``branch_prefix``: InstructPix2Pix's instruction and image-only branches are equal until the
  first cross-attention; the first down block runs its first ResNet block and self-attention on
  the rows that differ (:mod:`.branch_prefix`). The same operations on fewer rows.
- ``carry_conv_bias``: the VAE encoder's first convolution and its downsampling convolutions
  leave their bias to the next ResNet block, which adds it inside norm1 and with its shortcut
  (:mod:`.encoder_bias`): one full read and write fewer per such layer (the largest at 512²),
  the same sums.
- ``pad_conv_in``: the first convolution of the UNet and of the VAE encoder (4-8 or 3 input
  channels) on an input zero-padded to a multiple of 16 channels, with a zero-padded kernel: the
  same sums (the extra products are with zeros), but cuDNN's tensor-core kernels instead of its
  slow path for so few channels.
- ``stacked_time_bias``: the UNet's folded ResNet blocks get their norm2 input biases (conv1's
  bias plus the time-embedding projection) from one SiLU, one matmul on the blocks' stacked
  projection weights and one float32 sum per call, read by the norms as column slices
  (:mod:`.time_bias`), instead of five small launches per block. Same operations per element.
- ``cached_text_kv``: the cross-attentions' keys and values of the guidance's fixed text are
  computed once and kept with the text tensor (:mod:`.text_kv`) instead of in every call. The same
  matmuls on the same rows.
- ``row_softmax``: the VAE attention's softmax (its [B, L, L] scores, forward and backward) by
  :func:`tiger.ops.softmax.softmax_rows`, a row per block held in registers, instead of torch's
  kernels: the same values up to the order of the float32 sums.
- ``skip_concat``: the UNet's up blocks write each skip concatenation's hidden half where it is
  produced (the previous ResNet block's output pass, the transformer's ``proj_out`` pass, the
  previous block's sub-pixel upsampler) and copy only the skip in (:mod:`.skip_concat`): the
  hidden half's read and write fewer per concatenation, the same values bit for bit.
- ``head40_attention`` (opt-in): the UNet's self-attentions with head dim 40 (InstructPix2Pix's
  64² layers) by :func:`tiger.ops.attention.attention_rows`, whose Hopper kernel multiplies at
  head dim 48 / 40 with warpgroup MMAs instead of cuDNN's 64; level with cuDNN's SDPA on an
  H100 and the CSD step no faster with it (docs/BENCHMARKS.md, "Head-dim-40 attention").
- ``vae_downsample_4x4``: the VAE's stride-2 downsampling convolutions, which diffusers runs on
  a (0, 1, 0, 1) zero-padded copy of the map, as 4x4 convolutions with padding 1 whose kernel is
  the 3x3 one in its lower-right corner and zeros elsewhere: the same sums (the extra products
  are with zero weights) without the padded copy, forward and backward, for 16/9 of those
  layers' FLOPs.

Each ``set_*`` function is idempotent and reversible (``False``/``"model"`` restores the
diffusers computation), so one set of models can be measured under every setting.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any, Optional

import torch

from tiger.ops.fp8_rows import dequantize_rows, geglu, quantize_rows_fp8
from tiger.ops.layer_norm import layer_norm_rows

from .branch_prefix import set_branch_prefix
from .conv_layers import set_downsample_4x4, set_pad_conv_in, set_subpixel_upsample
from .diffusers_models import set_row_softmax
from .encoder_bias import set_carry_conv_bias
from .forward_switch import switch_forward
from .fused_norms import set_block_backward, set_fold_norm_bias
from .skip_concat import set_skip_concat
from .time_bias import set_stacked_time_bias
from .transformer_blocks import set_cached_text_kv, set_fused_transformer, set_head40_attention, set_lean_attention
from tiger.utils.lazy import require_diffusers

logger = logging.getLogger(__name__)

__all__ = ["MATMUL_PRECISIONS", "Fp8Linear", "ModelKernels", "apply_model_kernels", "fp8_matmul",
           "fp8_supported", "set_fused_geglu", "set_matmul_precision", "set_row_layer_norm"]

MATMUL_PRECISIONS = ("model", "fp8")


@dataclass(frozen=True)
class ModelKernels:
    """The kernels a guidance's UNet and VAE run (module docstring).

    Attributes:
        matmul_precision: ``"model"`` (the models' dtype) or ``"fp8"`` (opt-in; bfloat16 models
            on a GPU with FP8 tensor cores).
        fp8_fast_accum: ``torch._scaled_mm``'s ``use_fast_accum`` (Hopper's faster, less exactly
            accumulated FP8 products); only with ``"fp8"``.
        fused_geglu: the one-pass GEGLU; None: on where the UNet is on CUDA with tiger's CUDA
            kernels built (same values up to one rounding).
        vae_downsample_4x4: the VAE's unpadded 4x4 downsampling; None: on where the VAE is on
            CUDA (same sums; measured -1.7 ms per CSD step on an H100).
        fold_norm_bias: conv1's bias and the time embedding inside norm2 (models with fused norms
            only); None: on where the models are on CUDA with tiger's CUDA kernels (the sum
            rounded once less).
        row_layer_norm: the UNet's LayerNorms by tiger's row kernel; None: on where the UNet is
            on CUDA with tiger's CUDA kernels (same statistics, one rounding).
        subpixel_upsample: the UNet's upsampling layers as per-phase 2x2 convolutions; None: on
            where the UNet is on CUDA (the combined taps rounded once to the model's dtype).
        lean_attention: the UNet's attentions without diffusers' unused steps; None: on (the
            same operations and values on any device).
        block_backward: the VAE's ResNet blocks' own input-gradient backward (with
            ``fold_norm_bias``); None: on where the VAE is on CUDA with tiger's CUDA kernels (the
            shortcut's gradient summed before rounding instead of after).
        pad_conv_in: the first convolutions on inputs zero-padded to 16-channel multiples; None:
            on where the models are on CUDA (same sums).
        fused_transformer: the UNet's transformer blocks with their residual adds inside the
            output matmuls and q/k/v in one matmul; None: on where the UNet is on CUDA with
            tiger's CUDA kernels (each residual sum rounded once instead of twice).
        carry_conv_bias: the VAE encoder's ``conv_in`` and downsampler biases added by the next
            ResNet block (norm1's input bias, the shortcut's bias) instead of a pass of their
            own; None: on where the VAE is on CUDA with tiger's CUDA kernels (the biased map
            rounded once less).
        branch_prefix: the UNet's first down block computes, up to the first cross-attention,
            only the guidance branches that differ there (InstructPix2Pix's instruction and
            image-only branches share their first ResNet block and self-attention:
            :mod:`.branch_prefix`); None: on (the same operations on fewer rows, any device).
        stacked_time_bias: the folded ResNet blocks' time-embedding biases from one stacked
            matmul per UNet call (:mod:`.time_bias`); None: on where ``fold_norm_bias`` is (the
            same operations per element).
        cached_text_kv: the cross-attentions' keys and values of the fixed text computed once
            (:mod:`.text_kv`); None: on (the same matmuls, any device).
        row_softmax: the VAE attention's softmax by tiger's row kernel
            (:func:`.diffusers_models.set_row_softmax`); None: on where the VAE is on CUDA with
            tiger's CUDA kernels (the float32 sums in another order).
        skip_concat: the up blocks' skip concatenations written in place by their producers
            (:mod:`.skip_concat`); None: on where the UNet is on CUDA with tiger's CUDA kernels (the
            same values).
        head40_attention: the UNet's self-attentions of head dim 40 by tiger's Hopper kernel
            (:func:`tiger.ops.attention.attention_rows`) in the lean processor and the fused
            blocks; None: off (measured level with cuDNN's SDPA on an H100: 0.90-0.92 against 0.91
            ms for InstructPix2Pix's 12 x 8 x 4096² layer, and the CSD step no faster with it). The same error against float64 as
            SDPA's (P rounded to bfloat16 before its product with V, as cuDNN does).
    """

    matmul_precision: str = "model"
    fp8_fast_accum: bool = False
    fused_geglu: Optional[bool] = None
    vae_downsample_4x4: Optional[bool] = None
    fold_norm_bias: Optional[bool] = None
    row_layer_norm: Optional[bool] = None
    subpixel_upsample: Optional[bool] = None
    lean_attention: Optional[bool] = None
    block_backward: Optional[bool] = None
    pad_conv_in: Optional[bool] = None
    fused_transformer: Optional[bool] = None
    carry_conv_bias: Optional[bool] = None
    branch_prefix: Optional[bool] = None
    stacked_time_bias: Optional[bool] = None
    cached_text_kv: Optional[bool] = None
    skip_concat: Optional[bool] = None
    row_softmax: Optional[bool] = None
    head40_attention: Optional[bool] = None

    def __post_init__(self) -> None:
        if self.matmul_precision not in MATMUL_PRECISIONS:
            raise ValueError(f"tiger.edit: matmul_precision must be one of {', '.join(MATMUL_PRECISIONS)}, "
                             f"got {self.matmul_precision!r}")
        if self.fp8_fast_accum and self.matmul_precision != "fp8":
            raise ValueError("tiger.edit: fp8_fast_accum=True needs matmul_precision='fp8'")

    @classmethod
    def from_spec(cls, spec: str) -> "ModelKernels":
        """Kernels from ``"field=value,..."`` (values ``on``/``off``/``auto`` for the switches, the
        name for ``matmul_precision``), the other fields at their defaults: ``""`` is the default."""
        switches = {f.name for f in dataclasses.fields(cls)} - {"matmul_precision"}
        values: dict[str, Any] = {}
        for item in filter(None, (part.strip() for part in spec.split(","))):
            name, _, value = item.partition("=")
            if name == "matmul_precision":
                values[name] = value
            elif name in switches and value in ("on", "off", "auto"):
                values[name] = {"on": True, "off": False, "auto": None}[value]
            else:
                raise ValueError(f"tiger.edit: model kernels take field=on|off|auto (fields: "
                                 f"{', '.join(sorted(switches))}; matmul_precision=model|fp8), got {item!r}")
        return cls(**values)

    def settings(self) -> dict[str, Any]:
        """JSON record (None recorded as ``"auto"``)."""
        return {k: ("auto" if v is None else v) for k, v in dataclasses.asdict(self).items()}


def _on_cuda(module: torch.nn.Module) -> bool:
    p = next(module.parameters(), None)
    return p is not None and p.device.type == "cuda"


def _on_cuda_with_kernels(module: torch.nn.Module) -> bool:
    from tiger.ops import cuda_enabled

    return _on_cuda(module) and cuda_enabled()


def _resolve(setting: Optional[bool], default: bool) -> bool:
    """A :class:`ModelKernels` switch: ``default`` when None ("auto")."""
    return default if setting is None else bool(setting)


def fp8_supported(device: torch.device | str) -> tuple[bool, str]:
    """(whether ``torch._scaled_mm`` runs FP8 on ``device``, the reason when not)."""
    device = torch.device(device)
    if device.type != "cuda":
        return False, f"FP8 matmuls need a CUDA GPU with FP8 tensor cores; the models are on {device}"
    cap = torch.cuda.get_device_capability(device)
    if cap < (8, 9):
        return False, (f"FP8 matmuls need compute capability >= 8.9 (Ada, Hopper); "
                       f"{torch.cuda.get_device_name(device)} has {cap[0]}.{cap[1]}")
    return True, ""


# -- FP8 linear layers ----------------------------------------------------------------------------
class _RowsCache:
    """The last quantised input of an attention's q/k/v projections: they share one input (self-
    attention, or k and v of cross-attention), quantised once. Holds the input tensor itself, so
    identity (not an address that could be reused) decides a hit."""

    def __init__(self) -> None:
        self.key: Optional[torch.Tensor] = None
        self.rows: Optional[tuple[torch.Tensor, torch.Tensor]] = None

    def get(self, x: torch.Tensor) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
        return self.rows if self.key is x else None

    def put(self, x: torch.Tensor, rows: tuple[torch.Tensor, torch.Tensor]) -> None:
        self.key, self.rows = x, rows

    def clear(self) -> None:
        self.key = self.rows = None


def fp8_matmul(q: torch.Tensor, q_scale: torch.Tensor, weight: torch.Tensor, weight_scale: torch.Tensor,
               bias: Optional[torch.Tensor], out_dtype: torch.dtype, fast_accum: bool = False,
               emulate: bool = False) -> torch.Tensor:
    """``(q·q_scale) @ (weight·weight_scale)ᵀ + bias`` in ``out_dtype``.

    q [M, K], weight [N, K] float8_e4m3fn; q_scale [M, 1], weight_scale [1, N] float32; bias [N]
    (``out_dtype``) or None. On CUDA ``torch._scaled_mm`` (float32 accumulation, one rounding to
    ``out_dtype``); ``emulate``: the same operands dequantised and multiplied in float32 (the
    reference the CUDA test compares with)."""
    if emulate:
        y = dequantize_rows(q, q_scale) @ dequantize_rows(weight, weight_scale.t()).t()
        if bias is not None:
            y = y + bias.float()
        return y.to(out_dtype)
    return torch._scaled_mm(q, weight.t(), scale_a=q_scale, scale_b=weight_scale, bias=bias, out_dtype=out_dtype,
                            use_fast_accum=fast_accum)


class Fp8Linear(torch.nn.Module):
    """A frozen ``torch.nn.Linear`` (or a 1x1 ``Conv2d`` on channels-last maps) as an FP8 matmul.

    The weight [N, K] is quantised once per output channel (``weight_fp8`` float8_e4m3fn,
    ``weight_scale`` [1, N] float32); each call quantises its input per row
    (:func:`quantize_rows_fp8`) unless a shared cache already holds it. Output in the input's
    dtype. Forward only: the guidances' UNets run without gradients. The source layer is kept
    (not as a submodule) so :func:`set_matmul_precision` can put it back.
    """

    def __init__(self, source: torch.nn.Module, fast_accum: bool = False, emulate: bool = False) -> None:
        super().__init__()
        if isinstance(source, torch.nn.Conv2d):
            if source.kernel_size != (1, 1) or source.stride != (1, 1) or source.groups != 1 or source.padding != (0, 0):
                raise ValueError(f"tiger.edit: Fp8Linear takes a 1x1 convolution (stride 1, no padding, one group), "
                                 f"got {source}")
            weight = source.weight.detach().reshape(source.out_channels, source.in_channels)
        elif isinstance(source, torch.nn.Linear):
            weight = source.weight.detach()
        else:
            raise TypeError(f"tiger.edit: Fp8Linear takes a Linear or 1x1 Conv2d, got {type(source).__name__}")
        self.out_features, self.in_features = weight.shape
        if self.in_features % 16 or self.out_features % 16:
            raise ValueError(f"tiger.edit: FP8 matmuls need K and N divisible by 16, got a {self.in_features} -> "
                             f"{self.out_features} layer")
        self.conv = isinstance(source, torch.nn.Conv2d)
        wq, ws = quantize_rows_fp8(weight.contiguous())
        self.register_buffer("weight_fp8", wq, persistent=False)
        self.register_buffer("weight_scale", ws.t().contiguous(), persistent=False)  # [1, N]
        self.register_buffer("bias", None if source.bias is None else source.bias.detach(), persistent=False)
        self.fast_accum, self.emulate = bool(fast_accum), bool(emulate)
        self.rows_cache: Optional[_RowsCache] = None  # shared with the attention's other projections
        self.last_user = False  # drops the cache after use (v of q/k/v)
        self.__dict__["source"] = source  # not a submodule: no duplicate parameters

    def matmul_rows(self, q: torch.Tensor, scale: torch.Tensor, out_dtype: torch.dtype) -> torch.Tensor:
        """[M, N] from already quantised rows q [M, K], scale [M, 1]."""
        bias = None if self.bias is None else self.bias.to(out_dtype)
        return fp8_matmul(q, scale, self.weight_fp8, self.weight_scale, bias, out_dtype, self.fast_accum,
                          self.emulate)

    def _rows(self, x2: torch.Tensor, key: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        cache = self.rows_cache
        rows = None if cache is None else cache.get(key)
        if rows is None:
            rows = quantize_rows_fp8(x2)
            if cache is not None:
                cache.put(key, rows)
        if cache is not None and self.last_user:
            cache.clear()
        return rows

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled() and x.requires_grad:
            raise RuntimeError("tiger.edit: FP8 matmuls are forward-only (the guidances' UNets run without "
                               "gradients); use matmul_precision='model' to differentiate through the UNet")
        if self.conv:  # [N, C, H, W] channels-last: the pixels are rows of C channels
            n, c, h, w = x.shape
            rows = x.permute(0, 2, 3, 1).reshape(-1, c)
            y = self.matmul_rows(*self._rows(rows, x), x.dtype)
            return y.view(n, h, w, self.out_features).permute(0, 3, 1, 2)
        y = self.matmul_rows(*self._rows(x.reshape(-1, self.in_features), x), x.dtype)
        return y.view(*x.shape[:-1], self.out_features)

    def extra_repr(self) -> str:
        kind = "conv1x1" if self.conv else "linear"
        return f"{kind} {self.in_features} -> {self.out_features}, fast_accum={self.fast_accum}, emulate={self.emulate}"


def _fp8_targets(unet: torch.nn.Module) -> list[tuple[torch.nn.Module, str, Optional[_RowsCache], bool]]:
    """(parent, attribute, shared cache, last user) of every layer :func:`set_matmul_precision`
    converts: inside ``Transformer2DModel``s, the attention projections, the feed-forwards'
    linears and ``proj_in``/``proj_out``."""
    require_diffusers("FP8 matmuls")
    from diffusers.models.attention import FeedForward
    from diffusers.models.attention_processor import Attention
    from diffusers.models.transformers.transformer_2d import Transformer2DModel

    def convertible(layer: object) -> bool:
        src = layer.__dict__["source"] if isinstance(layer, Fp8Linear) else layer
        if type(src) is torch.nn.Linear:
            return True
        return type(src) is torch.nn.Conv2d and src.kernel_size == (1, 1) and src.stride == (1, 1) \
            and src.padding == (0, 0) and src.groups == 1

    targets = []
    for tr in unet.modules():
        if type(tr) is not Transformer2DModel:
            continue
        for name in ("proj_in", "proj_out"):
            if convertible(getattr(tr, name, None)):
                targets.append((tr, name, None, False))
        for m in tr.modules():
            if isinstance(m, Attention):
                cache = getattr(m, "_tiger_rows_cache", None) or _RowsCache()
                m._tiger_rows_cache = cache
                for name, last in (("to_q", False), ("to_k", False), ("to_v", True)):
                    if convertible(getattr(m, name, None)):
                        targets.append((m, name, cache, last))
                if convertible(m.to_out[0]):
                    targets.append((m.to_out, "0", None, False))
            elif type(m) is FeedForward and len(m.net) >= 3:
                # net: [GEGLU (or GELU) holding .proj, Dropout, Linear(, Dropout)]
                for layer_parent, name in ((m.net[0], "proj"), (m.net, "2")):
                    if convertible(getattr(layer_parent, name, None)):
                        targets.append((layer_parent, name, None, False))
    return targets


def set_matmul_precision(unet: torch.nn.Module, precision: str, *, fast_accum: bool = False,
                         emulate: bool = False) -> int:
    """Run the UNet's transformer-block matmuls in ``precision`` (``"model"`` or ``"fp8"``);
    returns how many layers are FP8 afterwards. ``"fp8"`` needs bfloat16 weights on a GPU with
    FP8 tensor cores (a clear ValueError otherwise) unless ``emulate`` (float32 emulation of the
    same quantisation: tests and CPU reference runs)."""
    if precision not in MATMUL_PRECISIONS:
        raise ValueError(f"tiger.edit: matmul_precision must be one of {', '.join(MATMUL_PRECISIONS)}, got {precision!r}")
    p = next(unet.parameters())
    if precision == "fp8" and not emulate:
        ok, why = fp8_supported(p.device)
        if not ok:
            raise ValueError(f"tiger.edit: matmul_precision='fp8' is not available: {why}; use 'model'")
        if p.dtype != torch.bfloat16:
            raise ValueError(f"tiger.edit: matmul_precision='fp8' needs bfloat16 models (row-scaled FP8 matmuls "
                             f"return bfloat16), got {p.dtype}")
    count = 0
    for parent, name, cache, last in _fp8_targets(unet):
        layer = parent._modules[name]
        source = layer.__dict__["source"] if isinstance(layer, Fp8Linear) else layer
        if precision == "model":
            parent._modules[name] = source
            continue
        if not (isinstance(layer, Fp8Linear) and layer.fast_accum == fast_accum and layer.emulate == emulate):
            layer = Fp8Linear(source, fast_accum=fast_accum, emulate=emulate)
        layer.rows_cache, layer.last_user = cache, last
        parent._modules[name] = layer
        count += 1
    if count:
        logger.info("%d UNet matmuls in FP8 (row-wise scales%s)", count, ", emulated" if emulate else "")
    return count


# -- fused GEGLU ----------------------------------------------------------------------------------
def _feed_forward_fused(self, hidden_states: torch.Tensor, *args: object, **kwargs: object) -> torch.Tensor:
    """diffusers 0.42's ``FeedForward`` (GEGLU, dropout, linear[, dropout]) with the GEGLU in one
    pass; an FP8 output layer gets the GEGLU's output quantised as it is computed."""
    proj, out = self.net[0].proj, self.net[2]
    y = proj(hidden_states)
    if isinstance(out, Fp8Linear):
        q, scale = quantize_rows_fp8(y.reshape(-1, y.shape[-1]), geglu=True)
        h = out.matmul_rows(q, scale, y.dtype).view(*y.shape[:-1], out.out_features)
    else:
        h = out(self.net[1](geglu(y)))
    for m in self.net[3:]:
        h = m(h)
    return h


def _fusable_feed_forward(ff: torch.nn.Module) -> bool:
    from diffusers.models.activations import GEGLU

    return (len(ff.net) in (3, 4) and type(ff.net[0]) is GEGLU and isinstance(ff.net[1], torch.nn.Dropout)
            and all(isinstance(m, torch.nn.Dropout) for m in ff.net[3:]))


def set_fused_geglu(unet: torch.nn.Module, on: bool) -> int:
    """Switch the UNet's GEGLU feed-forwards to the one-pass GEGLU (``on``) or diffusers' own;
    returns how many feed-forwards run fused afterwards."""
    require_diffusers("the fused GEGLU")
    from diffusers.models.attention import FeedForward

    return switch_forward(unet, lambda m: type(m) is FeedForward and _fusable_feed_forward(m), _feed_forward_fused, on)


# -- row LayerNorm --------------------------------------------------------------------------------
def _layer_norm_rows_forward(self, x: torch.Tensor) -> torch.Tensor:
    return layer_norm_rows(x, self.weight, self.bias, self.eps)


def set_row_layer_norm(unet: torch.nn.Module, on: bool) -> int:
    """Switch the UNet's LayerNorms (plain ``torch.nn.LayerNorm`` over one dimension, with a weight)
    to :func:`tiger.ops.layer_norm.layer_norm_rows` (``on``) or PyTorch's; returns how many run
    on tiger's op afterwards."""
    def eligible(m: torch.nn.Module) -> bool:
        return type(m) is torch.nn.LayerNorm and len(m.normalized_shape) == 1 and m.weight is not None

    return switch_forward(unet, eligible, _layer_norm_rows_forward, on)


# -- all of it ------------------------------------------------------------------------------------
def apply_model_kernels(unet: torch.nn.Module, vae: torch.nn.Module, kernels: ModelKernels, *,
                        emulate_fp8: bool = False) -> dict[str, Any]:
    """Put ``kernels`` on a guidance's models (idempotent; every setting reversible); returns what
    resolved: ``{"matmul_precision", "fp8_layers", "fused_geglu", "row_layer_norms", "subpixel_upsamples",
    "lean_attentions", "fused_transformer_blocks", "vae_downsample_4x4", "fold_norm_bias_blocks",
    "block_backward_blocks", "padded_conv_ins", "carry_conv_bias_encoders", "branch_prefix_blocks",
    "stacked_time_bias_blocks", "cached_text_kv_layers", "skip_concat_blocks", "row_softmax_layers",
    "head40_attention_layers"}``."""
    unet_kernels, vae_kernels = _on_cuda_with_kernels(unet), _on_cuda_with_kernels(vae)
    vae_cuda = _on_cuda(vae)
    geglu_on = _resolve(kernels.fused_geglu, unet_kernels)
    ds_on = _resolve(kernels.vae_downsample_4x4, vae_cuda)
    pad_on = _resolve(kernels.pad_conv_in, vae_cuda)
    fold_on = _resolve(kernels.fold_norm_bias, unet_kernels)
    fp8_layers = set_matmul_precision(unet, kernels.matmul_precision, fast_accum=kernels.fp8_fast_accum,
                                      emulate=emulate_fp8)
    set_fused_geglu(unet, geglu_on)
    row_norms = set_row_layer_norm(unet, _resolve(kernels.row_layer_norm, unet_kernels))
    subpixel = set_subpixel_upsample(unet, _resolve(kernels.subpixel_upsample, _on_cuda(unet)))
    lean = set_lean_attention(unet, _resolve(kernels.lean_attention, True))
    # after the matmul precision and the processors: FP8 layers and other processors are not fused
    fused_blocks = set_fused_transformer(unet, _resolve(kernels.fused_transformer, unet_kernels))
    padded = set_pad_conv_in(unet, pad_on) + set_pad_conv_in(vae, pad_on)
    set_downsample_4x4(vae, ds_on)
    folded = set_fold_norm_bias(unet, fold_on) + set_fold_norm_bias(vae, fold_on)
    own_backward = set_block_backward(vae, _resolve(kernels.block_backward, vae_kernels))
    carried = set_carry_conv_bias(vae, _resolve(kernels.carry_conv_bias, vae_kernels))
    prefix = set_branch_prefix(unet, _resolve(kernels.branch_prefix, True))
    # after the folded norms, the fused blocks and the processors they build on
    stacked = set_stacked_time_bias(unet, _resolve(kernels.stacked_time_bias, fold_on))
    text_kv = set_cached_text_kv(unet, _resolve(kernels.cached_text_kv, True))
    skip_concat = set_skip_concat(unet, _resolve(kernels.skip_concat, unet_kernels))
    row_softmax = set_row_softmax(vae, _resolve(kernels.row_softmax, vae_kernels))
    head40 = set_head40_attention(unet, _resolve(kernels.head40_attention, False))
    return {"matmul_precision": kernels.matmul_precision, "fp8_layers": fp8_layers, "fused_geglu": geglu_on,
            "row_layer_norms": row_norms, "subpixel_upsamples": subpixel, "lean_attentions": lean,
            "fused_transformer_blocks": fused_blocks, "vae_downsample_4x4": ds_on, "fold_norm_bias_blocks": folded,
            "block_backward_blocks": own_backward, "padded_conv_ins": padded, "carry_conv_bias_encoders": carried,
            "branch_prefix_blocks": prefix, "stacked_time_bias_blocks": stacked, "cached_text_kv_layers": text_kv,
            "skip_concat_blocks": skip_concat, "row_softmax_layers": row_softmax, "head40_attention_layers": head40}
