"""``tiger::attention_rows``: softmax attention over token rows (fake kernel and the function).
Kernels in ``csrc/attention/``.

The guidances' UNets hold q, k and v as token rows [batch·L, heads·D] (strided views of one
q/k/v matmul). InstructPix2Pix's 64² self-attentions have 8 heads of D = 40 over L = 4096 tokens,
a shape cuDNN's SDPA runs at ~0.9 ms on an H100 (padding the head dim to 64). The CUDA kernel here
(compute capability 9.0, bf16, D = 40, L a multiple of 128) multiplies at head dim 48 / 40 with
warpgroup MMAs, several warpgroups of a CTA sharing each key / value tile; measured 0.90-0.92 ms
for that layer, level with cuDNN's 0.91 and no faster in the guidance step, so the guidances keep
cuDNN's SDPA by default
(:class:`tiger.edit.guidance.model_kernels.ModelKernels` ``head40_attention``). Every other case, and the
CPU, computes the reference: float32 (float64 for float64) products and softmax, rounded once.

Forward only (the guidances run their UNets without autograd).
"""
from __future__ import annotations

from typing import Optional

import torch

__all__ = ["SCHEDULES", "attention_rows"]

# The CUDA kernel's schedules and the warpgroups (64 query rows each) a CTA of each may have.
SCHEDULES = {"producer": (2, 3), "lockstep": (1, 2, 3, 4)}


@torch.library.register_fake("tiger::attention_rows")
def _fake(q, k, v, batch, heads, scale=None, schedule="producer", warpgroups=3):
    torch._check(q.dim() == 2, lambda: f"tiger.attention_rows: q must be [batch·L, heads·D], got {tuple(q.shape)}")
    torch._check(k.shape == q.shape and v.shape == q.shape,
                 lambda: "tiger.attention_rows: k and v must have q's shape")
    return q.new_empty(q.shape)


def attention_rows(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, batch: int, heads: int,
                   scale: Optional[float] = None, schedule: str = "producer", warpgroups: int = 3) -> torch.Tensor:
    """Self-attention of ``batch`` sequences over token rows, all heads at once.

    Args:
        q, k, v: [batch·L, heads·D] floating point (bf16 for the CUDA kernel), one device and
            dtype; rows of sequence b are b·L … b·L + L − 1, head h the columns h·D … h·D + D − 1.
            Strided rows are fine (views of a stacked q/k/v matmul); the kernel needs unit column
            stride and 16-byte aligned rows (else the reference runs).
        batch: number of sequences; heads: number of heads.
        scale: the softmax's scale; None: 1/sqrt(D) (SDPA's default).
        schedule, warpgroups: the CUDA kernel's variant (:data:`SCHEDULES`): ``"producer"`` (a
            producer warpgroup fills four key / value stages behind mbarriers and hands its
            registers to the consumer warpgroups, which run free of each other, overlap a tile's
            softmax with the previous tile's PV and take a quarter of the exponentials on the FMA
            pipes: values differ from the lockstep schedule's within bf16 rounding) or ``"lockstep"`` (every thread copies, a CTA-wide barrier per key
            tile), with 64·warpgroups query rows a CTA sharing each key / value tile. The default
            is the fastest measured (docs/BENCHMARKS.md, "Head-dim-40 attention"). Within a
            schedule every warpgroup count gives the same values.

    Returns:
        [batch·L, heads·D] contiguous, q's dtype: row (b, t), head h holds
        ``softmax(q_bth · k_bh·ᵀ · scale) · v_bh``.

    Example:
        >>> q = torch.zeros(4, 2); v = torch.arange(8.0).reshape(4, 2)
        >>> attention_rows(q, q, v, batch=1, heads=1)[0].tolist()  # equal weights: the mean of v
        [3.0, 4.0]
    """
    if schedule not in SCHEDULES or int(warpgroups) not in SCHEDULES[schedule]:
        raise ValueError(f"tiger.attention_rows: (schedule, warpgroups) must be one of "
                         f"{[(k, w) for k, ws in SCHEDULES.items() for w in ws]}, got ({schedule!r}, {warpgroups})")
    if torch.is_grad_enabled() and any(t.requires_grad for t in (q, k, v)):
        raise RuntimeError("tiger.attention_rows: forward only (no autograd formula); call it under "
                           "torch.no_grad() or use torch.nn.functional.scaled_dot_product_attention")
    return torch.ops.tiger.attention_rows(q, k, v, int(batch), int(heads), scale, schedule, int(warpgroups))
