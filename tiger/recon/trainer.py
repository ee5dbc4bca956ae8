"""The 3DGS reconstruction loop: photometric fit of a Gaussian scene to posed images."""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Optional, Sequence, Union

import torch

from tiger.render import Camera
from tiger.scene.cameras import scene_extent
from tiger.scene.checkpoint import load_checkpoint, save_checkpoint
from tiger.scene.dataset import points_in_views
from tiger.scene.gaussian_scene import GaussianScene
from tiger.train import LoopOutcome, ViewSampler, restore_rng, run_loop

from .appearance import AffineAppearance
from .config import ReconConfig, expon_lr
from .init import colors_from_views
from .losses import photometric_loss, psnr, psnr_tensor, ssim
from .step import SceneOptimizer
from .strategy import InriaStrategy

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]


class Trainer:
    """Fit a :class:`GaussianScene` to images with the 3DGS recipe.

    The recipe on top of :class:`tiger.recon.step.SceneOptimizer` (``self.opt``; every
    Gaussian trainable): one view per step, the photometric loss, INRIA's schedule and
    densification (:class:`tiger.recon.strategy.InriaStrategy`), driven by
    :func:`tiger.train.run_loop` (time budget, checkpoints, Ctrl-C).

    Args:
        cameras: training views (pinhole; sizes must match ``images``).
        images: one [H, W, 3] float tensor in [0, 1] per camera.
        config: hyper-parameters (default INRIA's 30k recipe).
        scene: start from this scene (fine-tuning); default: initialise.
        init_points: [P, 3] points to initialise from (e.g. COLMAP's), with
            ``init_colors`` [P, 3] in [0, 1]; default random points seen by the cameras.
        device: where to train (default: the images' device).
        out_dir: where checkpoints go (``checkpoint.pt``).
        test_cameras, test_images: held-out views for :meth:`evaluate` during/after training.
        masks, test_masks: optional [H, W] bool per image, the pixels that count (e.g.
            :func:`tiger.scene.images.undistortion_valid_mask`: not the black border that
            undistortion leaves); the loss ignores the others, PSNR/SSIM are taken over them.
        trainable: [N] bool over ``scene`` (fine-tuning only): only these Gaussians are
            parameters and only they are densified or pruned; the others stay bit-identical.
    """

    def __init__(self, cameras: Sequence[Camera], images: Sequence[torch.Tensor],
                 config: Optional[ReconConfig] = None, scene: Optional[GaussianScene] = None,
                 init_points: Optional[torch.Tensor] = None, init_colors: Optional[torch.Tensor] = None,
                 device: Optional[Union[str, torch.device]] = None, out_dir: Optional[PathLike] = None,
                 test_cameras: Sequence[Camera] = (), test_images: Sequence[torch.Tensor] = (),
                 masks: Optional[Sequence[torch.Tensor]] = None,
                 test_masks: Optional[Sequence[torch.Tensor]] = None,
                 trainable: Optional[torch.Tensor] = None) -> None:
        self.cfg = config or ReconConfig()
        if len(cameras) == 0:
            raise ValueError("tiger.recon: no training cameras")
        if len(cameras) != len(images) or len(test_cameras) != len(test_images):
            raise ValueError(f"tiger.recon: {len(cameras)} cameras but {len(images)} images "
                             f"(test: {len(test_cameras)} vs {len(test_images)})")
        self.device = torch.device(device) if device is not None else images[0].device
        self.cameras = [self._check_view(c, im, i) for i, (c, im) in enumerate(zip(cameras, images))]
        self.images = [im.to(self.device, torch.float32) for im in images]
        self.test_cameras = [self._check_view(c, im, i) for i, (c, im) in enumerate(zip(test_cameras, test_images))]
        self.test_images = [im.to(self.device, torch.float32) for im in test_images]
        self.masks = self._check_masks(masks, self.images, "masks")
        self.test_masks = self._check_masks(test_masks, self.test_images, "test_masks")
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.extent = float(self.cfg.extent) if self.cfg.extent else scene_extent(self.cameras)
        self.gen = torch.Generator().manual_seed(self.cfg.seed)
        self.finetune = scene is not None
        self.input_gaussians = len(scene) if scene is not None else 0
        self.checkpoint_step: Optional[int] = None  # step held by the last checkpoint saved or loaded
        if trainable is not None and scene is None:
            raise ValueError("tiger.recon: a trainable mask needs a starting scene (scene=...)")
        self._trainable = trainable
        if scene is None:
            scene = self._initial_scene(init_points, init_colors)
        elif scene.sh_degree != self.cfg.sh_degree:
            scene = scene.with_sh_degree(self.cfg.sh_degree)
        self.scene = scene.to(self.device, torch.float32).clone()
        self.step = 0
        self.active_sh = self.cfg.sh_degree if (self.finetune or self.cfg.sh_increase_every == 0) else 0
        self.views = ViewSampler(len(self.cameras), self.gen)
        self.history: list = []
        self.elapsed = 0.0
        self.outcome: Optional[LoopOutcome] = None
        self._build_optimizer()
        self.strategy = self._strategy()
        self.appearance: Optional[AffineAppearance] = None
        if self.cfg.appearance:
            self.appearance = AffineAppearance(len(self.cameras), self.device)
            self.appearance_optimizer = torch.optim.Adam(self.appearance.parameters(), lr=self.cfg.lr_appearance,
                                                         eps=self.cfg.adam_eps)

    def _check_masks(self, masks: Optional[Sequence[torch.Tensor]], images: list,
                     what: str) -> Optional[list]:
        if masks is None:
            return None
        if len(masks) != len(images):
            raise ValueError(f"tiger.recon: {len(masks)} {what} for {len(images)} images")
        out = []
        for i, (m, im) in enumerate(zip(masks, images)):
            if m.dtype != torch.bool or tuple(m.shape) != tuple(im.shape[:2]):
                raise ValueError(f"tiger.recon: {what}[{i}] must be [H, W] = {list(im.shape[:2])} bool, got "
                                 f"{m.dtype} {list(m.shape)}")
            out.append(m.to(self.device))
        return out

    # -- set-up -------------------------------------------------------------------------
    def _check_view(self, cam: Camera, img: torch.Tensor, i: int) -> Camera:
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"tiger.recon: image {i} ({cam.image_name}) must be [H, W, 3], got {list(img.shape)}")
        if (img.shape[0], img.shape[1]) != (cam.height, cam.width):
            raise ValueError(f"tiger.recon: image {i} ({cam.image_name}) is {img.shape[1]}x{img.shape[0]} but "
                             f"its camera is {cam.width}x{cam.height}")
        if cam.distortion is not None:
            raise ValueError(f"tiger.recon: camera {i} ({cam.image_name}) still has lens distortion; load its "
                             "image with tiger.scene.images.load_image (which undistorts)")
        return cam.to(self.device, torch.float32)

    def _initial_scene(self, points: Optional[torch.Tensor], colors: Optional[torch.Tensor]) -> GaussianScene:
        if points is None:
            pts = points_in_views(self.cameras, self.cfg.init_random_points, self.cfg.init_min_view_fraction,
                                  generator=self.gen, radius_fraction=self.cfg.init_radius_fraction)
            if self.cfg.init_colors == "views":
                colors = colors_from_views(pts, self.cameras, self.images, self.masks)
            else:
                colors = torch.rand(pts.shape, generator=self.gen)
            log.info("random initialisation: %d points seen by >= %.0f%% of the views", len(pts),
                     100 * self.cfg.init_min_view_fraction)
        else:
            pts = points.detach().float().cpu()
            colors = None if colors is None else colors.detach().float().cpu()
        return GaussianScene.from_points(pts, colors, sh_degree=self.cfg.sh_degree, opacity=self.cfg.init_opacity)

    def _build_optimizer(self) -> None:
        c = self.cfg
        lrs = {"means": self._means_lr(), "log_scales": c.lr_log_scales, "quats": c.lr_quats,
               "opacity_logits": c.lr_opacity, "sh_dc": c.lr_sh_dc, "sh_rest": c.lr_sh_rest}
        names = [n for n in lrs if n != "sh_rest" or self.scene.sh_rest.shape[1] > 0]
        self.opt = SceneOptimizer(self.scene, {n: lrs[n] for n in names}, eps=c.adam_eps, trainable=self._trainable)

    @property
    def optimizer(self) -> torch.optim.Optimizer:
        """The torch Adam inside :attr:`opt` (its state dict is what checkpoints hold)."""
        return self.opt.optimizer

    def _means_lr(self) -> float:
        c = self.cfg
        return self.extent * expon_lr(self.step, c.lr_means_init, c.lr_means_final,
                                      c.lr_means_max_steps or c.iterations, c.lr_means_delay_steps,
                                      c.lr_means_delay_mult)

    def _strategy(self) -> InriaStrategy:
        return self.cfg.strategy(len(self.scene), self.device, self.extent, finetune=self.finetune)

    def _background(self) -> torch.Tensor:
        if self.cfg.random_background:
            return torch.rand(3, generator=self.gen).to(self.device)
        return torch.tensor(self.cfg.background, dtype=torch.float32, device=self.device)

    # -- training -----------------------------------------------------------------------
    def train_step(self, read_back: bool = True) -> dict:
        """One optimizer step on one view; returns {'loss', 'psnr', 'gaussians'}: floats, or with
        ``read_back=False`` 0-d tensors on the device (no host synchronisation for them, so the
        GPU is not drained at the end of every step; :meth:`fit` reads them every 10 steps)."""
        c = self.cfg
        self.step += 1
        self.opt.set_lr("means", self._means_lr())
        if c.sh_increase_every and self.step % c.sh_increase_every == 0:
            self.active_sh = min(self.active_sh + 1, c.sh_degree)
        i = self.views.next()
        cam, target = self.cameras[i], self.images[i]
        mask = self.masks[i] if self.masks is not None else None
        background = self._background()

        def render(scene: GaussianScene, view: tuple) -> dict:
            out = scene.render(view[0], sh_degree=self.active_sh, background=background, check_finite=False)
            out["means2d"].retain_grad()
            return out

        def loss(out: dict, view: tuple) -> torch.Tensor:
            pred = out["color"] if self.appearance is None else self.appearance(out["color"], i)
            if mask is not None:   # pixels outside the mask: no error, no gradient
                pred = torch.where(mask[..., None], pred, view[1])
            return photometric_loss(pred, view[1], c.lambda_dssim)

        res = self.opt.step(loss, (cam, target), render)
        if self.appearance is not None:
            self.appearance_optimizer.step()
            self.appearance_optimizer.zero_grad(set_to_none=True)
        out = res.renders
        self.strategy.observe(self.step, out, cam.width, cam.height)
        info = {"loss": res.loss, "psnr": psnr_tensor(out["color"], target, mask), "gaussians": len(self.scene)}
        if read_back:
            info["loss"], info["psnr"] = float(info["loss"]), float(info["psnr"])
        densified = self.strategy.step_post_backward(self.opt, self.step, self.gen)
        if densified is not None:
            info["densify"] = densified
        return info

    # -- the loop (tiger.train.run_loop) ---------------------------------------------------
    def step_once(self) -> dict:
        """:meth:`train_step` without read-back, PSNR bounded for the running mean."""
        info = self.train_step(read_back=False)
        info["psnr"] = info["psnr"].nan_to_num(posinf=99.0)
        return info

    def generators(self) -> list:
        return [self.gen]

    def fit(self) -> GaussianScene:
        """Train until ``config.iterations`` (continuing a resumed run), ``config.time_budget_s``
        seconds of training or Ctrl-C (:func:`tiger.train.run_loop`); evaluates the test views at
        the end. With ``out_dir``, ``out_dir/checkpoint.pt`` is written every
        ``config.checkpoint_every`` steps, at the end and on Ctrl-C (then KeyboardInterrupt is
        re-raised). :attr:`outcome` says why it stopped. Returns the scene (detached)."""
        c = self.cfg

        def after(rec: dict) -> None:
            if c.eval_every and self.test_cameras and self.step % c.eval_every == 0:
                self._record_eval()

        self.outcome = run_loop(self, c.iterations, checkpoint=self.out_dir / "checkpoint.pt" if self.out_dir else None,
                                checkpoint_every=c.checkpoint_every, time_budget_s=c.time_budget_s,
                                progress=c.progress, desc="3DGS fit", show={"loss": ".4f", "psnr": ".2f"},
                                after_step=after)
        if self.appearance is not None and self.opt.trainable is None:
            # the saved scene (and held-out views) show the training images' average appearance
            # (with a trainable mask the frozen Gaussians must stay bit-identical: not recentred)
            self.appearance.recentre(self.scene.sh_dc.data, self.scene.sh_rest.data)
        if self.test_cameras and (not self.history or self.history[-1]["step"] != self.step):
            self._record_eval()
        return self.scene.detach()

    def _record_eval(self) -> None:
        m = self.evaluate()
        m.update(step=self.step, time_s=self.elapsed, gaussians=len(self.scene))
        m.pop("per_view", None)
        self.history.append(m)
        log.info("step %d: test PSNR %.2f dB, SSIM %.4f, %d Gaussians", self.step, m["psnr"], m["ssim"],
                 len(self.scene))

    @torch.no_grad()
    def evaluate(self, cameras: Optional[Sequence[Camera]] = None,
                 images: Optional[Sequence[torch.Tensor]] = None,
                 masks: Optional[Sequence[torch.Tensor]] = None) -> dict:
        """Mean PSNR (dB) and SSIM over views (default the test views and their masks), full
        SH degree, renders clamped to [0, 1], over the pixels of ``masks`` (default all)."""
        cams = self.test_cameras if cameras is None else [c.to(self.device, torch.float32) for c in cameras]
        imgs = self.test_images if images is None else [im.to(self.device, torch.float32) for im in images]
        if cameras is None and masks is None:
            masks = self.test_masks
        if not cams:
            raise ValueError("tiger.recon: evaluate needs views (no test views were given)")
        scene = self.scene.detach()
        bg = torch.tensor(self.cfg.background, dtype=torch.float32, device=self.device)
        per = []
        for j, (cam, img) in enumerate(zip(cams, imgs)):
            m = masks[j] if masks is not None else None
            out = scene.render(cam, background=bg, check_finite=False)["color"].clamp(0, 1)
            per.append((psnr(out, img, m), float(ssim(out, img, mask=m))))
        return {"psnr": sum(p for p, _ in per) / len(per), "ssim": sum(s for _, s in per) / len(per),
                "per_view": per}

    # -- checkpoints ----------------------------------------------------------------------
    def signature(self) -> dict:
        """The inputs and settings a checkpoint belongs to (a resume with others is refused)."""
        cfg = {k: v for k, v in self.cfg.to_dict().items()
               if k not in ("iterations", "progress", "checkpoint_every", "eval_every", "time_budget_s")}
        return {"views": len(self.cameras), "size": [self.cameras[0].width, self.cameras[0].height],
                "test_views": len(self.test_cameras), "masks": self.masks is not None,
                "start_gaussians": None if not self.finetune else self.input_gaussians, "config": cfg}

    def save(self, path: PathLike) -> None:
        """Checkpoint everything needed to resume bit-for-bit (atomic write)."""
        extra = {"strategy": self.strategy.state_dict(), "active_sh": self.active_sh,
                 "views": self.views.state_dict(), "extent": self.extent,
                 "history": self.history, "elapsed": self.elapsed, "finetune": self.finetune}
        if self.opt.trainable is not None:
            extra["trainable"] = self.opt.trainable
        if self.appearance is not None:
            extra["appearance"] = self.appearance.state_dict()
            extra["appearance_optimizer"] = self.appearance_optimizer.state_dict()
        save_checkpoint(path, self.scene, self.optimizer, self.step, extra, signature=self.signature(),
                        generators=self.generators())
        self.checkpoint_step = self.step

    def load(self, path: PathLike) -> None:
        """Resume from a checkpoint written by :meth:`save`; one of other views or settings is
        refused (:class:`tiger.train.CheckpointMismatch` naming what differs)."""
        ck = load_checkpoint(path, map_location=self.device, signature=self.signature(), what="reconstruction")
        ex = ck["extra"]
        self.scene = ck["scene"].to(self.device, torch.float32)
        self.step = self.checkpoint_step = ck["step"]
        self.extent = float(ex.get("extent", self.extent))
        self.active_sh = int(ex.get("active_sh", self.active_sh))
        self.finetune = bool(ex.get("finetune", self.finetune))
        self._trainable = ex["trainable"].to(self.device) if "trainable" in ex else None
        self._build_optimizer()
        if ck["optimizer"] is not None:
            self.optimizer.load_state_dict(ck["optimizer"])
        self.strategy = self._strategy()
        self.strategy.load_state_dict(ex["strategy"], self.device)
        restore_rng(ck["rng"], self.generators())
        self.views.load_state_dict(ex["views"])
        self.history = list(ex.get("history", []))
        self.elapsed = float(ex.get("elapsed", 0.0))
        if self.appearance is not None and "appearance" in ex:
            self.appearance.load_state_dict(ex["appearance"])
            self.appearance_optimizer.load_state_dict(ex["appearance_optimizer"])
        log.info("resumed from %s at step %d (%d Gaussians)", path, self.step, len(self.scene))
