"""Relevance of language features to text queries through the fused ``tiger::relevancy`` op."""
from __future__ import annotations

from typing import Optional

import torch

from tiger.ops.relevancy import relevancy_scores

#: LERF's softmax temperature.
DEFAULT_TEMPERATURE = 10.0


def relevancy(features: torch.Tensor, positives: torch.Tensor, negatives: Optional[torch.Tensor] = None,
              *, temperature: float = DEFAULT_TEMPERATURE, check_finite: bool = True
              ) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """Cosine similarity and LERF relevancy of features to queries, in one pass.

    Args:
        features: [..., D] language features (per Gaussian [N, D], or a rendered map [H, W, D]);
            float16, float32 or float64, any device the op supports (CPU, CUDA). Need not be
            normalised; zero vectors get cosine 0.
        positives: [Q, D] or [D] query embeddings (normalised inside).
        negatives: [M, D] canonical negatives, or None / [0, D] for cosine only.
        temperature: the LERF softmax temperature (10).
        check_finite: raise on NaN/Inf features (one extra read; off for benchmarks).
    Returns:
        (cosine [..., Q], relevancy [..., Q] or None without negatives), float32 (float64 for
        float64 features), where ``relevancy = min_j exp(t c) / (exp(t c) + exp(t c_j))``.
    """
    if features.dim() < 1:
        raise ValueError("tiger.relevancy: features must be [..., D]")
    d = features.shape[-1]
    positives = torch.as_tensor(positives)
    if positives.dim() == 1:
        positives = positives[None]
    if positives.dim() != 2 or positives.shape[1] != d:
        raise ValueError(f"tiger.relevancy: positives must be [Q, D={d}], got {list(positives.shape)}")
    if negatives is None:
        negatives = positives.new_zeros((0, d))
    negatives = torch.as_tensor(negatives)
    if negatives.dim() != 2 or negatives.shape[1] != d:
        raise ValueError(f"tiger.relevancy: negatives must be [M, D={d}], got {list(negatives.shape)}")
    if not features.is_floating_point():
        raise ValueError(f"tiger.relevancy: features must be floating point, got {features.dtype}")
    if features.dtype not in (torch.float16, torch.float32, torch.float64):
        features = features.float()
    if check_finite and features.numel() and not bool(torch.isfinite(features).all()):
        raise ValueError("tiger.relevancy: features contain NaN or Inf")
    lead = features.shape[:-1]
    flat = features.reshape(-1, d)
    pos = positives.to(device=features.device)
    neg = negatives.to(device=features.device)
    cos, rel = relevancy_scores(flat, pos, neg, temperature)
    q = pos.shape[0]
    cos = cos.reshape(*lead, q)
    rel = rel.reshape(*lead, q) if neg.shape[0] > 0 else None
    return cos, rel
