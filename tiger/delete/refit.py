"""The deletion's refit: train only the Gaussians around the holes on the inpainted views.

Built on :class:`tiger.recon.SceneOptimizer` with a trainable mask: the other Gaussians are not
parameters (no gradient work, no optimizer state) and stay bit-identical. Each step renders one
view's window around its hole (a cropped camera: that window of the full render, nothing else
rasterized), takes L1 + D-SSIM against the inpainted target, and steps Adam. The views come from a
:class:`tiger.train.ViewSampler`; every ``densify_every`` steps a
:class:`tiger.recon.strategy.RegionTopKStrategy` clones or splits the top ``densify_fraction`` of
the trainable Gaussians by screen-space gradient (children inherit every attribute, ``lang``
included, and are trainable). The loop is :func:`tiger.train.run_loop`: a checkpoint
(``delete_refit.pt``) every ``checkpoint_every`` steps, at the end and on Ctrl-C makes the refit
resumable bit for bit. A finished refit may also be continued with more ``steps``; with
densification on, that is not identical to one longer run (densification ends before a run's last
step, so that step's gradients are not in the statistics).
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
from tiger.recon.strategy import DensifySchedule, RegionTopKStrategy
from tiger.render import Camera
from tiger.scene.cameras import scene_extent
from tiger.scene.gaussian_scene import GaussianScene
from tiger.train import ViewSampler, read_checkpoint, restore_rng, run_loop, write_checkpoint

from .config import DeleteConfig
from .seeds import crop_camera

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
CHECKPOINT = "delete_refit.pt"
CHECKPOINT_FORMAT = "tiger.delete-refit/1"
#: DeleteConfig fields the refit reads; all but ``steps`` and ``checkpoint_every`` sign its checkpoint.
REFIT_FIELDS = ("lrs", "densify_every", "densify_fraction", "lambda_dssim", "background", "seed")
_PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


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


def _signature(scene: GaussianScene, trainable: torch.Tensor, targets: torch.Tensor,
               windows: Sequence[Optional[tuple[int, int, int, int]]], cfg: DeleteConfig) -> dict:
    """What a refit checkpoint belongs to: the input scene, trainable rows, targets, windows and
    settings (sums rounded so that a reload on another device still matches)."""
    return {"gaussians": len(scene), "trainable": int(trainable.sum()),
            "targets_sum": round(float(targets.double().sum()), 3),
            "means_sum": round(float(scene.means.detach().double().sum()), 3),
            "windows": [list(w) if w is not None else None for w in windows],
            "config": {k: getattr(cfg, k) for k in REFIT_FIELDS}}


def _state_rows(opt: SceneOptimizer) -> int:
    if opt.optimizer is None:
        return 0
    return max((int(st["exp_avg"].shape[0]) for st in opt.optimizer.state.values() if "exp_avg" in st), default=0)


class _RefitSession:
    """The state :func:`tiger.train.run_loop` drives: the optimizer over the trainable rows, the
    view sampler, the densification strategy and the per-step losses (kept on the device)."""

    def __init__(self, work: GaussianScene, trainable: torch.Tensor, cameras: Sequence[Camera],
                 targets: torch.Tensor, windows: Sequence[Optional[tuple[int, int, int, int]]], views: list[int],
                 cfg: DeleteConfig, signature: dict) -> None:
        dev, dt = work.device, work.dtype
        self.cfg, self.signature = cfg, signature
        self.crops = {i: crop_camera(cameras[i], *windows[i]).to(dev, dt) for i in views}
        self.crop_targets = {i: targets[i, windows[i][1]:windows[i][1] + windows[i][3],
                                        windows[i][0]:windows[i][0] + windows[i][2]].to(dev, dt) for i in views}
        self.bg = torch.tensor(cfg.background, dtype=dt, device=dev)
        self.opt = SceneOptimizer(work, {k: v for k, v in cfg.lrs.items() if getattr(work, k, None) is not None},
                                  trainable=trainable)
        self.gen = torch.Generator().manual_seed(int(cfg.seed))
        self.views = ViewSampler(views, self.gen)
        # densify after steps densify_every, 2 densify_every, ... before the last one
        self.strategy = RegionTopKStrategy(len(work), dev, DensifySchedule(cfg.densify_every, 1, cfg.steps - 1),
                                           scene_extent(list(cameras)), top_percent=100.0 * cfg.densify_fraction,
                                           min_opacity=None)
        self.losses: list[torch.Tensor] = []
        self.step, self.elapsed, self.added = 0, 0.0, 0
        self._visible: dict[int, torch.Tensor] = {}

    def generators(self) -> list[torch.Generator]:
        return [self.gen]

    def _rows_for(self, i: int) -> torch.Tensor:
        """Rows that can touch view i's window: the trainable ones and the frozen ones the window
        sees (computed once per view and again after each densification)."""
        if i not in self._visible:
            s = self.opt.scene
            with torch.no_grad():
                radii = s.render(self.crops[i], s.opacities[:, None], check_finite=False)["radii"]
            self._visible[i] = torch.nonzero((radii > 0) | self.opt.trainable_mask()).reshape(-1)
        return self._visible[i]

    def _render(self, s: GaussianScene, i: int) -> dict:
        idx = self._rows_for(i)
        sub = GaussianScene(**{n: getattr(s, n).index_select(0, idx) for n in _PARAMS})
        out = sub.render(self.crops[i], background=self.bg, check_finite=False)
        out["means2d"].retain_grad()
        out["rows"] = idx
        return out

    def _loss(self, out: dict, i: int) -> torch.Tensor:
        return photometric_loss(out["color"], self.crop_targets[i], self.cfg.lambda_dssim)

    def step_once(self) -> dict:
        i = self.views.next()
        res = self.opt.step(self._loss, i, self._render)
        self.step += 1
        grad = res.renders["means2d"].grad
        if grad is not None:  # screen-space gradients of the rendered rows, scattered to all rows
            rows, n = res.renders["rows"], len(self.opt.scene)
            g_full = grad.new_zeros(n, 2).index_copy_(0, rows, grad)
            r_full = res.renders["radii"].new_zeros(n).index_copy_(0, rows, res.renders["radii"])
            self.strategy.observe_grad(self.step, g_full, r_full, self.crops[i].width, self.crops[i].height)
        info = self.strategy.step_post_backward(self.opt, self.step, self.gen)
        if info is not None:
            self.added += int(info["cloned"]) + int(info["split"])
            self._visible.clear()
        self.losses.append(res.loss)
        return {"loss": res.loss, "gaussians": len(self.opt.scene)}

    def save(self, path: PathLike) -> None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        state = {"optimizer": self.opt.state_dict(), "step": self.step, "views": self.views.state_dict(),
                 "strategy": self.strategy.state_dict(), "losses": [float(x) for x in self.losses],
                 "added": self.added, "elapsed": self.elapsed}
        write_checkpoint(path, CHECKPOINT_FORMAT, state, signature=self.signature, generators=self.generators())

    def load(self, ck: dict) -> None:
        dev = self.opt.scene.device
        self.opt.load_state_dict(ck["optimizer"])
        self.strategy.load_state_dict(ck["strategy"], dev)
        self.views.load_state_dict(ck["views"])
        restore_rng(ck["rng"], self.generators())
        self.step, self.added, self.elapsed = int(ck["step"]), int(ck["added"]), float(ck.get("elapsed", 0.0))
        self.losses = [torch.tensor(x, device=dev) for x in ck["losses"]]


def refit(scene: GaussianScene, trainable: torch.Tensor, cameras: Sequence[Camera], targets: torch.Tensor,
          windows: Sequence[Optional[tuple[int, int, int, int]]], cfg: DeleteConfig, *,
          checkpoint_dir: Optional[PathLike] = None, resume: bool = False, progress: bool = True) -> RefitResult:
    """Refit ``scene`` (module docstring); ``scene`` itself is not modified.

    Args:
        scene: the scene after removal, seeds appended.
        trainable: [N] bool, the Gaussians that may change.
        cameras, targets: the V views and their inpainted images [V, H, W, 3] in [0, 1].
        windows: per view (x0, y0, width, height) in pixels of the loss window, or None to skip the view.
        cfg: the deletion's settings (reads ``steps``, ``lrs``, ``densify_every``, ``densify_fraction``,
            ``lambda_dssim``, ``background``, ``seed``, ``checkpoint_every``).
        checkpoint_dir, resume: where ``delete_refit.pt`` goes; continue from it (one of another
            deletion is refused, naming what differs, even when there is nothing to train).
    """
    if trainable.shape != (len(scene),) or trainable.dtype != torch.bool:
        raise ValueError(f"tiger.delete.refit: trainable must be [N={len(scene)}] bool, got "
                         f"{list(trainable.shape)} {trainable.dtype}")
    if len(windows) != len(cameras):
        raise ValueError(f"tiger.delete.refit: {len(windows)} windows for {len(cameras)} cameras")
    dev = scene.device
    trainable = trainable.to(dev)
    views = [i for i, w in enumerate(windows) if w is not None]
    signature = _signature(scene, trainable, targets, windows, cfg)
    ckpt = Path(checkpoint_dir) / CHECKPOINT if checkpoint_dir is not None else None
    ck = None
    if resume and ckpt is not None and ckpt.is_file():  # checked before the early return below
        ck = read_checkpoint(ckpt, CHECKPOINT_FORMAT, signature=signature, map_location=dev, what="deletion")
    work = scene.clone()
    if not views or cfg.steps <= 0 or not bool(trainable.any()):  # nothing to fit
        return RefitResult(work, trainable.clone(), [], 0, 0, 0)
    session = _RefitSession(work, trainable, cameras, targets, windows, views, cfg, signature)
    if ck is not None:
        session.load(ck)
        log.info("refit resumed at step %d of %d from %s", session.step, cfg.steps, ckpt)
    run_loop(session, cfg.steps, checkpoint=ckpt, checkpoint_every=cfg.checkpoint_every, progress=progress,
             desc="delete: refit")
    opt = session.opt
    losses = torch.stack(session.losses).tolist() if session.losses else []  # one read-back at the end
    log.info("refit: %d steps, loss %.4f -> %.4f, %d trainable (+%d densified)", session.step,
             losses[0] if losses else float("nan"), losses[-1] if losses else float("nan"),
             opt.num_trainable, session.added)
    return RefitResult(opt.scene.detach(), opt.trainable_mask().clone(), losses, session.added, _state_rows(opt),
                       opt.optimizer_state_bytes())


__all__ = ["CHECKPOINT", "RefitResult", "refit"]
