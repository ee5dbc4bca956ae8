"""Densification rules: which Gaussians to duplicate, split or remove, and when.

* :func:`inria_densify` — adaptive density control of 3DGS (Kerbl et al. 2023, §5.2):
  Gaussians whose mean screen-space positional gradient exceeds a threshold are cloned
  (small) or split (large); transparent and huge ones are pruned.
* :func:`region_topk_densify` — TIGER §3.3: only the top ``top_percent`` % of a region's
  Gaussians by mean accumulated screen-space gradient are densified (1 % per call).
* :func:`prune_transparent` — remove Gaussians below an opacity inside a region.

The statistics (:class:`DensifyStats`) follow INRIA: the norm of the gradient of the loss
w.r.t. each projected centre, in NDC units (pixel gradient x size/2), summed over the views
that see it. All row changes go through :mod:`.primitives`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from ..step import SceneOptimizer
from .primitives import clone_and_split, remove


@dataclass
class DensifyStats:
    """Per-Gaussian statistics gathered between densification steps (all [N])."""

    grad_accum: torch.Tensor
    count: torch.Tensor
    max_radii: torch.Tensor

    @classmethod
    def zeros(cls, n: int, device: torch.device) -> "DensifyStats":
        z = torch.zeros(n, device=device)
        return cls(z.clone(), z.clone(), z.clone())

    def add(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        """Record views: ``means2d_grad`` [N, 2] or [V, N, 2] (pixel units), ``radii`` [N] or
        [V, N] (0 = not seen). Masked arithmetic, not boolean indexing: no host synchronisation."""
        vis = radii > 0
        g = means2d_grad.detach().float()
        ndc = torch.hypot(g[..., 0] * (0.5 * width), g[..., 1] * (0.5 * height))
        ndc = torch.where(vis, ndc, 0.0)
        r = torch.where(vis, radii.float(), 0.0)  # the statistics are >= 0: an unseen view leaves them
        if vis.dim() == 2:
            ndc, vis, r = ndc.sum(0), vis.sum(0), r.amax(0)
        self.grad_accum += ndc
        self.count += vis
        torch.maximum(self.max_radii, r, out=self.max_radii)

    def mean_grad(self) -> torch.Tensor:
        """[N] mean NDC gradient norm over the views that saw each Gaussian (0 if none)."""
        grads = self.grad_accum / self.count.clamp_min(1)
        grads[self.count == 0] = 0
        return grads

    def rows(self) -> dict[str, torch.Tensor]:
        """The live per-Gaussian tensors, for the primitives' ``state`` (writing to the dict
        updates these statistics)."""
        return self.__dict__

    def clear(self, rows: Optional[slice] = None) -> None:
        """Zero the statistics (of ``rows``): a new accumulation window."""
        for t in self.rows().values():
            t[rows if rows is not None else slice(None)] = 0

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum, "count": self.count, "max_radii": self.max_radii}

    @classmethod
    def from_state_dict(cls, d: dict) -> "DensifyStats":
        return cls(d["grad_accum"], d["count"], d["max_radii"])


def _region(opt: SceneOptimizer, region: Optional[torch.Tensor]) -> torch.Tensor:
    n = len(opt.scene)
    if region is None:
        return opt.trainable_mask()
    if region.dtype != torch.bool or region.shape != (n,):
        raise ValueError(f"tiger.recon: region must be [N={n}] bool, got {region.dtype} {list(region.shape)}")
    return region.to(opt.scene.device)


def _grow(opt: SceneOptimizer, stats: DensifyStats, want: torch.Tensor, large: torch.Tensor,
          generator: Optional[torch.Generator]) -> tuple[int, int]:
    """Clone ``want & ~large``, split ``want & large``; children start with empty statistics."""
    n0 = len(opt.scene)
    cloned, n_split = clone_and_split(opt, want & ~large, want & large, stats.rows(), generator)
    stats.clear(slice(n0 - n_split, None))
    return cloned, n_split


def inria_densify(opt: SceneOptimizer, stats: DensifyStats, grad_threshold: float, extent: float,
                  percent_dense: float = 0.01, min_opacity: float = 0.005,
                  max_screen_size: Optional[float] = None, max_world_size: Optional[float] = None,
                  max_gaussians: Optional[int] = None, generator: Optional[torch.Generator] = None,
                  region: Optional[torch.Tensor] = None) -> dict:
    """One round of clone / split / prune (INRIA's ``densify_and_prune``).

    Args:
        grad_threshold: mean NDC positional gradient above which a Gaussian is densified.
        extent: scene radius; a Gaussian is "large" when its largest scale exceeds
            ``percent_dense * extent``.
        min_opacity: prune below this opacity.
        max_screen_size: prune Gaussians whose screen radius exceeded this (px) since the
            last densification (None: off).
        max_world_size: prune Gaussians whose largest scale exceeds ``max_world_size *
            extent`` (None: off; INRIA turns it on, at 0.1, after the first opacity reset).
        max_gaussians: do not grow past this count (the largest gradients win).
        region: [N] bool, only these Gaussians are densified or pruned (default: the
            optimizer's trainable ones).
    Returns:
        counts {"cloned", "split", "pruned", "total", "before"}. The statistics start a new
        window afterwards.
    """
    with torch.no_grad():
        region = _region(opt, region)
        n0 = len(opt.scene)
        grads = stats.mean_grad()
        large = opt.scene.scales.max(dim=1).values > percent_dense * extent
        want = (grads >= grad_threshold) & region
        if max_gaussians is not None:
            room = max(0, max_gaussians - n0)
            # a split adds one net Gaussian, a clone one: keep the strongest ``room``
            if int(want.sum()) > room:
                order = torch.argsort(torch.where(want, grads, torch.full_like(grads, -1.0)), descending=True)
                want = torch.zeros_like(want)
                want[order[:room]] = True
        cloned, n_split = _grow(opt, stats, want, large, generator)
        region = torch.cat([region[~(want & large)], region.new_ones(len(opt.scene) - n0 + n_split)])

        s = opt.scene
        prune = s.opacities.detach() < min_opacity
        if max_screen_size is not None:
            prune |= stats.max_radii > max_screen_size
        if max_world_size is not None:
            prune |= s.scales.detach().max(dim=1).values > max_world_size * extent
        prune &= region
        if bool(prune.all()):
            # never delete everything: keep the most opaque Gaussian
            prune[torch.argmax(s.opacity_logits.detach())] = False
        n_pruned = remove(opt, prune, stats.rows())
        stats.clear()
    return {"cloned": cloned, "split": n_split, "pruned": n_pruned, "total": len(opt.scene), "before": n0}


def region_topk_densify(opt: SceneOptimizer, stats: DensifyStats, extent: float, top_percent: float = 1.0,
                        percent_dense: float = 0.01, region: Optional[torch.Tensor] = None,
                        generator: Optional[torch.Generator] = None) -> dict:
    """Densify the top ``top_percent`` % of the ``region``'s Gaussians (default: the trainable
    ones) by mean accumulated screen-space gradient (TIGER §3.3, 1 % per call).

    ``floor(top_percent / 100 * |region|)`` Gaussians at most, only ones with a non-zero
    gradient; small ones are cloned and large ones (largest scale > ``percent_dense *
    extent``) split, so the scene grows by at most that many. Children inherit every
    attribute (``lang`` included). The statistics start a new window afterwards.
    Returns {"cloned", "split", "total", "before"}.
    """
    if not 0 <= top_percent <= 100:
        raise ValueError(f"tiger.recon: top_percent must be in [0, 100], got {top_percent}")
    with torch.no_grad():
        region = _region(opt, region)
        n0 = len(opt.scene)
        grads = stats.mean_grad()
        candidates = region & (grads > 0)
        k = min(int(math.floor(top_percent / 100.0 * int(region.sum()))), int(candidates.sum()))
        want = torch.zeros_like(region)
        if k > 0:
            want[torch.topk(torch.where(candidates, grads, torch.full_like(grads, -1.0)), k).indices] = True
        large = opt.scene.scales.max(dim=1).values > percent_dense * extent
        cloned, n_split = _grow(opt, stats, want, large, generator)
        stats.clear()
    return {"cloned": cloned, "split": n_split, "total": len(opt.scene), "before": n0}


def prune_transparent(opt: SceneOptimizer, min_opacity: float = 0.005, region: Optional[torch.Tensor] = None,
                      state: Optional[dict[str, torch.Tensor]] = None) -> int:
    """Remove the Gaussians of ``region`` (default: the trainable ones) whose opacity is below
    ``min_opacity``; returns how many."""
    with torch.no_grad():
        prune = (opt.scene.opacities.detach() < min_opacity) & _region(opt, region)
        return remove(opt, prune, state)


__all__ = ["DensifyStats", "inria_densify", "region_topk_densify", "prune_transparent"]
