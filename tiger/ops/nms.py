"""``tiger::box_nms``, ``tiger::mask_intersections`` and ``tiger::mask_nms``: fake kernels and
Python entry points (semantics in ``csrc/nms/nms.h``). None of them is differentiable."""
from __future__ import annotations

import torch

__all__ = ["box_nms", "mask_intersections", "mask_nms"]


@torch.library.register_fake("tiger::box_nms")
def _fake_box_nms(boxes, scores, iou_threshold):
    n = torch.library.get_ctx().new_dynamic_size()
    return boxes.new_empty((n,), dtype=torch.int64)


@torch.library.register_fake("tiger::mask_intersections")
def _fake_mask_intersections(masks):
    return masks.new_empty((masks.shape[0], masks.shape[0]), dtype=torch.int64)


@torch.library.register_fake("tiger::mask_nms")
def _fake_mask_nms(masks, scores, iou_threshold=0.8, score_threshold=0.7, inner_threshold=0.5):
    n = torch.library.get_ctx().new_dynamic_size()
    return masks.new_empty((n,), dtype=torch.int64)


def box_nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy NMS of boxes [N, 4] (x1, y1, x2, y2, pixels) by scores [N]; returns kept indices
    [K] int64 by decreasing score (as ``torchvision.ops.nms``)."""
    return torch.ops.tiger.box_nms(boxes, scores, float(iou_threshold))


def mask_intersections(masks: torch.Tensor) -> torch.Tensor:
    """Pairwise pixel counts of ``masks_i & masks_j`` for masks [M, H, W] bool: [M, M] int64."""
    return torch.ops.tiger.mask_intersections(masks)


def mask_nms(
    masks: torch.Tensor,
    scores: torch.Tensor,
    iou_threshold: float = 0.8,
    score_threshold: float = 0.7,
    inner_threshold: float = 0.5,
) -> torch.Tensor:
    """LangSplat's mask NMS of masks [M, H, W] bool by scores [M]; returns kept indices [K]
    int64 by decreasing score. See ``csrc/nms/nms.h`` for the exact rule."""
    return torch.ops.tiger.mask_nms(
        masks, scores, float(iou_threshold), float(score_threshold), float(inner_threshold)
    )
