"""Every folded ResNet block's time-embedding bias of one UNet call from one matmul
(:class:`~tiger.edit.guidance.model_kernels.ModelKernels` field ``stacked_time_bias``).

A folded ``ResnetBlock2D`` (:mod:`.fused_norms` with ``fold_norm_bias``) adds
``conv1.bias + time_emb_proj(silu(temb))`` inside norm2 as a float32 [N, C] input bias. Computed
block by block that is five small launches per block (SiLU, the projection, two casts, the sum):
about 110 launches per call of a Stable Diffusion UNet's 22 blocks, each a few microseconds of a
nearly idle GPU on the step's critical path. All blocks receive the same ``temb``, so the UNet's
projections are stacked into one [ΣC, E] weight: one SiLU, one matmul and one float32 sum give
every block's bias as a column slice of an [N, ΣC] matrix, which tiger's GroupNorm reads in place
(its ``input_bias`` rows may be strided). Same operations per element: the projection rounded to
the model's dtype, then the float32 sum with conv1's bias, as the block computes it.

The stacked weights are derived from the blocks' parameters and derived again when one changes in
place (its version counter) or the model moves to another device or dtype. The result is kept
for the ``temb`` tensor it was computed from (the UNet passes one tensor to every block; the
shared branch prefix passes a compacted copy to its first block, hence two entries), and never
reused across a CUDA-graph capture boundary: a capture computes its own, so a replayed step
always projects its own ``temb``. With gradients needed (a ``temb`` or a parameter that
requires grad) the block computes its own bias as before.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from .cuda_graph import capturing
from .fused_norms import TIME_BIAS_KEY as _KEY, SiLUThenLinear, folds_norm_bias

__all__ = ["StackedTimeBias", "set_stacked_time_bias"]

_ENTRIES = 2  # the full batch's temb and the branch prefix's compacted one


@dataclass
class _Stacked:
    sources: tuple[torch.Tensor, ...]
    versions: tuple[int, ...]
    weight: torch.Tensor      # [ΣC, E], the projections' weights stacked (model dtype)
    proj_bias: torch.Tensor   # [ΣC], their biases (model dtype; zeros where absent)
    conv_bias: torch.Tensor   # [ΣC], conv1's biases in float32 (float64 for float64 models)


class StackedTimeBias:
    """The time-embedding biases of a UNet's folded ResNet blocks, computed together (module
    docstring). ``blocks`` share the projection's input width."""

    def __init__(self, blocks: list[torch.nn.Module]) -> None:
        self.blocks = blocks
        self.offsets: dict[int, tuple[int, int]] = {}
        start = 0
        for b in blocks:
            c = b.time_emb_proj.out_features
            self.offsets[id(b)] = (start, start + c)
            start += c
        self.width = start
        self._stacked = self._derive()
        self._entries: list[tuple[torch.Tensor, int, bool, torch.Tensor]] = []  # (temb, version, captured, [N, ΣC])

    def _sources(self) -> tuple[torch.Tensor, ...]:
        return tuple(p for b in self.blocks for p in (b.time_emb_proj.weight, b.time_emb_proj.bias, b.conv1.bias)
                     if p is not None)

    def _derive(self) -> _Stacked:
        with torch.no_grad():
            w0 = self.blocks[0].time_emb_proj.weight
            acc = torch.float64 if w0.dtype == torch.float64 else torch.float32
            weight = torch.cat([b.time_emb_proj.weight for b in self.blocks])
            zeros = lambda b, dt: torch.zeros(b.time_emb_proj.out_features, dtype=dt, device=w0.device)  # noqa: E731
            proj_bias = torch.cat([b.time_emb_proj.bias if b.time_emb_proj.bias is not None else zeros(b, w0.dtype)
                                   for b in self.blocks])
            conv_bias = torch.cat([b.conv1.bias.to(acc) if b.conv1.bias is not None else zeros(b, acc)
                                   for b in self.blocks])
            sources = self._sources()
            return _Stacked(sources, tuple(p._version for p in sources), weight, proj_bias, conv_bias)

    def _current(self) -> _Stacked:
        s = self._stacked
        w = self.blocks[0].time_emb_proj.weight
        sources = self._sources()
        if (len(sources) != len(s.sources) or any(a is not b for a, b in zip(sources, s.sources))
                or s.versions != tuple(p._version for p in sources) or s.weight.device != w.device
                or s.weight.dtype != w.dtype):
            self._stacked = s = self._derive()
            self._entries.clear()
        return s

    def input_bias(self, block: torch.nn.Module, temb: torch.Tensor, n: int) -> Optional[torch.Tensor]:
        """norm2's input bias of ``block`` for ``temb`` [N or 1, E] and a batch of ``n``: a float32
        [n, C] view of the stacked biases, or None where the block must compute its own
        (gradients needed, another dtype, device or width)."""
        span = self.offsets.get(id(block))
        w = block.time_emb_proj.weight
        if (span is None or temb.dim() != 2 or temb.shape[1] != w.shape[1] or temb.shape[0] not in (1, n)
                or temb.dtype != w.dtype or temb.device != w.device):
            return None
        if torch.is_grad_enabled() and (temb.requires_grad or any(p.requires_grad for p in self._sources())):
            return None
        in_capture = capturing(temb)
        out = None
        for t, version, captured, biases in self._entries:  # the blocks after the first of a call
            if t is temb and version == temb._version and captured == in_capture:
                out = biases
                break
        if out is None:
            s = self._current()
            with torch.no_grad():
                out = torch.add(s.conv_bias, F.linear(F.silu(temb), s.weight, s.proj_bias))
            self._entries = [(temb, temb._version, in_capture, out)] + self._entries[:_ENTRIES - 1]
        a, b = span
        rows = out[:, a:b]
        return rows if rows.shape[0] == n else rows.expand(n, -1)


def set_stacked_time_bias(unet: torch.nn.Module, on: bool) -> int:
    """Give the UNet's folded ResNet blocks (``fold_norm_bias`` on) one :class:`StackedTimeBias`
    (``on``), or take it away; returns how many blocks share it. Blocks whose time projection is
    not the fused :class:`~.fused_norms.SiLUThenLinear` of the common width keep their own."""
    blocks = [m for m in unet.modules() if _KEY in m.__dict__]
    for m in blocks:
        m.__dict__.pop(_KEY)
    if not on:
        return 0
    eligible = [m for m in unet.modules() if folds_norm_bias(m) and type(getattr(m, "time_emb_proj", None))
                is SiLUThenLinear]
    if not eligible:
        return 0
    width = eligible[0].time_emb_proj.in_features
    eligible = [m for m in eligible if m.time_emb_proj.in_features == width]
    shared = StackedTimeBias(eligible)
    for m in eligible:
        m.__dict__[_KEY] = shared
    return len(eligible)
