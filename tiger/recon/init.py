"""Initial colours for Gaussians without a point cloud's colours."""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from tiger.render import Camera


@torch.no_grad()
def colors_from_views(points: torch.Tensor, cameras: Sequence[Camera], images: Sequence[torch.Tensor],
                      masks: Optional[Sequence[torch.Tensor]] = None) -> torch.Tensor:
    """[P, 3] mean colour of each point's pixel (nearest) over the views that see it.

    Args:
        points: [P, 3] world positions.
        cameras, images: the views; images [H, W, 3] in [0, 1].
        masks: optional [H, W] bool per image, the pixels that may be sampled.
    Points seen by no view get mid grey. A random point in free space gets the average of
    what lies behind it, which the fit corrects quickly; random colours (INRIA's synthetic
    init) take hundreds of steps at INRIA's colour learning rate to fade.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"tiger.recon: colors_from_views needs points [P, 3], got {list(points.shape)}")
    pts = points.detach().double().cpu()
    total = torch.zeros(pts.shape[0], 3, dtype=torch.float64)
    count = torch.zeros(pts.shape[0], dtype=torch.float64)
    for j, (cam, img) in enumerate(zip(cameras, images)):
        uv, z = cam.to("cpu", torch.float64).project(pts)
        u, v = torch.floor(uv[:, 0]), torch.floor(uv[:, 1])
        ok = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        ui, vi = u[ok].long(), v[ok].long()
        if masks is not None:
            good = masks[j].cpu()[vi, ui]
            idx = torch.nonzero(ok).reshape(-1)[good]
            ui, vi = ui[good], vi[good]
        else:
            idx = torch.nonzero(ok).reshape(-1)
        total[idx] += img.detach().cpu().double()[vi, ui]
        count[idx] += 1
    out = torch.full_like(total, 0.5)
    seen = count > 0
    out[seen] = total[seen] / count[seen, None]
    return out.to(points.dtype)
