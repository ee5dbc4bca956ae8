"""Virtual cameras: look-at matrices and orbits around a point."""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from .camera import Camera


def look_at(eye: Sequence[float], target: Sequence[float],
            up: Sequence[float] = (0.0, -1.0, 0.0)) -> Tensor:
    """World→camera [4,4] (OpenCV axes: +x right, +y down, +z forward) from ``eye`` to ``target``.

    ``up`` is the world's up direction (default -y, the COLMAP/OpenCV habit of y pointing down).
    """
    eye_t, tgt = torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    f = tgt - eye_t
    f = f / f.norm()
    r = torch.linalg.cross(f, torch.tensor(up, dtype=torch.float64))
    if float(r.norm()) < 1e-9:  # looking along up: any perpendicular will do
        r = torch.linalg.cross(f, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    r = r / r.norm()
    d = torch.linalg.cross(f, r)
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = torch.stack([r, d, f])
    V[:3, 3] = -V[:3, :3] @ eye_t
    return V.float()


def pinhole_K(width: int, height: int, fov_y_deg: float = 45.0) -> Tensor:
    """[3,3] intrinsics with the given vertical field of view, principal point at the centre."""
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def orbit_viewmats(n: int, center: Sequence[float] = (0.0, 0.0, 0.0), radius: float = 3.0,
                   elevation_deg: float = 25.0, start_deg: float = 0.0,
                   up: Sequence[float] = (0.0, -1.0, 0.0)) -> list[Tensor]:
    """``n`` world→camera [4,4] matrices evenly spaced on a circle around ``center``,
    ``elevation_deg`` above its horizontal plane (the plane normal to ``up``)."""
    c = torch.tensor(center, dtype=torch.float64)
    u = torch.tensor(up, dtype=torch.float64)
    u = u / u.norm()
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(a @ u)) > 0.9:
        a = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    e1 = a - (a @ u) * u
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(u, e1)
    el = math.radians(elevation_deg)
    out = []
    for i in range(n):
        t = math.radians(start_deg) + 2 * math.pi * i / n
        eye = c + radius * (math.cos(el) * (math.cos(t) * e1 + math.sin(t) * e2) + math.sin(el) * u)
        out.append(look_at(eye.tolist(), c.tolist(), u.tolist()))
    return out


def orbit_cameras(n: int, width: int, height: int, fov_y_deg: float = 45.0,
                  **orbit: float | Sequence[float]) -> list[Camera]:
    """:class:`Camera` views on an orbit (see :func:`orbit_viewmats` for ``orbit``)."""
    K = pinhole_K(width, height, fov_y_deg)
    return [Camera(viewmat=V, K=K.clone(), width=width, height=height, image_name=f"orbit{i:03d}")
            for i, V in enumerate(orbit_viewmats(n, **orbit))]


def orbit_cameras_around(points: Tensor, n: int, width: int, height: int,
                         fov_y_deg: float = 45.0) -> list[Camera]:
    """``n`` orbit cameras (:func:`orbit_cameras`) around the bulk of ``points`` [P, 3]: centred on
    the middle of their 2%-98% quantile box, at 1.1 x that box's diagonal (outliers ignored)."""
    m = points.detach().float().cpu()
    lo, hi = torch.quantile(m, 0.02, dim=0), torch.quantile(m, 0.98, dim=0)
    return orbit_cameras(n, width, height, fov_y_deg, center=((lo + hi) / 2).tolist(),
                         radius=max(float((hi - lo).norm()) * 1.1, 1e-3))
