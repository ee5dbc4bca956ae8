"""Densification strategies: each owns what to densify (a rule of :mod:`.rules`), when (a
:class:`DensifySchedule`) and the statistics it decides on (:class:`~.rules.DensifyStats`), after
gsplat's ``strategy/``. A loop calls :meth:`observe` after its backward and
:meth:`step_post_backward` after its optimizer step; it never spells out the schedule itself.

* :class:`InriaStrategy` — reconstruction: INRIA's clone / split / prune and opacity reset.
* :class:`RegionTopKStrategy` — editing and refits: the top ``top_percent`` % of a region by
  gradient (TIGER §3.3); children inherit every attribute (``lang``, relevance weights).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from ..step import SceneOptimizer
from .primitives import reset_opacity
from .rules import DensifyStats, inria_densify, prune_transparent, region_topk_densify


@dataclass(frozen=True)
class DensifySchedule:
    """When densification runs: after step ``s`` (steps counted from 1) with ``every > 0``,
    ``s % every == 0`` and ``first <= s <= last``. Statistics are gathered at every step up to
    ``last``. ``every = 0`` turns densification off."""

    every: int
    first: int = 1
    last: Optional[int] = None  # None: no end

    def collecting(self, step: int) -> bool:
        """Whether step ``step``'s screen-space gradients feed the statistics."""
        return self.every > 0 and (self.last is None or step <= self.last)

    def due(self, step: int) -> bool:
        """Whether to densify after step ``step``."""
        return self.collecting(step) and step >= self.first and step % self.every == 0


class _Strategy:
    """The statistics and their checkpoint state, shared by the strategies."""

    schedule: DensifySchedule

    def __init__(self, n: int, device: torch.device) -> None:
        self.stats = DensifyStats.zeros(n, device)

    def observe(self, step: int, renders: dict, width: int, height: int) -> None:
        """Add step ``step``'s renders (``means2d`` with its ``.grad``, ``radii``) of views
        ``width`` x ``height`` px to the statistics, while the schedule gathers them."""
        if renders["means2d"].grad is not None:
            self.observe_grad(step, renders["means2d"].grad, renders["radii"], width, height)

    def observe_grad(self, step: int, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int,
                     height: int) -> None:
        """:meth:`observe` from the gradient itself: ``means2d_grad`` [N, 2] or [V, N, 2] (pixel
        units) and ``radii`` [N] or [V, N] over all N rows (e.g. scattered from a subset render)."""
        if self.schedule.collecting(step):
            self.stats.add(means2d_grad, radii, width, height)

    def state_dict(self) -> dict:
        return {"stats": self.stats.state_dict()}

    def load_state_dict(self, state: dict, device: torch.device) -> None:
        self.stats = DensifyStats.from_state_dict({k: v.to(device) for k, v in state["stats"].items()})


class InriaStrategy(_Strategy):
    """INRIA's densification (``densify_and_prune`` + opacity reset) on a schedule.

    Args:
        n, device: Gaussians at the start and where the statistics live.
        schedule: when to densify (INRIA: ``first = densify_from + 1``, ``last = densify_until``).
        extent: scene radius; grad_threshold, percent_dense, min_opacity, max_screen_size,
            max_world_size, max_gaussians: as :func:`~.rules.inria_densify`.
        opacity_reset_every: reset opacities every this many steps while densifying (0: never);
            the screen- and world-size pruning start after the first reset.
        prune_large_from_start: prune by world size from the first densification (fine-tuning).
    """

    def __init__(self, n: int, device: torch.device, schedule: DensifySchedule, extent: float, *,
                 grad_threshold: float = 2e-4, percent_dense: float = 0.01, min_opacity: float = 0.005,
                 max_screen_size: Optional[float] = None, max_world_size: Optional[float] = 0.1,
                 max_gaussians: Optional[int] = None, opacity_reset_every: int = 3000,
                 prune_large_from_start: bool = False) -> None:
        super().__init__(n, device)
        self.schedule, self.extent = schedule, extent
        self.grad_threshold, self.percent_dense, self.min_opacity = grad_threshold, percent_dense, min_opacity
        self.max_screen_size, self.max_world_size, self.max_gaussians = max_screen_size, max_world_size, max_gaussians
        self.opacity_reset_every, self.prune_large_from_start = opacity_reset_every, prune_large_from_start

    def step_post_backward(self, opt: SceneOptimizer, step: int,
                           generator: Optional[torch.Generator] = None) -> Optional[dict]:
        """Densify and/or reset opacities after step ``step`` as scheduled; returns the
        densification's counts, or None when it did not run."""
        info = None
        if self.schedule.due(step):
            reset_done = bool(self.opacity_reset_every) and step > self.opacity_reset_every
            info = inria_densify(opt, self.stats, self.grad_threshold, self.extent, self.percent_dense,
                                 self.min_opacity, self.max_screen_size if reset_done else None,
                                 self.max_world_size if (reset_done or self.prune_large_from_start) else None,
                                 self.max_gaussians, generator)
        if self.schedule.collecting(step) and self.opacity_reset_every and step % self.opacity_reset_every == 0:
            reset_opacity(opt)
        return info


class RegionTopKStrategy(_Strategy):
    """TIGER's region densification on a schedule: the top ``top_percent`` % of the trainable
    Gaussians by mean screen-space gradient are cloned or split (largest scale above
    ``percent_dense * extent``: split); then, with ``min_opacity``, trainable ones below it are pruned.
    """

    def __init__(self, n: int, device: torch.device, schedule: DensifySchedule, extent: float, *,
                 top_percent: float = 1.0, percent_dense: float = 0.01,
                 min_opacity: Optional[float] = None) -> None:
        super().__init__(n, device)
        self.schedule, self.extent = schedule, extent
        self.top_percent, self.percent_dense, self.min_opacity = top_percent, percent_dense, min_opacity

    def step_post_backward(self, opt: SceneOptimizer, step: int,
                           generator: Optional[torch.Generator] = None) -> Optional[dict]:
        """Densify (and prune) after step ``step`` as scheduled; returns the counts
        ({"cloned", "split", "pruned", "total", "before"}) or None when it did not run."""
        if not self.schedule.due(step):
            return None
        info = region_topk_densify(opt, self.stats, extent=self.extent, top_percent=self.top_percent,
                                   percent_dense=self.percent_dense, generator=generator)
        info["pruned"] = (prune_transparent(opt, self.min_opacity, state=self.stats.rows())
                          if self.min_opacity is not None else 0)
        info["total"] = len(opt.scene)
        return info


__all__ = ["DensifySchedule", "InriaStrategy", "RegionTopKStrategy"]
