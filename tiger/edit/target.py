"""What an edit changes: per-Gaussian update weights from retrieval (paper §3.2, score-based updating).

A target is a text (retrieved from the scene's language field), a :class:`~tiger.retrieval.Retrieval`,
a [N] bool mask, or [N] float weights. The weight of Gaussian i is its relevance

    w_i = s_i  if s_i > tau  else 0          (s_i = cos(T*, L_i), clamped at 0)

so Gaussians below the retrieval threshold get exactly 0 and are not parameters of the edit at all.
A bool mask gives w = 1 on the mask. The object's centre and robust box (per-axis median and
2 %–98 % quantiles of the editable positions, :func:`tiger.retrieval.robust_bounds`) place the
edit cameras.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import torch

from tiger.retrieval import Retrieval, retrieve, robust_bounds
from tiger.retrieval.text import TextEncoder
from tiger.scene import GaussianScene

TargetLike = Union[str, Retrieval, torch.Tensor, "EditTarget"]


class EmptyTargetError(ValueError):
    """The target selects no Gaussian."""


@dataclass
class EditTarget:
    """The resolved target of one edit round.

    Attributes:
        weights: [N] float32 update weight per Gaussian (0 = frozen), in [0, 1].
        description: the query text or a description of the given mask.
        tau: the retrieval threshold (None for a given mask / weights).
        center, bbox_min, bbox_max: [3] float64 object centre and robust box.
    """

    weights: torch.Tensor
    description: str
    tau: Optional[float]
    center: torch.Tensor
    bbox_min: torch.Tensor
    bbox_max: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        """[N] bool, the editable Gaussians (weight > 0)."""
        return self.weights > 0

    @property
    def count(self) -> int:
        return int(self.mask.sum())


def resolve_target(scene: GaussianScene, target: TargetLike, encoder: Optional[TextEncoder] = None,
                   tau: Union[float, str] = "auto",
                   score: str = "cosine", quantiles: tuple[float, float] = (0.02, 0.98)) -> EditTarget:
    """Turn ``target`` into per-Gaussian weights, centre and box (see the module docstring).

    Args:
        scene: the GaussianScene (``lang`` needed for a text target).
        target: text, a query embedding ([F] CLIP-space or [D]; any float tensor not shaped [N]),
            Retrieval, [N] bool mask, [N] float weights in [0, 1], or an EditTarget (returned as is).
        encoder: text encoder for a text target (``encode_text``), see :func:`tiger.retrieval.retrieve`.
        tau, score: retrieval threshold rule and score for a text target.
    Raises:
        EmptyTargetError: nothing selected; ValueError: no language features, bad mask shape.
    """
    n = len(scene)
    if isinstance(target, EditTarget):
        if target.weights.shape != (n,):
            raise ValueError(f"tiger.edit: the EditTarget has {target.weights.shape[0]} weights, the scene {n} Gaussians")
        return target
    query = target if isinstance(target, str) else None
    is_embedding = torch.is_tensor(target) and target.is_floating_point() and target.shape != (n,)
    if isinstance(target, str) or is_embedding:
        if getattr(scene, "lang", None) is None:
            raise ValueError("tiger.edit: the scene has no language features (lang_*): run `tiger embed` "
                             "(tiger.language.train_field) first, or pass a mask as the target")
        target = retrieve(scene, target, encoder=encoder, score=score, tau=tau, quantiles=quantiles)
    if isinstance(target, Retrieval):
        s = target.scores.detach().float().to(scene.device)
        w = torch.where(target.mask.to(scene.device), s.clamp(0, 1), torch.zeros_like(s))
        desc, t = f"retrieval ({target.score} > {target.tau:.4f})", float(target.tau)
        if query is not None:
            desc = f"'{query}': {desc}"
    elif torch.is_tensor(target):
        if target.shape != (n,):
            raise ValueError(f"tiger.edit: a target mask/weights must be [N={n}], got {list(target.shape)}")
        if target.dtype == torch.bool:
            w = target.to(scene.device).float()
            desc = f"mask of {int(target.sum())} Gaussians"
        else:
            w = target.detach().float().to(scene.device)
            if not bool(torch.isfinite(w).all()) or float(w.min()) < 0 or float(w.max()) > 1:
                raise ValueError("tiger.edit: target weights must be finite and in [0, 1]")
            desc = f"weights on {int((w > 0).sum())} Gaussians"
        t = None
    else:
        raise TypeError(f"tiger.edit: target must be a text, a Retrieval or an [N] tensor, got {type(target).__name__}")
    k = int((w > 0).sum())
    if k == 0:
        raise EmptyTargetError(f"tiger.edit: the target ({desc}) selects no Gaussian; try another text or a "
                               "lower --tau")
    center, lo, hi = robust_bounds(scene.means.detach()[w > 0], quantiles)
    return EditTarget(weights=w, description=desc, tau=t, center=center, bbox_min=lo, bbox_max=hi)


__all__ = ["EditTarget", "EmptyTargetError", "TargetLike", "resolve_target"]
