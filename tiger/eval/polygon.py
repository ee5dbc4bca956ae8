"""Polygon rasterization like ``cv2.fillPoly`` (the LERF-OVS ground-truth masks), without OpenCV.

LangSplat builds the ground-truth masks with ``cv2.fillPoly(mask, [int32 points], 1)``; this is
the same integer algorithm: vertices truncated to int32, each non-horizontal edge walked in 16-bit
fixed point (x step truncated toward zero), spans ``ceil(x_left) .. floor(x_right)`` filled per row
(rows ``y0 <= y < y1`` of each edge, even-odd pairing), and the outline drawn with OpenCV's
8-connected line iterator (left to right, major axis stepping, diagonal step when err < 0).
Lines are not pre-clipped to the image as OpenCV does, so a polygon reaching outside the frame can
differ from OpenCV by a pixel on its clipped edges.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

_SHIFT = 16
_ONE = 1 << _SHIFT


def _tdiv(a: int, b: int) -> int:
    """C integer division (truncation toward zero)."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b > 0) else -q


def _line8(mask: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> None:
    h, w = mask.shape
    if x1 < x0:  # OpenCV draws left to right
        x0, y0, x1, y1 = x1, y1, x0, y0
    dx, dy = x1 - x0, y1 - y0
    sy = -1 if dy < 0 else 1
    dy = abs(dy)
    steep = dy > dx
    major, minor = (dy, dx) if steep else (dx, dy)
    err = major - 2 * minor
    x, y = x0, y0
    for _ in range(major + 1):
        if 0 <= x < w and 0 <= y < h:
            mask[y, x] = True
        diag = err < 0
        err += -2 * minor + (2 * major if diag else 0)
        if steep:
            y += sy
            if diag:
                x += 1
        else:
            x += 1
            if diag:
                y += sy


def polygon_mask(height: int, width: int, polygon: Sequence[Sequence[float]]) -> np.ndarray:
    """[H, W] bool mask of one polygon given as [[x, y], ...] pixel coordinates."""
    pts = np.asarray(polygon, dtype=np.float64).reshape(-1, 2).astype(np.int32).tolist()
    mask = np.zeros((height, width), dtype=bool)
    n = len(pts)
    if n == 0:
        return mask
    edges = []  # (y0, y1, x at y0 in fixed point, dx per row in fixed point)
    for i in range(n):
        (ax, ay), (bx, by) = pts[i - 1], pts[i]
        _line8(mask, ax, ay, bx, by)
        if ay == by:
            continue
        fa, fb = ax << _SHIFT, bx << _SHIFT
        dx = _tdiv(fb - fa, by - ay)
        edges.append((ay, by, fa, dx) if ay < by else (by, ay, fb, dx))
    if not edges:
        return mask
    e = np.asarray(edges, dtype=np.int64)
    y_lo, y_hi = max(0, int(e[:, 0].min())), min(height, int(e[:, 1].max()))
    for y in range(y_lo, y_hi):
        act = (e[:, 0] <= y) & (y < e[:, 1])
        if not act.any():
            continue
        xs = np.sort(e[act, 2] + (y - e[act, 0]) * e[act, 3])
        for a, b in zip(xs[0::2], xs[1::2]):
            x1, x2 = int((a + _ONE - 1) >> _SHIFT), int(b >> _SHIFT)
            if x1 < width and x2 >= 0:
                mask[y, max(x1, 0):min(x2, width - 1) + 1] = True
    return mask
