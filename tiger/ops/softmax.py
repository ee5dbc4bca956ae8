"""``tiger::softmax_rows``: softmax over the last dimension (fake kernel, autograd, the function).
Kernels in ``csrc/softmax/``.

The guidances back-propagate through the VAE encoder's mid-block attention every step; its
single 512-wide head over 4096 tokens (512² renders) runs as two batched matmuls around a
softmax of [4, 4096, 4096] scores (:func:`tiger.edit.guidance.diffusers_models.matmul_vae_attention`),
where torch's CUDA softmax and its backward ran at about half of an H100's copy bandwidth. The
CUDA kernels here keep a row in one block's registers: one read and one write forward, two reads
and one write backward. Values as torch's softmax (float arithmetic, rounded once; the CPU runs
torch's own).
"""
from __future__ import annotations

import torch

__all__ = ["softmax_rows"]


@torch.library.register_fake("tiger::softmax_rows")
def _fake(x):
    return torch.empty_like(x, memory_format=torch.contiguous_format)


@torch.library.register_fake("tiger::softmax_rows_backward")
def _fake_backward(y, grad_y):
    torch._check(grad_y.shape == y.shape, lambda: f"tiger.softmax_rows_backward: grad_y must have y's shape "
                                                  f"{tuple(y.shape)}, got {tuple(grad_y.shape)}")
    return torch.empty_like(y, memory_format=torch.contiguous_format)


def _setup_context(ctx, inputs, output):
    ctx.save_for_backward(output)


def _backward(ctx, grad_y):
    (y,) = ctx.saved_tensors
    return torch.ops.tiger.softmax_rows_backward(y, grad_y)


torch.library.register_autograd("tiger::softmax_rows", _backward, setup_context=_setup_context)


def softmax_rows(x: torch.Tensor) -> torch.Tensor:
    """``torch.softmax(x, dim=-1)`` with tiger's CUDA kernels (forward and backward).

    Args:
        x: [..., L] floating point; on CUDA float32 / bfloat16 / float16 rows of whole 16-byte
            vectors up to 16384 (bf16/fp16) or 8192 (float32) values take tiger's kernels, any
            other input torch's softmax.

    Returns:
        [..., L] contiguous, x's dtype: ``exp(x − max) / Σ exp(x − max)`` per row, computed in float
        (double for float64) and rounded once. Differentiable (the backward
        ``y ⊙ (grad − ⟨grad, y⟩)`` per row, from the saved output).

    Example:
        >>> softmax_rows(torch.tensor([[0.0, 0.0]])).tolist()
        [[0.5, 0.5]]
    """
    return torch.ops.tiger.softmax_rows(x)
