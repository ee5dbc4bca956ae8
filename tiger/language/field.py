"""Training the language field (paper §3.1): only each Gaussian's L is optimised.

Every other parameter is frozen and enters the rasterizer detached, so the backward is the
features-only kernel (no geometry gradient is ever computed). The loss compares the rendered
D-dim features with per-view feature maps (pixels marked invalid, e.g. in no SAM mask, are
ignored). Gaussians culled in every view are reported and skipped (their L stays 0, so no query
ever retrieves them); Gaussians that are in view but never receive a gradient are reported and
reset to 0 at the end for the same reason.
"""
from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Optional, Protocol, Sequence, Union

import torch

from tiger.retrieval.text import PCASource
from tiger.render import Camera
from tiger.scene import GaussianScene
from tiger.utils.io import atomic_torch_save

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]
#: One view's target: features [H, W, D], (features, valid [H, W]) or {"features", "valid"}.
FeatureMap = Union[torch.Tensor, tuple[torch.Tensor, Optional[torch.Tensor]], Mapping[str, torch.Tensor]]


class FeatureStore(Protocol):
    """Feature maps on disk by image name (``tiger.language.FeatureSet``)."""

    names: Sequence[str]

    def load(self, name: str) -> FeatureMap: ...


FeatureSource = Union[Sequence[FeatureMap], Callable[[int], FeatureMap], FeatureStore]


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


# ------------------------------------------------------------------------------------ inputs
def _as_map(item: FeatureMap, index: int) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """(features [H, W, D], valid [H, W] bool or None) from a tensor, a pair or a dict."""
    if isinstance(item, dict):
        feats, valid = item.get("features"), item.get("valid", item.get("mask"))
    elif isinstance(item, (tuple, list)) and len(item) == 2:
        feats, valid = item
    else:
        feats, valid = item, None
    if not torch.is_tensor(feats) or feats.dim() != 3:
        raise ValueError(f"tiger.train_field: feature map {index} must be [H, W, D], got "
                         f"{list(feats.shape) if torch.is_tensor(feats) else type(feats).__name__}")
    if valid is not None:
        valid = torch.as_tensor(valid)
        if valid.shape != feats.shape[:2]:
            raise ValueError(f"tiger.train_field: valid mask {index} is {list(valid.shape)}, its feature "
                             f"map is {list(feats.shape[:2])}")
        valid = valid.bool()
    return feats, valid


def _map_loader(feature_maps: FeatureSource, cameras: Sequence[Camera]) -> Callable[[int], FeatureMap]:
    """index -> raw map item. Accepts a sequence, a callable, or a store with ``names``/``load(name)``
    (``tiger.language.FeatureSet``), matched to cameras by image name (or its stem)."""
    n = len(cameras)
    if hasattr(feature_maps, "load") and hasattr(feature_maps, "names"):
        names = list(feature_maps.names)
        by_name = {nm: nm for nm in names}
        by_name.update({Path(nm).stem: nm for nm in names})
        chosen = []
        for i, cam in enumerate(cameras):
            img = cam.image_name
            key = img if img in by_name else Path(img).stem if Path(img).stem in by_name else None
            if key is None:
                if len(names) != n:
                    raise ValueError(f"tiger.train_field: camera {i} ('{img}') has no feature map among "
                                     f"{len(names)} names, and the counts differ ({n} cameras)")
                chosen.append(names[i])
            else:
                chosen.append(by_name[key])
        return lambda i: feature_maps.load(chosen[i])
    if callable(feature_maps):
        return feature_maps
    if len(feature_maps) != n:
        raise ValueError(f"tiger.train_field: {len(feature_maps)} feature maps for {n} cameras")
    return lambda i: feature_maps[i]


def _render(scene: GaussianScene, camera: Camera, lang: torch.Tensor, height: int, width: int) -> dict:
    """``lang`` rendered at ``width x height`` (K rescaled); ``scene`` is detached, so the backward
    is the features-only kernel."""
    return scene.render(camera.resized(width, height), lang, check_finite=False)


def _visibility(scene: GaussianScene, cameras: Sequence[Camera]) -> torch.Tensor:
    """[N] bool: projected into at least one view (radius > 0)."""
    vis = torch.zeros(len(scene), dtype=torch.bool, device=scene.device)
    one = scene.means.new_zeros((len(scene), 1))
    with torch.no_grad():
        for cam in cameras:
            vis |= scene.render(cam, one, check_finite=False)["radii"] > 0
    return vis


def _loss(pred: torch.Tensor, target: torch.Tensor, valid: Optional[torch.Tensor], kind: str) -> torch.Tensor:
    if valid is not None:
        pred, target = pred[valid], target[valid]
    if pred.numel() == 0:
        return pred.sum()
    if kind == "l1":
        return (pred - target).abs().mean()
    if kind == "l2":
        return (pred - target).square().mean()
    return (1 - torch.nn.functional.cosine_similarity(pred, target, dim=-1, eps=1e-8)).mean()


# ------------------------------------------------------------------------------- checkpoints
def _save_ckpt(path: Path, lang_full: torch.Tensor, opt: torch.optim.Optimizer, step: int,
               gen: torch.Generator, order: list, losses: list, touched: torch.Tensor,
               visible: torch.Tensor, cfg: FieldConfig) -> None:
    atomic_torch_save({"lang": lang_full.detach().cpu(), "optimizer": opt.state_dict(), "step": step,
                       "generator": gen.get_state(), "order": list(order), "losses": list(losses),
                       "touched": touched.cpu(), "visible": visible.cpu(), "config": asdict(cfg)}, path)


def _load_ckpt(path: Path, n: int, d: int) -> dict:
    ck = torch.load(str(path), map_location="cpu", weights_only=False)
    missing = {"lang", "optimizer", "step", "generator", "order", "losses", "touched", "visible"} - set(ck)
    if missing:
        raise ValueError(f"tiger.train_field: checkpoint {path} is incomplete (missing {sorted(missing)})")
    if tuple(ck["lang"].shape) != (n, d):
        raise ValueError(f"tiger.train_field: checkpoint {path} holds L of shape {list(ck['lang'].shape)}, "
                         f"the scene needs [{n}, {d}]")
    return ck


# ------------------------------------------------------------------------------------ train
def train_field(scene: GaussianScene, cameras: Sequence[Camera], feature_maps: FeatureSource, *,
                config: Optional[FieldConfig] = None, pca: PCASource = None,
                checkpoint: Optional[PathLike] = None, resume: bool = True,
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
        config: :class:`FieldConfig`; keyword ``overrides`` replace its fields (``steps=...``).
        pca: the PCA that produced the maps (``PCABasis`` or (basis, mean)), stored with the scene.
        checkpoint: file for periodic checkpoints; with ``resume`` an existing one is continued.
        callback: called as ``callback(step, loss)`` after every step.
    Returns:
        :class:`FieldResult`.
    """
    cfg = FieldConfig(**{**asdict(config or FieldConfig()), **overrides})
    cfg.validate()
    cameras = list(cameras)
    if not cameras:
        raise ValueError("tiger.train_field: no cameras given")
    means = scene.means.detach()
    n, device, dtype = means.shape[0], means.device, means.dtype
    load = _map_loader(feature_maps, cameras)

    # Only the first map is read up front (for D): maps may live on disk, one per view.
    first, _ = _as_map(load(0), 0)
    d = cfg.dim or (scene.lang.shape[1] if scene.lang is not None else first.shape[2])
    del first

    gen = torch.Generator().manual_seed(cfg.seed)
    ckpt_path = Path(checkpoint) if checkpoint is not None else None
    ck = _load_ckpt(ckpt_path, n, d) if (ckpt_path and resume and ckpt_path.is_file()) else None

    if ck is not None:
        visible = ck["visible"].to(device)
        lang_full = ck["lang"].to(device=device, dtype=dtype)
        log.info("train_field: resuming %s at step %d", ckpt_path, ck["step"])
    else:
        # Culling does not depend on the resolution (K scales with it): the cameras' own sizes do.
        visible = _visibility(scene.detach(), cameras)
        if cfg.init == "keep":
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
    lang = lang_full[vis_idx].clone().requires_grad_(True)
    opt = torch.optim.Adam([lang], lr=cfg.lr)
    touched = torch.zeros(n, dtype=torch.bool, device=device)
    losses: list = []
    step, order = 0, []
    if ck is not None:
        opt.load_state_dict(ck["optimizer"])
        gen.set_state(ck["generator"])
        step, order, losses = int(ck["step"]), list(ck["order"]), list(ck["losses"])
        touched = ck["touched"].to(device)
    # The frozen geometry of the Gaussians in view, detached once for every step.
    frozen = scene.detach() if not n_invisible else scene.subset(visible)
    frozen.lang = None

    def save() -> None:
        if ckpt_path is not None:
            full = lang_full.clone()
            full[vis_idx] = lang.detach()
            _save_ckpt(ckpt_path, full, opt, step, gen, order, losses, touched, visible, cfg)

    from tqdm.auto import tqdm

    t0 = time.perf_counter()
    bar = tqdm(total=cfg.steps, initial=min(step, cfg.steps), desc="language field", unit="step",
               disable=not cfg.progress)
    try:
        while step < cfg.steps and vis_idx.numel() > 0:
            views = []
            while len(views) < min(cfg.batch_views, len(cameras)):
                if not order:
                    order = torch.randperm(len(cameras), generator=gen).tolist()
                views.append(order.pop())
            opt.zero_grad(set_to_none=True)
            total = 0.0
            for v in views:
                feats, valid = _as_map(load(v), v)
                if feats.shape[2] != d:
                    raise ValueError(f"tiger.train_field: feature map {v} has {feats.shape[2]} channels, L has {d}")
                h, w = int(feats.shape[0]), int(feats.shape[1])
                out = _render(frozen, cameras[v], lang, h, w)
                target = feats.to(device=device, dtype=dtype)
                loss = _loss(out["color"], target, None if valid is None else valid.to(device), cfg.loss)
                (loss / len(views)).backward()
                total += float(loss.detach()) / len(views)
            if lang.grad is not None:
                touched[vis_idx] |= (lang.grad != 0).any(dim=1)
            opt.step()
            step += 1
            losses.append(total)
            bar.update(1)
            if step % 10 == 0 or step == cfg.steps:
                bar.set_postfix(loss=f"{total:.4g}")
            if callback is not None:
                callback(step, total)
            if ckpt_path is not None and cfg.checkpoint_every > 0 and step % cfg.checkpoint_every == 0:
                save()
    finally:
        bar.close()
    save()

    lang_full[vis_idx] = lang.detach()
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
    return FieldResult(lang=lang_full, losses=losses, invisible=~visible, untouched=untouched, steps=step,
                       seconds=time.perf_counter() - t0)
