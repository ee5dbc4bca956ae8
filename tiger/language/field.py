"""Training the language field (paper §3.1): only each Gaussian's L is optimised.

Every other parameter is frozen and enters the rasterizer detached, so the backward is the
features-only kernel (no geometry gradient is ever computed). The loss compares the rendered
D-dim features with per-view feature maps (pixels marked invalid, e.g. in no SAM mask, are
ignored). Gaussians culled in every view are reported and skipped (their L stays 0, so no query
ever retrieves them); Gaussians that are in view but never receive a gradient are reported and
reset to 0 at the end for the same reason.

The maps are read once (:class:`tiger.language.feature_maps.ResidentMaps`: on the device when they
fit, else pinned host memory streamed a step ahead) and the loss stays on the device (read back
for the progress bar every 10 steps), so a step costs what its render, backward and Adam cost.
The loop is :func:`tiger.train.run_loop` (checkpoints, Ctrl-C).
"""
from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import torch

from tiger.retrieval.text import PCASource
from tiger.render import Camera
from tiger.scene import GaussianScene
from tiger.train import (CheckpointMismatch, ViewSampler, read_checkpoint, restore_rng, run_loop,
                         signature_differences, write_checkpoint)

from .feature_maps import PLACEMENTS, FeatureMap, FeatureSource, FeatureStore, ResidentMaps, ViewMap, map_loader

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
CHECKPOINT_FORMAT = "tiger.field-checkpoint/1"
#: FieldConfig fields that may change between a run and its resume.
RESUMABLE_CHANGES = ("steps", "checkpoint_every", "progress", "map_placement")


@dataclass
class FieldConfig:
    """Language field training settings.

    Attributes:
        steps: optimisation steps (each renders ``batch_views`` views).
        lr: Adam learning rate for L (LangSplat's 2.5e-3 suits features of unit scale).
        batch_views: views rendered and averaged per step (sampled without replacement per epoch).
        loss: ``"l1"`` (LangSplat), ``"l2"`` or ``"cosine"`` (1 - cos, per pixel).
        init: ``"random"`` (N(0, init_std^2)), ``"zeros"`` or ``"keep"`` (the scene's current L).
        init_std: spread of the random initialisation.
        dim: D, the language dimension, used when the scene has no L yet (default: the maps').
        checkpoint_every: steps between checkpoints (0: only at the end) when a path is given.
        seed: seeds the initialisation and the view order (resumed runs continue the stream).
        progress: show a tqdm progress bar.
        map_placement: where the maps are kept: ``"auto"`` (the device when they fit, else pinned
            host memory streamed to it), ``"device"`` or ``"host"``.
    """

    steps: int = 10_000
    lr: float = 2.5e-3
    batch_views: int = 1
    loss: str = "l1"
    init: str = "random"
    init_std: float = 0.1
    dim: Optional[int] = None
    checkpoint_every: int = 1000
    seed: int = 0
    progress: bool = True
    map_placement: str = "auto"

    def validate(self) -> None:
        if self.steps < 0:
            raise ValueError(f"tiger.train_field: steps must be >= 0, got {self.steps}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"tiger.train_field: lr must be finite and > 0, got {self.lr}")
        if self.batch_views < 1:
            raise ValueError(f"tiger.train_field: batch_views must be >= 1, got {self.batch_views}")
        if self.loss not in ("l1", "l2", "cosine"):
            raise ValueError(f"tiger.train_field: loss must be 'l1', 'l2' or 'cosine', got '{self.loss}'")
        if self.init not in ("random", "zeros", "keep"):
            raise ValueError(f"tiger.train_field: init must be 'random', 'zeros' or 'keep', got '{self.init}'")
        if self.map_placement not in PLACEMENTS:
            raise ValueError(f"tiger.train_field: map_placement must be one of {PLACEMENTS}, "
                             f"got '{self.map_placement}'")


@dataclass
class FieldResult:
    """Outcome of :func:`train_field`.

    Attributes:
        lang: [N, D] the trained embeddings (also written to ``scene.lang``).
        losses: loss per step (the whole run, resumed parts included).
        invisible: [N] bool, culled in every view: outside it or too faint (skipped, L = 0).
        untouched: [N] bool, in view somewhere but reaching no valid pixel (hidden behind others,
            or only over masked-out pixels), so never given a gradient (L reset to 0).
            :meth:`coverage` says both in one line.
        steps: steps done in total; seconds: wall time of this call.
    """

    lang: torch.Tensor
    losses: list = field(default_factory=list)
    invisible: Optional[torch.Tensor] = None
    untouched: Optional[torch.Tensor] = None
    steps: int = 0
    seconds: float = 0.0

    def coverage(self) -> str:
        """One line on the Gaussians left without a feature, in the words the logs use."""
        n = int(self.lang.shape[0])
        out_of_view = int(self.invisible.sum()) if self.invisible is not None else 0
        silent = int(self.untouched.sum()) if self.untouched is not None else 0
        return (f"{out_of_view + silent} of {n} Gaussians without a language feature (L = 0): "
                f"{out_of_view} culled in every view (outside it or too faint), {silent} in view but "
                f"reaching no valid pixel (hidden or masked out)")


# ------------------------------------------------------------------------------------ steps
def _render(scene: GaussianScene, camera: Camera, lang: torch.Tensor) -> dict:
    """``lang`` rendered from ``camera`` (already at its map's size); ``scene`` is detached, so
    the backward is the features-only kernel."""
    return scene.render(camera, lang, check_finite=False)


def _visibility(scene: GaussianScene, cameras: Sequence[Camera]) -> torch.Tensor:
    """[N] bool: projected into at least one view (radius > 0)."""
    vis = torch.zeros(len(scene), dtype=torch.bool, device=scene.device)
    one = scene.means.new_zeros((len(scene), 1))
    with torch.no_grad():
        for cam in cameras:
            vis |= scene.render(cam, one, check_finite=False)["radii"] > 0
    return vis


def _loss(pred: torch.Tensor, target: ViewMap, kind: str) -> torch.Tensor:
    """Mean per-pixel loss over the valid pixels. Masked sums, not boolean indexing: indexing
    would wait for the device to count the pixels every step (they are counted once)."""
    t = target.features
    if kind == "cosine":
        per = 1 - torch.nn.functional.cosine_similarity(pred, t.to(pred.dtype), dim=-1, eps=1e-8)
        per_pixel = 1
    else:
        per = (pred - t).abs() if kind == "l1" else (pred - t).square()  # promotes float16 maps on the fly
        per_pixel = pred.shape[-1]
    if target.valid is not None:
        per = torch.where(target.valid if per.dim() == 2 else target.valid[..., None], per, 0)
    return per.sum() / max(target.n_valid * per_pixel, 1)


class _FieldSession:
    """The state :func:`tiger.train.run_loop` drives: L of the Gaussians in view, Adam, the view
    sampler, the per-step losses (on the device) and which Gaussians got a gradient."""

    def __init__(self, frozen: GaussianScene, cameras: list, maps: ResidentMaps, lang: torch.Tensor,
                 cfg: FieldConfig, gen: torch.Generator, signature: dict, total_steps: int) -> None:
        self.frozen, self.cameras, self.maps, self.cfg, self.gen = frozen, cameras, maps, cfg, gen
        self.lang = lang.requires_grad_(True)
        self.opt = torch.optim.Adam([self.lang], lr=cfg.lr)
        self.views = ViewSampler(len(cameras), gen)
        self.losses = torch.zeros(total_steps, device=lang.device)
        self.touched = torch.zeros(lang.shape[0], dtype=torch.bool, device=lang.device)
        self.step, self.elapsed, self.signature = 0, 0.0, signature
        self.full: Optional[Callable[[], tuple]] = None  # set by train_field: (L [N, D], touched, visible)

    def generators(self) -> list:
        return [self.gen]

    def step_once(self) -> dict:
        views = self.views.take(self.cfg.batch_views)
        self.opt.zero_grad(set_to_none=True)
        total = self.lang.new_zeros(())
        for v in views:
            out = _render(self.frozen, self.cameras[v], self.lang)
            loss = _loss(out["color"], self.maps.get(v), self.cfg.loss) / len(views)
            loss.backward()
            total = total + loss.detach()
        self.maps.prefetch(self.views.peek(self.cfg.batch_views))  # the next step's maps, while this one runs
        if self.lang.grad is not None:
            self.touched |= (self.lang.grad != 0).any(dim=1)
        self.opt.step()
        self.losses[self.step] = total
        self.step += 1
        return {"loss": total}

    def save(self, path: PathLike) -> None:
        lang_full, touched, visible = self.full()
        state = {"lang": lang_full.detach().cpu(), "optimizer": self.opt.state_dict(), "step": self.step,
                 "views": self.views.state_dict(), "losses": self.losses[:self.step].cpu(),
                 "touched": touched.cpu(), "visible": visible.cpu()}
        write_checkpoint(path, CHECKPOINT_FORMAT, state, signature=self.signature, generators=self.generators())


def _read_ckpt(path: Path, n: int, d: int, signature: dict) -> dict:
    ck = read_checkpoint(path, CHECKPOINT_FORMAT)
    if tuple(ck["lang"].shape) != (n, d):
        raise ValueError(f"tiger.train_field: checkpoint {path} holds L of shape {list(ck['lang'].shape)}, "
                         f"the scene needs [{n}, {d}]")
    diff = signature_differences(ck.get("signature") or {}, signature)
    if diff:
        raise CheckpointMismatch(path, diff, "language field")
    return ck


# ------------------------------------------------------------------------------------ train
def train_field(scene: GaussianScene, cameras: Sequence[Camera], feature_maps: FeatureSource, *,
                config: Optional[FieldConfig] = None, pca: PCASource = None,
                checkpoint: Optional[PathLike] = None, resume: bool = True,
                init: Union[torch.Tensor, str, None] = None,
                callback: Optional[Callable[[int, float], None]] = None,
                **overrides: Union[int, float, str, bool, None]) -> FieldResult:
    """Optimise each Gaussian's language embedding L so that rendered features match the maps.

    Args:
        scene: the scene; its geometry stays frozen, its ``lang`` ([N, D] or None) is replaced by
            the result, and with ``pca`` its ``lang_pca_basis`` [F, D] / ``lang_pca_mean`` [F] are
            set, so ``scene.save_ply`` writes ``lang_*`` and the basis.
        cameras: V views; rendering happens at each feature map's size (K rescaled).
        feature_maps: per view ``[H, W, D]`` (any float dtype), ``(features, valid)`` or
            ``{"features", "valid"}`` with ``valid`` [H, W] bool (False: ignored pixel); a
            sequence, a callable ``i -> map`` (for maps on disk), or a ``tiger.language.FeatureSet``.
            Each map is read once (see the module docstring).
        config: :class:`FieldConfig`; keyword ``overrides`` replace its fields (``steps=...``).
        pca: the PCA that produced the maps (``PCABasis`` or (basis, mean)), stored with the scene.
        checkpoint: file for checkpoints (every ``checkpoint_every`` steps, at the end and on
            Ctrl-C); with ``resume`` an existing one is continued exactly (one made with other
            settings or another scene is refused, naming what differs).
        init: [N, D] initial embeddings (e.g. lifted from the maps without training), replacing
            ``config.init``; Gaussians culled in every view still start (and stay) at 0. A string
            is ``config.init`` (``"random"``, ``"zeros"``, ``"keep"``).
        callback: called as ``callback(step, loss)`` after every step (reading the loss back from
            the device every step: leave it None for speed).
    Returns:
        :class:`FieldResult`.
    """
    if isinstance(init, str):
        overrides["init"], init = init, None
    cfg = FieldConfig(**{**asdict(config or FieldConfig()), **overrides})
    cfg.validate()
    cameras = list(cameras)
    if not cameras:
        raise ValueError("tiger.train_field: no cameras given")
    means = scene.means.detach()
    n, device, dtype = means.shape[0], means.device, means.dtype
    t0 = time.perf_counter()
    maps = ResidentMaps(map_loader(feature_maps, cameras), len(cameras),
                        cfg.dim or (scene.lang.shape[1] if scene.lang is not None else None), device,
                        cfg.map_placement)
    d = maps.dim
    if init is not None and (not torch.is_tensor(init) or tuple(init.shape) != (n, d)):
        raise ValueError(f"tiger.train_field: init must be [N={n}, D={d}], got "
                         f"{list(init.shape) if torch.is_tensor(init) else type(init).__name__}")
    signature = {"gaussians": n, "dim": d, "views": len(cameras), "map_sizes": maps.sizes,
                 "init": "tensor" if init is not None else cfg.init,
                 "config": {k: v for k, v in asdict(cfg).items() if k not in RESUMABLE_CHANGES + ("init",)}}

    gen = torch.Generator().manual_seed(cfg.seed)
    ckpt_path = Path(checkpoint) if checkpoint is not None else None
    ck = _read_ckpt(ckpt_path, n, d, signature) if (ckpt_path and resume and ckpt_path.is_file()) else None

    if ck is not None:
        visible = ck["visible"].to(device)
        lang_full = ck["lang"].to(device=device, dtype=dtype)
        log.info("train_field: resuming %s at step %d", ckpt_path, ck["step"])
    else:
        # Culling does not depend on the resolution (K scales with it): the cameras' own sizes do.
        visible = _visibility(scene.detach(), cameras)
        if init is not None:
            lang_full = init.detach().to(device=device, dtype=dtype).clone()
        elif cfg.init == "keep":
            if scene.lang is None or scene.lang.shape != (n, d):
                raise ValueError("tiger.train_field: init='keep' needs scene.lang of shape [N, D]")
            lang_full = scene.lang.detach().to(dtype).clone()
        elif cfg.init == "zeros":
            lang_full = means.new_zeros((n, d))
        else:
            lang_full = (torch.randn(n, d, generator=gen, dtype=torch.float64) * cfg.init_std).to(means)
        lang_full[~visible] = 0
    n_invisible = int((~visible).sum())
    if n_invisible:
        log.warning("train_field: %d of %d Gaussians are culled in every view (outside it or too faint); "
                    "skipped (L = 0)", n_invisible, n)

    vis_idx = torch.nonzero(visible).reshape(-1)
    # The frozen geometry of the Gaussians in view, detached once for every step.
    frozen = scene.detach() if not n_invisible else scene.subset(visible)
    frozen.lang = None
    at_map_size = [c.resized(w, h) for c, (h, w) in zip(cameras, maps.sizes)]
    done = int(ck["step"]) if ck is not None else 0
    session = _FieldSession(frozen, at_map_size, maps, lang_full[vis_idx].clone(), cfg, gen, signature,
                            max(cfg.steps, done))
    if ck is not None:
        session.opt.load_state_dict(ck["optimizer"])
        restore_rng(ck["rng"], session.generators())
        session.views.load_state_dict(ck["views"])
        session.step = done
        session.losses[:done] = ck["losses"].to(device)
        session.touched = ck["touched"].to(device)[vis_idx]

    def full() -> tuple:
        out = lang_full.clone()
        out[vis_idx] = session.lang.detach()
        touched = torch.zeros(n, dtype=torch.bool, device=device)
        touched[vis_idx] = session.touched
        return out, touched, visible

    session.full = full
    after = (lambda rec: callback(session.step, float(rec["loss"]))) if callback is not None else None
    if vis_idx.numel() > 0:
        run_loop(session, cfg.steps, checkpoint=ckpt_path, checkpoint_every=cfg.checkpoint_every,
                 progress=cfg.progress, desc="language field", after_step=after)
    elif ckpt_path is not None:
        session.save(ckpt_path)

    lang_full, touched, _ = full()
    step = session.step
    untouched = visible & ~touched
    n_untouched = int(untouched.sum())
    if n_untouched and step > 0:
        log.warning("train_field: %d Gaussians are in view but reach no valid pixel (hidden or masked "
                    "out); L reset to 0", n_untouched)
        lang_full[untouched] = 0
    scene.lang = lang_full
    if pca is not None:
        from tiger.retrieval.text import pca_of

        pair = pca_of(pca)
        if pair is not None:
            scene.lang_pca_basis, scene.lang_pca_mean = pair[0].to(device), pair[1].to(device)
    return FieldResult(lang=lang_full, losses=session.losses[:step].tolist(), invisible=~visible,
                       untouched=untouched, steps=step, seconds=time.perf_counter() - t0)


__all__ = ["FieldConfig", "FieldResult", "train_field"]
