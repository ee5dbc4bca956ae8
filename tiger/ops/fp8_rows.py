"""``tiger::quantize_rows_fp8`` and ``tiger::geglu`` (fake kernels, GEGLU's autograd, the
functions). Kernels in ``csrc/fp8_rows/``.

FP8 matmuls (``torch._scaled_mm`` on Hopper) take float8_e4m3fn operands and float32 scales.
The activations of a frozen diffusion UNet are quantised per call with one scale per row
(token): :func:`quantize_rows_fp8` computes each row's max |value| on the device and writes the
scaled e4m3 bytes in one pass (no host synchronisation: CUDA-graph capturable). With
``geglu=True`` it quantises a GEGLU's output ``a·gelu(g)`` computed on the fly from the [M, 2F]
projection, so the feed-forward's hidden activations are never written in 16 bits.
:func:`geglu` is the same GEGLU without quantisation (one pass instead of diffusers' chunk,
gelu and multiply passes).
"""
from __future__ import annotations

import torch

__all__ = ["E4M3_MAX", "dequantize_rows", "geglu", "quantize_rows_fp8"]

E4M3_MAX = 448.0  # largest finite float8_e4m3fn


@torch.library.register_fake("tiger::quantize_rows_fp8")
def _fake_quantize(x, geglu=False):
    cols = x.shape[1] // 2 if geglu else x.shape[1]
    return (x.new_empty((x.shape[0], cols), dtype=torch.float8_e4m3fn),
            x.new_empty((x.shape[0], 1), dtype=torch.float32))


@torch.library.register_fake("tiger::geglu")
def _fake_geglu(x):
    return x.new_empty((*x.shape[:-1], x.shape[-1] // 2))


def _geglu_setup_context(ctx, inputs, output):
    ctx.save_for_backward(inputs[0])


def _geglu_backward(ctx, grad_y):
    (x,) = ctx.saved_tensors
    acc = torch.float64 if x.dtype == torch.float64 else torch.float32
    a, g = x.to(acc).chunk(2, dim=-1)
    gy = grad_y.to(acc)
    cdf = 0.5 * (1.0 + torch.erf(g * 0.5 ** 0.5))
    pdf = torch.exp(-0.5 * g * g) * (2.0 * torch.pi) ** -0.5
    return torch.cat([gy * g * cdf, gy * a * (cdf + g * pdf)], dim=-1).to(x.dtype)


torch.library.register_autograd("tiger::geglu", _geglu_backward, setup_context=_geglu_setup_context)


def quantize_rows_fp8(x: torch.Tensor, geglu: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Row-wise float8_e4m3fn quantisation of a matmul's left operand.

    Args:
        x: [M, K] float32/bfloat16/float16 (float64 on the CPU); with ``geglu`` K = 2F, the value
            half first and the gate half second (diffusers' ``GEGLU`` projection output).
        geglu: quantise ``h = x[:, :F]·gelu(x[:, F:])`` (exact erf GELU, float) instead of x.

    Returns:
        (q [M, K'] float8_e4m3fn, scale [M, 1] float32) with K' = F or K: per row ``amax = max |h|``,
        ``scale = amax / 448``, ``q = e4m3(h·(448 / amax))`` rounded to nearest even, saturating
        (``scale = 1``, q = 0 for an all-zero row), so ``h ≈ q·scale`` within e4m3's 2^-4 relative
        rounding. Not differentiable (the guidances' UNets run without gradients).
    """
    return torch.ops.tiger.quantize_rows_fp8(x, bool(geglu))


def dequantize_rows(q: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """float32 ``q·scale`` ([M, K] float8, [M, 1] or [1, K] float32): the values a scaled matmul sees."""
    return q.float() * scale


def geglu(x: torch.Tensor) -> torch.Tensor:
    """``x[..., :F]·gelu(x[..., F:])`` for x [..., 2F] (exact erf GELU), in float and rounded once to
    x's dtype; differentiable. diffusers' ``GEGLU`` computes the same after its projection."""
    return torch.ops.tiger.geglu(x)
