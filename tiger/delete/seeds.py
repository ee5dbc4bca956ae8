"""New Gaussians for the parts of a hole that nothing in the scene can fill, and view crops.

After a deletion, where a view's hole is thin (nothing remains behind the removed object) the
refit has no Gaussian to move there. Seeds are made from the inpainted views: hole pixels on a
grid of ``stride`` pixels are lifted to 3D at an inpainted depth (the remainder's depth filled
into the thin region from the surrounding surface), coloured with the inpainted target.

A seed is kept only if the other views agree: in every other view it projects either outside
the image, inside that view's ``allowed`` region (the hole; :func:`tiger.delete` grows it by
a few pixels of slack for the filled depth's error), or behind the remainder's surface
(occluded). A seed that would show up in another view outside its hole is dropped, so seeding
does not change what a view showed elsewhere. Seeds are only made where the target differs from the remainder's
render (``min_change``): where the inpainting just continued the background, nothing is added.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional, Sequence

import logging

import torch

from tiger.render import Camera

log = logging.getLogger(__name__)


def crop_camera(camera: Camera, x0: int, y0: int, width: int, height: int) -> Camera:
    """The sub-window [y0:y0+height, x0:x0+width] of ``camera`` as a camera of its own: its
    render equals that window of the full render (principal point shifted, pixel centres kept)."""
    if not (0 <= x0 and 0 <= y0 and width > 0 and height > 0 and x0 + width <= camera.width
            and y0 + height <= camera.height):
        raise ValueError(f"tiger.delete.crop_camera: window x0={x0} y0={y0} {width}x{height} is not inside "
                         f"the {camera.width}x{camera.height} image")
    K = camera.K.clone()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return dataclasses.replace(camera, K=K, width=int(width), height=int(height))


def mask_window(mask: torch.Tensor, margin: int, multiple: int = 16) -> tuple[int, int, int, int]:
    """(x0, y0, width, height): the bounding box of ``mask`` [H, W] grown by ``margin`` pixels,
    sizes rounded up to ``multiple`` (tile-aligned renders), clipped to the image. Empty mask:
    the whole image."""
    h, w = mask.shape
    ys, xs = torch.nonzero(mask, as_tuple=True)
    if ys.numel() == 0:
        return 0, 0, w, h
    x0, x1 = max(int(xs.min()) - margin, 0), min(int(xs.max()) + 1 + margin, w)
    y0, y1 = max(int(ys.min()) - margin, 0), min(int(ys.max()) + 1 + margin, h)
    cw = min(-(-(x1 - x0) // multiple) * multiple, w)
    ch = min(-(-(y1 - y0) // multiple) * multiple, h)
    return min(x0, w - cw), min(y0, h - ch), cw, ch


@dataclass
class Seeds:
    """Seed Gaussians: means [S, 3], rgb [S, 3] in [0, 1], scales [S] (isotropic std, world units),
    and the view each came from, views [S] int64."""

    means: torch.Tensor
    rgb: torch.Tensor
    scales: torch.Tensor
    views: torch.Tensor

    def __len__(self) -> int:
        return int(self.means.shape[0])


def seed_points(cameras: Sequence[Camera], holes: torch.Tensor, thin: torch.Tensor, depth: torch.Tensor,
                targets: torch.Tensor, rest_rgb: torch.Tensor, rest_depth: torch.Tensor,
                rest_alpha: torch.Tensor, *, stride: int = 4, min_change: float = 0.05,
                depth_tolerance: float = 0.02, opaque: float = 0.5, max_views: int = 8,
                allowed: Optional[torch.Tensor] = None) -> Seeds:
    """Lift thin hole pixels to seed Gaussians (module docstring).

    Args:
        cameras: the V views.
        holes: [V, H, W] bool hole masks (dilated).
        thin: [V, H, W] bool, where the remainder's alpha is below the thin threshold.
        depth: [V, H, W] inpainted depth (camera z) valid at ``holes & thin``.
        targets: [V, H, W, 3] inpainted target images.
        rest_rgb, rest_depth, rest_alpha: [V, H, W, (3)] the remainder's render.
        stride: seed grid spacing in pixels (a seed's std is ``stride / 2`` pixels at its depth).
        min_change: minimal mean |target - remainder| over RGB for a pixel to need a seed.
        depth_tolerance: relative depth margin of the occlusion test in other views.
        opaque: remainder alpha above which a pixel counts as a surface for the occlusion test.
        max_views: seeds come from at most this many views (those with the largest thin holes).
        allowed: [V, H, W] bool, where a seed may be seen in the other views (default ``holes``).
    """
    v, h, w = holes.shape
    dev = depth.device
    need = holes & thin & (depth > 0) & ((targets - rest_rgb).abs().mean(-1) > min_change)
    grid = torch.zeros(h, w, dtype=torch.bool, device=dev)
    grid[stride // 2::stride, stride // 2::stride] = True
    need &= grid
    order = torch.argsort(need.flatten(1).sum(1), descending=True)[:max_views]
    means, rgb, scales, views = [], [], [], []
    for i in order.tolist():
        ys, xs = torch.nonzero(need[i], as_tuple=True)
        if ys.numel() == 0:
            continue
        cam = cameras[i]
        K = cam.K.to(dev, torch.float32)
        z = depth[i, ys, xs]
        xc = (xs.float() + 0.5 - K[0, 2]) / K[0, 0] * z
        yc = (ys.float() + 0.5 - K[1, 2]) / K[1, 1] * z
        pc = torch.stack([xc, yc, z], 1)
        c2w = cam.c2w.to(dev, torch.float32)
        means.append(pc @ c2w[:3, :3].T + c2w[:3, 3])
        rgb.append(targets[i, ys, xs])
        scales.append(0.5 * stride * z / K[0, 0])
        views.append(torch.full_like(z, i, dtype=torch.long))
    if not means:
        e = torch.zeros(0, 3, device=dev)
        return Seeds(e, e.clone(), torch.zeros(0, device=dev), torch.zeros(0, dtype=torch.long, device=dev))
    seeds = Seeds(torch.cat(means), torch.cat(rgb), torch.cat(scales), torch.cat(views))
    keep = torch.ones(len(seeds), dtype=torch.bool, device=dev)
    reasons = torch.zeros(len(cameras), dtype=torch.long)
    for j, cam in enumerate(cameras):
        uv, z = cam.to(dev, torch.float32).project(seeds.means)
        px, py = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        inside = (z > 0) & (px >= 0) & (px < w) & (py >= 0) & (py < h) & (seeds.views != j)
        pxc, pyc = px.clamp(0, w - 1), py.clamp(0, h - 1)
        in_hole = (holes if allowed is None else allowed)[j, pyc, pxc]
        surface = rest_alpha[j, pyc, pxc] > opaque
        occluded = surface & (rest_depth[j, pyc, pxc] < z * (1 - depth_tolerance))
        ok = ~inside | in_hole | occluded
        reasons[j] = int((~ok).sum())
        keep &= ok
    log.debug("seeds: %d candidates, %d kept; dropped as visible outside the hole per view: %s",
              len(seeds), int(keep.sum()), reasons.tolist())
    return Seeds(seeds.means[keep], seeds.rgb[keep], seeds.scales[keep], seeds.views[keep])
