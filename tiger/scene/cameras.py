"""Camera helpers over sets of views: intrinsics, rotations, centres and INRIA's scene extent.

:class:`Camera` and :class:`Distortion` have one home a floor down, :mod:`tiger.render.camera`
(public as ``tiger.render.Camera``; the renderer and the virtual views need them).
"""
from __future__ import annotations

from typing import Sequence

import torch

from tiger.render import Camera

__all__ = ["intrinsics", "quat_to_rotmat", "camera_centers", "scene_extent"]


def intrinsics(fx: float, fy: float, cx: float, cy: float,
               dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """[3, 3] pinhole matrix."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] quaternions (w, x, y, z; normalised here) -> [..., 3, 3] rotations."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def camera_centers(cameras: Sequence[Camera]) -> torch.Tensor:
    """[V, 3] centres of ``cameras`` (float64)."""
    return torch.stack([c.center.double() for c in cameras])


def scene_extent(cameras: Sequence[Camera]) -> float:
    """INRIA's scene radius: 1.1 x the largest distance of a camera centre from their mean.

    Scales the position learning rate and the densification size thresholds.
    """
    if len(cameras) == 0:
        raise ValueError("tiger: scene_extent needs at least one camera")
    c = camera_centers(cameras)
    radius = float((c - c.mean(0)).norm(dim=1).max()) * 1.1
    return radius if radius > 0 else 1.0
