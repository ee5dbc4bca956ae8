"""A small two-object scene with language features for the edit-loop tests (CPU, float32)."""
import math

import torch

from tiger.scene import GaussianScene

D = 8


def sphere_points(n, center, radius, g):
    d = torch.randn(n, 3, generator=g)
    return torch.tensor(center) + radius * d / d.norm(dim=1, keepdim=True)


def two_objects(n=300, seed=0, sh_degree=1):
    """Object A (blue ball at x=-0.4, lang e0) and B (green ball at x=+0.4, lang e1, view-dependent SH)."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.cat([sphere_points(n, (-0.4, 0.0, 0.0), 0.25, g), sphere_points(n, (0.4, 0.0, 0.0), 0.25, g)])
    cols = torch.cat([torch.tensor([0.1, 0.3, 0.85]).expand(n, 3), torch.tensor([0.2, 0.7, 0.2]).expand(n, 3)])
    s = GaussianScene.from_points(pts, cols, sh_degree=sh_degree, opacity=0.9, scales=torch.full((2 * n,), 0.05))
    s.sh_rest = 0.05 * torch.randn(s.sh_rest.shape, generator=g)
    e = torch.eye(D)
    lang = torch.cat([e[0].expand(n, D), e[1].expand(n, D)]) + 0.05 * torch.randn(2 * n, D, generator=g)
    s.lang = torch.nn.functional.normalize(lang, dim=1)
    return s


def query_a():
    return torch.eye(D)[0]
