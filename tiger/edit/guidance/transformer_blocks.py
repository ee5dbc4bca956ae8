"""The guidances' UNet transformer layers: the lean attention processor and the fused transformer
blocks (:class:`~tiger.edit.guidance.model_kernels.ModelKernels` fields ``lean_attention`` and
``fused_transformer``).

A diffusers ``BasicTransformerBlock`` (LayerNorm, self-attention, LayerNorm, cross-attention,
LayerNorm, GEGLU feed-forward, each sub-layer added to the residual stream) spends a quarter of its
non-attention time on three residual adds, each a full read of two token maps and a write of one.
The fused block (forward, without autograd) moves them into the output matmuls:

- the residual stream ``h`` is the matmul's accumulator: ``h += o · W_outᵀ`` (``addmm_``, one
  read and one write of ``h`` inside the GEMM);
- the attention outputs' biases, which that matmul cannot add, are carried instead of added: the
  next LayerNorm normalises ``h + b`` (:func:`tiger.ops.layer_norm.layer_norm_rows`'
  ``input_bias``), and the feed-forward's output matmul adds all of them with its own bias through
  one extra input column: the GEGLU projection gets 8 extra output pairs whose weights are zero
  and whose biases are (0.125, 8) for the first and (0, 0) for the others, so the GEGLU's extra
  outputs are ``0.125 · gelu(8) = 1`` (erf(8/√2) is 1 in float32) and zeros, and the output
  matmul's extra column holds ``b_ff + b_attn1 + b_attn2``. The block's output is the residual
  stream with every bias added, as diffusers computes it;
- the self-attention's q, k, v come from one matmul on stacked weights (and the cross-attention's
  k, v from one on the text), read as strided views by SDPA;
- MVDream's multi-view self-attention (the F views of a sample attend jointly) is SDPA on B/F
  rows of F·L tokens: a group's rows are adjacent, so no reshape copies;
- in a whole fused ``Transformer2DModel`` (with :mod:`.fused_norms`' output) the last block does
  not add its three biases at all: they go into ``proj_out``'s bias as ``W·B + b`` (the
  projection is linear), so that block's feed-forward matmuls keep their own shapes (N = 2F,
  K = F: the extra pairs cost 10-20 % of those GEMMs at 64² on an H100) and the extra-pair
  weights are never made for it (every transformer of these UNets has one block).

Same sums; the roundings differ: each residual sum is rounded once instead of twice, and the
summed biases are rounded once to the model's dtype. The derived weights are built once from the
block's (frozen) weights and rebuilt when a source parameter changes in place (its version
counter: ``load_state_dict`` and ``param.add_`` count, writes through ``param.data`` do not) or
the block moves to another device or dtype. The
block writes its output into its input tensor (the UNet's transformer passes each block a map it
owns and never reads again); with gradients enabled, in training mode, with masks or other
arguments, or on a block whose derived weights are elsewhere, diffusers' forward runs.
"""
from __future__ import annotations

import types
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from tiger.ops.attention import attention_rows
from tiger.ops.fp8_rows import geglu
from tiger.ops.layer_norm import layer_norm_rows
from tiger.utils.lazy import require_diffusers

from .fused_norms import _continuous_output_keep_layout
from .mvdream_attention import MultiViewAttnProcessor
from .text_kv import memo_text_kv

__all__ = ["LeanAttnProcessor", "extra_pair_weights", "fused_blocks_output", "fused_cross_feed_forward", "fused_derived",
           "fused_self_attention",
           "set_cached_text_kv", "set_fused_transformer", "set_head40_attention",
           "set_lean_attention"]

# The GEGLU projection's extra outputs: pairs (a, g) giving a · gelu(g) = 1, then 0 (one 16-byte
# vector of bfloat16 per half, so rows stay aligned).
_EXTRA = 8
_ONE_A, _ONE_G = 0.125, 8.0
_CACHED_TEXT_KV = "_tiger_cached_text_kv"
_HEAD40 = "_tiger_head40_attention"


# -- lean attention -------------------------------------------------------------------------------
class LeanAttnProcessor:
    """diffusers 0.42's ``AttnProcessor2_0`` for the layers these UNets have (token input [B, L, C],
    no mask, no norms, no residual, output factor 1): q/k/v projections, SDPA (its default scale,
    as diffusers), output projection and dropout, without the division by
    ``rescale_output_factor`` = 1 that costs a pass over every attention output. Anything else
    goes to the processor it replaced (``fallback``)."""

    def __init__(self, fallback) -> None:
        self.fallback = fallback
        self.cache_text = False  # cross-attention keys/values kept on the text (:mod:`.text_kv`)

    @staticmethod
    def plain(attn) -> bool:
        """Whether the layer has none of the features this processor leaves to diffusers."""
        return (attn.spatial_norm is None and attn.group_norm is None and not attn.norm_cross
                and attn.norm_q is None and attn.norm_k is None and not attn.residual_connection
                and attn.rescale_output_factor == 1.0)

    @classmethod
    def handles(cls, attn, hidden_states: torch.Tensor, attention_mask, args: tuple, kwargs: dict) -> bool:
        return (attention_mask is None and hidden_states.ndim == 3 and not args and kwargs.get("scale") is None
                and cls.plain(attn))

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states: Optional[torch.Tensor] = None,
                 attention_mask: Optional[torch.Tensor] = None, temb: Optional[torch.Tensor] = None,
                 *args: object, **kwargs: object) -> torch.Tensor:
        if not self.handles(attn, hidden_states, attention_mask, args, kwargs):
            return self.fallback(attn, hidden_states, encoder_hidden_states, attention_mask, temb, *args, **kwargs)
        b = hidden_states.shape[0]
        q = attn.to_q(hidden_states).flatten(0, 1)
        if encoder_hidden_states is None:
            k, v = attn.to_k(hidden_states).flatten(0, 1), attn.to_v(hidden_states).flatten(0, 1)
        else:
            k, v = self._text_kv(attn, encoder_hidden_states)
        out = _attend(attn, q, k, v, b).unflatten(0, (b, -1))
        return attn.to_out[1](attn.to_out[0](out))

    def _text_kv(self, attn, text: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # only plain linear projections are kept (an FP8 layer's weights are its own)
        keep = self.cache_text and type(attn.to_k) is torch.nn.Linear and type(attn.to_v) is torch.nn.Linear
        weights = [attn.to_k.weight, attn.to_k.bias, attn.to_v.weight, attn.to_v.bias] if keep else []
        return memo_text_kv(attn, text, weights, lambda: (attn.to_k(text).flatten(0, 1), attn.to_v(text).flatten(0, 1)),
                            keep)


def set_lean_attention(unet: torch.nn.Module, on: bool) -> int:
    """Put :class:`LeanAttnProcessor` in front of the UNet's SDPA attention processors (also inside
    MVDream's multi-view processor) (``on``), or take it away; returns how many layers have it."""
    diffusers = require_diffusers("the lean attention")
    sdpa = diffusers.models.attention_processor.AttnProcessor2_0
    from diffusers.models.attention_processor import Attention

    count = 0
    for m in unet.modules():
        if not isinstance(m, Attention):
            continue
        proc = m.processor
        wraps = type(getattr(proc, "inner", None)) in (sdpa, LeanAttnProcessor)  # MVDream's multi-view processor
        holder, attr = (proc, "inner") if wraps else (m, "processor")
        current = getattr(holder, attr)
        if on and type(current) is sdpa:
            setattr(holder, attr, LeanAttnProcessor(current))
        elif not on and type(current) is LeanAttnProcessor:
            setattr(holder, attr, current.fallback)
        count += type(getattr(holder, attr)) is LeanAttnProcessor
    return count


# -- fused transformer blocks ---------------------------------------------------------------------
@dataclass
class _Derived:
    """A fused block's weights, derived from its parameters (``sources``, at ``versions``)."""

    sources: tuple[torch.Tensor, ...]
    versions: tuple[int, ...]
    qkv_weight: torch.Tensor            # [3I, C]: attn1's to_q, to_k, to_v stacked
    qkv_bias: Optional[torch.Tensor]    # [3I] or None
    kv_weight: torch.Tensor             # [2I, D]: attn2's to_k, to_v stacked (D: the text's width)
    kv_bias: Optional[torch.Tensor]
    norm2_shift: torch.Tensor           # [C]: attn1's output bias, carried into norm2
    norm3_shift: torch.Tensor           # [C]: attn1's + attn2's output biases, carried into norm3
    carried: torch.Tensor               # [C] float32 (float64): b_ff + b_attn1 + b_attn2
    # (proj_weight [2(F + 8), C], proj_bias [2(F + 8)], out_weight [C, F + 8]): the feed-forward with
    # the extra pairs and the biases' column, made on first use (a carrying transformer's last
    # block never uses them: :func:`extra_pair_weights`)
    extra_pairs: Optional[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = None


def _linear_parts(layer: torch.nn.Linear) -> tuple[torch.Tensor, torch.Tensor]:
    bias = layer.bias if layer.bias is not None else torch.zeros_like(layer.weight[:, 0])
    return layer.weight, bias


def _stack(layers: list[torch.nn.Linear]) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    weight = torch.cat([m.weight for m in layers])
    if all(m.bias is None for m in layers):
        return weight, None
    return weight, torch.cat([_linear_parts(m)[1] for m in layers])


def _sources(block) -> tuple[torch.Tensor, ...]:
    a1, a2, ff = block.attn1, block.attn2, block.ff
    layers = [a1.to_q, a1.to_k, a1.to_v, a1.to_out[0], a2.to_k, a2.to_v, a2.to_out[0], ff.net[0].proj, ff.net[2]]
    return tuple(p for m in layers for p in (m.weight, m.bias) if p is not None)


def _derive(block) -> _Derived:
    """The fused block's weights from ``block``'s (module docstring), in the weights' dtype; the
    summed biases are added in float32 (float64 for float64) and rounded once."""
    a1, a2, ff = block.attn1, block.attn2, block.ff
    with torch.no_grad():
        qkv_w, qkv_b = _stack([a1.to_q, a1.to_k, a1.to_v])
        kv_w, kv_b = _stack([a2.to_k, a2.to_v])
        b1, b2 = _linear_parts(a1.to_out[0])[1], _linear_parts(a2.to_out[0])[1]
        out_b = _linear_parts(ff.net[2])[1]
        acc = torch.float64 if out_b.dtype == torch.float64 else torch.float32
        sources = _sources(block)
        return _Derived(
            sources=sources, versions=tuple(p._version for p in sources),
            qkv_weight=qkv_w, qkv_bias=qkv_b, kv_weight=kv_w, kv_bias=kv_b,
            norm2_shift=b1.clone(), norm3_shift=(b1.to(acc) + b2.to(acc)).to(b1.dtype),
            carried=out_b.to(acc) + b1.to(acc) + b2.to(acc))


def extra_pair_weights(block, d: _Derived) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The feed-forward of a block that adds its own biases (module docstring): the GEGLU
    projection with 8 extra output pairs, (weight [2(F + 8), C], bias [2(F + 8)]), and the
    output matmul's weight [C, F + 8] whose first extra column holds ``d.carried`` rounded once
    to the weights' dtype. Made on first use and kept with ``d`` (not while a CUDA graph
    captures)."""
    if d.extra_pairs is not None:
        return d.extra_pairs
    ff = block.ff
    with torch.no_grad():
        proj_w, proj_b = _linear_parts(ff.net[0].proj)
        out_w = ff.net[2].weight
        f, c = out_w.shape[1], proj_w.shape[1]
        zeros = proj_w.new_zeros(_EXTRA, c)
        pair_a, pair_g = proj_b.new_zeros(_EXTRA), proj_b.new_zeros(_EXTRA)
        pair_a[0], pair_g[0] = _ONE_A, _ONE_G
        bias_columns = out_w.new_zeros(out_w.shape[0], _EXTRA)
        bias_columns[:, 0] = d.carried.to(out_w.dtype)
        weights = (torch.cat([proj_w[:f], zeros, proj_w[f:], zeros]), torch.cat([proj_b[:f], pair_a, proj_b[f:], pair_g]),
                   torch.cat([out_w, bias_columns], dim=1).contiguous())
    if not (out_w.is_cuda and torch.cuda.is_current_stream_capturing()):
        d.extra_pairs = weights
    return weights


def _derived(block) -> _Derived:
    """The block's derived weights, derived again when a parameter changed in place (its version
    counter) or the block moved to another device or dtype."""
    d = block.__dict__["_tiger_fused_weights"]
    w = block.attn1.to_q.weight
    if (d.versions != tuple(p._version for p in d.sources) or d.qkv_weight.device != w.device
            or d.qkv_weight.dtype != w.dtype):
        d = block.__dict__["_tiger_fused_weights"] = _derive(block)
    return d


def _joint_views(attn) -> int:
    """How many consecutive batch rows ``attn`` attends over jointly: MVDream's multi-view
    processor (:class:`.mvdream_attention.MultiViewAttnProcessor`) its ``num_views``, else 1."""
    return int(getattr(attn.processor, "num_views", 1))


def _plain_processor(attn) -> bool:
    """diffusers' SDPA processor or :class:`LeanAttnProcessor`, directly or inside MVDream's
    multi-view processor (which only regroups the rows around it)."""
    from diffusers.models.attention_processor import AttnProcessor2_0

    proc = attn.processor
    if type(proc) is MultiViewAttnProcessor:
        proc = proc.inner
    return type(proc) in (AttnProcessor2_0, LeanAttnProcessor)


def _heads(t: torch.Tensor, b: int, heads: int) -> torch.Tensor:
    """[B·L, heads·d] (a strided view is fine) → [B, heads, L, d] view."""
    return t.unflatten(-1, (heads, -1)).unflatten(0, (b, -1)).transpose(1, 2)


def _attend(attn, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, b: int) -> torch.Tensor:
    """SDPA over [B·L, I] token rows (strided views allowed) → [B·L, I] (a view of SDPA's output);
    a self-attention marked by :func:`set_head40_attention` runs :func:`tiger.ops.attention.attention_rows`
    (which takes head dim 40 on an H100 and computes the reference otherwise)."""
    if attn.__dict__.get(_HEAD40) and k.shape[0] == q.shape[0] and not torch.is_grad_enabled():
        return attention_rows(q, k, v, b, attn.heads)
    out = F.scaled_dot_product_attention(_heads(q, b, attn.heads), _heads(k, b, attn.heads), _heads(v, b, attn.heads),
                                         dropout_p=0.0, is_causal=False)
    return out.transpose(1, 2).reshape(q.shape[0], -1)


def fused_derived(block, x: torch.Tensor, encoder_hidden_states: Optional[torch.Tensor], attention_mask=None,
                  encoder_attention_mask=None, timestep=None, cross_attention_kwargs=None, class_labels=None,
                  added_cond_kwargs=None) -> Optional[_Derived]:
    """The derived weights when ``block`` can run fused on this call (a plain call: fused block,
    no gradients, eval mode, no masks or extra arguments, contiguous [B, L, C] tokens and text in
    the weights' dtype and device), else None (diffusers' forward runs)."""
    plain_call = ("_tiger_fused_weights" in block.__dict__ and not torch.is_grad_enabled() and not block.training
                  and attention_mask is None and encoder_attention_mask is None and timestep is None
                  and class_labels is None and not cross_attention_kwargs and not added_cond_kwargs
                  and encoder_hidden_states is not None and x.ndim == 3 and x.is_contiguous())
    d = _derived(block) if plain_call else None
    if (d is None or x.dtype != d.qkv_weight.dtype or x.device != d.qkv_weight.device
            or encoder_hidden_states.dtype != x.dtype or x.shape[0] % _joint_views(block.attn1)):
        return None  # (a batch of partial view groups: diffusers' forward, whose processor says why)
    return d


def fused_self_attention(block, d: _Derived, x: torch.Tensor) -> torch.Tensor:
    """The fused block's first half on tokens ``x`` [B, L, C], in place: norm1, self-attention and
    its output matmul accumulated into the residual stream (attn1's bias carried, not added). A
    multi-view self-attention (MVDream: F views of a sample in consecutive rows) attends over the
    F·L tokens of each group: the group's rows are adjacent in ``x``, so that is SDPA on B/F
    rows of F·L tokens, what its processor computes by reshaping."""
    b, c = x.shape[0], x.shape[-1]
    h = x.view(-1, c)
    n = layer_norm_rows(h, block.norm1.weight, block.norm1.bias, block.norm1.eps)
    q, k, v = F.linear(n, d.qkv_weight, d.qkv_bias).chunk(3, dim=-1)
    h.addmm_(_attend(block.attn1, q, k, v, b // _joint_views(block.attn1)), block.attn1.to_out[0].weight.t())
    return x


def fused_cross_feed_forward(block, d: _Derived, x: torch.Tensor, encoder_hidden_states: torch.Tensor,
                             carry: bool = False) -> torch.Tensor:
    """The fused block's second half on ``x`` [B, L, C] (the first half's output), in place:
    norm2 with attn1's bias, cross-attention on ``encoder_hidden_states`` [B, T, D], norm3 with both
    attention biases, the GEGLU feed-forward whose output matmul adds every carried bias; with
    ``carry`` the feed-forward is the block's own (no extra pair, no bias column) and the result
    lacks ``d.carried`` [C], which the caller adds (:func:`fused_blocks_output`)."""
    b, c = x.shape[0], x.shape[-1]
    h = x.view(-1, c)
    a2 = block.attn2
    n = layer_norm_rows(h, block.norm2.weight, block.norm2.bias, block.norm2.eps, input_bias=d.norm2_shift)
    text = encoder_hidden_states.reshape(-1, encoder_hidden_states.shape[-1])
    k, v = memo_text_kv(block, encoder_hidden_states, [d.kv_weight, d.kv_bias],
                        lambda: F.linear(text, d.kv_weight, d.kv_bias).chunk(2, dim=-1),
                        block.__dict__.get(_CACHED_TEXT_KV, False))
    h.addmm_(_attend(a2, a2.to_q(n), k, v, b), a2.to_out[0].weight.t())
    n = layer_norm_rows(h, block.norm3.weight, block.norm3.bias, block.norm3.eps, input_bias=d.norm3_shift)
    if carry:  # even GEMM shapes: N = 2F, K = F (the extra pairs cost 10-20 % at 64², H100)
        proj, out = block.ff.net[0].proj, block.ff.net[2]
        h.addmm_(geglu(F.linear(n, proj.weight, proj.bias)), out.weight.t())
    else:
        proj_weight, proj_bias, out_weight = extra_pair_weights(block, d)
        h.addmm_(geglu(F.linear(n, proj_weight, proj_bias)), out_weight.t())
    return x


# -- fused transformers: the last block's biases through proj_out ----------------------------------
_CARRY = "_tiger_carry_out"
_OUT_BIAS = "_tiger_out_bias"


def _carried_out_bias(tr, d: _Derived) -> torch.Tensor:
    """proj_out's bias plus its weights times the last block's carried biases
    (``proj_out(h + B) = W·h + (W·B + b)``: the projection is linear), summed in float32
    (float64) and rounded once to the weights' dtype; kept until a weight changes (version
    counters), not written while a CUDA graph captures."""
    po = tr.proj_out
    w = po.weight
    key = (w._version, None if po.bias is None else po.bias._version, w.device, w.dtype)
    hit = tr.__dict__.get(_OUT_BIAS)
    if hit is not None and hit[0] is d and hit[1] == key:
        return hit[2]
    with torch.no_grad():
        acc = d.carried.dtype
        bias = w.reshape(w.shape[0], -1).to(acc) @ d.carried
        if po.bias is not None:
            bias = bias + po.bias.to(acc)
        bias = bias.to(w.dtype)
    if not (w.is_cuda and torch.cuda.is_current_stream_capturing()):
        tr.__dict__[_OUT_BIAS] = (d, key, bias)
    return bias


def fused_blocks_output(tr, x: torch.Tensor, residual: torch.Tensor, encoder_hidden_states: torch.Tensor,
                        height: int, width: int, inner_dim: int, first_half_done: bool = False,
                        out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """A continuous-input ``Transformer2DModel``'s blocks on its tokens ``x`` [B, H·W, C] and its
    output (``proj_out`` and ``residual`` [B, C, H, W]). Fused blocks run in place; when the
    transformer carries (:func:`set_fused_transformer`), the last one leaves its three biases to
    ``proj_out``'s bias (:func:`_carried_out_bias`), so its feed-forward matmuls keep the block's
    own shapes. ``first_half_done``: the first block's self-attention half already ran on ``x``
    (:mod:`.branch_prefix`). ``out``: a tensor of the output's shape to write the output into (no
    gradient; :mod:`.skip_concat`)."""
    blocks = list(tr.transformer_blocks)
    carried = None
    for i, block in enumerate(blocks):
        d = fused_derived(block, x, encoder_hidden_states)
        if d is None:
            if i == 0 and first_half_done:
                raise RuntimeError("tiger.edit: the first transformer block's first half ran fused, its second cannot")
            x = block(x, encoder_hidden_states=encoder_hidden_states)
            continue
        if not (i == 0 and first_half_done):
            fused_self_attention(block, d, x)
        last = i == len(blocks) - 1 and tr.__dict__.get(_CARRY, False)
        fused_cross_feed_forward(block, d, x, encoder_hidden_states, carry=last)
        carried = d if last else None
    output = tr._get_output_for_continuous_inputs
    takes_out = getattr(output, "__func__", None) is _continuous_output_keep_layout
    kwargs = {} if out is None or not takes_out else {"out": out}
    if carried is not None:
        kwargs["out_bias"] = _carried_out_bias(tr, carried)
    y = output(x, residual, x.shape[0], height, width, inner_dim, **kwargs)
    return y if out is None or takes_out else out.copy_(y)


def _fused_transformer_forward(self, hidden_states: torch.Tensor, encoder_hidden_states: Optional[torch.Tensor] = None,
                               timestep=None, added_cond_kwargs=None, class_labels=None, cross_attention_kwargs=None,
                               attention_mask=None, encoder_attention_mask=None, return_dict: bool = True,
                               out: Optional[torch.Tensor] = None):
    """``Transformer2DModel.forward`` (diffusers 0.42, continuous input) through
    :func:`fused_blocks_output`; any other call runs diffusers' forward. ``out``: a tensor of the
    output's shape to write the output into (no gradient; :mod:`.skip_concat`)."""
    plain = (encoder_hidden_states is not None and timestep is None and added_cond_kwargs is None
             and class_labels is None and not cross_attention_kwargs and attention_mask is None
             and encoder_attention_mask is None and not torch.is_grad_enabled() and not self.training
             and hidden_states.ndim == 4)
    if not plain:
        y = type(self).forward(self, hidden_states, encoder_hidden_states, timestep, added_cond_kwargs, class_labels,
                               cross_attention_kwargs, attention_mask, encoder_attention_mask, return_dict)
        if out is not None:
            out.copy_(y[0] if isinstance(y, tuple) else y.sample)
            return (out,) if isinstance(y, tuple) else type(y)(sample=out)
        return y
    _, _, height, width = hidden_states.shape
    x, inner_dim = self._operate_on_continuous_inputs(hidden_states)
    y = fused_blocks_output(self, x.contiguous(), hidden_states, encoder_hidden_states, height, width, inner_dim,
                            out=out)
    if not return_dict:
        return (y,)
    from diffusers.models.modeling_outputs import Transformer2DModelOutput

    return Transformer2DModelOutput(sample=y)


def _carries(tr) -> bool:
    """Whether ``tr`` may run :func:`_fused_transformer_forward` with the carried biases: a
    continuous-input ``Transformer2DModel`` whose blocks are all fused, whose output is
    :mod:`.fused_norms`' (which takes ``out_bias``) and whose ``proj_out`` is linear (a linear
    layer, or a 1x1 convolution on the map)."""
    from diffusers.models.transformers.transformer_2d import Transformer2DModel

    if type(tr) is not Transformer2DModel or not tr.is_input_continuous or len(tr.transformer_blocks) == 0:
        return False
    out = tr.__dict__.get("_get_output_for_continuous_inputs")
    po = tr.proj_out
    linear = (type(po) is torch.nn.Linear if tr.use_linear_projection else
              type(po) is torch.nn.Conv2d and po.kernel_size == (1, 1) and po.stride == (1, 1)
              and po.padding == (0, 0) and po.groups == 1)
    return (linear and getattr(out, "__func__", None) is _continuous_output_keep_layout
            and all("_tiger_fused_weights" in b.__dict__ for b in tr.transformer_blocks))


def _fused_block_forward(self, hidden_states: torch.Tensor, attention_mask: Optional[torch.Tensor] = None,
                         encoder_hidden_states: Optional[torch.Tensor] = None,
                         encoder_attention_mask: Optional[torch.Tensor] = None, timestep=None,
                         cross_attention_kwargs=None, class_labels=None, added_cond_kwargs=None) -> torch.Tensor:
    """``BasicTransformerBlock.forward`` with the residual adds inside the output matmuls (module
    docstring); writes the result into ``hidden_states`` and returns it."""
    d = fused_derived(self, hidden_states, encoder_hidden_states, attention_mask, encoder_attention_mask,
                      timestep, cross_attention_kwargs, class_labels, added_cond_kwargs)
    if d is None:
        return type(self).forward(self, hidden_states, attention_mask, encoder_hidden_states, encoder_attention_mask,
                                  timestep, cross_attention_kwargs, class_labels, added_cond_kwargs)
    fused_self_attention(self, d, hidden_states)
    return fused_cross_feed_forward(self, d, hidden_states, encoder_hidden_states)


def _fusable(block) -> bool:
    """A plain self- plus cross-attention block with LayerNorms and a GEGLU feed-forward whose
    attentions run diffusers' SDPA processor or :class:`LeanAttnProcessor` (the self-attention
    also inside MVDream's multi-view processor)."""
    from diffusers.models.activations import GEGLU
    from diffusers.models.attention import BasicTransformerBlock

    if type(block) is not BasicTransformerBlock:
        return False
    a1, a2, ff = block.attn1, block.attn2, block.ff
    norms_plain = all(type(m) is torch.nn.LayerNorm and m.weight is not None and len(m.normalized_shape) == 1
                      for m in (block.norm1, block.norm2, block.norm3))

    def attention_plain(attn, cross: bool) -> bool:
        linear = all(type(m) is torch.nn.Linear for m in (attn.to_q, attn.to_k, attn.to_v, attn.to_out[0]))
        grouped = _joint_views(attn) > 1
        return (attn is not None and _plain_processor(attn) and linear and not (cross and grouped)
                and LeanAttnProcessor.plain(attn) and attn.is_cross_attention == cross
                and len(attn.to_out) == 2 and isinstance(attn.to_out[1], torch.nn.Dropout)
                and attn.to_out[0].out_features == attn.to_q.in_features)

    ff_plain = (ff is not None and len(ff.net) in (3, 4) and type(ff.net[0]) is GEGLU
                and type(ff.net[0].proj) is torch.nn.Linear and type(ff.net[2]) is torch.nn.Linear
                and isinstance(ff.net[1], torch.nn.Dropout)
                and all(isinstance(m, torch.nn.Dropout) for m in ff.net[3:]))
    return (block.norm_type == "layer_norm" and block.pos_embed is None and not block.only_cross_attention
            and block._chunk_size is None and not hasattr(block, "fuser") and norms_plain and ff_plain
            and attention_plain(a1, False) and a2 is not None and attention_plain(a2, True))


def set_fused_transformer(unet: torch.nn.Module, on: bool) -> int:
    """Give the UNet's plain ``BasicTransformerBlock`` s the fused forward (``on``; module
    docstring) or diffusers' again; returns how many blocks run fused afterwards. MVDream's
    multi-view self-attention fuses too (SDPA over each group of views); blocks whose attentions
    or feed-forward are anything else (FP8 layers, other processors) keep diffusers' forward."""
    require_diffusers("the fused transformer blocks")
    count = 0
    for m in unet.modules():
        fusable = on and _fusable(m)
        if fusable:
            if "_tiger_fused_weights" not in m.__dict__:
                m.__dict__["_tiger_fused_weights"] = _derive(m)
            m.forward = types.MethodType(_fused_block_forward, m)
            count += 1
        elif "_tiger_fused_weights" in m.__dict__:
            m.__dict__.pop("_tiger_fused_weights")
            m.__dict__.pop("forward", None)
    for m in unet.modules():  # after the blocks: a transformer carries only if all its blocks are fused
        carries = on and _carries(m)
        if carries:
            m.__dict__[_CARRY] = True
            m.forward = types.MethodType(_fused_transformer_forward, m)
        elif _CARRY in m.__dict__:
            for key in (_CARRY, _OUT_BIAS, "forward"):
                m.__dict__.pop(key, None)
    return count


def set_head40_attention(unet: torch.nn.Module, on: bool) -> int:
    """Run the UNet's self-attentions with head dim 40 (InstructPix2Pix's 64² layers: 8 heads of 40
    over 4096 tokens) by :func:`tiger.ops.attention.attention_rows` in the lean processor and the
    fused blocks (``on``), or by SDPA; returns how many layers it takes. Forward only: a call with
    gradients enabled runs SDPA. Opt-in (:class:`.model_kernels.ModelKernels` ``head40_attention``):
    on an H100 the kernel is level with cuDNN's SDPA for these layers (0.90-0.92 against 0.91 ms a
    12-row layer) and the CSD step no faster with it."""
    from diffusers.models.attention_processor import Attention

    count = 0
    for m in unet.modules():
        if not isinstance(m, Attention):
            continue
        m.__dict__.pop(_HEAD40, None)
        head_dim = m.to_q.out_features // m.heads if isinstance(m.to_q, torch.nn.Linear) else None
        if on and not m.is_cross_attention and head_dim == 40:
            m.__dict__[_HEAD40] = True
            count += 1
    return count


def set_cached_text_kv(unet: torch.nn.Module, on: bool) -> int:
    """Keep the cross-attentions' keys and values of a fixed text (:mod:`.text_kv`) in the UNet's
    fused transformer blocks and :class:`LeanAttnProcessor` cross-attentions (``on``), or compute
    them every call; returns how many cross-attentions keep them. Set after
    :func:`set_fused_transformer` and :func:`set_lean_attention`."""
    from diffusers.models.attention_processor import Attention

    count = 0
    fused_cross = set()
    for m in unet.modules():
        m.__dict__.pop(_CACHED_TEXT_KV, None)
        if on and "_tiger_fused_weights" in m.__dict__:
            m.__dict__[_CACHED_TEXT_KV] = True
            count += 1
            fused_cross.add(id(m.attn2))
    for m in unet.modules():
        if not isinstance(m, Attention):
            continue
        proc = m.processor
        lean = proc if type(proc) is LeanAttnProcessor else getattr(proc, "inner", None)
        if type(lean) is LeanAttnProcessor:
            lean.cache_text = bool(on) and m.is_cross_attention
            count += lean.cache_text and id(m) not in fused_cross
    return count
