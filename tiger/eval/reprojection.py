"""Deletion metrics (the edit's, :mod:`tiger.eval.edit`, plus the hole's): locality outside the removed object, fidelity inside the holes, and the
multi-view consistency of the fill by reprojection between neighbouring views.

Reprojection consistency: each hole pixel of view i with an opaque result (alpha > 0.5) is
lifted to 3D with the result's depth and projected into the nearest other view j (by camera
centre); it counts when it lands inside j, j's result is opaque there and j's depth agrees within
``depth_tolerance`` (the same surface point, not occluded). The PSNR between the colours at the
matched pixel pairs is reported for the result's renders (the 3D fill) and for the inpainted
targets (the independent 2D inpaints, which a refit should make consistent).
"""
from __future__ import annotations

import math
from typing import Sequence

import torch

from tiger.render import Camera

from .edit import PSNR_CAP, psnr_outside


def _psnr_inside(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR (dB, capped as :func:`tiger.eval.edit.psnr_outside`) of images [V,H,W,C] over the
    pixels of ``mask`` [V,H,W]; NaN for an empty mask."""
    if not bool(mask.any()):
        return float("nan")
    return psnr_outside(a.clamp(0, 1), b.clamp(0, 1), ~mask.to(a.device), 0)["psnr"]


def _nearest_views(cameras: Sequence[Camera]) -> list[int]:
    c = torch.stack([cam.center.double().cpu() for cam in cameras])
    d = torch.cdist(c, c)
    d.fill_diagonal_(float("inf"))
    return d.argmin(1).tolist()


def reprojection_pairs(cameras: Sequence[Camera], mask: torch.Tensor, depth: torch.Tensor,
                       alpha: torch.Tensor, depth_tolerance: float = 0.02
                       ) -> list[tuple[int, int, torch.Tensor, torch.Tensor]]:
    """Matched pixels of ``mask`` [V,H,W] between each view and its nearest neighbour.

    Returns [(i, j, pix_i [P,2] (y, x), pix_j [P,2] (y, x))] (see the module docstring).
    """
    v, h, w = mask.shape
    out = []
    if v < 2:
        return out
    for i, j in enumerate(_nearest_views(cameras)):
        ys, xs = torch.nonzero(mask[i] & (alpha[i] > 0.5), as_tuple=True)
        if ys.numel() == 0:
            continue
        ci, cj = cameras[i].to(depth.device, torch.float64), cameras[j].to(depth.device, torch.float64)
        z = depth[i, ys, xs].double()
        K = ci.K
        pc = torch.stack([(xs + 0.5 - K[0, 2]) / K[0, 0] * z, (ys + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
        c2w = ci.c2w
        world = pc @ c2w[:3, :3].T + c2w[:3, 3]
        uv, zj = cj.project(world)
        px, py = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        ok = (zj > 0) & (px >= 0) & (px < w) & (py >= 0) & (py < h)
        pxc, pyc = px.clamp(0, w - 1), py.clamp(0, h - 1)
        ok &= alpha[j, pyc, pxc] > 0.5
        ok &= (depth[j, pyc, pxc].double() - zj).abs() <= depth_tolerance * zj
        out.append((i, j, torch.stack([ys[ok], xs[ok]], 1), torch.stack([pyc[ok], pxc[ok]], 1)))
    return out


def pair_psnr(images: torch.Tensor, pairs) -> float:
    """PSNR between the colours of ``images`` [V,H,W,C] at matched pixel pairs."""
    a = [images[i][p[:, 0], p[:, 1]] for i, _, p, _ in pairs]
    b = [images[j][q[:, 0], q[:, 1]] for _, j, _, q in pairs]
    if not a or sum(x.shape[0] for x in a) == 0:
        return float("nan")
    d = (torch.cat(a).clamp(0, 1) - torch.cat(b).clamp(0, 1)).double()
    mse = float((d * d).mean())
    return PSNR_CAP if mse <= 10 ** (-PSNR_CAP / 10) else -10.0 * math.log10(mse)


@torch.no_grad()
def delete_metrics(cameras: Sequence[Camera], before: torch.Tensor, remaining: torch.Tensor,
                   targets: torch.Tensor, after: torch.Tensor, holes: torch.Tensor,
                   footprint: torch.Tensor, scene, background=(0.0, 0.0, 0.0)) -> dict:
    """Metrics of a deletion on its V views (images [V,H,W,3], masks [V,H,W] bool).

    - ``locality_psnr``: result vs the scene before deletion, outside the removed object's
      dilated footprint (what should not change did not; :func:`tiger.eval.edit.psnr_outside`,
      capped at ``PSNR_CAP`` like every PSNR here);
    - ``rest_psnr``: result vs the scene right after removal, outside the holes;
    - ``hole_psnr``: result vs the inpainted targets inside the holes; ``hole_surface_psnr`` the
      same over the hole pixels the result covers with a surface (alpha > 0.5), and
      ``hole_surface_fraction`` their share: where a hole borders empty space, the views' 2D
      inpaints disagree and the refit keeps them empty, as the other views require;
    - ``fill_reprojection_psnr`` / ``inpaint_reprojection_psnr`` and ``reprojected_pixels``:
      the consistency of the fill between neighbouring views (module docstring).
    """
    s = scene.detach()
    depth, alpha = [], []
    for cam in cameras:
        r = s.render(cam, s.opacities[:, None], check_finite=False)
        depth.append(r["depth"])
        alpha.append(r["alpha"])
    alpha_t = torch.stack(alpha)
    pairs = reprojection_pairs(cameras, holes, torch.stack(depth), alpha_t)
    surface = holes & (alpha_t > 0.5)
    return {"locality_psnr": _psnr_inside(after, before, ~footprint),
            "rest_psnr": _psnr_inside(after, remaining, ~holes),
            "hole_psnr": _psnr_inside(after, targets, holes),
            "hole_surface_psnr": _psnr_inside(after, targets, surface),
            "hole_surface_fraction": float(surface.sum()) / max(int(holes.sum()), 1),
            "fill_reprojection_psnr": pair_psnr(after, pairs),
            "inpaint_reprojection_psnr": pair_psnr(targets, pairs),
            "reprojected_pixels": int(sum(p.shape[0] for _, _, p, _ in pairs))}


def evaluate_delete(result, background=(0.0, 0.0, 0.0)) -> dict:
    """:func:`delete_metrics` of a :class:`tiger.delete.DeleteResult` (its views, renders and
    masks), stored in ``result.metrics`` (so ``result.save`` writes them) and returned.
    ``background``: the deletion's (``DeleteConfig.background``)."""
    result.metrics = delete_metrics(result.cameras, result.before, result.remaining, result.targets, result.after,
                                    result.holes, result.footprint, result.scene, background)
    return result.metrics
