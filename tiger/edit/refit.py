"""The deletion's refit: train only the Gaussians around the holes on the inpainted views.

The scene is split into a frozen part (never a parameter: no gradient work, no optimizer state,
bit-identical afterwards) and the trainable part (the remaining Gaussians seen in a hole, and
the seeds). Each step renders one view's window around its hole (a cropped camera: the window of
the full render, nothing else rasterized), takes L1 + D-SSIM against the inpainted target, and
steps Adam on the trainable part. Every ``densify_every`` steps the top ``densify_fraction`` of the
trainable Gaussians by accumulated screen-space gradient are cloned or split (children inherit
every attribute, ``lang`` included). A checkpoint (``delete_refit.pt``) makes the refit resumable.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Union

import torch

from tiger.recon.densify import DensifyStats, densify_and_prune
from tiger.recon.losses import photometric_loss
from tiger.scene.cameras import Camera
from tiger.scene.checkpoint import load_checkpoint, save_checkpoint
from tiger.scene.gaussian_scene import GaussianScene

from .seeds import crop_camera

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
CHECKPOINT = "delete_refit.pt"


@dataclass
class RefitResult:
    """scene: frozen Gaussians first (in their input order), then the trained ones;
    trainable [N] bool marks the latter; losses per step; added: Gaussians added by densification;
    optimizer_state_rows: rows of Adam state held at the end (= trainable count)."""

    scene: GaussianScene
    trainable: torch.Tensor
    losses: list
    added: int
    optimizer_state_rows: int


def _fingerprint(frozen: GaussianScene, train: GaussianScene, targets: torch.Tensor) -> list[float]:
    return [float(len(frozen)), float(len(train)), float(targets.double().sum()),
            float(train.means.double().sum())]


def refit(scene: GaussianScene, trainable: torch.Tensor, cameras: Sequence[Camera], targets: torch.Tensor,
          windows: Sequence[Optional[tuple[int, int, int, int]]], cfg, *,
          checkpoint_dir: Optional[PathLike] = None, resume: bool = False, progress: bool = True) -> RefitResult:
    """Refit ``scene`` (module docstring).

    Args:
        scene: the scene after removal, seeds appended.
        trainable: [N] bool, the Gaussians that may change.
        cameras, targets: the V views and their inpainted images [V, H, W, 3].
        windows: per view (x0, y0, width, height) of the loss window, or None to skip the view.
        cfg: a :class:`tiger.edit.delete.DeleteConfig` (steps, lrs, densify_*, lambda_dssim,
            background, seed, checkpoint_every).
    """
    from tqdm.auto import tqdm

    if trainable.shape != (len(scene),) or trainable.dtype != torch.bool:
        raise ValueError(f"tiger.edit.refit: trainable must be [N={len(scene)}] bool, got "
                         f"{list(trainable.shape)} {trainable.dtype}")
    trainable = trainable.to(scene.device)
    frozen = scene.subset(~trainable)
    train = scene.subset(trainable)
    views = [i for i, w in enumerate(windows) if w is not None]
    if not views or cfg.steps <= 0 or len(train) == 0:
        out = GaussianScene.concat([frozen, train])
        return RefitResult(out, _mask(len(frozen), len(train), scene.device), [], 0, 0)
    crops = {i: crop_camera(cameras[i], *windows[i]).to(scene.device, scene.dtype) for i in views}
    crop_targets = {i: targets[i, windows[i][1]:windows[i][1] + windows[i][3],
                               windows[i][0]:windows[i][0] + windows[i][2]].to(scene.device, scene.dtype)
                    for i in views}
    fingerprint = _fingerprint(frozen, train, targets)
    bg = torch.tensor(cfg.background, dtype=scene.dtype, device=scene.device)
    gen = torch.Generator().manual_seed(int(cfg.seed))
    step, losses, added, order = 0, [], 0, []
    n_start = len(train)
    opt = _optimizer(train, cfg.lrs)
    stats = DensifyStats.zeros(len(train), scene.device)
    ckpt = Path(checkpoint_dir) / CHECKPOINT if checkpoint_dir is not None else None
    if resume and ckpt is not None and ckpt.is_file():
        ck = load_checkpoint(ckpt, map_location=scene.device)
        ex = ck["extra"]
        if [round(x, 3) for x in ex.get("fingerprint", [])] != [round(x, 3) for x in fingerprint]:
            raise ValueError(f"tiger.edit.refit: {ckpt} belongs to another deletion (different scene, "
                             "target, views or settings); delete it or pass another checkpoint folder")
        train = ck["scene"].to(scene.device, scene.dtype)
        opt = _optimizer(train, cfg.lrs)
        opt.load_state_dict(ck["optimizer"])
        stats = DensifyStats.from_state_dict({k: v.to(scene.device) for k, v in ex["stats"].items()})
        gen.set_state(ex["generator"])
        step, losses, added, order = ck["step"], list(ex["losses"]), int(ex["added"]), list(ex["order"])
        log.info("refit resumed at step %d of %d from %s", step, cfg.steps, ckpt)
    bar = tqdm(total=cfg.steps, initial=step, desc="delete: refit", disable=not progress, dynamic_ncols=True)
    frozen_d = frozen.detach()
    while step < cfg.steps:
        if not order:
            order = [views[k] for k in torch.randperm(len(views), generator=gen).tolist()]
        i = order.pop()
        cam = crops[i]
        out = _joined(frozen_d, train).render(cam, background=bg, check_finite=False)
        out["means2d"].retain_grad()
        loss = photometric_loss(out["color"], crop_targets[i], cfg.lambda_dssim)
        loss.backward()
        if out["means2d"].grad is not None:
            stats.add(out["means2d"].grad[len(frozen_d):], out["radii"][len(frozen_d):], cam.width, cam.height)
        opt.step()
        opt.zero_grad(set_to_none=True)
        step += 1
        losses.append(float(loss.detach()))
        if cfg.densify_every and step % cfg.densify_every == 0 and step < cfg.steps:
            added += _densify_top(train, opt, stats, cfg.densify_fraction, gen)
            stats = DensifyStats.zeros(len(train), scene.device)
        bar.update(1)
        bar.set_postfix(loss=f"{losses[-1]:.4f}", N=len(train), refresh=False)
        if ckpt is not None and cfg.checkpoint_every and step % cfg.checkpoint_every == 0:
            ckpt.parent.mkdir(parents=True, exist_ok=True)
            save_checkpoint(ckpt, train.detach(), opt, step, {
                "fingerprint": fingerprint, "stats": stats.state_dict(), "generator": gen.get_state(),
                "losses": losses, "added": added, "order": order})
    bar.close()
    rows = max((int(st["exp_avg"].shape[0]) for st in opt.state.values() if "exp_avg" in st), default=0)
    out_scene = GaussianScene.concat([frozen, train.detach()])
    log.info("refit: %d steps, loss %.4f -> %.4f, %d trainable (+%d densified)", step,
             losses[0] if losses else float("nan"), losses[-1] if losses else float("nan"), len(train), added)
    return RefitResult(out_scene, _mask(len(frozen), len(train), scene.device), losses, added, rows)


def _mask(n_frozen: int, n_train: int, device) -> torch.Tensor:
    return torch.cat([torch.zeros(n_frozen, dtype=torch.bool, device=device),
                      torch.ones(n_train, dtype=torch.bool, device=device)])


def _optimizer(train: GaussianScene, lrs: dict) -> torch.optim.Adam:
    names = [n for n in train.params() if n != "lang"]
    return torch.optim.Adam(train.parameter_groups(lrs, names=names), lr=0.0, eps=1e-15)


def _joined(frozen: GaussianScene, train: GaussianScene) -> GaussianScene:
    """Frozen rows then the trainable ones, keeping the trainable tensors' autograd (what is
    rendered; ``lang`` is not needed for that and left out)."""
    kw = {n: torch.cat([getattr(frozen, n), getattr(train, n)])
          for n in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")}
    return GaussianScene(**kw)


def _densify_top(train: GaussianScene, opt: torch.optim.Optimizer, stats: DensifyStats, fraction: float,
                 gen: torch.Generator) -> int:
    grads = stats.grad_accum / stats.count.clamp_min(1)
    k = int(fraction * len(train))
    if k <= 0 or not bool((grads > 0).any()):
        return 0
    thr = float(torch.topk(grads, min(k, len(train))).values[-1])
    before = len(train)
    densify_and_prune(train, opt, stats, max(thr, 1e-12), extent=float(train.scales.max()) * 10,
                      min_opacity=0.0, generator=gen)
    return len(train) - before
