"""PCA 512 -> 64 over a whole image set (SPEC §4), fitted from streamed sufficient statistics.

``StreamingPCA`` keeps only the count, the sum and the sum of outer products (float64, D x D), so
its memory does not grow with the number of images, and statistics from several processes or
cached images add up exactly. The fitted :class:`PCABasis` (mean and components) is saved with
the feature maps so text embeddings are projected identically.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import torch

from tiger.utils.io import atomic_torch_save
from tiger.utils.pca import moments, principal_axes

PathLike = Union[str, os.PathLike]


@dataclass
class PCABasis:
    """``project(x) = (x - mean) @ components``; mean [D], components [D, k] (orthonormal columns,
    by decreasing variance; each column's largest-magnitude entry is positive), variances [k]."""

    mean: torch.Tensor
    components: torch.Tensor
    explained_variance: torch.Tensor

    @property
    def dim(self) -> int:
        return int(self.components.shape[1])

    def project(self, x: torch.Tensor) -> torch.Tensor:
        """[..., D] -> [..., k] in x's dtype (computed in float32 or better)."""
        dt = torch.promote_types(x.dtype, torch.float32)
        c = self.components.to(x.device, dt)
        return ((x.to(dt) - self.mean.to(x.device, dt)) @ c).to(x.dtype if x.is_floating_point() else dt)

    def reconstruct(self, y: torch.Tensor) -> torch.Tensor:
        """[..., k] -> [..., D]: the point of the PCA subspace with coordinates y."""
        dt = torch.promote_types(y.dtype, torch.float32)
        return y.to(dt) @ self.components.to(y.device, dt).T + self.mean.to(y.device, dt)

    def fingerprint(self) -> str:
        import hashlib

        h = hashlib.sha1()
        for t in (self.mean, self.components):
            h.update(t.detach().cpu().double().numpy().tobytes())
        return h.hexdigest()[:16]

    def save(self, path: PathLike) -> None:
        atomic_torch_save({"mean": self.mean.cpu(), "components": self.components.cpu(),
                           "explained_variance": self.explained_variance.cpu()}, path)

    @classmethod
    def load(cls, path: PathLike) -> "PCABasis":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"tiger: no PCA basis at {path} (written by extract_features as pca.pt)")
        d = torch.load(str(path), map_location="cpu", weights_only=True)
        missing = {"mean", "components", "explained_variance"} - set(d)
        if missing:
            raise ValueError(f"tiger: {path} is not a PCA basis (missing {sorted(missing)})")
        return cls(d["mean"], d["components"], d["explained_variance"])


class StreamingPCA:
    """Accumulate weighted feature vectors, then :meth:`fit` the top ``n_components`` directions.

    ``update(x [N, D], weights [N] | None)`` adds vectors (a weight w counts the row w times: a
    mask mean standing for its pixels). Equal to a batch PCA of all rows (up to float64 round-off).
    """

    def __init__(self, dim: int, n_components: int = 64) -> None:
        if not 0 < n_components <= dim:
            raise ValueError(f"tiger.StreamingPCA: need 0 < n_components <= dim, got {n_components} and {dim}")
        self.dim, self.n_components = dim, n_components
        self.count = torch.zeros((), dtype=torch.float64)
        self.sum = torch.zeros(dim, dtype=torch.float64)
        self.outer = torch.zeros(dim, dim, dtype=torch.float64)

    @staticmethod
    def statistics(x: torch.Tensor, weights: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """(count, sum [D], outer [D, D]) of rows x [N, D] in float64 on the CPU
        (:func:`tiger.utils.pca.moments`)."""
        return moments(x, weights)

    def add_statistics(self, stats: dict[str, torch.Tensor]) -> None:
        if stats["sum"].shape != (self.dim,):
            raise ValueError(f"tiger.StreamingPCA: statistics of dimension {stats['sum'].shape[0]}, expected {self.dim}")
        self.count += stats["count"].double().cpu()
        self.sum += stats["sum"].double().cpu()
        self.outer += stats["outer"].double().cpu()

    def update(self, x: torch.Tensor, weights: torch.Tensor | None = None) -> None:
        self.add_statistics(self.statistics(x, weights))

    def fit(self) -> PCABasis:
        mean, comps, var = principal_axes(self.count, self.sum, self.outer, self.n_components)
        return PCABasis(mean.float(), comps.float(), var.float())
