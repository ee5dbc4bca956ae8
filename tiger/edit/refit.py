"""The deletion's refit: train only the Gaussians around the holes on the inpainted views.

Built on :class:`tiger.recon.SceneOptimizer` with a trainable mask: the other Gaussians are not
parameters (no gradient work, no optimizer state) and stay bit-identical. Each step renders one
view's window around its hole (a cropped camera: that window of the full render, nothing else
rasterized), takes L1 + D-SSIM against the inpainted target, and steps Adam. Every
``densify_every`` steps :func:`tiger.recon.strategy.region_topk_densify` clones or splits the top
``densify_fraction`` of the trainable Gaussians by screen-space gradient (children inherit every
attribute, ``lang`` included, and are trainable). A checkpoint (``delete_refit.pt``) every
``checkpoint_every`` steps and at the end makes the refit resumable bit for bit (also to continue
a finished refit with more ``steps``).
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Union

import torch

from tiger.recon.losses import photometric_loss
from tiger.recon.step import SceneOptimizer
from tiger.recon.strategy import DensifyStats, region_topk_densify
from tiger.render import Camera
from tiger.scene.cameras import scene_extent
from tiger.scene.gaussian_scene import GaussianScene
from tiger.utils.io import atomic_torch_save

from .seeds import crop_camera

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
CHECKPOINT = "delete_refit.pt"


@dataclass
class RefitResult:
    """scene: the refitted scene (input rows in order, densified children appended);
    trainable [N] bool: the rows the refit could change; losses per step; added: Gaussians added
    by densification; optimizer_state_rows / optimizer_state_bytes: Adam state held at the end
    (rows = the trainable count)."""

    scene: GaussianScene
    trainable: torch.Tensor
    losses: list
    added: int
    optimizer_state_rows: int
    optimizer_state_bytes: int


def _fingerprint(scene: GaussianScene, trainable: torch.Tensor, targets: torch.Tensor) -> list[float]:
    return [float(len(scene)), float(trainable.sum()), float(targets.double().sum()),
            float(scene.means.detach().double().sum())]


def _state_rows(opt: SceneOptimizer) -> int:
    if opt.optimizer is None:
        return 0
    return max((int(st["exp_avg"].shape[0]) for st in opt.optimizer.state.values() if "exp_avg" in st), default=0)


def _load_checkpoint(ckpt: Path, fingerprint: list[float], device: torch.device) -> dict:
    """The refit checkpoint at ``ckpt``, refused unless it belongs to this deletion."""
    try:
        ck = torch.load(ckpt, map_location=device, weights_only=True)
    except Exception as e:  # zip/pickle errors come in many types
        raise ValueError(f"tiger.edit.refit: cannot read the checkpoint {ckpt}: {e}") from None
    if [round(x, 3) for x in ck.get("fingerprint", [])] != [round(x, 3) for x in fingerprint]:
        raise ValueError(f"tiger.edit.refit: {ckpt} belongs to another deletion (different scene, "
                         "target, views or settings); remove it or use another output folder")
    return ck


def refit(scene: GaussianScene, trainable: torch.Tensor, cameras: Sequence[Camera], targets: torch.Tensor,
          windows: Sequence[Optional[tuple[int, int, int, int]]], cfg, *,
          checkpoint_dir: Optional[PathLike] = None, resume: bool = False, progress: bool = True) -> RefitResult:
    """Refit ``scene`` (module docstring); ``scene`` itself is not modified.

    Args:
        scene: the scene after removal, seeds appended.
        trainable: [N] bool, the Gaussians that may change.
        cameras, targets: the V views and their inpainted images [V, H, W, 3].
        windows: per view (x0, y0, width, height) of the loss window, or None to skip the view.
        cfg: a :class:`tiger.edit.delete.DeleteConfig` (steps, lrs, densify_every,
            densify_fraction, lambda_dssim, background, seed, checkpoint_every).
        checkpoint_dir, resume: where ``delete_refit.pt`` goes; continue from it.
    """
    from tqdm.auto import tqdm

    if trainable.shape != (len(scene),) or trainable.dtype != torch.bool:
        raise ValueError(f"tiger.edit.refit: trainable must be [N={len(scene)}] bool, got "
                         f"{list(trainable.shape)} {trainable.dtype}")
    dev = scene.device
    trainable = trainable.to(dev)
    views = [i for i, w in enumerate(windows) if w is not None]
    work = scene.clone()
    fingerprint = _fingerprint(scene, trainable, targets)
    ckpt = Path(checkpoint_dir) / CHECKPOINT if checkpoint_dir is not None else None
    ck = _load_checkpoint(ckpt, fingerprint, dev) if resume and ckpt is not None and ckpt.is_file() else None
    if not views or cfg.steps <= 0 or not bool(trainable.any()):  # nothing to fit (checkpoint checked first)
        return RefitResult(work, trainable.clone(), [], 0, 0, 0)
    crops = {i: crop_camera(cameras[i], *windows[i]).to(dev, scene.dtype) for i in views}
    crop_targets = {i: targets[i, windows[i][1]:windows[i][1] + windows[i][3],
                               windows[i][0]:windows[i][0] + windows[i][2]].to(dev, scene.dtype)
                    for i in views}
    bg = torch.tensor(cfg.background, dtype=scene.dtype, device=dev)
    lrs = {k: v for k, v in cfg.lrs.items() if getattr(work, k, None) is not None}
    opt = SceneOptimizer(work, lrs, trainable=trainable)
    stats = DensifyStats.zeros(len(work), dev)
    gen = torch.Generator().manual_seed(int(cfg.seed))
    extent = scene_extent(list(cameras))
    step, losses, added, order = 0, [], 0, []
    if ck is not None:
        opt.load_state_dict(ck["optimizer"])
        stats = DensifyStats.from_state_dict(ck["stats"])
        gen.set_state(ck["generator"])
        step, losses, added, order = int(ck["step"]), list(ck["losses"]), int(ck["added"]), list(ck["order"])
        log.info("refit resumed at step %d of %d from %s", step, cfg.steps, ckpt)

    visible: dict[int, torch.Tensor] = {}

    def rows_for(i: int) -> torch.Tensor:
        """Rows that can touch view i's window: the trainable ones and the frozen ones the window
        sees (computed once per view and again after each densification)."""
        if i not in visible:
            with torch.no_grad():
                radii = opt.scene.render(crops[i], opt.scene.opacities[:, None], check_finite=False)["radii"]
            visible[i] = torch.nonzero((radii > 0) | opt.trainable_mask()).reshape(-1)
        return visible[i]

    def render(s: GaussianScene, i: int) -> dict:
        idx = rows_for(i)
        sub = GaussianScene(**{n: getattr(s, n).index_select(0, idx)
                               for n in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")})
        out = sub.render(crops[i], background=bg, check_finite=False)
        out["means2d"].retain_grad()
        out["rows"] = idx
        return out

    def loss(out: dict, i: int) -> torch.Tensor:
        return photometric_loss(out["color"], crop_targets[i], cfg.lambda_dssim)

    bar = tqdm(total=cfg.steps, initial=step, desc="delete: refit", disable=not progress, dynamic_ncols=True)
    while step < cfg.steps:
        if not order:
            order = [views[k] for k in torch.randperm(len(views), generator=gen).tolist()]
        i = order.pop()
        res = opt.step(loss, i, render)
        grad = res.renders["means2d"].grad
        if cfg.densify_every and grad is not None:  # screen-space gradients, scattered to all rows
            rows = res.renders["rows"]
            g_full = grad.new_zeros(len(opt.scene), 2).index_copy_(0, rows, grad)
            r_full = res.renders["radii"].new_zeros(len(opt.scene)).index_copy_(0, rows, res.renders["radii"])
            stats.add(g_full, r_full, crops[i].width, crops[i].height)
        step += 1
        losses.append(float(res.loss))
        if cfg.densify_every and step % cfg.densify_every == 0 and step < cfg.steps:
            d = region_topk_densify(opt, stats, extent, top_percent=100.0 * cfg.densify_fraction, generator=gen)
            added += int(d["cloned"]) + int(d["split"])
            visible.clear()
        bar.update(1)
        bar.set_postfix(loss=f"{losses[-1]:.4f}", trainable=opt.num_trainable, refresh=False)
        if ckpt is not None and ((cfg.checkpoint_every and step % cfg.checkpoint_every == 0) or step == cfg.steps):
            ckpt.parent.mkdir(parents=True, exist_ok=True)
            atomic_torch_save({"fingerprint": fingerprint, "optimizer": opt.state_dict(), "step": step,
                               "stats": stats.state_dict(), "generator": gen.get_state(), "losses": losses,
                               "added": added, "order": order}, ckpt)
    bar.close()
    log.info("refit: %d steps, loss %.4f -> %.4f, %d trainable (+%d densified)", step,
             losses[0] if losses else float("nan"), losses[-1] if losses else float("nan"),
             opt.num_trainable, added)
    return RefitResult(opt.scene.detach(), opt.trainable_mask().clone(), losses, added, _state_rows(opt),
                       opt.optimizer_state_bytes())
