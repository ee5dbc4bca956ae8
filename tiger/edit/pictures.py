"""Pictures of an edit: before/after grids and turntable frames around the edited object."""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from tiger.scene.cameras import Camera
from tiger.scene.gaussian_scene import GaussianScene


@torch.no_grad()
def render_color(scene: GaussianScene, cameras: Sequence[Camera],
                 background: Optional[torch.Tensor] = None) -> list[torch.Tensor]:
    """[H, W, 3] renders in [0, 1] of ``scene`` (full SH colour) from each camera."""
    out = []
    bg = None if background is None else torch.as_tensor(background).to(scene.means)
    for cam in cameras:
        c = cam.to(scene.device, scene.dtype)
        r = scene.render(c, "rgb", background=bg, check_finite=False)
        out.append(r["color"].clamp(0, 1).cpu())
    return out


def before_after_grid(before: GaussianScene, after: GaussianScene, cameras: Sequence[Camera],
                      background: Optional[torch.Tensor] = None, gap: int = 4) -> torch.Tensor:
    """[2 H + gap, V W + (V - 1) gap, 3]: the views before the edit (top row) and after (bottom)."""
    rows = []
    for scene in (before, after):
        imgs = render_color(scene, cameras, background)
        h = imgs[0].shape[0]
        sep = torch.ones(h, gap, 3)
        row = [x for img in imgs for x in (img, sep)][:-1]
        rows.append(torch.cat(row, 1))
    return torch.cat([rows[0], torch.ones(gap, rows[0].shape[1], 3), rows[1]], 0)


__all__ = ["before_after_grid", "render_color"]
