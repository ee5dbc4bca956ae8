"""Cameras in MVDream's convention, from our OpenCV world-to-camera matrices.

MVDream conditions on camera-to-world 4x4 matrices with OpenGL camera axes (+x right, +y up,
+z backward: the camera looks along −z) in a z-up world with the object at the origin, the
translation scaled to unit length (``normalize_camera``), flattened row-major to 16 values. Its
own cameras are built in a y-up OpenGL world and turned z-up by ``flip_yz`` (x, y, z) → (x, −z, y).

From a :class:`~tiger.render.Camera` (OpenCV world-to-camera ``viewmat``):
    c2w_cv = viewmat⁻¹;  R_gl = R_c2w · diag(1, −1, −1)  (flip the camera's y and z axes);
    world → MVDream world: subtract the object centre, rotate by the smallest rotation taking the
    scene's up direction to +z (for a y-up world that rotation is exactly ``flip_yz``);
    translation normalised to unit length.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from tiger.render import Camera

_FLIP_YZ_CAMERA = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))


def estimate_world_up(cameras: Sequence[Camera]) -> torch.Tensor:
    """[3] unit mean of the cameras' up directions (−y of OpenCV cameras) in world coordinates."""
    ups = torch.stack([-c.viewmat.to(torch.float64)[1, :3] for c in cameras])
    up = ups.mean(0)
    n = float(up.norm())
    if n < 1e-6:
        raise ValueError("tiger.edit.mvdream: the cameras' up directions cancel out; pass world_up explicitly")
    return up / n


def rotation_to_z(up: torch.Tensor) -> torch.Tensor:
    """[3, 3] float64: the smallest rotation taking the unit vector ``up`` to +z (Rodrigues)."""
    a = up.to(torch.float64) / up.to(torch.float64).norm()
    b = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    v = torch.linalg.cross(a, b)
    s, c = float(v.norm()), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return torch.eye(3, dtype=torch.float64)
        return torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # π about x
    vx = torch.tensor([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + vx + vx @ vx * ((1.0 - c) / s ** 2)


def mvdream_cameras(cameras: Sequence[Camera], object_center: torch.Tensor,
                    world_up: Optional[torch.Tensor] = None) -> torch.Tensor:
    """[V, 16] float32 camera conditions in MVDream's convention (module docstring).

    Args:
        cameras: V cameras (OpenCV world-to-camera).
        object_center: [3] world position of the object (MVDream's origin).
        world_up: [3] the scene's up direction; None: estimated from the cameras.
    """
    if len(cameras) == 0:
        raise ValueError("tiger.edit.mvdream: no cameras given")
    center = torch.as_tensor(object_center, dtype=torch.float64).reshape(-1)
    if center.shape != (3,) or not bool(torch.isfinite(center).all()):
        raise ValueError(f"tiger.edit.mvdream: object_center must be a finite [3] vector, got {list(center.shape)}")
    up = estimate_world_up(cameras) if world_up is None else torch.as_tensor(world_up, dtype=torch.float64).reshape(3)
    if float(up.norm()) < 1e-12:
        raise ValueError("tiger.edit.mvdream: world_up must be non-zero")
    rot = rotation_to_z(up)
    # all V cameras in one batched inverse and two matmuls (the edit calls this every step)
    c2w = torch.linalg.inv(torch.stack([cam.viewmat.to(torch.float64) for cam in cameras]))
    r = rot @ c2w[:, :3, :3] @ _FLIP_YZ_CAMERA
    p = (c2w[:, :3, 3] - center) @ rot.T
    p = p / (p.norm(dim=1, keepdim=True) + 1e-8)
    m = torch.eye(4, dtype=torch.float64).repeat(len(cameras), 1, 1)
    m[:, :3, :3], m[:, :3, 3] = r, p
    return m.reshape(-1, 16).float()
