"""A procedural tabletop scene built from Gaussians: a table with a mug, a ball, a box
and a potted plant, every Gaussian labelled with its object.

World axes follow the OpenCV/COLMAP habit: +y points down (the table top is the plane
y = 0 and objects sit at y < 0). Units are arbitrary (the table is 1.6 wide).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from tiger.scene import GaussianScene
from tiger.scene.labelled import LabelledScene
from tiger.scene.sh import rgb_to_sh

__all__ = ["DEMO_ORBIT", "tabletop_scene"]

#: The demo's views: cameras circling the table, looking slightly down at it (the orbit keywords
#: of :func:`tiger.render.views.orbit_cameras` / ``orbit_viewmats``; add ``start_deg``).
DEMO_ORBIT = {"center": (0.0, -0.1, 0.0), "radius": 3.0, "elevation_deg": 25.7, "up": (0.0, -1.0, 0.0)}

#: The demo's objects; a Gaussian's label indexes this list.
_NAMES = ["table", "mug", "ball", "box", "plant"]


def _frame_quats(normals: Tensor) -> Tensor:
    """Quaternions rotating the local z axis onto ``normals`` [N,3] → [N,4] (w,x,y,z)."""
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(normals)
    n = normals / normals.norm(dim=1, keepdim=True)
    axis = torch.linalg.cross(z, n)
    w = 1.0 + (z * n).sum(1, keepdim=True)
    q = torch.cat([w, axis], dim=1)
    flip = w.squeeze(1) < 1e-6  # normal = -z: rotate by pi about x
    q[flip] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    return q / q.norm(dim=1, keepdim=True)


def _surfels(points: Tensor, normals: Tensor, rgb: Tensor, size: float, label: int,
             g: torch.Generator, opacity: float = 0.95, jitter: float = 0.08) -> LabelledScene:
    """Flat Gaussians (thin along the normal) covering a sampled surface."""
    n = points.shape[0]
    s = size * (1 + jitter * torch.randn(n, 1, generator=g)).clamp(0.5, 1.5)
    scales = torch.cat([s, s, 0.15 * s], dim=1)
    col = (rgb.expand(n, 3) * (1 + 0.06 * torch.randn(n, 1, generator=g))).clamp(0, 1)
    gs = GaussianScene.from_values(points, _frame_quats(normals), scales, torch.full((n,), opacity), col)
    return LabelledScene(gs, torch.full((n,), label, dtype=torch.long), _NAMES)


def _recolor(part: LabelledScene, rgb: Tensor) -> None:
    """Give the Gaussians of ``part`` the colours ``rgb`` [N, 3]."""
    part.scene.sh_dc = rgb_to_sh(rgb)


def _box(center, size, n, g):
    """Points and outward normals on the surface of an axis-aligned box."""
    c = torch.tensor(center)
    half = torch.tensor(size) / 2
    areas = torch.tensor([size[1] * size[2], size[0] * size[2], size[0] * size[1]]).repeat(2)
    face = torch.multinomial(areas, n, replacement=True, generator=g)
    u = torch.rand(n, 3, generator=g) * 2 - 1
    axis, sign = face % 3, torch.where(face < 3, 1.0, -1.0)
    u[torch.arange(n), axis] = sign
    normals = torch.zeros(n, 3)
    normals[torch.arange(n), axis] = sign
    return c + u * half, normals


def _cylinder(center, radius, height, n, g, caps=(True, True)):
    c = torch.tensor(center)
    side = int(n * (2 * math.pi * radius * height) /
               (2 * math.pi * radius * height + sum(caps) * math.pi * radius**2))
    th = torch.rand(side, generator=g) * 2 * math.pi
    y = (torch.rand(side, generator=g) - 0.5) * height
    pts = [torch.stack([radius * torch.cos(th), y, radius * torch.sin(th)], 1)]
    nrm = [torch.stack([torch.cos(th), torch.zeros_like(th), torch.sin(th)], 1)]
    rest = n - side
    for k, (on, sy) in enumerate(zip(caps, (-1.0, 1.0))):
        if not on:
            continue
        m = rest // max(sum(caps), 1)
        r = radius * torch.sqrt(torch.rand(m, generator=g))
        a = torch.rand(m, generator=g) * 2 * math.pi
        pts.append(torch.stack([r * torch.cos(a), torch.full((m,), sy * height / 2), r * torch.sin(a)], 1))
        nrm.append(torch.tensor([0.0, sy, 0.0]).expand(m, 3))
    return torch.cat(pts) + c, torch.cat(nrm)


def _sphere(center, radius, n, g, squash=(1.0, 1.0, 1.0)):
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    sq = torch.tensor(squash)
    return torch.tensor(center) + radius * d * sq, d / sq


def tabletop_scene(density: float = 1.0, seed: int = 0) -> LabelledScene:
    """The demo scene (~20k Gaussians at density 1). Labels: table, mug, ball, box, plant."""
    g = torch.Generator().manual_seed(seed)
    k = lambda n: max(int(n * density), 16)  # noqa: E731
    parts = []
    top, nt = _box((0.0, 0.03, 0.0), (1.6, 0.06, 1.0), k(6000), g)
    parts.append(_surfels(top, nt, torch.tensor([0.55, 0.36, 0.2]), 0.022, 0, g))
    for x in (-0.7, 0.7):
        for z in (-0.4, 0.4):
            p, nn = _cylinder((x, 0.4, z), 0.04, 0.68, k(400), g, caps=(False, True))
            parts.append(_surfels(p, nn, torch.tensor([0.4, 0.26, 0.15]), 0.02, 0, g))
    # mug: white body with a red band, and a handle
    p, nn = _cylinder((-0.4, -0.13, 0.1), 0.11, 0.26, k(2200), g, caps=(False, True))
    col = torch.where((p[:, 1:2] > -0.17) & (p[:, 1:2] < -0.09), torch.tensor([0.85, 0.1, 0.1]),
                      torch.tensor([0.93, 0.93, 0.9]))
    mug = _surfels(p, nn, torch.ones(3), 0.014, 1, g)
    _recolor(mug, (col * (1 + 0.04 * torch.randn(p.shape[0], 1, generator=g))).clamp(0, 1))
    parts.append(mug)
    th = torch.rand(k(500), generator=g) * math.pi * 1.2 - 0.6 * math.pi
    ph = torch.rand(k(500), generator=g) * 2 * math.pi
    R, r = 0.07, 0.018
    ring = torch.stack([(R + r * torch.cos(ph)) * torch.cos(th), (R + r * torch.cos(ph)) * torch.sin(th),
                        r * torch.sin(ph)], 1)
    hp = ring + torch.tensor([-0.4 - 0.11 - 0.03, -0.13, 0.1])
    hn = torch.stack([torch.cos(ph) * torch.cos(th), torch.cos(ph) * torch.sin(th), torch.sin(ph)], 1)
    parts.append(_surfels(hp, hn, torch.tensor([0.93, 0.93, 0.9]), 0.01, 1, g))
    # ball: blue with a yellow stripe
    p, nn = _sphere((0.05, -0.16, -0.25), 0.16, k(2600), g)
    ball = _surfels(p, nn, torch.ones(3), 0.016, 2, g)
    _recolor(ball, torch.where(((p[:, 1:2] + 0.16).abs() < 0.035), torch.tensor([0.95, 0.8, 0.1]),
                               torch.tensor([0.1, 0.3, 0.85])))
    parts.append(ball)
    # box: cardboard cube
    p, nn = _box((0.45, -0.14, 0.15), (0.28, 0.28, 0.28), k(3000), g)
    parts.append(_surfels(p, nn, torch.tensor([0.78, 0.6, 0.35]), 0.016, 3, g))
    # plant: terracotta pot + green leafy crown
    p, nn = _cylinder((-0.05, -0.09, 0.3), 0.09, 0.18, k(1500), g, caps=(False, False))
    parts.append(_surfels(p, nn, torch.tensor([0.75, 0.35, 0.2]), 0.014, 4, g))
    for j in range(7):
        a = 2 * math.pi * j / 7
        cen = (-0.05 + 0.09 * math.cos(a), -0.3 - 0.05 * (j % 3), 0.3 + 0.09 * math.sin(a))
        p, nn = _sphere(cen, 0.08, k(350), g, squash=(1.0, 0.45, 1.0))
        parts.append(_surfels(p, nn, torch.tensor([0.15, 0.55 + 0.05 * (j % 3), 0.18]), 0.016, 4, g))
    return LabelledScene.concat(parts, _NAMES)

