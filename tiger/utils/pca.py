"""Principal component analysis from moments: the one PCA of the package.

Used in batch (:func:`fit_pca`), streamed over many images (``tiger.language.StreamingPCA``
adds up :func:`moments`), and for false-colour pictures of feature maps.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

__all__ = ["moments", "principal_axes", "fit_pca"]


def moments(x: Tensor, weights: Optional[Tensor] = None) -> dict[str, Tensor]:
    """Weighted sufficient statistics of rows ``x`` [N, D], float64 on the CPU.

    Returns ``count`` [] (Σ w), ``sum`` [D] (Σ w x) and ``outer`` [D, D] (Σ w x xᵀ); a weight w
    counts its row w times (default 1).
    """
    if x.dim() != 2:
        raise ValueError(f"tiger.pca: x must be [N, D], got {tuple(x.shape)}")
    xd = x.double()
    if weights is None:
        return {"count": torch.tensor(float(x.shape[0]), dtype=torch.float64), "sum": xd.sum(0).cpu(),
                "outer": (xd.T @ xd).cpu()}
    if weights.shape != (x.shape[0],):
        raise ValueError(f"tiger.pca: weights must be [N] = [{x.shape[0]}], got {tuple(weights.shape)}")
    wd = weights.to(xd)
    return {"count": wd.sum().cpu(), "sum": (wd[:, None] * xd).sum(0).cpu(),
            "outer": ((xd * wd[:, None]).T @ xd).cpu()}


def principal_axes(count: Tensor, total: Tensor, outer: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor]:
    """The top-``k`` principal directions from :func:`moments` (float64).

    Returns:
        mean [D], components [D, k] (orthonormal columns by decreasing variance, each column's
        largest-magnitude entry positive, so the basis is deterministic), variances [k] (the
        unbiased covariance's eigenvalues, clamped at 0). The same bits for any thread count.
    """
    d = total.shape[0]
    if not 0 < k <= d:
        raise ValueError(f"tiger.pca: need 0 < k <= D, got k={k} for D={d}")
    if float(count) <= 1:
        raise ValueError("tiger.pca: a PCA needs more than one (weighted) sample")
    mean = total / count
    cov = (outer - count * torch.outer(mean, mean)) / (count - 1)
    # one thread: LAPACK's result depends on its thread count in the last bits, and the basis
    # must be the same in a single process and in each torchrun rank (OMP_NUM_THREADS=1 there)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        evals, evecs = torch.linalg.eigh(0.5 * (cov + cov.T).cpu())
    finally:
        torch.set_num_threads(threads)
    comps = evecs[:, -k:].flip(1)
    var = evals[-k:].flip(0).clamp_min(0)
    sign = torch.sign(comps.gather(0, comps.abs().argmax(0, keepdim=True)))
    return mean, comps * torch.where(sign == 0, torch.ones_like(sign), sign), var


def fit_pca(x: Tensor, k: int, weights: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor]:
    """Batch PCA of rows ``x`` [N, D]: (mean [D], components [D, k], variances [k]), float64 on the
    CPU (see :func:`principal_axes`)."""
    m = moments(x, weights)
    return principal_axes(m["count"], m["sum"], m["outer"], k)
