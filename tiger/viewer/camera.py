"""Browser camera <-> :class:`tiger.render.Camera`.

viser reports a client's camera as a camera-to-world rotation (quaternion w, x, y, z) and position
with OpenCV axes (+z forward, +y down), a vertical field of view in radians and the canvas aspect
ratio; the rasterizer takes a world-to-camera ``viewmat`` and pinhole ``K``.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch

from tiger.render import Camera


def quat_to_matrix(wxyz: Sequence[float]) -> torch.Tensor:
    """[3, 3] float64 rotation of a (w, x, y, z) quaternion (normalised here)."""
    q = torch.as_tensor(wxyz, dtype=torch.float64)
    w, x, y, z = (q / q.norm()).tolist()
    return torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]],
                        dtype=torch.float64)


def camera_from_pose(wxyz: Sequence[float], position: Sequence[float], fov_y: float, width: int,
                     height: int) -> Camera:
    """The pinhole :class:`Camera` of a browser view.

    Args:
        wxyz: camera-to-world rotation (OpenCV axes) as a quaternion.
        position: [3] camera centre in world units.
        fov_y: vertical field of view in radians.
        width, height: image size in pixels (the principal point is the centre).
    """
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = quat_to_matrix(wxyz)
    c2w[:3, 3] = torch.as_tensor(position, dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    R = c2w[:3, :3].T
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ c2w[:3, 3]
    f = 0.5 * height / math.tan(0.5 * fov_y)
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(viewmat=viewmat, K=K, width=width, height=height, image_name="browser")


def pose_of(camera: Camera, distance: float = 1.0) -> dict:
    """What the browser needs to show ``camera``: position, look_at (``distance`` ahead), up
    (the camera's -y in world) and the vertical field of view in radians, as float lists."""
    c2w = camera.c2w.double().cpu()
    pos = c2w[:3, 3]
    forward, down = c2w[:3, 2], c2w[:3, 1]
    return {"position": pos.tolist(), "look_at": (pos + distance * forward).tolist(),
            "up": (-down).tolist(), "fov": float(camera.fov_y)}


def fit_size(width: int, height: int, max_pixels: int) -> tuple[int, int]:
    """(w, h) with the aspect of ``width x height`` and at most ``max_pixels`` pixels (never larger
    than the canvas), each at least 16."""
    scale = min(1.0, math.sqrt(max_pixels / max(width * height, 1)))
    return max(16, int(round(width * scale))), max(16, int(round(height * scale)))
