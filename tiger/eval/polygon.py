"""Ground-truth polygon masks of LERF-OVS, exactly as the published evaluation builds them.

LangSplat's ``polygon_to_mask`` (eval/utils.py): ``cv2.fillPoly(mask, [np.asarray(points,
np.int32)], 1)``. OpenCV is called itself: its outline is drawn with lines clipped to the frame
first, so polygons with vertices outside the frame are filled differently from any unclipped
scan-line fill (about one pixel per row along each edge that crosses the border).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np


def _cv2():
    try:
        import cv2  # type: ignore
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("tiger.eval: ground-truth masks need OpenCV (cv2.fillPoly, as LangSplat's evaluation); "
                          "install it with `pip install opencv-python-headless`") from exc
    return cv2


def polygon_mask(height: int, width: int, polygon: Sequence[Sequence[float]]) -> np.ndarray:
    """[H, W] bool mask of one polygon given as [[x, y], ...] pixel coordinates (truncated to
    int32 as LangSplat does; vertices may lie outside the frame)."""
    pts = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    mask = np.zeros((height, width), dtype=np.uint8)
    if len(pts) == 0:
        return mask.astype(bool)
    if not np.isfinite(pts).all():
        raise ValueError("tiger.eval: polygon vertices must be finite numbers")
    _cv2().fillPoly(mask, [pts.astype(np.int32)], 1)
    return mask.astype(bool)
