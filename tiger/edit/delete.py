"""Object deletion (paper appendix; SPEC §6): remove what a text names, inpaint the views, refit.

Stages (each timed in ``DeleteResult.timings``):
  1. **remove**: retrieve the target, add the floaters that belong to it and the Gaussians it
     hid from every view (:mod:`tiger.edit.removal`), drop them.
  2. **render**: every view before (RGB + the removed part's visible share) and after removal
     (RGB, alpha, depth); the hole masks (:mod:`tiger.edit.holes`); which remaining Gaussians
     are seen inside a hole (their summed compositing weight there, from one features-only
     backward per view).
  3. **inpaint**: the view with the object gone (the remainder's render; with captured
     ``images``, the captured pixels outside the object's dilated footprint) is inpainted inside
     its hole, in a window around the hole; the remainder's inverse depth is filled into the thin
     part of the hole the same way (linear across a plane), for the seeds (:mod:`tiger.edit.seeds`).
  4. **refit**: only the Gaussians seen mostly inside the holes (``near_weight``, ``hole_share``)
     and the seeds are trainable; the loss is L1 + D-SSIM against the inpainted views in a window around each
     view's hole; the rest of the scene is bit-identical. Resumable from ``checkpoint_dir``.
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence, Union

import torch

from tiger.retrieval import CANONICAL_NEGATIVES, Retrieval, TextEncoder, retrieve
from tiger.retrieval.select import Tau
from tiger.render import Camera
from tiger.scene.gaussian_scene import GaussianScene, inverse_sigmoid, render_views
from tiger.scene.sh import rgb_to_sh

from .holes import disk_dilate, hole_masks
from .inpaint import Inpainter, OpenCVInpainter, make_inpainter
from .removal import Removal, removal_mask
from .seeds import Seeds, mask_window, seed_points

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
Target = Union[str, Retrieval, torch.Tensor]  # text, retrieval, [N] bool mask or a query embedding


@dataclass
class DeleteConfig:
    """Parameters of :func:`delete` (defaults are the CLI's).

    Removal: ``score``/``tau`` of the retrieval; ``floater_fraction``, ``box_margin`` of the floater
    rule, ``unseen_norm`` of the unseen rule, ``appearance_margin`` of the appearance rule (None:
    off; see :mod:`tiger.edit.removal`). Holes: ``visible_alpha``, ``thin_alpha``, ``dilate`` (pixels). Inpainting:
    ``inpaint_margin`` (pixels of context around a hole given to the inpainter; None: the whole
    view); ``depth_source_alpha`` (pixels at least this opaque give the depth filled into the
    holes for the seeds). Refit: ``steps`` (one view each), ``near_weight`` and ``hole_share`` (a remaining
    Gaussian is trainable when its summed compositing weight inside the holes is at least
    ``near_weight`` and at least ``hole_share`` of its weight over all the views, so changing it
    changes mostly hole pixels), ``window_margin`` (pixels around a view's
    hole rendered for the loss; views without a hole are not refitted on), seeds (``seed_stride`` px, ``seed_min_change``,
    ``seed_opacity``, ``seed_depth_tolerance``, ``seed_slack``: a seed may show in another view
    only inside that view's hole grown by this many pixels; see :mod:`tiger.edit.seeds`), ``densify_every`` / ``densify_fraction`` (top fraction of the trainable
    Gaussians by screen-space gradient, split or cloned), ``lambda_dssim``, learning rates ``lrs``
    (GaussianScene parameter names; means in world units), ``background`` (RGB behind the scene).
    """

    score: str = "cosine"
    tau: Tau = "auto"
    floater_fraction: float = 0.5
    unseen_norm: float = 0.1
    appearance_margin: Optional[float] = 0.5
    box_margin: float = 0.1
    visible_alpha: float = 0.3
    thin_alpha: float = 0.9
    dilate: int = 3
    inpaint_margin: Optional[int] = 32
    depth_source_alpha: float = 0.95
    steps: int = 150
    near_weight: float = 0.05
    hole_share: float = 0.5
    window_margin: int = 16
    seed_stride: int = 2
    seed_min_change: float = 0.05
    seed_opacity: float = 0.5
    seed_depth_tolerance: float = 0.05
    seed_slack: int = 4
    densify_every: int = 50
    densify_fraction: float = 0.1
    lambda_dssim: float = 0.2
    lrs: dict = field(default_factory=lambda: {"means": 1e-3, "log_scales": 5e-3, "quats": 1e-3,
                                                 "opacity_logits": 5e-2, "sh_dc": 1e-2, "sh_rest": 5e-4})
    background: tuple = (0.0, 0.0, 0.0)
    seed: int = 0
    checkpoint_every: int = 50


@dataclass
class DeleteResult:
    """What :func:`delete` did. Images are [V, H, W, 3] in [0, 1], masks [V, H, W] bool.

    Attributes:
        scene: the scene without the object, refitted.
        removal: the removed Gaussians (masks over the input scene) and the rule's thresholds.
        cameras: the V views used.
        before, remaining, targets, after: renders of the input scene, of the scene right after
            removal, the inpainted views, and renders of the result.
        holes: the (dilated) hole masks; footprint: where the removed part was visible (dilated).
        trainable: [N_out] bool, which Gaussians of ``scene`` the refit could change (the seeds
            and their children included); the others are bit-identical to the input's, in order.
        near: [N_rest] bool over the Gaussians kept after removal: those made trainable.
        counts: Gaussians retrieved / floaters / removed / trainable / seeded / added / final.
        timings: seconds per stage (remove, render, inpaint, refit, total).
        metrics: locality and hole PSNRs, multi-view consistency (see :func:`delete_metrics`).
        losses: refit loss per step.
    """

    scene: GaussianScene
    removal: Removal
    cameras: list
    before: torch.Tensor
    remaining: torch.Tensor
    targets: torch.Tensor
    after: torch.Tensor
    holes: torch.Tensor
    footprint: torch.Tensor
    trainable: torch.Tensor
    near: torch.Tensor
    counts: dict
    timings: dict
    metrics: dict
    losses: list

    def save(self, folder: PathLike, n_pairs: int = 4, extra: Optional[dict] = None) -> list[Path]:
        """Write ``scene.ply``, ``before_k.png``/``after_k.png`` for the ``n_pairs`` views that saw
        most of the object, every view's hole mask (``holes/``) and inpainted view
        (``inpainted/``), and ``delete.json`` (:meth:`report` plus ``extra``), atomically.
        Returns the before/after paths."""
        import json

        from tiger.utils.images import save_png
        from tiger.utils.io import atomic_write

        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        self.scene.save_ply(out / "scene.ply")
        paths = []
        for k, i in enumerate(self.best_views(n_pairs)):
            paths.append(save_png(out / f"before_{k}.png", self.before[i]))
            paths.append(save_png(out / f"after_{k}.png", self.after[i]))
        for i, cam in enumerate(self.cameras):
            stem = Path(cam.image_name or f"view{i}").stem
            stem = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in stem) or f"view{i}"
            save_png(out / "holes" / f"{i:03d}_{stem}.png", self.holes[i].float())
            save_png(out / "inpainted" / f"{i:03d}_{stem}.png", self.targets[i])
        with atomic_write(out / "delete.json", "w") as fh:
            json.dump({**(extra or {}), **self.report()}, fh, indent=2, default=str)
        return paths

    def best_views(self, n: int = 4) -> list[int]:
        """Indices of the ``n`` views that saw most of the removed object."""
        return torch.argsort(self.footprint.flatten(1).sum(1), descending=True)[:n].tolist()

    def report(self) -> dict:
        """JSON-ready summary: counts, timings, metrics, thresholds."""
        return {"counts": self.counts, "timings_s": self.timings, "metrics": self.metrics,
                "tau": self.removal.tau, "floater_tau": self.removal.floater_tau,
                "box_min": self.removal.box_min.tolist(), "box_max": self.removal.box_max.tolist(),
                "views": len(self.cameras), "hole_pixels": int(self.holes.sum())}


def select_removal(scene: GaussianScene, target: Target, cfg: DeleteConfig,
                   encoder: Optional[TextEncoder]) -> Removal:
    """Stage 1: the Gaussians to remove, from a text or query embedding (retrieved here), a
    :class:`Retrieval`, or a [N] bool mask."""
    if isinstance(target, torch.Tensor) and target.dtype == torch.bool:
        m = target.to(scene.device)
        if m.dtype != torch.bool or m.shape != (len(scene),):
            raise ValueError(f"tiger.edit.delete: a target mask must be [N={len(scene)}] bool, "
                             f"got {list(m.shape)} {m.dtype}")
        return removal_mask(m.float(), m, scene.means, 0.5, floater_fraction=1.0,
                            box_margin=cfg.box_margin)
    r = target if isinstance(target, Retrieval) else retrieve(
        scene, target, encoder=encoder, score=cfg.score, tau=cfg.tau,
        negatives=None if cfg.score == "cosine" else CANONICAL_NEGATIVES)
    if r.mask.shape != (len(scene),):
        raise ValueError(f"tiger.edit.delete: the retrieval covers {r.mask.shape[0]} Gaussians, "
                         f"the scene has {len(scene)}")
    if r.count == 0:
        raise ValueError(f"tiger.edit.delete: the target {target if isinstance(target, str) else ''!r} "
                         f"selected no Gaussian ({r.score} > {r.tau:.3f}); nothing to delete")
    norms = scene.lang.detach().norm(dim=1) if scene.lang is not None else None
    return removal_mask(r.scores.to(scene.device), r.mask.to(scene.device), scene.means, r.tau,
                        floater_fraction=cfg.floater_fraction, box_margin=cfg.box_margin,
                        lang_norms=norms, unseen_norm=cfg.unseen_norm, colors=scene.rgb,
                        appearance_margin=cfg.appearance_margin,
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
    bg4 = torch.cat([bg3, bg3.new_zeros(1)])
    flag = removed.to(scene.dtype)[:, None]
    # two unit channels whose colour gradients are each Gaussian's compositing weight inside the
    # hole (channel 3) and over the whole view (channel 4): one features-only backward per view
    ones = torch.ones(len(rest), 2, dtype=rest.dtype, device=dev, requires_grad=True)
    bg5 = torch.cat([bg3, bg3.new_zeros(2)])
    scene_d, rest_d = scene.detach(), rest.detach()
    rows = []
    for cam in cameras:
        with torch.no_grad():
            b = scene_d.render(cam, torch.cat([scene_d.view_colors(cam), flag], 1), background=bg4,
                               check_finite=False)["color"]
            rest_colors = rest_d.view_colors(cam)
        r = rest_d.render(cam, torch.cat([rest_colors, ones], 1), background=bg5, check_finite=False)
        vis = b[..., 3]
        hole = hole_masks(vis[None], r["alpha"].detach()[None], visible_alpha=cfg.visible_alpha,
                          thin_alpha=cfg.thin_alpha, dilate=cfg.dilate)[0]
        ((r["color"][..., 3] * hole).sum() + r["color"][..., 4].sum()).backward()
        rows.append((b[..., :3], vis, r["color"][..., :3].detach(), r["alpha"].detach(),
                     r["depth"].detach(), hole))
    grad = ones.grad.detach() if ones.grad is not None else torch.zeros(len(rest), 2, device=dev)
    before, vis, rgb, alpha, depth, holes = (torch.stack(t) for t in zip(*rows))
    footprint = disk_dilate(vis >= cfg.visible_alpha, cfg.dilate)
    return ViewStack(before.clamp(0, 1), vis, rgb.clamp(0, 1), alpha, depth, holes, footprint, grad[:, 0],
                     grad[:, 1])


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
            locates it) or any :class:`~tiger.edit.inpaint.Inpainter`.
        encoder: text encoder for a text target.
        config: :class:`DeleteConfig`.
        checkpoint_dir: where the refit's checkpoint goes (``delete_refit.pt``).
        resume: continue the refit from that checkpoint.
        progress: show a progress bar during the refit.
    Returns:
        a :class:`DeleteResult`.
    """
    from .refit import refit

    cfg = config or DeleteConfig()
    if not cameras:
        raise ValueError("tiger.edit.delete: no cameras given")
    if images is not None:
        shape = (len(cameras), cameras[0].height, cameras[0].width, 3)
        if tuple(images.shape) != shape:
            raise ValueError(f"tiger.edit.delete: images must be [V, H, W, 3] = {list(shape)}, "
                             f"got {list(images.shape)}")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"tiger.edit.delete: all views must have one size, got {sorted(sizes)}")
    times: dict[str, float] = {}
    dev = scene.device

    def now() -> float:  # stage boundaries wait for queued GPU work, so each stage gets its own time
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        return time.perf_counter()

    t_all = now()
    inp = make_inpainter(inpainter, models=models, device=scene.device) if isinstance(inpainter, str) else inpainter
    t0 = now()
    removal = select_removal(scene, target, cfg, encoder)
    if bool(removal.mask.all()):
        raise ValueError(f"tiger.edit.delete: the target covers all {len(scene)} Gaussians; deleting it "
                         "would leave an empty scene (check the threshold)")
    rest = scene.subset(~removal.mask)
    times["remove"] = now() - t0

    t0 = now()
    views = render_stage(scene, rest, removal.mask, cameras, cfg)
    times["render"] = now() - t0

    t0 = now()
    targets, depth = inpaint_stage(views, images, inp, cfg)
    times["inpaint"] = now() - t0

    t0 = now()
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
    times["refit"] = now() - t0
    times["total"] = now() - t_all

    after = render_rgb(fit.scene, cameras, cfg.background)
    from tiger.eval.reprojection import delete_metrics

    metrics = delete_metrics(cameras, views.before, views.rest_rgb, targets, after, views.holes,
                             views.footprint, fit.scene, cfg.background)
    counts = {**removal.counts(), "trainable_kept": int(near.sum()), "seeded": len(seeds),
              "added_by_densify": fit.added, "trainable": int(fit.trainable.sum()), "final": len(fit.scene)}
    log.info("delete: removed %d (retrieved %d + floaters %d + unseen %d + similar %d), %d trainable, "
             "%d seeds, %d final", counts["removed"], counts["retrieved"] - counts["stray_kept"], counts["floaters"],
             counts["unseen"],
             counts["similar"], counts["trainable"], counts["seeded"], counts["final"])
    return DeleteResult(scene=fit.scene, removal=removal, cameras=list(cameras), before=views.before,
                        remaining=views.rest_rgb, targets=targets, after=after, holes=views.holes,
                        footprint=views.footprint, trainable=fit.trainable, near=near, counts=counts,
                        timings=times, metrics=metrics, losses=fit.losses)


@torch.no_grad()
def render_rgb(scene: GaussianScene, cameras: Sequence[Camera], background=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """[V, H, W, 3] RGB renders in [0, 1] of ``scene`` from ``cameras`` over ``background``."""
    bg = torch.tensor(background, dtype=scene.dtype, device=scene.device)
    return render_views(scene.detach(), cameras, background=bg, check_finite=False)["color"].clamp(0, 1)



def views_around(retrieval: Retrieval, n: int, width: int, height: int, fill: float = 2.0,
                 elevation_deg: float = 30.0) -> list[Camera]:
    """``n`` evenly spread views around the retrieved object for a scene without its capture
    (:class:`tiger.edit.views.ObjectViews`, 360° about -y): the object's box fills about
    1 / ``fill`` of the view, so the hole keeps surroundings for the inpainter and the refit."""
    from .views import ObjectViews

    if retrieval.center is None:
        raise ValueError("tiger.edit.delete: the retrieval selected nothing; no object to look at")
    ov = ObjectViews(retrieval.center, retrieval.bbox_min, retrieval.bbox_max, n_views=n, width=width,
                     height=height, fill=fill, force_360=True)
    return ov.fixed(n, elevation_deg=elevation_deg)
