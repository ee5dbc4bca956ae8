"""Object deletion (paper appendix; SPEC §6): remove what a text names, inpaint the views, refit.

Stages (each timed in ``DeleteResult.timings``):
  1. **remove**: retrieve the target, add the floaters that belong to it and the Gaussians it
     hid from every view (:mod:`tiger.delete.removal`), drop them.
  2. **render**: every view before (RGB + the removed part's visible share) and after removal
     (RGB, alpha, depth); the hole masks (:mod:`tiger.delete.holes`); which remaining Gaussians
     are seen inside a hole (their summed compositing weight there, from one features-only
     backward per view).
  3. **inpaint**: the view with the object gone (the remainder's render; with captured
     ``images``, the captured pixels outside the object's dilated footprint) is inpainted inside
     its hole, in a window around the hole; the remainder's inverse depth is filled into the thin
     part of the hole the same way (linear across a plane), for the seeds (:mod:`tiger.delete.seeds`).
  4. **refit**: only the Gaussians seen mostly inside the holes (``near_weight``, ``hole_share``)
     and the seeds are trainable; the loss is L1 + D-SSIM against the inpainted views in a window around each
     view's hole; the rest of the scene is bit-identical. Resumable from ``checkpoint_dir``.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import torch

from tiger.render import Camera
from tiger.retrieval import CANONICAL_NEGATIVES, Retrieval, TextEncoder, retrieve
from tiger.scene.gaussian_scene import GaussianScene, inverse_sigmoid, render_rgb, render_view_chunks
from tiger.scene.sh import rgb_to_sh
from tiger.train import StageTimer

from .config import DeleteConfig, DeleteResult
from .holes import disk_dilate, hole_masks
from .inpaint import Inpainter, OpenCVInpainter, make_inpainter
from .refit import refit
from .removal import Removal, removal_mask
from .seeds import Seeds, mask_window, seed_points

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
#: The timed stages, in ``DeleteResult.timings`` order (``total`` also counts loading the inpainter).
STAGES = ("remove", "render", "inpaint", "refit", "total")
Target = Union[str, Retrieval, torch.Tensor]  # text, retrieval, [N] bool mask or a query embedding


def select_removal(scene: GaussianScene, target: Target, cfg: DeleteConfig,
                   encoder: Optional[TextEncoder]) -> Removal:
    """Stage 1: the Gaussians to remove, from a text or query embedding (retrieved here), a
    :class:`Retrieval`, or a [N] bool mask."""
    if isinstance(target, torch.Tensor) and target.dtype == torch.bool:
        m = target.to(scene.device)
        if m.dtype != torch.bool or m.shape != (len(scene),):
            raise ValueError(f"tiger.delete: a target mask must be [N={len(scene)}] bool, "
                             f"got {list(m.shape)} {m.dtype}")
        return removal_mask(m.float(), m, scene.means, 0.5, floater_fraction=1.0,
                            box_margin=cfg.box_margin)
    r = target if isinstance(target, Retrieval) else retrieve(
        scene, target, encoder=encoder, score=cfg.score, tau=cfg.tau,
        negatives=None if cfg.score == "cosine" else CANONICAL_NEGATIVES)
    if r.mask.shape != (len(scene),):
        raise ValueError(f"tiger.delete: the retrieval covers {r.mask.shape[0]} Gaussians, "
                         f"the scene has {len(scene)}")
    if r.count == 0:
        raise ValueError(f"tiger.delete: the target {target if isinstance(target, str) else ''!r} "
                         f"selected no Gaussian ({r.score} > {r.tau:.3f}); nothing to delete")
    norms = scene.lang.detach().norm(dim=1) if scene.lang is not None else None
    return removal_mask(r.scores.to(scene.device), r.mask.to(scene.device), scene.means, r.tau,
                        floater_fraction=cfg.floater_fraction, box_margin=cfg.box_margin,
                        lang_norms=norms, unseen_norm=cfg.unseen_norm, colors=scene.rgb,
                        appearance_margin=cfg.appearance_margin, attach_k=cfg.attach_k,
                        sizes=scene.log_scales.detach().exp().amax(dim=1))


@dataclass
class ViewStack:
    """Per-view renders of stage 2, stacked: rgb [V,H,W,3], alpha/depth [V,H,W]."""

    before: torch.Tensor
    removed_visible: torch.Tensor
    rest_rgb: torch.Tensor
    rest_alpha: torch.Tensor
    rest_depth: torch.Tensor
    holes: torch.Tensor
    footprint: torch.Tensor
    hole_weight: torch.Tensor  # [N_rest] summed compositing weight of each remaining Gaussian in holes
    view_weight: torch.Tensor  # [N_rest] ... over the whole of every view


def render_stage(scene: GaussianScene, rest: GaussianScene, removed: torch.Tensor,
                 cameras: Sequence[Camera], cfg: DeleteConfig) -> ViewStack:
    """Stage 2 (module docstring)."""
    dev = scene.device
    bg3 = torch.tensor(cfg.background, dtype=scene.dtype, device=dev)
    before, vis = render_rgb(scene, cameras, bg3, footprint=removed)
    # two unit channels whose colour gradients are each Gaussian's compositing weight inside the
    # hole (channel 3) and over the whole view (channel 4): one features-only backward per chunk
    # of views (render_view_chunks: a few views per pass), the SH colour in the same pass
    ones = torch.ones(len(rest), 2, dtype=rest.dtype, device=dev, requires_grad=True)
    bg5 = torch.cat([bg3, bg3.new_zeros(2)])
    rows = []
    for first, r in render_view_chunks(rest.detach(), cameras, ("rgb", ones), background=bg5, check_finite=False):
        v = r["color"].shape[0]
        hole = hole_masks(vis[first:first + v], r["alpha"].detach(), visible_alpha=cfg.visible_alpha,
                          thin_alpha=cfg.thin_alpha, dilate=cfg.dilate)
        ((r["color"][..., 3] * hole).sum() + r["color"][..., 4].sum()).backward()
        rows.append((r["color"][..., :3].detach(), r["alpha"].detach(), r["depth"].detach(), hole))
    grad = ones.grad.detach() if ones.grad is not None else torch.zeros(len(rest), 2, device=dev)
    rgb, alpha, depth, holes = (torch.cat(t) for t in zip(*rows))
    footprint = disk_dilate(vis >= cfg.visible_alpha, cfg.dilate)
    return ViewStack(before, vis, rgb.clamp(0, 1), alpha, depth, holes, footprint, grad[:, 0], grad[:, 1])


def inpaint_stage(views: ViewStack, images: Optional[torch.Tensor], inpainter: Inpainter,
                  cfg: DeleteConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Stage 3: (targets [V,H,W,3], inpainted depth [V,H,W]) (module docstring)."""
    base = views.rest_rgb
    if images is not None:
        base = torch.where(views.footprint[..., None], views.rest_rgb, images.to(base))
    targets, depth = base.clone(), views.rest_depth.clone()
    thin = views.rest_alpha < cfg.thin_alpha
    depth_filler = OpenCVInpainter()
    for i in range(base.shape[0]):
        hole = views.holes[i]
        if not bool(hole.any()):
            continue
        h, w = hole.shape
        x0, y0, cw, ch = (0, 0, w, h) if cfg.inpaint_margin is None else \
            mask_window(hole, cfg.inpaint_margin, multiple=8)
        win = (slice(y0, y0 + ch), slice(x0, x0 + cw))
        img = base[i][win].permute(2, 0, 1)[None]
        targets[i][win] = inpainter(img, hole[win][None, None])[0].permute(1, 2, 0)
        if bool((thin[i][win] & hole[win]).any()):  # filled as inverse depth: linear across a plane
            inv = (1.0 / depth[i][win].clamp_min(1e-6)).float().cpu().numpy()[..., None]
            # only nearly opaque pixels are sources: elsewhere the expected depth mixes in what
            # lies behind the first surface
            sources = views.rest_alpha[i][win] >= cfg.depth_source_alpha
            filled = depth_filler.fill_channels(inv, (~sources).cpu().numpy())[..., 0]
            depth[i][win] = 1.0 / torch.from_numpy(filled).to(depth).clamp_min(1e-6)
    return targets.clamp(0, 1), depth


def _nearest(points: torch.Tensor, refs: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """Index of the nearest row of ``refs`` [R,3] for each of ``points`` [P,3]."""
    out = [torch.cdist(points[s:s + chunk], refs).argmin(1) for s in range(0, points.shape[0], chunk)]
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.long, device=points.device)


def seeds_scene(seeds: Seeds, like: GaussianScene, lang_from: torch.Tensor, opacity: float) -> GaussianScene:
    """Seeds as Gaussians of ``like``'s layout: isotropic, given opacity, DC colour of the
    inpainted pixel, higher SH bands zero, ``lang`` (when present) copied from the nearest
    Gaussian among ``like``'s rows ``lang_from`` [N] bool (or all when none)."""
    s = len(seeds)
    dt, dev = like.dtype, like.device
    lang = None
    if like.lang is not None:
        pool = lang_from if bool(lang_from.any()) else torch.ones_like(lang_from)
        idx = torch.nonzero(pool).reshape(-1)
        near = idx[_nearest(seeds.means.to(dt), like.means.detach()[idx])] if s else idx[:0]
        lang = like.lang.detach()[near].clone()
    return GaussianScene(
        means=seeds.means.to(dt), log_scales=seeds.scales.to(dt).clamp_min(1e-8).log()[:, None].expand(s, 3).clone(),
        quats=torch.tensor([1.0, 0, 0, 0], dtype=dt, device=dev).expand(s, 4).clone(),
        opacity_logits=inverse_sigmoid(torch.full((s,), opacity, dtype=dt, device=dev)),
        sh_dc=rgb_to_sh(seeds.rgb.to(dt)), sh_rest=like.sh_rest.new_zeros((s,) + tuple(like.sh_rest.shape[1:])),
        lang=lang, lang_pca_basis=like.lang_pca_basis, lang_pca_mean=like.lang_pca_mean,
        metadata=dict(like.metadata))


def delete(scene: GaussianScene, target: Target, cameras: Sequence[Camera],
           images: Optional[torch.Tensor] = None, inpainter: Union[str, Inpainter] = "opencv", *,
           encoder: Optional[TextEncoder] = None, config: Optional[DeleteConfig] = None,
           checkpoint_dir: Optional[PathLike] = None, resume: bool = False, progress: bool = True,
           models=None) -> DeleteResult:
    """Delete what ``target`` names from ``scene`` and refit the hole it leaves.

    Args:
        scene: the scene (with ``lang`` when ``target`` is a text).
        target: a text (retrieved with ``encoder``), a query embedding ([F] CLIP space or [D]),
            a :class:`~tiger.retrieval.Retrieval`, or a [N] bool mask of the Gaussians to remove
            (no floater rule then).
        cameras: the V views to inpaint and refit on (the capture's training views, or views
            around the object, e.g. from :func:`tiger.render.views.orbit_cameras`).
        images: optional [V, H, W, 3] captured images in [0, 1] for those views (context for the
            inpainter outside the object's footprint); default: the scene's own renders.
        inpainter: ``"opencv"`` (Telea, built in), ``"lama"`` (needs big-lama.pt; ``models``
            locates it) or any :class:`~tiger.delete.inpaint.Inpainter`.
        encoder: text encoder for a text target.
        config: :class:`DeleteConfig`.
        checkpoint_dir: where the refit's checkpoint goes (``delete_refit.pt``).
        resume: continue the refit from that checkpoint.
        progress: show a progress bar during the refit.
    Returns:
        a :class:`DeleteResult`.
    """
    cfg = config or DeleteConfig()
    if not cameras:
        raise ValueError("tiger.delete: no cameras given")
    if images is not None:
        shape = (len(cameras), cameras[0].height, cameras[0].width, 3)
        if tuple(images.shape) != shape:
            raise ValueError(f"tiger.delete: images must be [V, H, W, 3] = {list(shape)}, "
                             f"got {list(images.shape)}")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"tiger.delete: all views must have one size, got {sorted(sizes)}")
    timer = StageTimer(scene.device, prefix="delete", stages=STAGES)
    with timer.stage("total"):
        inp = make_inpainter(inpainter, models=models, device=scene.device) if isinstance(inpainter, str) \
            else inpainter
        with timer.stage("remove"):
            removal = select_removal(scene, target, cfg, encoder)
            if bool(removal.mask.all()):
                raise ValueError(f"tiger.delete: the target covers all {len(scene)} Gaussians; deleting it "
                                 "would leave an empty scene (check the threshold)")
            rest = scene.subset(~removal.mask)
        with timer.stage("render"):
            views = render_stage(scene, rest, removal.mask, cameras, cfg)
        with timer.stage("inpaint"):
            targets, depth = inpaint_stage(views, images, inp, cfg)
        with timer.stage("refit"):
            near = (views.hole_weight >= cfg.near_weight) & \
                (views.hole_weight >= cfg.hole_share * views.view_weight)
            seeds = seed_points(cameras, views.holes, views.rest_alpha < cfg.thin_alpha, depth, targets,
                                views.rest_rgb, views.rest_depth, views.rest_alpha, stride=cfg.seed_stride,
                                min_change=cfg.seed_min_change, opaque=cfg.thin_alpha,
                                allowed=disk_dilate(views.holes, cfg.seed_slack),
                                depth_tolerance=cfg.seed_depth_tolerance)
            start = GaussianScene.concat([rest, seeds_scene(seeds, rest, near, cfg.seed_opacity)])
            trainable = torch.cat([near, torch.ones(len(seeds), dtype=torch.bool, device=near.device)])
            windows = [mask_window(views.holes[i], cfg.window_margin) if bool(views.holes[i].any()) else None
                       for i in range(len(cameras))]
            fit = refit(start, trainable, cameras, targets, windows, cfg, checkpoint_dir=checkpoint_dir,
                        resume=resume, progress=progress)

    after = render_rgb(fit.scene, cameras, cfg.background)
    counts = {**removal.counts(), "trainable_kept": int(near.sum()), "seeded": len(seeds),
              "added_by_densify": fit.added, "trainable": int(fit.trainable.sum()), "final": len(fit.scene)}
    log.info("delete: removed %d (retrieved %d + floaters %d + unseen %d + similar %d), %d trainable, "
             "%d seeds, %d final", counts["removed"], counts["retrieved"] - counts["stray_kept"], counts["floaters"],
             counts["unseen"], counts["similar"], counts["trainable"], counts["seeded"], counts["final"])
    return DeleteResult(scene=fit.scene, removal=removal, cameras=list(cameras), before=views.before,
                        remaining=views.rest_rgb, targets=targets, after=after, holes=views.holes,
                        footprint=views.footprint, trainable=fit.trainable, near=near, counts=counts,
                        timings=timer.summary(), losses=fit.losses)


def views_around(retrieval: Retrieval, n: int, width: int, height: int, fill: float = 2.0,
                 elevation_deg: float = 30.0) -> list[Camera]:
    """``n`` evenly spread views around the retrieved object for a scene without its capture
    (:class:`tiger.edit.views.ObjectViews`, 360° about -y): the object's box fills about
    1 / ``fill`` of the view, so the hole keeps surroundings for the inpainter and the refit."""
    from tiger.edit.views import ObjectViews

    if retrieval.center is None:
        raise ValueError("tiger.delete: the retrieval selected nothing; no object to look at")
    ov = ObjectViews(retrieval.center, retrieval.bbox_min, retrieval.bbox_max, n_views=n, width=width,
                     height=height, fill=fill, force_360=True)
    return ov.fixed(n, elevation_deg=elevation_deg)
