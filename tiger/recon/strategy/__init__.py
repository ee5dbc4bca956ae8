"""Densification as in gsplat's ``strategy/``: primitives (row operations that keep the
optimizer in step), rules (which rows) and strategies (rule + schedule + statistics: what and
when, the one place a loop's densification is decided)."""
from __future__ import annotations

from .primitives import clone_and_split, duplicate, remove, reset_opacity, split
from .rules import DensifyStats, inria_densify, prune_transparent, region_topk_densify
from .strategies import DensifySchedule, InriaStrategy, RegionTopKStrategy

__all__ = ["DensifySchedule", "DensifyStats", "InriaStrategy", "RegionTopKStrategy", "clone_and_split", "duplicate",
           "inria_densify", "prune_transparent", "region_topk_densify", "remove", "reset_opacity", "split"]
