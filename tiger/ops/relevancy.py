"""``torch.ops.tiger.relevancy``: fused normalise + cosine + LERF relevancy (fake kernel, autograd).

Forward (CPU and CUDA kernels, ``csrc/relevancy``), for features ``f`` [N, D] (float16/32/64),
positives ``q`` [Q, D] and negatives ``n`` [M, D]::

    c[i, k] = f_i . q_k / (max(|f_i|, eps) max(|q_k|, eps))
    r[i, k] = min_j exp(t c[i, k]) / (exp(t c[i, k]) + exp(t c'[i, j]))  = sigmoid(t (c[i, k] - max_j c'[i, j]))

with ``c'`` the cosines against the negatives. Returns ``(c, r)``: float32 for float16/32 features,
float64 for float64; ``r`` is an empty ``[0]`` tensor when M == 0. The backward (written here with
torch ops: gradients are only needed for analysis, never on the retrieval hot path) follows the
forward's sub-gradient at ties (the first maximal negative).
"""
from __future__ import annotations

from typing import Any

import torch

_OP = "tiger::relevancy"

__all__ = ["relevancy_scores"]


def relevancy_scores(features: torch.Tensor, positives: torch.Tensor, negatives: torch.Tensor,
                     temperature: float = 10.0, eps: float = 1e-12) -> tuple[torch.Tensor, torch.Tensor]:
    """Cosines and LERF relevancy of N features against Q positives and M negatives (fused).

    Args:
        features: [N, D] float16/32/64; positives: [Q, D]; negatives: [M, D] (M may be 0), on
            the features' device; temperature: the softmax temperature t; eps: norm floor.
    Returns:
        cos [N, Q] and rel [N, Q] = sigmoid(t (cos - max_j cos'_j)) (an empty [0] tensor when
        M == 0); float32 for float16/32 features, float64 for float64. Differentiable.
    """
    return torch.ops.tiger.relevancy(features, positives, negatives, float(temperature), float(eps))


def _acc_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


@torch.library.register_fake(_OP)
def _relevancy_fake(features: torch.Tensor, positives: torch.Tensor, negatives: torch.Tensor,
                    temperature: float = 10.0, eps: float = 1e-12) -> tuple[torch.Tensor, torch.Tensor]:
    torch._check(features.dim() == 2, lambda: "tiger.relevancy: features must be [N, D]")
    torch._check(positives.dim() == 2 and positives.shape[1] == features.shape[1],
                 lambda: "tiger.relevancy: positives must be [Q, D]")
    torch._check(negatives.dim() == 2 and negatives.shape[1] == features.shape[1],
                 lambda: "tiger.relevancy: negatives must be [M, D]")
    acc = _acc_dtype(features.dtype)
    n, q, m = features.shape[0], positives.shape[0], negatives.shape[0]
    cos = features.new_empty((n, q), dtype=acc)
    rel = features.new_empty((n, q), dtype=acc) if m > 0 else features.new_empty((0,), dtype=acc)
    return cos, rel


def _setup_context(ctx: Any, inputs: tuple, output: tuple) -> None:
    features, positives, negatives, temperature, eps = inputs
    cos, rel = output
    ctx.save_for_backward(features, positives, negatives, rel)
    ctx.temperature = float(temperature)
    ctx.eps = float(eps)


def _unit(x: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(x / max(|x|, eps), max(|x|, eps), |x| >= eps) row-wise."""
    norm = x.norm(dim=1, keepdim=True)
    clamped = norm.clamp_min(eps)
    return x / clamped, clamped, norm >= eps


def _grad_unit(g_hat: torch.Tensor, x_hat: torch.Tensor, clamped: torch.Tensor,
               above: torch.Tensor) -> torch.Tensor:
    """Chain rule through x_hat = x / max(|x|, eps): (g - (g . x_hat) x_hat [|x| >= eps]) / max(|x|, eps)."""
    radial = (g_hat * x_hat).sum(dim=1, keepdim=True) * x_hat
    return (g_hat - torch.where(above, radial, torch.zeros_like(radial))) / clamped


def _backward(ctx: Any, grad_cos: torch.Tensor | None, grad_rel: torch.Tensor | None):
    features, positives, negatives, rel = ctx.saved_tensors
    t, eps = ctx.temperature, ctx.eps
    acc = _acc_dtype(features.dtype)
    f_hat, f_norm, f_above = _unit(features.to(acc), eps)
    q_hat, q_norm, q_above = _unit(positives.to(acc), eps)
    n_hat, n_norm, n_above = _unit(negatives.to(acc), eps)

    # Gradients with respect to the cosines against the positives (g_c) and negatives (g_n).
    g_c = grad_cos.to(acc) if grad_cos is not None else f_hat.new_zeros(f_hat.shape[0], q_hat.shape[0])
    g_n = f_hat.new_zeros(f_hat.shape[0], n_hat.shape[0])
    if grad_rel is not None and negatives.shape[0] > 0 and rel.numel() > 0:
        # d sigmoid(t (c - c_max)) = t r (1 - r) (dc - dc_max), c_max = cosine of the hardest negative.
        w = grad_rel.to(acc) * t * rel * (1.0 - rel)  # [N, Q]
        g_c = g_c + w
        hardest = (f_hat @ n_hat.T).argmax(dim=1)  # [N]
        g_n.scatter_add_(1, hardest[:, None], -w.sum(dim=1, keepdim=True))

    grads: list[torch.Tensor | None] = [None, None, None, None, None]
    if ctx.needs_input_grad[0]:
        g_fhat = g_c @ q_hat + g_n @ n_hat
        grads[0] = _grad_unit(g_fhat, f_hat, f_norm, f_above).to(features.dtype)
    if ctx.needs_input_grad[1]:
        grads[1] = _grad_unit(g_c.T @ f_hat, q_hat, q_norm, q_above).to(positives.dtype)
    if ctx.needs_input_grad[2]:
        grads[2] = _grad_unit(g_n.T @ f_hat, n_hat, n_norm, n_above).to(negatives.dtype)
    return tuple(grads)


torch.library.register_autograd(_OP, _backward, setup_context=_setup_context)
