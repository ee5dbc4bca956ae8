"""Virtual cameras: look-at matrices, orbits around a point, and the views to render of a
captured scene: along the capture's camera path when the cameras are known
(:func:`path_view_indices`), else an arc over the side the scene was observed from
(:func:`observed_orbit_cameras`)."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Optional, Sequence, Union

import torch
from torch import Tensor

from tiger.ops.sh import sh_to_color

from .camera import Camera

if TYPE_CHECKING:
    from tiger.scene import GaussianScene


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


def observed_direction(scene: "GaussianScene", candidates: int = 64) -> Optional[Tensor]:
    """The direction [3] (from the scene's centre towards where the cameras were) that the
    scene's view-dependent colour says was observed, or None for SH degree 0.

    Rule: training fits the SH colours only for the directions the cameras saw; elsewhere the
    higher bands extrapolate and the colours leave [0, 1]. For ``candidates`` directions d
    spread over the sphere, each Gaussian's colour is evaluated for a distant camera at d
    (view direction -d), and d scores the opacity-weighted mean amount by which the colours
    fall outside [0, 1]. The answer is the mean of the directions scoring within 10 % (of the
    score range) of the best: the centre of the observed cap.
    """
    if scene.sh_degree == 0 or len(scene) == 0:
        return None
    with torch.no_grad():
        sh = scene.sh.detach().float()
        w = scene.opacities.detach().float()
        dirs = fibonacci_directions(candidates).float().to(sh.device)
        scores = []
        for d in dirs:
            view = (-d).expand(sh.shape[0], 3)
            rgb = sh_to_color(view, sh, scene.sh_degree) + 0.5
            outside = (rgb - 1).clamp_min(0) + (-rgb).clamp_min(0)
            scores.append(float((outside.sum(1) * w).sum() / w.sum().clamp_min(1e-12)))
    sc = torch.tensor(scores, dtype=torch.float64)
    lo, hi = float(sc.min()), float(sc.max())
    if hi - lo <= 1e-9 * max(hi, 1.0):  # no direction stands out: nothing was learnt about views
        return None
    good = dirs.double().cpu()[sc <= lo + 0.1 * (hi - lo)]  # the best directions: a cap
    mean = good.mean(0)
    return mean / mean.norm() if float(mean.norm()) > 1e-6 else good[0]


def observed_orbit_cameras(scene: "GaussianScene", n: int, width: int, height: int, *,
                           arc_deg: float = 120.0, elevation_deg: float = 15.0,
                           up: Sequence[float] = (0.0, -1.0, 0.0), fov_y_deg: float = 45.0) -> list[Camera]:
    """``n`` views on an arc of ``arc_deg`` around the observed side of a scene with no cameras.

    The centre and radius are :func:`orbit_cameras_around`'s (the 2-98 % quantile box of the
    means); the arc is centred on :func:`observed_direction` (the full circle when the
    scene's colours do not say: SH degree 0), ``elevation_deg`` above the plane normal to
    ``up`` (the COLMAP/OpenCV habit: -y).
    """
    front = observed_direction(scene)
    arc = {} if front is None else {"front": front.tolist(), "arc_deg": arc_deg}
    return orbit_cameras_around(scene.means, n, width, height, fov_y_deg, elevation_deg=elevation_deg,
                                up=up, **arc)
