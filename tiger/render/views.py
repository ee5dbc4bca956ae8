"""Virtual cameras: look-at matrices, orbits around a point or a point cloud, and the views to
render along a capture's camera path (:func:`path_view_indices`). Views chosen from a scene's
content (the side it was observed from) are :mod:`tiger.scene.observed`."""
from __future__ import annotations

import math
from typing import Optional, Sequence, Union

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
                   up: Sequence[float] = (0.0, -1.0, 0.0), front: Optional[Sequence[float]] = None,
                   arc_deg: Optional[float] = None) -> list[Tensor]:
    """``n`` world→camera [4,4] matrices evenly spaced on a circle around ``center``,
    ``elevation_deg`` above its horizontal plane (the plane normal to ``up``).

    Angle 0 lies towards ``front`` [3] (its part in that plane; default world x, or z when up
    is near x). With ``arc_deg`` the views spread over an arc of that many degrees centred on
    angle ``start_deg`` (first and last view at its ends) instead of the whole circle.
    """
    c = torch.tensor(center, dtype=torch.float64)
    u = torch.tensor(up, dtype=torch.float64)
    u = u / u.norm()
    e1 = None
    if front is not None:
        f = torch.as_tensor(front, dtype=torch.float64).cpu()
        e1 = f - (f @ u) * u
        if float(e1.norm()) < 1e-6 * float(f.norm()):  # front along up: any horizontal axis
            e1 = None
    if e1 is None:
        a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        if abs(float(a @ u)) > 0.9:
            a = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        e1 = a - (a @ u) * u
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(u, e1)
    el = math.radians(elevation_deg)
    out = []
    for i in range(n):
        if arc_deg is None:
            t = math.radians(start_deg) + 2 * math.pi * i / n
        else:
            t = math.radians(start_deg) + math.radians(arc_deg) * ((i / (n - 1) - 0.5) if n > 1 else 0.0)
        eye = c + radius * (math.cos(el) * (math.cos(t) * e1 + math.sin(t) * e2) + math.sin(el) * u)
        out.append(look_at(eye.tolist(), c.tolist(), u.tolist()))
    return out


def orbit_cameras(n: int, width: int, height: int, fov_y_deg: float = 45.0, *, names: str = "orbit{:03d}",
                  **orbit: float | Sequence[float]) -> list[Camera]:
    """:class:`Camera` views on an orbit (see :func:`orbit_viewmats` for ``orbit``), the i-th
    named ``names.format(i)``."""
    K = pinhole_K(width, height, fov_y_deg)
    return [Camera(viewmat=V, K=K.clone(), width=width, height=height, image_name=names.format(i))
            for i, V in enumerate(orbit_viewmats(n, **orbit))]


def orbit_cameras_around(points: Tensor, n: int, width: int, height: int, fov_y_deg: float = 45.0,
                         **orbit: float | Sequence[float]) -> list[Camera]:
    """``n`` orbit cameras (:func:`orbit_cameras`) around the bulk of ``points`` [P, 3]: centred on
    the middle of their 2%-98% quantile box, at 1.1 x that box's diagonal (outliers ignored).
    ``orbit``: the other keywords of :func:`orbit_viewmats` (elevation_deg, up, front, arc_deg, ...)."""
    m = points.detach().float().cpu()
    lo, hi = torch.quantile(m, 0.02, dim=0), torch.quantile(m, 0.98, dim=0)
    return orbit_cameras(n, width, height, fov_y_deg, center=((lo + hi) / 2).tolist(),
                         radius=max(float((hi - lo).norm()) * 1.1, 1e-3), **orbit)


# -- views for scenes of a capture (forward-facing or not) ------------------------------------
def path_view_indices(count: int, views: Union[None, int, str, Sequence[int]] = None,
                      default: int = 8) -> list[int]:
    """Which of ``count`` cameras along a capture path to render.

    ``views``: None (``default`` views), a count ``k`` (an int or a string of digits: ``k`` views
    evenly spaced along the path, first and last included), or indices (a sequence, or a string
    with commas such as ``"0,12,24"``; a single index is written ``"12,"``). Counts above
    ``count`` give every view. Bad indices raise ValueError naming them.
    """
    if count <= 0:
        raise ValueError("tiger: no cameras to choose views from")
    if isinstance(views, str):
        text = views.strip()
        try:
            views = ([int(v) for v in text.split(",") if v.strip()] if "," in text else int(text))
        except ValueError:
            raise ValueError(f"tiger: views must be a count (8) or comma-separated indices (0,12,24), "
                             f"got {text!r}") from None
    if views is None or isinstance(views, int):
        k = default if views is None else views
        if k <= 0:
            raise ValueError(f"tiger: the number of views must be positive, got {k}")
        if k >= count:
            return list(range(count))
        return sorted({round(i * (count - 1) / max(k - 1, 1)) for i in range(k)})
    idx = [int(v) for v in views]
    bad = [v for v in idx if not 0 <= v < count]
    if bad or not idx:
        raise ValueError(f"tiger: view indices {bad or '[]'} are out of range: there are {count} cameras "
                         f"(0..{count - 1})")
    return idx


def fibonacci_directions(n: int) -> Tensor:
    """[n, 3] unit vectors spread evenly over the sphere (Fibonacci lattice), float64."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = (1 - z * z).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=1)
