"""A known Gaussian scene and cameras around it, for reconstruction tests and benchmarks."""
from __future__ import annotations

import math

import torch

from tiger.render.views import look_at
from tiger.render import Camera
from tiger.scene import GaussianScene
from tiger.scene.cameras import intrinsics


def sphere_cameras(n: int, size: int = 64, radius: float = 4.0, offset: float = 0.0) -> list:
    """``n`` cameras on a (Fibonacci) sphere looking at the origin; ``offset`` shifts the
    spiral (in [0, 1)) so that two calls give disjoint view sets."""
    cams = []
    for i in range(n):
        t = (i + 0.25 + 0.5 * offset) / n   # never exactly at a pole (up vector)
        z = 1 - 2 * t
        r = math.sqrt(max(0.0, 1 - z * z))
        phi = (i + offset) * 2.399963229728653
        eye = (radius * r * math.cos(phi), radius * r * math.sin(phi), 0.8 * radius * z)
        cams.append(Camera(look_at(eye, (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)).double(), intrinsics(1.1 * size, 1.1 * size, size / 2, size / 2), size, size,
                           image_name=f"view_{i:03d}_{offset}"))
    return cams


def ground_truth(n: int = 64, seed: int = 1) -> GaussianScene:
    """``n`` opaque, anisotropic, randomly coloured Gaussians in [-1, 1]^3 (SH degree 0)."""
    g = torch.Generator().manual_seed(seed)
    s = GaussianScene.random_in_box(n, [-1, -1, -1], [1, 1, 1], sh_degree=0, generator=g)
    s.log_scales = torch.log(0.08 + 0.15 * torch.rand(n, 3, generator=g))
    s.quats = torch.randn(n, 4, generator=g)
    s.opacity_logits = torch.full((n,), 3.0)
    return s


@torch.no_grad()
def render_views(scene: GaussianScene, cams: list) -> list:
    return [scene.render(c)["color"].clamp(0, 1) for c in cams]
