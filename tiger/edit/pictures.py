"""Pictures of an edit: before/after grids around the edited object."""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from tiger.render import Camera
from tiger.scene.gaussian_scene import GaussianScene, render_rgb


def before_after_grid(before: GaussianScene, after: GaussianScene, cameras: Sequence[Camera],
                      background: Optional[torch.Tensor] = None, gap: int = 4) -> torch.Tensor:
    """[2 H + gap, V W + (V - 1) gap, 3] on the CPU: the views before the edit (top row) and
    after (bottom), rendered by :func:`tiger.scene.render_rgb`."""
    rows = []
    for scene in (before, after):
        imgs = render_rgb(scene, cameras, background).cpu()
        h = imgs.shape[1]
        sep = torch.ones(h, gap, 3)
        row = [x for img in imgs for x in (img, sep)][:-1]
        rows.append(torch.cat(row, 1))
    return torch.cat([rows[0], torch.ones(gap, rows[0].shape[1], 3), rows[1]], 0)


__all__ = ["before_after_grid"]
