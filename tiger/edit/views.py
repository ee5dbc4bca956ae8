"""Object-centred cameras for editing and deletion (paper §3.2, SPEC §6).

Every edit step renders V (default 4) virtual cameras that look at the retrieved object's centre
from a distance at which its robust bounding box fills the view. How they are spread depends on the
capture:

* **360° capture** (the capture's cameras surround the object): the V azimuths are evenly spaced
  (every 360°/V, i.e. 90° for 4 views) with one random offset per step, each with its own random
  elevation in ``elevation_deg`` above the object's horizontal plane.
* **Forward-facing capture**: the V azimuths are spread evenly over the capture's own azimuth
  range as seen from the object (stratified: view k at ``a_min + (k + u_k) / V * span``, u_k
  uniform), elevations uniform in the capture's elevation range.

The rule (:func:`capture_layout`): the capture's camera centres are expressed as azimuths around the
object's centre in the plane orthogonal to the world up direction; the capture is 360° when the
largest azimuth gap between neighbouring cameras is below ``gap_deg`` (default 120°), so that the
object has been seen from all sides; otherwise it is forward-facing. The up direction is the mean of
the capture cameras' up axes (-y in OpenCV axes), which is right for COLMAP and NeRF captures
taken upright; it can be given explicitly.

The distance: the box's half-diagonal r is the radius of a sphere holding the box; a pinhole with
the smaller field of view ``fov`` sees that sphere exactly at ``d = r / sin(fov / 2)``;
``fill`` (default 1.1) adds a margin, ``d = fill · r / sin(fov / 2)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from tiger.render.views import look_at, pinhole_K
from tiger.render import Camera
from tiger.scene.cameras import camera_centers


def capture_up(cameras: Sequence[Camera]) -> torch.Tensor:
    """[3] unit world up direction: the mean of the cameras' up axes (OpenCV: -y row of R)."""
    if len(cameras) == 0:
        raise ValueError("tiger.edit.views: capture_up needs at least one camera")
    ups = torch.stack([-c.viewmat.double()[1, :3] for c in cameras])
    up = ups.mean(0)
    if float(up.norm()) < 1e-6:
        raise ValueError("tiger.edit.views: the cameras' up axes cancel out; pass up= explicitly")
    return up / up.norm()


def _frame(up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(u, e1, e2): up and two unit axes spanning the plane orthogonal to it (right-handed)."""
    u = up.double() / up.double().norm()
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(a @ u)) > 0.9:
        a = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    e1 = a - (a @ u) * u
    e1 = e1 / e1.norm()
    return u, e1, torch.linalg.cross(u, e1)


def _wrap(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a, 2 * math.pi)


@dataclass
class CaptureLayout:
    """How the capture sees the object: its azimuth/elevation ranges around the object's centre.

    Attributes:
        is_360: whether the capture surrounds the object (largest azimuth gap < ``gap_deg``).
        up: [3] world up direction.
        azimuth_start_deg, azimuth_span_deg: the capture's azimuth arc (start, counter-clockwise
            span about ``up``) around the object; span 360 for a 360° capture.
        elevation_min_deg, elevation_max_deg: the capture's elevation range above the object's
            horizontal plane.
        largest_gap_deg: the largest azimuth gap between neighbouring capture cameras.
    """

    is_360: bool
    up: torch.Tensor
    azimuth_start_deg: float
    azimuth_span_deg: float
    elevation_min_deg: float
    elevation_max_deg: float
    largest_gap_deg: float


def capture_layout(cameras: Sequence[Camera], center: torch.Tensor, up: Optional[torch.Tensor] = None,
                   gap_deg: float = 120.0) -> CaptureLayout:
    """Decide 360° vs forward-facing for an object at ``center`` [3] from the capture ``cameras``.

    See the module docstring for the rule. ``up`` defaults to :func:`capture_up`.
    """
    if len(cameras) == 0:
        raise ValueError("tiger.edit.views: capture_layout needs the scene's cameras (got none)")
    u = capture_up(cameras) if up is None else torch.as_tensor(up).detach().cpu().double()
    u, e1, e2 = _frame(u)
    d = camera_centers(cameras) - torch.as_tensor(center).detach().cpu().double().reshape(1, 3)
    h = d - (d @ u)[:, None] * u
    az = _wrap(torch.atan2(h @ e2, h @ e1))
    el = torch.atan2(d @ u, h.norm(dim=1))
    s = torch.sort(az).values
    gaps = torch.cat([s[1:] - s[:-1], (s[:1] + 2 * math.pi) - s[-1:]])
    k = int(torch.argmax(gaps))
    gap = float(gaps[k])
    start = float(s[(k + 1) % len(s)])  # the arc begins after the largest gap
    span = 2 * math.pi - gap
    return CaptureLayout(is_360=math.degrees(gap) < gap_deg, up=u, azimuth_start_deg=math.degrees(start),
                         azimuth_span_deg=math.degrees(span), elevation_min_deg=math.degrees(float(el.min())),
                         elevation_max_deg=math.degrees(float(el.max())), largest_gap_deg=math.degrees(gap))


def fill_distance(bbox_min: torch.Tensor, bbox_max: torch.Tensor, fov_rad: float, fill: float = 1.1) -> float:
    """Camera distance at which the box [bbox_min, bbox_max] (world units) fills a view of ``fov_rad``."""
    r = 0.5 * float((torch.as_tensor(bbox_max).detach().cpu().double()
                     - torch.as_tensor(bbox_min).detach().cpu().double()).norm())
    if not (0 < fov_rad < math.pi):
        raise ValueError(f"tiger.edit.views: field of view must be in (0, pi) radians, got {fov_rad}")
    return fill * max(r, 1e-6) / math.sin(fov_rad / 2)


class ObjectViews:
    """Draws V cameras around an object every edit step (see the module docstring).

    Args:
        center: [3] the object's centre (retrieval's median position).
        bbox_min, bbox_max: [3] its robust bounding box.
        capture: the scene's cameras (decide 360° vs forward-facing and the up direction); or None
            with ``layout`` given.
        n_views: V (4 in the paper).
        width, height: render size in pixels; fov_deg: vertical field of view.
        elevation_deg: (lo, hi) elevation range for 360° captures (degrees above the horizontal).
        fill: margin on the fill distance (1 = the box's sphere touches the frame).
        layout: a precomputed :class:`CaptureLayout` (else from ``capture``).
        force_360: override the rule (True/False), None: decided from the capture. Without a
            capture, ``force_360=True`` places a 360° ring about ``up`` (default -y, OpenCV habit).
    """

    def __init__(self, center: torch.Tensor, bbox_min: torch.Tensor, bbox_max: torch.Tensor,
                 capture: Optional[Sequence[Camera]] = None, n_views: int = 4, width: int = 512,
                 height: int = 512, fov_deg: float = 49.1, elevation_deg: tuple[float, float] = (0.0, 30.0),
                 fill: float = 1.1, layout: Optional[CaptureLayout] = None,
                 force_360: Optional[bool] = None, up: Optional[torch.Tensor] = None) -> None:
        if n_views < 1:
            raise ValueError(f"tiger.edit.views: n_views must be >= 1, got {n_views}")
        if layout is None and not capture:
            if force_360 is not True:
                raise ValueError("tiger.edit.views: give the scene's cameras (capture=), a layout, or force_360=True")
            u = (torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64) if up is None
                 else torch.as_tensor(up).detach().cpu().double())
            layout = CaptureLayout(True, u / u.norm(), 0.0, 360.0, float(elevation_deg[0]), float(elevation_deg[1]), 0.0)
        elif layout is None:
            layout = capture_layout(capture, center, up=up)
        self.layout = layout
        self.is_360 = layout.is_360 if force_360 is None else bool(force_360)
        self.center = torch.as_tensor(center).detach().cpu().double().reshape(3)  # cameras live on the CPU
        self.n_views, self.width, self.height = int(n_views), int(width), int(height)
        self.K = pinhole_K(self.width, self.height, fov_deg)
        fov = min(math.radians(fov_deg), 2 * math.atan(0.5 * self.width / float(self.K[0, 0])))
        self.distance = fill_distance(bbox_min, bbox_max, fov, fill)
        self.elevation_deg = (tuple(map(float, elevation_deg)) if self.is_360 else
                              (layout.elevation_min_deg, layout.elevation_max_deg))
        self._u, self._e1, self._e2 = _frame(layout.up)

    def angles(self, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(azimuths [V], elevations [V]) in radians for one step, drawn from ``generator``."""
        V = self.n_views
        r = torch.rand(V + 1, generator=generator, dtype=torch.float64)
        k = torch.arange(V, dtype=torch.float64)
        if self.is_360:
            az = r[0] * 2 * math.pi + k * (2 * math.pi / V)
        else:
            start, span = math.radians(self.layout.azimuth_start_deg), math.radians(self.layout.azimuth_span_deg)
            az = start + (k + r[1:]) / V * span
        lo, hi = (math.radians(e) for e in self.elevation_deg)
        el = lo + (hi - lo) * torch.rand(V, generator=generator, dtype=torch.float64)
        return _wrap(az), el

    def cameras_at(self, azimuths: torch.Tensor, elevations: torch.Tensor) -> list[Camera]:
        """Cameras on the sphere of radius ``distance`` around the centre at the given angles (radians)."""
        out = []
        for i, (a, e) in enumerate(zip(azimuths.tolist(), elevations.tolist())):
            direction = math.cos(e) * (math.cos(a) * self._e1 + math.sin(a) * self._e2) + math.sin(e) * self._u
            eye = self.center + self.distance * direction
            V = look_at(eye.tolist(), self.center.tolist(), self._u.tolist()).double()
            out.append(Camera(viewmat=V, K=self.K.double().clone(), width=self.width, height=self.height,
                              image_name=f"edit_view{i}",
                              metadata={"azimuth_deg": math.degrees(a), "elevation_deg": math.degrees(e)}))
        return out

    def sample(self, generator: torch.Generator) -> list[Camera]:
        """V fresh cameras for one step (deterministic given the generator's state)."""
        return self.cameras_at(*self.angles(generator))

    def fixed(self, n: Optional[int] = None, elevation_deg: Optional[float] = None) -> list[Camera]:
        """``n`` (default V) evenly spread cameras, no randomness (pictures, metrics, turntables).

        360°: azimuths 0, 360/n, ...; forward-facing: the midpoints of n equal parts of the
        capture's azimuth arc. Elevation: the middle of the range unless given.
        """
        n = self.n_views if n is None else int(n)
        k = torch.arange(n, dtype=torch.float64)
        if self.is_360:
            az = k * (2 * math.pi / n)
        else:
            start, span = math.radians(self.layout.azimuth_start_deg), math.radians(self.layout.azimuth_span_deg)
            az = start + (k + 0.5) / n * span
        e = (sum(self.elevation_deg) / 2) if elevation_deg is None else float(elevation_deg)
        return self.cameras_at(_wrap(az), torch.full((n,), math.radians(e), dtype=torch.float64))


__all__ = ["CaptureLayout", "ObjectViews", "capture_layout", "capture_up", "fill_distance"]
