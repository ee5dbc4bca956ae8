"""Views of a scene that has no cameras: the side its view-dependent colour says was observed,
and an arc of orbit cameras around it (``tiger render`` without a capture)."""
from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor

from tiger.ops.sh import sh_to_color
from tiger.render import Camera
from tiger.render.views import fibonacci_directions, orbit_cameras_around

from .gaussian_scene import GaussianScene

__all__ = ["observed_direction", "observed_orbit_cameras"]


def observed_direction(scene: GaussianScene, candidates: int = 64) -> Optional[Tensor]:
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


def observed_orbit_cameras(scene: GaussianScene, n: int, width: int, height: int, *,
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
