"""Densification as in gsplat's ``strategy/``: primitives (row operations that keep the
optimizer in step) and rules (which rows, when)."""
from __future__ import annotations

from .primitives import duplicate, remove, reset_opacity, split
from .rules import DensifyStats, inria_densify, prune_transparent, region_topk_densify

__all__ = ["DensifyStats", "duplicate", "inria_densify", "prune_transparent", "region_topk_densify", "remove",
           "reset_opacity", "split"]
