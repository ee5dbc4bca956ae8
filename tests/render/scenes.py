"""Random test scenes and cameras shared by the rendering tests."""
from __future__ import annotations

import math

import torch


def look_at_viewmat(eye, target=(0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0), dtype=torch.float64):
    """World→camera [4,4] (OpenCV axes) for a camera at ``eye`` looking at ``target``."""
    eye = torch.tensor(eye, dtype=dtype)
    target = torch.tensor(target, dtype=dtype)
    f = target - eye
    f = f / f.norm()
    r = torch.linalg.cross(f, torch.tensor(up, dtype=dtype))
    r = r / r.norm()
    d = torch.linalg.cross(f, r)
    R = torch.stack([r, d, f])  # rows: camera axes in world
    V = torch.eye(4, dtype=dtype)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V


def intrinsics(width, height, fov_y_deg=50.0, dtype=torch.float64):
    fy = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return torch.tensor([[fy, 0, width / 2], [0, fy, height / 2], [0, 0, 1]], dtype=dtype)


def random_scene(n, channels=3, dtype=torch.float64, seed=0, scale_range=(0.02, 0.2),
                 opacity_range=(0.05, 0.95)):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * (hi - lo) + lo)
    opac = torch.rand(n, generator=g, dtype=dtype) * (opacity_range[1] - opacity_range[0]) + opacity_range[0]
    colors = torch.rand(n, channels, generator=g, dtype=dtype)
    return means, quats, scales, opac, colors


def camera(width, height, distance=3.5, dtype=torch.float64, eye=None):
    eye = eye if eye is not None else (0.3 * distance, -0.2 * distance, -distance)
    return look_at_viewmat(eye, dtype=dtype), intrinsics(width, height, dtype=dtype)
