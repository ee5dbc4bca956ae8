"""The standard scene and camera, shared by the rendering tests and benchmarks.

Scene: N Gaussians with means uniform in [-1, 1]^3, scales log-uniform in [0.003, 0.03]
(world units), uniformly random rotations (normalised Gaussian quaternions), opacities
uniform in [0.05, 0.95], colours uniform in [0, 1] and 64-d features standard normal.
Camera: 3.5 units from the origin looking at it, vertical field of view 50 degrees,
pinhole with the principal point at the image centre, OpenCV axes.

:func:`heavy_tailed_scene` is its counterpart with real-scene statistics (log-normal scales
with a long tail, some Gaussians close to the camera), small enough for CI on the CPU.

Two views of the same definition: :func:`standard_scene` (tensors in a dict, channels chosen
up front) and :func:`standard_view` (a :class:`StandardScene` bundling the camera, with RGB
and features that ``.colors(C)`` combines for C in {3, 64, 67}).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

SCALE_RANGE = (0.003, 0.03)
OPACITY_RANGE = (0.05, 0.95)
CAMERA_DISTANCE = 3.5
FOV_Y_DEG = 50.0


def standard_scene(n: int, channels: int = 3, *, device: str = "cpu",
                   dtype: torch.dtype = torch.float32, seed: int = 0) -> dict[str, Tensor]:
    """Means [N,3], quats [N,4] (w,x,y,z), scales [N,3], opacities [N], colors [N,C].

    channels: 3 -> RGB uniform in [0,1]; 64 -> standard-normal features; otherwise the
    first 3 channels are RGB and the rest standard-normal features (C = 67 is RGB + 64-d).
    Drawn on the CPU in float64 from ``seed`` so every device and dtype sees the same scene.
    """
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    means = torch.rand(n, 3, generator=g, dtype=f64) * 2 - 1
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    lo, hi = math.log(SCALE_RANGE[0]), math.log(SCALE_RANGE[1])
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=f64) * (hi - lo) + lo)
    opac = torch.rand(n, generator=g, dtype=f64) * (OPACITY_RANGE[1] - OPACITY_RANGE[0]) + OPACITY_RANGE[0]
    if channels == 64:
        colors = torch.randn(n, 64, generator=g, dtype=f64)
    else:
        rgb = torch.rand(n, min(channels, 3), generator=g, dtype=f64)
        feats = torch.randn(n, max(channels - 3, 0), generator=g, dtype=f64)
        colors = torch.cat([rgb, feats], dim=1)
    out = {"means": means, "quats": quats, "scales": scales, "opacities": opac, "colors": colors}
    return {k: v.to(device=device, dtype=dtype) for k, v in out.items()}


HEAVY_SCALE_MEDIAN = 0.01   # world units
HEAVY_SCALE_LOG_SIGMA = 1.2  # log-normal: p99 ~ 16x, p99.9 ~ 40x the median
HEAVY_NEAR_FRACTION = 0.03   # share of Gaussians 0.15-1.0 units in front of the camera


def heavy_tailed_scene(n: int, channels: int = 3, *, device: str = "cpu",
                       dtype: torch.dtype = torch.float32, seed: int = 0) -> dict[str, Tensor]:
    """The standard scene's layout with real-scene statistics, for :func:`standard_camera`:
    per-axis scales log-normal (median HEAVY_SCALE_MEDIAN, sigma HEAVY_SCALE_LOG_SIGMA in
    log space: a long tail of large Gaussians) and HEAVY_NEAR_FRACTION of the means inside
    the view frustum 0.15-1 units from the camera, where they cover hundreds to thousands
    of tiles. Same keys, channels and seeding rules as :func:`standard_scene`."""
    s = standard_scene(n, channels, dtype=torch.float64, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    f64 = torch.float64
    s["scales"] = HEAVY_SCALE_MEDIAN * torch.exp(HEAVY_SCALE_LOG_SIGMA * torch.randn(n, 3, generator=g, dtype=f64))
    n_near = int(round(HEAVY_NEAR_FRACTION * n))
    depth = 0.15 + 0.85 * torch.rand(n_near, generator=g, dtype=f64)
    half = math.tan(math.radians(FOV_Y_DEG) / 2) * depth  # stay inside the vertical field of view
    xy = (torch.rand(n_near, 2, generator=g, dtype=f64) * 2 - 1) * half[:, None]
    s["means"][:n_near] = torch.stack([xy[:, 0], xy[:, 1], depth - CAMERA_DISTANCE], dim=1)
    return {k: v.to(device=device, dtype=dtype) for k, v in s.items()}


def standard_camera(width: int, height: int, *, device: str = "cpu",
                    dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """World->camera viewmat [4,4] (camera on -z at CAMERA_DISTANCE, looking at the origin,
    +y down) and intrinsics K [3,3] with a 50 degree vertical field of view."""
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[2, 3] = CAMERA_DISTANCE  # camera at (0, 0, -d): p_cam = p_world + (0, 0, d)
    fy = 0.5 * height / math.tan(math.radians(FOV_Y_DEG) / 2)
    K = torch.tensor([[fy, 0.0, width / 2], [0.0, fy, height / 2], [0.0, 0.0, 1.0]],
                     dtype=torch.float64)
    return viewmat.to(device=device, dtype=dtype), K.to(device=device, dtype=dtype)


@dataclass
class StandardScene:
    """The standard scene and camera as one object (see :func:`standard_view`)."""

    means: Tensor      # [N, 3]
    quats: Tensor      # [N, 4] (w, x, y, z), unit
    scales: Tensor     # [N, 3]
    opacities: Tensor  # [N]
    rgb: Tensor        # [N, 3]
    features: Tensor   # [N, 64]
    viewmat: Tensor    # [4, 4] world->camera, OpenCV axes
    K: Tensor          # [3, 3]
    width: int
    height: int

    def colors(self, channels: int) -> Tensor:
        """[N, C] channels: 3 = RGB, 64 = features, 67 = both; other C: uniform channels."""
        if channels == 3:
            return self.rgb
        if channels == 64:
            return self.features
        if channels == 67:
            return torch.cat([self.rgb, self.features], dim=1).contiguous()
        g = torch.Generator(device="cpu").manual_seed(channels)
        return torch.rand(self.rgb.shape[0], channels, generator=g).to(self.rgb)

    def to(self, device=None, dtype=None) -> "StandardScene":
        f = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
        return StandardScene(f(self.means), f(self.quats), f(self.scales), f(self.opacities),
                             f(self.rgb), f(self.features), f(self.viewmat), f(self.K),
                             self.width, self.height)


def standard_view(n: int, width: int, height: int, seed: int = 0,
                  dtype: torch.dtype = torch.float32, heavy_tailed: bool = False) -> StandardScene:
    """The standard scene (RGB + 64-d features, drawn as C = 67) with its camera, on the CPU;
    ``heavy_tailed``: :func:`heavy_tailed_scene` instead (same camera, channels and seed rules)."""
    s = (heavy_tailed_scene if heavy_tailed else standard_scene)(n, 67, dtype=torch.float64, seed=seed)
    V, K = standard_camera(width, height, dtype=torch.float64)
    c = s["colors"]
    return StandardScene(s["means"], s["quats"], s["scales"], s["opacities"], c[:, :3].contiguous(),
                         c[:, 3:].contiguous(), V, K, width, height).to(dtype=dtype)
