"""``tiger::connected_components`` and ``tiger::remove_small_regions``: fake kernels and Python
entry points (semantics in ``csrc/components/components.h``). Neither is differentiable."""
from __future__ import annotations

import torch

__all__ = ["connected_components", "remove_small_regions"]


def _check_masks(masks: torch.Tensor, op: str) -> None:
    torch._check(masks.dim() == 3, lambda: f"tiger.{op}: masks must be [M, H, W], got {tuple(masks.shape)}")
    torch._check(masks.dtype == torch.bool, lambda: f"tiger.{op}: masks must be bool, got {masks.dtype}")


@torch.library.register_fake("tiger::connected_components")
def _fake_connected_components(masks):
    _check_masks(masks, "connected_components")
    return masks.new_empty(masks.shape, dtype=torch.int32)


@torch.library.register_fake("tiger::remove_small_regions")
def _fake_remove_small_regions(masks, area_threshold):
    _check_masks(masks, "remove_small_regions")
    torch._check(area_threshold >= 0, lambda: f"tiger.remove_small_regions: area_threshold must be >= 0, "
                 f"got {area_threshold}")
    return masks.new_empty(masks.shape), masks.new_empty((masks.shape[0],))


def connected_components(masks: torch.Tensor) -> torch.Tensor:
    """8-connected components of every mask of masks [M, H, W] bool: labels [M, H, W] int32, each
    foreground pixel labelled with the row-major index (y * W + x) of its component's first pixel
    in raster order, background -1."""
    return torch.ops.tiger.connected_components(masks)


def remove_small_regions(masks: torch.Tensor, area_threshold: int) -> tuple[torch.Tensor, torch.Tensor]:
    """SAM's small-region clean-up of masks [M, H, W] bool: holes, then islands, of fewer than
    ``area_threshold`` pixels removed (8-connectivity; an all-small mask keeps its largest island).
    Returns (cleaned [M, H, W] bool, changed [M] bool: a small hole or island was found)."""
    return torch.ops.tiger.remove_small_regions(masks, int(area_threshold))
