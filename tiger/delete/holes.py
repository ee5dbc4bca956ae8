"""Where a deletion leaves a hole in each view, from two rendered alphas.

A pixel is a hole when the removed Gaussians were visible there (their share of the pixel in the
scene before deletion, occlusion by the rest included, is at least ``visible_alpha``) and what
remains is thin there (the remainder's alpha is below ``thin_alpha``). Holes are then grown by
``dilate`` pixels (a disk) to cover the object's soft border. Pixels where the removed part was
visible but the remainder is opaque (the table behind a mug) are not holes: the remainder already
shows what belongs there. Small dilations matter: oversized masks are what make inpainted
deletions smear (a GaussianEditor complaint).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from tiger.utils.filters import dilate


def disk_dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Dilate bool masks [..., H, W] by a disk of ``radius`` pixels (0: unchanged)."""
    return dilate(mask, radius, "disk")


def hole_masks(removed_visible: torch.Tensor, remaining_alpha: torch.Tensor, *,
               visible_alpha: float = 0.3, thin_alpha: float = 0.5, dilate: int = 3) -> torch.Tensor:
    """Per-view hole masks (module docstring).

    Args:
        removed_visible: [V, H, W] the removed Gaussians' visible share of each pixel in the scene
            before deletion (render the full scene with a 0/1 "removed" channel).
        remaining_alpha: [V, H, W] alpha of the scene after removal.
        visible_alpha, thin_alpha: the two thresholds (see above).
        dilate: disk radius in pixels.
    Returns:
        [V, H, W] bool.
    """
    if removed_visible.shape != remaining_alpha.shape or removed_visible.dim() != 3:
        raise ValueError(f"tiger.delete.hole_masks: removed_visible and remaining_alpha must both be "
                         f"[V, H, W], got {list(removed_visible.shape)} and {list(remaining_alpha.shape)}")
    core = (removed_visible >= visible_alpha) & (remaining_alpha < thin_alpha)
    return disk_dilate(core, int(dilate))
