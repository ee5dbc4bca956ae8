"""Training the language field (paper §3.1): only each Gaussian's L is optimised.

Every other parameter is frozen and enters the rasterizer detached, so the backward is the
features-only kernel (no geometry gradient is ever computed). The loss compares the rendered
D-dim features with per-view feature maps (pixels marked invalid, e.g. in no SAM mask, are
ignored). Gaussians culled in every view are reported and skipped (their L stays 0, so no query
ever retrieves them); Gaussians that are in view but never receive a gradient are reported and
reset to 0 at the end for the same reason.

The maps are read once (:class:`tiger.language.feature_maps.ResidentMaps`: on the device when they
fit, else pinned host memory streamed a step ahead); each view's projection and tile lists are
computed once (:class:`tiger.language.frozen_views.FrozenViews`: the geometry is frozen), so a step
runs only the compositing kernel, its features-only backward, the loss and Adam, with no host
synchronisation (the loss is read back for the progress bar every 10 steps).

The defaults spend 1,500 steps, most of them cheap, where the earlier default spent 10,000 steps of
one whole view each (``FieldConfig.before_lift``): the field starts from the lifted embeddings (:func:`tiger.language.lift.lift_views`, one
pass over the views, from the maps already read); the first two thirds of the steps train on the
maps averaged over 2 x 2 blocks with the views rendered at half size (a quarter of the pixels, and
every Gaussian in view still updated; views under 2^18 pixels are not pooled); the last third at full resolution render a band of at most
half a million pixels of a view (a quarter of a 1080x1920 view); the learning rate decays from
1e-2 to the earlier default's constant 2.5e-3.
:attr:`FieldResult.full_loss` is the loss over every pixel of every view at the end, the measure
the defaults were chosen by (``benchmarks/language_field.py``). The loop is
:func:`tiger.train.run_loop` (checkpoints, Ctrl-C).
"""
from __future__ import annotations

import dataclasses
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

from .feature_maps import (PLACEMENTS, FeatureMap, FeatureSource, FeatureStore, ResidentMaps, ViewMap, map_loader,
                           pooled)
from .frozen_views import FrozenViews

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
CHECKPOINT_FORMAT = "tiger.field-checkpoint/2"
#: FieldConfig fields that may change between a run and its resume.
RESUMABLE_CHANGES = ("steps", "checkpoint_every", "progress", "map_placement", "evaluate")
INITS = ("lift", "random", "zeros", "keep")
#: Views of fewer pixels train at full resolution in the coarse steps too: a whole-view step is
#: cheap there, and pooling would lose the detail of a small map.
COARSE_MIN_PIXELS = 1 << 18


@dataclass
class FieldConfig:
    """Language field training settings.

    Attributes:
        steps: optimisation steps in all (each renders ``batch_views`` views, or bands of them).
        coarse: the fraction of the steps (the first ones) that train on coarse maps: each view's
            map averaged over ``coarse_factor`` x ``coarse_factor`` blocks, the view rendered at
            that size. A coarse step costs about ``1 / coarse_factor**2`` of a whole view and
            updates every Gaussian in view, so most of the fitting is done cheaply; the
            full-resolution steps after them settle the detail. Views of fewer than
            :data:`COARSE_MIN_PIXELS` pixels are never pooled. 0: every step at full resolution.
        coarse_factor: the block size of the coarse maps (px).
        lr: Adam learning rate for L at the first step (features of unit scale).
        lr_final: the learning rate at the last step, as a fraction of ``lr`` (exponential decay
            in between; 1: constant).
        batch_views: views rendered and averaged per step (sampled without replacement per epoch).
        crop_pixels: how many pixels of a view a step renders at most: a full-width band of
            whole tile rows (16 px; at least one) at a random height, its loss the mean over the
            band's valid pixels; views that small or smaller are rendered whole, and 0 renders
            every view whole. The default is a quarter of a 1080x1920 view: where a whole view
            costs far more than a step's fixed work (Adam, launches), several updates on parts
            of views learn more than one on the whole.
        loss: ``"l1"`` (LangSplat), ``"l2"`` or ``"cosine"`` (1 - cos, per pixel).
        init: ``"lift"`` (each Gaussian's blending-weighted mean of the maps, one pass over the
            views: :func:`tiger.language.lift.lift_views`), ``"random"`` (N(0, init_std^2)),
            ``"zeros"`` or ``"keep"`` (the scene's current L).
        init_std: spread of the random initialisation.
        dim: D, the language dimension, used when the scene has no L yet (default: the maps').
        checkpoint_every: steps between checkpoints (0: only at the end) when a path is given.
        seed: seeds the initialisation, the view order and the bands (resumed runs continue the stream).
        progress: show a tqdm progress bar.
        map_placement: where the maps are kept: ``"auto"`` (the device when they fit, else pinned
            host memory streamed to it), ``"device"`` or ``"host"``.
        evaluate: measure the loss over every pixel of every view at the end
            (:attr:`FieldResult.full_loss`; one forward render per view).
    """

    steps: int = 1500
    coarse: float = 0.67
    coarse_factor: int = 2
    lr: float = 1e-2
    lr_final: float = 0.25
    batch_views: int = 1
    crop_pixels: int = 1 << 19
    loss: str = "l1"
    init: str = "lift"
    init_std: float = 0.1
    dim: Optional[int] = None
    checkpoint_every: int = 1000
    seed: int = 0
    progress: bool = True
    map_placement: str = "auto"
    evaluate: bool = True

    @classmethod
    def before_lift(cls, **overrides) -> "FieldConfig":
        """The settings ``tiger embed`` trained with before the fast defaults (10,000 steps of
        one whole view each, constant learning rate 2.5e-3), from the lifted embeddings."""
        return cls(**{"steps": 10_000, "coarse": 0.0, "lr": 2.5e-3, "lr_final": 1.0, "crop_pixels": 0,
                      **overrides})

    def validate(self) -> None:
        if self.steps < 0:
            raise ValueError(f"tiger.train_field: steps must be >= 0, got {self.steps}")
        if not (0 <= self.coarse <= 1) or self.coarse_factor < 1:
            raise ValueError(f"tiger.train_field: coarse must be in [0, 1] and coarse_factor >= 1, got "
                             f"{self.coarse} and {self.coarse_factor}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"tiger.train_field: lr must be finite and > 0, got {self.lr}")
        if not (0 < self.lr_final <= 1):
            raise ValueError(f"tiger.train_field: lr_final must be in (0, 1], got {self.lr_final}")
        if self.batch_views < 1:
            raise ValueError(f"tiger.train_field: batch_views must be >= 1, got {self.batch_views}")
        if self.crop_pixels < 0:
            raise ValueError(f"tiger.train_field: crop_pixels must be >= 0, got {self.crop_pixels}")
        if self.loss not in ("l1", "l2", "cosine"):
            raise ValueError(f"tiger.train_field: loss must be 'l1', 'l2' or 'cosine', got '{self.loss}'")
        if self.init not in INITS:
            raise ValueError(f"tiger.train_field: init must be one of {INITS}, got '{self.init}'")
        if self.map_placement not in PLACEMENTS:
            raise ValueError(f"tiger.train_field: map_placement must be one of {PLACEMENTS}, "
                             f"got '{self.map_placement}'")


@dataclass
class FieldResult:
    """Outcome of :func:`train_field`.

    Attributes:
        lang: [N, D] the trained embeddings (also written to ``scene.lang``).
        losses: loss per step (the whole run, resumed parts included; a step's own pixels).
        invisible: [N] bool, culled in every view: outside it or too faint (skipped, L = 0).
        untouched: [N] bool, in view but given no gradient and no lifted value (hidden behind
            others, or only over masked-out pixels; L reset to 0). :meth:`coverage` says both in
            one line.
        steps: steps done in total; seconds: wall time of this call.
        full_loss: the loss over every valid pixel of every view at the end (mean of the views'
            means), None with ``evaluate=False``.
        lift_seconds: time of the lifting pass (0 without ``init="lift"``).
        stages: seconds per stage of this call: ``"read maps"``, ``"project and bin"`` (the views'
            projections and tile lists, and the visibility they give), ``"lift"``, ``"train"``,
            ``"evaluate"`` (the device is synchronised at each stage's end).
    """

    lang: torch.Tensor
    losses: list = field(default_factory=list)
    invisible: Optional[torch.Tensor] = None
    untouched: Optional[torch.Tensor] = None
    steps: int = 0
    seconds: float = 0.0
    full_loss: Optional[float] = None
    lift_seconds: float = 0.0
    stages: dict = field(default_factory=dict)

    def coverage(self) -> str:
        """One line on the Gaussians left without a feature, in the words the logs use."""
        n = int(self.lang.shape[0])
        out_of_view = int(self.invisible.sum()) if self.invisible is not None else 0
        silent = int(self.untouched.sum()) if self.untouched is not None else 0
        return (f"{out_of_view + silent} of {n} Gaussians without a language feature (L = 0): "
                f"{out_of_view} culled in every view (outside it or too faint), {silent} in view but "
                f"reaching no valid pixel (hidden or masked out)")


# ------------------------------------------------------------------------------------ loss
class _MaskedL1(torch.autograd.Function):
    """sum over valid pixels of |pred - target| / count, its gradient made in the same pass:
    three passes over [H, W, D] instead of the eight of the composed ops (difference, mask,
    absolute value and their backward), and no float32 copy of the map."""

    @staticmethod
    def forward(ctx, pred: torch.Tensor, target: torch.Tensor, valid: Optional[torch.Tensor],
                count: float) -> torch.Tensor:
        diff = pred.detach() - target  # promotes a float16 map on the fly
        if valid is not None:
            diff.mul_(valid.unsqueeze(-1))
        loss = torch.linalg.vector_norm(diff, 1) / count
        ctx.save_for_backward(diff.sign_().div_(count))
        return loss

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        (sign,) = ctx.saved_tensors
        return sign.mul_(grad), None, None, None  # each step's graph is walked once


def _loss(pred: torch.Tensor, target: ViewMap, kind: str) -> torch.Tensor:
    """Mean per-pixel loss over the valid pixels. Masked sums, not boolean indexing: indexing
    would wait for the device to count the pixels every step (they are counted once)."""
    t = target.features
    if kind == "l1":
        return _MaskedL1.apply(pred, t, target.valid, float(max(target.n_valid * pred.shape[-1], 1)))
    if kind == "cosine":
        per = 1 - torch.nn.functional.cosine_similarity(pred, t.to(pred.dtype), dim=-1, eps=1e-8)
        per_pixel = 1
    else:
        per = (pred - t).square()  # promotes float16 maps on the fly
        per_pixel = pred.shape[-1]
    if target.valid is not None:
        per = torch.where(target.valid if per.dim() == 2 else target.valid[..., None], per, 0)
    return per.sum() / max(target.n_valid * per_pixel, 1)


def _band(m: ViewMap, first_row: int, stop_row: int, valid_rows: torch.Tensor) -> ViewMap:
    """Rows ``first_row:stop_row`` of a map (views, no copies); ``valid_rows`` [H + 1] is the
    host cumulative count of valid pixels by row."""
    n = int(valid_rows[stop_row] - valid_rows[first_row])
    return ViewMap(m.features[first_row:stop_row], None if m.valid is None else m.valid[first_row:stop_row], n)


def full_view_loss(views: FrozenViews, maps: ResidentMaps, lang: torch.Tensor, kind: str = "l1") -> float:
    """The loss of ``lang`` [N, D] over every valid pixel of every view: the mean of the views'
    per-pixel means (each view weighs the same, as in training)."""
    total = lang.new_zeros((), dtype=torch.float64)
    with torch.no_grad():
        for v in range(len(views)):
            m = maps.get(v)
            maps.prefetch([v + 1] if v + 1 < len(views) else [])
            total += _loss(views.render(v, lang)[0], m, kind).double()
    return float(total) / len(views)


# ------------------------------------------------------------------------------------ steps
def _coarse_camera(cam: Camera, factor: int) -> Camera:
    """``cam`` at ``1 / factor`` of its size for maps pooled by :func:`pooled`: coarse pixel j
    covers full pixels ``factor * j`` to ``factor * j + factor - 1``, so K is divided by
    ``factor`` exactly (the size rounds down, as the pooled maps do)."""
    K = cam.K.clone()
    K[:2] /= factor
    return dataclasses.replace(cam, K=K, width=max(1, cam.width // factor), height=max(1, cam.height // factor))


def lr_at(cfg: FieldConfig, step: int) -> float:
    """The learning rate of step ``step`` (0-based): ``lr * lr_final ** (step / (steps - 1))``,
    from ``lr`` at the first step to ``lr * lr_final`` at the last (and after it, on a resume
    that asks for more steps than the schedule was made for)."""
    span = max(cfg.steps - 1, 1)
    return cfg.lr * cfg.lr_final ** (min(step, span) / span)


class _FieldSession:
    """The state :func:`tiger.train.run_loop` drives: L of every Gaussian (those culled in every
    view get no gradient, so Adam leaves them at 0), Adam, the view sampler, the bands, the
    per-step losses (on the device) and which Gaussians got a gradient."""

    def __init__(self, views: FrozenViews, maps: ResidentMaps, lang: torch.Tensor, cfg: FieldConfig,
                 gen: torch.Generator, signature: dict, total_steps: int) -> None:
        self.frozen, self.maps, self.cfg, self.gen = views, maps, cfg, gen
        self.lang = lang.requires_grad_(True)
        self.opt = torch.optim.Adam([self.lang], lr=cfg.lr)
        self.views = ViewSampler(len(views), gen)
        self.losses = torch.zeros(total_steps, device=lang.device)
        self.touched = torch.zeros(lang.shape[0], dtype=torch.bool, device=lang.device)
        self.step, self.elapsed, self.signature = 0, 0.0, signature
        self.visible: Optional[torch.Tensor] = None  # [N] bool, set by train_field
        # per view: host cumulative valid pixels by row, for the bands' pixel counts
        self.valid_rows = [maps.valid_rows(v) for v in range(len(views))]
        self.coarse: Optional[tuple[FrozenViews, list]] = None  # made at the first coarse step
        self.coarse_steps = round(cfg.coarse * cfg.steps) if cfg.coarse_factor > 1 else 0
        self.scene: Optional[GaussianScene] = None  # set by train_field (for the coarse views)

    def _coarse(self) -> tuple[FrozenViews, list]:
        """The coarse views and their pooled maps (on the training device), made once."""
        if self.coarse is None:
            f = self.cfg.coarse_factor
            cams = [_coarse_camera(c, f) for c in self.frozen.cameras]
            pooled_maps = []
            for v in range(len(self.frozen)):
                pooled_maps.append(pooled(self.maps.get(v), f))
                self.maps.prefetch([v + 1] if v + 1 < len(self.frozen) else [])
            self.coarse = (FrozenViews(self.scene, cams), pooled_maps)
        return self.coarse

    def generators(self) -> list:
        return [self.gen]

    def _rows(self, v: int) -> Optional[tuple[int, int]]:
        """A random band of whole tile rows of view ``v`` (None: the whole view)."""
        cam, budget = self.frozen.cameras[v], self.cfg.crop_pixels
        if budget <= 0 or budget >= cam.width * cam.height:
            return None
        tiles = self.frozen.tile_rows(v)
        band = max(1, budget // (cam.width * self.frozen.tile_size))
        if band >= tiles:
            return None
        first = int(torch.randint(0, tiles - band + 1, (1,), generator=self.gen))
        return first, first + band

    def step_once(self) -> dict:
        views = self.views.take(self.cfg.batch_views)
        for group in self.opt.param_groups:
            group["lr"] = lr_at(self.cfg, self.step)
        self.opt.zero_grad(set_to_none=True)
        total = self.lang.new_zeros(())
        ts = self.frozen.tile_size
        coarse = self.step < self.coarse_steps
        for v in views:
            if coarse and self.frozen.cameras[v].width * self.frozen.cameras[v].height >= COARSE_MIN_PIXELS:
                coarse_views, coarse_maps = self._coarse()
                color, _ = coarse_views.render(v, self.lang)
                target = coarse_maps[v]
            else:
                rows = self._rows(v)
                color, _ = self.frozen.render(v, self.lang, rows)
                target = self.maps.get(v)
                if rows is not None:
                    target = _band(target, rows[0] * ts, rows[0] * ts + color.shape[0], self.valid_rows[v])
            loss = _loss(color, target, self.cfg.loss) / len(views)
            loss.backward()
            total = total + loss.detach()
        if self.step + 1 >= self.coarse_steps:  # the next step's full-resolution maps, while this one runs
            self.maps.prefetch(self.views.peek(self.cfg.batch_views))
        if self.lang.grad is not None:
            self.touched |= (self.lang.grad != 0).any(dim=1)
        self.opt.step()
        self.losses[self.step] = total
        self.step += 1
        return {"loss": total}

    def save(self, path: PathLike) -> None:
        state = {"lang": self.lang.detach().cpu(), "optimizer": self.opt.state_dict(), "step": self.step,
                 "views": self.views.state_dict(), "losses": self.losses[:self.step].cpu(),
                 "touched": self.touched.cpu(), "visible": self.visible.cpu()}
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
            Each map is read once (see the module docstring), lifting included.
        config: :class:`FieldConfig`; keyword ``overrides`` replace its fields (``steps=...``).
        pca: the PCA that produced the maps (``PCABasis`` or (basis, mean)), stored with the scene.
        checkpoint: file for checkpoints (every ``checkpoint_every`` steps, at the end and on
            Ctrl-C); with ``resume`` an existing one is continued exactly (one made with other
            settings or another scene is refused, naming what differs).
        init: [N, D] initial embeddings, replacing ``config.init``; Gaussians culled in every
            view still start (and stay) at 0. A string is ``config.init`` (``"lift"``,
            ``"random"``, ``"zeros"``, ``"keep"``).
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
    stages: dict[str, float] = {}
    clock = [t0]

    def stage(name: str) -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        now = time.perf_counter()
        stages[name] = stages.get(name, 0.0) + now - clock[0]
        clock[0] = now

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
    # Each view at its map's size; projections and tile lists computed once (culling does not
    # depend on the resolution: K scales with it).
    stage("read maps")
    views = FrozenViews(scene, [c.resized(w, h) for c, (h, w) in zip(cameras, maps.sizes)])
    lift_seconds, lifted_weight = 0.0, None
    if ck is not None:
        visible = ck["visible"].to(device)
        lang_full = ck["lang"].to(device=device, dtype=dtype)
        log.info("train_field: resuming %s at step %d", ckpt_path, ck["step"])
    else:
        visible = torch.zeros(n, dtype=torch.bool, device=device)
        for v in range(len(views)):
            visible |= views.radii(v) > 0
        stage("project and bin")
        if init is not None:
            lang_full = init.detach().to(device=device, dtype=dtype).clone()
        elif cfg.init == "lift":
            from .lift import lift_views

            lifted = lift_views(views, maps, progress=cfg.progress)
            lang_full, lift_seconds, lifted_weight = lifted.lang.to(dtype), lifted.seconds, lifted.weight
            log.info("train_field: lifted in %.1f s; %s", lifted.seconds, lifted.coverage())
            stage("lift")
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

    done = int(ck["step"]) if ck is not None else 0
    session = _FieldSession(views, maps, lang_full, cfg, gen, signature, max(cfg.steps, done))
    session.visible, session.scene = visible, scene
    if lifted_weight is not None:
        session.touched |= lifted_weight > 0  # a lifted value is a feature (kept when no step reaches it)
    if ck is not None:
        session.opt.load_state_dict(ck["optimizer"])
        restore_rng(ck["rng"], session.generators())
        session.views.load_state_dict(ck["views"])
        session.step = done
        session.losses[:done] = ck["losses"].to(device)
        session.touched = ck["touched"].to(device)

    after = (lambda rec: callback(session.step, float(rec["loss"]))) if callback is not None else None
    if bool(visible.any()):
        run_loop(session, cfg.steps, checkpoint=ckpt_path, checkpoint_every=cfg.checkpoint_every,
                 progress=cfg.progress, desc="language field", after_step=after)
    elif ckpt_path is not None:
        session.save(ckpt_path)
    stage("train")

    lang_full = session.lang.detach().clone()
    step = session.step
    untouched = visible & ~session.touched
    n_untouched = int(untouched.sum())
    if n_untouched and (step > 0 or lifted_weight is not None):
        log.warning("train_field: %d Gaussians are in view but reach no valid pixel (hidden or masked "
                    "out); L reset to 0", n_untouched)
        lang_full[untouched] = 0
    full_loss = full_view_loss(views, maps, lang_full, cfg.loss) if cfg.evaluate else None
    if cfg.evaluate:
        stage("evaluate")
    scene.lang = lang_full
    if pca is not None:
        from tiger.retrieval.text import pca_of

        pair = pca_of(pca)
        if pair is not None:
            scene.lang_pca_basis, scene.lang_pca_mean = pair[0].to(device), pair[1].to(device)
    return FieldResult(lang=lang_full, losses=session.losses[:step].tolist(), invisible=~visible,
                       untouched=untouched, steps=step, seconds=time.perf_counter() - t0, full_loss=full_loss,
                       lift_seconds=lift_seconds, stages=stages)


__all__ = ["FieldConfig", "FieldResult", "full_view_loss", "train_field"]
