"""The edit loop: Coherent Score Distillation on the retrieved Gaussians only (paper §3.2, SPEC §6).

Each step: draw V cameras around the object (:class:`tiger.edit.views.ObjectViews`), render the
current scene and the original scene from them, ask the guidance for ``dL/drenders``, back-propagate
through the rasterizer, and take a relevance-scaled Adam step on the editable Gaussians.

* **Sparse parameters.** The scene is split once into a frozen block (weight 0: plain tensors, no
  ``requires_grad``, no optimizer state, their view colours computed without autograd) and an
  editable block (weight > 0: Adam over means, log-scales, rotations, opacity and base colour).
  Frozen Gaussians come out bit-identical, in their original order. (The rasterizer's backward
  still visits every Gaussian in a tile; only the editable rows are read from it.)
* **Score-based updating.** Adam normalises gradients, so scaling a gradient would not scale the
  update; instead each Adam *update* is scaled: ``p ← p_old + w_i · (p_adam − p_old)``, with
  ``w_i`` the Gaussian's relevance (:mod:`tiger.edit.target`).
* **View-independent colour.** Editable Gaussians' higher SH bands are zeroed at the start of the
  round and not optimised; they render with their base colour, ``max(C0 · dc + 0.5, 0)``.
* **Densification** every ``densify_every`` steps (INRIA's clone/split/prune from
  :func:`tiger.recon.densify.densify_and_prune`, restricted to the editable block): the top
  ``densify_fraction`` (1 %) of the editable Gaussians by mean accumulated screen-space gradient are
  cloned (small) or split (large); transparent ones (< ``min_opacity``) are pruned. Children inherit
  the parent's language embedding and relevance weight (carried as extra columns of the block's
  ``lang``, so every row operation moves them together).
* **Checkpoints**: every ``checkpoint_every`` steps and on Ctrl-C (then the interrupt is re-raised);
  ``resume=True`` continues bit-for-bit (views, guidance noise, Adam, densification statistics).
"""
from __future__ import annotations

import logging
import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence, Union

import torch

from tiger.recon.densify import DensifyStats, densify_and_prune, prune_gaussians
from tiger.render import rasterize_gaussians
from tiger.scene.cameras import Camera
from tiger.scene.gaussian_scene import GaussianScene
from tiger.scene.sh import sh_to_rgb
from tiger.utils.io import atomic_torch_save

from .config import EditConfig
from .guidance.base import Guidance, ViewBatch
from .target import EditTarget, TargetLike, resolve_target
from .views import ObjectViews

log = logging.getLogger(__name__)
CHECKPOINT_FORMAT = "tiger.edit-checkpoint/1"
OPTIMISED = ("means", "log_scales", "quats", "opacity_logits", "sh_dc")
STAGES = ("render", "guidance", "backward", "optimizer", "densify")


@dataclass
class EditResult:
    """The outcome of :func:`edit`.

    Attributes:
        scene: the edited scene (frozen Gaussians bit-identical and in their original order, the
            surviving editable ones at their original positions, densification children appended;
            language embeddings and PCA kept, so it can be queried and edited again).
        weights: [N'] the edit weight of every Gaussian (children inherit their parent's).
        rounds: one record per edit round applied to this scene so far (earlier rounds come from
            ``scene.metadata["tiger_edits"]``), the last is this one.
        history: per logged step: step, loss, lambdas, Gaussians.
        timings_s: total seconds per stage (render, guidance, backward, optimizer, densify).
    """

    scene: GaussianScene
    weights: torch.Tensor
    rounds: list[dict]
    history: list[dict] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def editable(self) -> torch.Tensor:
        """[N'] bool, the Gaussians this round could change."""
        return self.weights > 0


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class _Timer:
    def __init__(self, device: torch.device) -> None:
        self.device, self.total = device, {k: 0.0 for k in STAGES}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        _sync(self.device)
        t0 = time.perf_counter()
        yield
        _sync(self.device)
        self.total[stage] += time.perf_counter() - t0


def _generators(guidance: Any) -> list[torch.Generator]:
    """Every torch.Generator a guidance (or a CSDGuidance's parts) draws from, in a fixed order."""
    out = []
    for g in (guidance, getattr(guidance, "ip2p", None), getattr(guidance, "mvdream", None)):
        gen = getattr(g, "generator", None) if g is not None else None
        if isinstance(gen, torch.Generator) and all(gen is not o for o in out):
            out.append(gen)
    return out


def _base_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    """[M, 3] view-independent colour of the base SH band, clamped at 0 like the renderer."""
    return (sh_to_rgb(sh_dc)).clamp_min(0)


class EditSession:
    """The state of one edit round (built by :func:`edit`; usable directly for step-wise control)."""

    def __init__(self, scene: GaussianScene, target: EditTarget, guidance: Guidance, instruction: str,
                 cameras: Optional[Sequence[Camera]], config: EditConfig) -> None:
        self.cfg, self.guidance, self.instruction, self.target = config, guidance, instruction, target
        self.device = scene.device
        self.input_len = len(scene)
        self.lang_dim = 0 if scene.lang is None else scene.lang.shape[1]
        w = target.weights.to(self.device)
        editable = w > 0
        self.frozen_idx = torch.nonzero(~editable).reshape(-1)
        self.frozen = scene.subset(self.frozen_idx)
        self.original = scene.detach()
        self.orig_indicator = editable.to(scene.dtype)
        self.frozen_scales, self.frozen_opac = self.frozen.scales, self.frozen.opacities
        edit = scene.subset(editable)
        if config.view_independent:
            edit.sh_rest = torch.zeros_like(edit.sh_rest)
        # carried columns: [lang | weight | original index] follow every row operation
        orig_idx = torch.nonzero(editable).reshape(-1).to(edit.dtype)
        parts = ([edit.lang] if edit.lang is not None else []) + [w[editable, None].to(edit.dtype), orig_idx[:, None]]
        edit.lang = torch.cat(parts, 1)
        edit.lang_pca_basis = edit.lang_pca_mean = None
        self.edit = edit
        self.radius = 0.5 * float((target.bbox_max - target.bbox_min).norm())
        self.views = ObjectViews(target.center, target.bbox_min, target.bbox_max, capture=cameras,
                                 n_views=config.n_views, width=config.width, height=config.height,
                                 fov_deg=config.fov_deg, elevation_deg=config.elevation_deg, fill=config.fill,
                                 force_360=True if not cameras else None)
        self.background = torch.tensor(config.background, dtype=scene.dtype, device=self.device)
        self.gen = torch.Generator().manual_seed(config.seed)
        self.step = 0
        self.history: list[dict] = []
        self.elapsed = 0.0
        self.timer = _Timer(self.device)
        self._rng_at_start: Optional[tuple] = None
        self._build_optimizer()
        self.stats = DensifyStats.zeros(len(self.edit), self.device)

    # -- parameters ---------------------------------------------------------------------------
    def _build_optimizer(self) -> None:
        lrs = self.cfg.learning_rates()
        lrs = {**lrs, "means": lrs["means"] * max(self.radius, 1e-6)}
        groups = self.edit.parameter_groups(lrs, names=OPTIMISED)
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)

    @property
    def weights(self) -> torch.Tensor:
        """[M] relevance weights of the editable block."""
        return self.edit.lang[:, self.lang_dim].detach()

    @property
    def optimizer_state_numel(self) -> int:
        """Elements held in Adam's state (both moments of every editable parameter)."""
        return sum(v.numel() for st in self.optimizer.state.values() for v in st.values()
                   if torch.is_tensor(v) and v.dim() > 0)

    # -- rendering ------------------------------------------------------------------------------
    def _render(self, cam: Camera, grad: bool) -> dict:
        """Render frozen + editable Gaussians from ``cam``; editable ones in their base colour."""
        c = cam.to(self.device, self.edit.dtype)
        e = self.edit
        with torch.no_grad():
            frozen_rgb = self.frozen.view_colors(c) if len(self.frozen) else e.means.new_zeros((0, 3))
        with torch.set_grad_enabled(grad):
            means = torch.cat([self.frozen.means, e.means])
            quats = torch.cat([self.frozen.quats, e.quats])
            scales = torch.cat([self.frozen_scales, e.scales])
            opac = torch.cat([self.frozen_opac, e.opacities])
            rgb = torch.cat([frozen_rgb, _base_rgb(e.sh_dc)])
            return rasterize_gaussians(means, quats, scales, opac, rgb, c.viewmat, c.K, c.width, c.height,
                                       background=self.background, check_finite=False)

    @torch.no_grad()
    def _render_originals(self, cams: Sequence[Camera]) -> tuple[torch.Tensor, torch.Tensor]:
        """Original renders [V, 3, H, W] (full SH) and the object's footprint [V, 1, H, W]."""
        s = self.original
        imgs, masks = [], []
        bg = torch.cat([self.background, self.background.new_zeros(1)])
        for cam in cams:
            c = cam.to(self.device, s.dtype)
            cols = torch.cat([s.view_colors(c), self.orig_indicator[:, None]], 1)
            r = rasterize_gaussians(s.means, s.quats, s.scales, s.opacities, cols, c.viewmat, c.K, c.width,
                                    c.height, background=bg, check_finite=False)["color"]
            imgs.append(r[..., :3].clamp(0, 1).permute(2, 0, 1))
            masks.append(r[..., 3:].clamp(0, 1).permute(2, 0, 1))
        return torch.stack(imgs), torch.stack(masks)

    # -- one step -------------------------------------------------------------------------------
    def step_once(self) -> dict:
        """One CSD step (views, renders, guidance, backward, scaled Adam, densification)."""
        cfg, T = self.cfg, self.timer
        self._rng_at_start = (self.gen.get_state(), [g.get_state() for g in _generators(self.guidance)])
        cams = self.views.sample(self.gen)
        with T("render"):
            originals, masks = self._render_originals(cams)
            outs = [self._render(c, grad=True) for c in cams]
            for o in outs:
                o["means2d"].retain_grad()
            x = torch.stack([o["color"].permute(2, 0, 1) for o in outs]).clamp(0, 1)
        batch = ViewBatch(cameras=cams, originals=originals, masks=masks, step=self.step,
                          total_steps=cfg.steps, object_center=self.target.center.to(self.device))
        with T("guidance"):
            g, info = self.guidance.grad(x.detach(), batch)
        if g.shape != x.shape:
            raise ValueError(f"tiger.edit: guidance '{getattr(self.guidance, 'name', '?')}' returned a gradient "
                             f"of shape {list(g.shape)} for renders {list(x.shape)}")
        with T("backward"):
            x.backward(torch.nan_to_num(g.to(x), nan=0.0, posinf=0.0, neginf=0.0))
            nf = len(self.frozen)
            if cfg.densify_every:
                for o, c in zip(outs, cams):
                    if o["means2d"].grad is not None:
                        self.stats.add(o["means2d"].grad[nf:], o["radii"][nf:], c.width, c.height)
        with T("optimizer"):
            self._scaled_adam_step()
        self.step += 1
        self._rng_at_start = None  # from here on an interrupt keeps this step
        rec = {"step": self.step, "loss": float(info.loss), "gaussians": len(self.frozen) + len(self.edit)}
        rec.update({k: float(v) for k, v in info.extra.items() if k.startswith("lambda")})
        until = cfg.densify_until if cfg.densify_until is not None else int(0.9 * cfg.steps)
        if (cfg.densify_every and self.step >= cfg.densify_from and self.step <= until
                and self.step % cfg.densify_every == 0):
            with T("densify"):
                rec["densify"] = self.densify()
        return rec

    def _scaled_adam_step(self) -> None:
        params = [g["params"][0] for g in self.optimizer.param_groups]
        olds = [p.detach().clone() for p in params]
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        w = self.weights
        with torch.no_grad():
            for p, old in zip(params, olds):
                ws = w.view(-1, *([1] * (p.dim() - 1)))
                p.sub_(old).mul_(ws).add_(old)

    def densify(self) -> dict:
        """Clone/split the top ``densify_fraction`` of the editable Gaussians, prune transparent ones."""
        m = len(self.edit)
        k = int(math.floor(self.cfg.densify_fraction * m))
        grads = self.stats.grad_accum / self.stats.count.clamp_min(1)
        grads = torch.where(self.stats.count > 0, grads, torch.zeros_like(grads))
        positive = int((grads > 0).sum())
        k = min(k, positive)
        thr = float(torch.topk(grads, k).values[-1]) if k > 0 else math.inf
        # no pruning inside (min_opacity -1): the appended rows are still at the end, marked as children
        info = densify_and_prune(self.edit, self.optimizer, self.stats, grad_threshold=thr,
                                 extent=max(self.radius, 1e-6), percent_dense=self.cfg.percent_dense,
                                 min_opacity=-1.0, max_gaussians=m + k, generator=self.gen)
        n_new = info["cloned"] + 2 * info["split"]
        with torch.no_grad():
            if n_new:
                self.edit.lang[len(self.edit) - n_new:, self.lang_dim + 1] = -1.0
            prune = self.edit.opacities.detach() < self.cfg.min_opacity
            if bool(prune.all()):
                prune[torch.argmax(self.edit.opacity_logits.detach())] = False
            prune_gaussians(self.edit, self.optimizer, self.stats, prune)
        info.update(pruned=int(prune.sum()), total=len(self.edit), editable=len(self.edit))
        return info

    # -- result -----------------------------------------------------------------------------------
    def result_scene(self) -> tuple[GaussianScene, torch.Tensor]:
        """(the full edited scene, [N'] weights) in the documented order."""
        e = self.edit.detach()
        d = self.lang_dim
        carry = e.lang
        w_edit, origin = carry[:, d], carry[:, d + 1].round().long()
        o = self.original
        e_scene = GaussianScene(e.means, e.log_scales, e.quats, e.opacity_logits, e.sh_dc, e.sh_rest,
                                lang=carry[:, :d] if d else None, lang_pca_basis=o.lang_pca_basis,
                                lang_pca_mean=o.lang_pca_mean)
        both = GaussianScene.concat([self.frozen.detach(), e_scene]) if len(self.frozen) else e_scene
        n = self.input_len
        child = origin < 0
        key = torch.cat([self.frozen_idx, torch.where(child, n + torch.arange(len(e), device=self.device), origin)])
        order = torch.argsort(key)
        out = both.subset(order)
        out.lang_pca_basis, out.lang_pca_mean = self.original.lang_pca_basis, self.original.lang_pca_mean
        out.metadata = dict(self.original.metadata)
        w = torch.cat([torch.zeros(len(self.frozen), device=self.device, dtype=w_edit.dtype), w_edit])[order]
        return out, w.float()

    # -- checkpoints ------------------------------------------------------------------------------
    def signature(self) -> dict:
        return {"instruction": self.instruction, "target": self.target.description, "gaussians": self.input_len,
                "guidance": getattr(self.guidance, "name", type(self.guidance).__name__),
                "config": self.cfg.to_dict()}

    def save(self, path: Union[str, Path]) -> None:
        payload = {
            "format": CHECKPOINT_FORMAT, "signature": self.signature(), "step": self.step,
            "edit": self.edit.state_dict(), "optimizer": self.optimizer.state_dict(),
            "stats": self.stats.state_dict(), "view_rng": self.gen.get_state(),
            "guidance_rng": [g.get_state() for g in _generators(self.guidance)],
            "history": self.history, "elapsed": self.elapsed, "timings": dict(self.timer.total),
        }
        atomic_torch_save(payload, path)

    def load(self, path: Union[str, Path]) -> None:
        path = Path(path)
        try:
            ck = torch.load(path, map_location=self.device, weights_only=True)
        except Exception as exc:  # corrupt files raise many types
            raise ValueError(f"tiger.edit: cannot read checkpoint {path} ({type(exc).__name__}: {exc})") from None
        if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"tiger.edit: {path} is not an edit checkpoint (format {CHECKPOINT_FORMAT})")
        if ck["signature"] != self.signature():
            raise ValueError(f"tiger.edit: checkpoint {path} belongs to another edit "
                             f"({ck['signature'].get('instruction')!r} on {ck['signature'].get('target')!r}); "
                             "use another output folder or start without --resume")
        self.edit = GaussianScene.from_state_dict(ck["edit"]).to(self.device)
        self._build_optimizer()
        self.optimizer.load_state_dict(ck["optimizer"])
        self.stats = DensifyStats.from_state_dict({k: v.to(self.device) for k, v in ck["stats"].items()})
        self.gen.set_state(ck["view_rng"].cpu())
        gens = _generators(self.guidance)
        for g, st in zip(gens, ck.get("guidance_rng", [])):
            g.set_state(st.cpu())
        self.step, self.history, self.elapsed = int(ck["step"]), list(ck["history"]), float(ck["elapsed"])
        self.timer.total.update(ck.get("timings", {}))
        log.info("edit resumed from %s at step %d of %d", path, self.step, self.cfg.steps)

    # -- the loop -----------------------------------------------------------------------------------
    def run(self, checkpoint: Optional[Union[str, Path]] = None) -> None:
        """Step until ``config.steps``; checkpoints as configured and on Ctrl-C (re-raised)."""
        from tqdm.auto import tqdm

        cfg = self.cfg
        bar = tqdm(total=cfg.steps, initial=self.step, desc=f"edit: {self.instruction}"[:40],
                   disable=not cfg.progress, dynamic_ncols=True)
        t0, start = time.perf_counter(), self.elapsed
        ema = None
        try:
            while self.step < cfg.steps:
                rec = self.step_once()
                self.elapsed = start + time.perf_counter() - t0
                ema = rec["loss"] if ema is None else 0.9 * ema + 0.1 * rec["loss"]
                if self.step % 10 == 0 or self.step == cfg.steps or "densify" in rec:
                    self.history.append(rec)
                    bar.set_postfix(loss=f"{ema:.4g}", N=rec["gaussians"], refresh=False)
                bar.update(1)
                if checkpoint and cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0:
                    self.save(checkpoint)
        except KeyboardInterrupt:
            if self._rng_at_start is not None:  # the step did not finish: it is redone on resume
                self.gen.set_state(self._rng_at_start[0])
                for g, st in zip(_generators(self.guidance), self._rng_at_start[1]):
                    g.set_state(st)
            if checkpoint:
                self.save(checkpoint)
                log.warning("edit interrupted at step %d; resumable checkpoint in %s", self.step, checkpoint)
            raise
        finally:
            bar.close()
        if checkpoint:
            self.save(checkpoint)


def edit(scene: GaussianScene, instruction: str, target: TargetLike, guidance: Guidance, *,
         cameras: Optional[Sequence[Camera]] = None, config: Optional[EditConfig] = None,
         encoder: Any = None, tau: Any = "auto", checkpoint: Optional[Union[str, Path]] = None,
         resume: bool = False, **overrides: Any) -> EditResult:
    """Edit the Gaussians ``target`` names so that renders follow ``guidance`` (paper §3.2).

    Args:
        scene: the scene (with ``lang`` for a text target); not modified.
        instruction: the edit instruction (recorded; the guidance already carries it).
        target: text (retrieved with ``encoder``/``tau``), Retrieval, [N] bool mask or [N] weights.
        guidance: any :class:`~tiger.edit.guidance.base.Guidance` (``RecolorGuidance``,
            ``CSDGuidance(ip2p, mvdream)``, the analytic ``IdealDenoiserGuidance``, ...).
        cameras: the scene's capture cameras (decide 360° vs forward-facing placement); None: 360°.
        config: :class:`EditConfig`; ``**overrides`` replace its fields (e.g. ``steps=300``).
        checkpoint: file for checkpoints (written every ``checkpoint_every`` steps, at the end, and on
            Ctrl-C); with ``resume=True`` and an existing file, continue from it exactly.
    Returns:
        :class:`EditResult`.
    """
    import dataclasses

    cfg = dataclasses.replace(config or EditConfig(), **overrides)
    if not isinstance(scene, GaussianScene):
        raise TypeError(f"tiger.edit: scene must be a GaussianScene, got {type(scene).__name__}")
    tgt = resolve_target(scene, target, encoder=encoder, tau=tau)
    session = EditSession(scene, tgt, guidance, instruction, cameras, cfg)
    if resume and checkpoint and Path(checkpoint).exists():
        session.load(checkpoint)
    log.info("edit '%s': %d of %d Gaussians editable (%s), %s views, %d steps", instruction, tgt.count, len(scene),
             tgt.description, "360°" if session.views.is_360 else "forward-facing", cfg.steps)
    session.run(checkpoint)
    out, w = session.result_scene()
    record = {"instruction": instruction, "target": tgt.description, "guidance": session.signature()["guidance"],
              "steps": session.step, "editable": tgt.count, "gaussians_before": len(scene),
              "gaussians_after": len(out), "time_s": round(session.elapsed, 3),
              "views": "360" if session.views.is_360 else "forward-facing",
              "center": tgt.center.tolist(), "bbox_min": tgt.bbox_min.tolist(), "bbox_max": tgt.bbox_max.tolist(),
              "config": cfg.to_dict()}
    rounds = list(scene.metadata.get("tiger_edits", [])) + [record]
    out.metadata["tiger_edits"] = rounds
    return EditResult(scene=out, weights=w, rounds=rounds, history=session.history,
                      timings_s=dict(session.timer.total))


__all__ = ["EditResult", "EditSession", "edit"]
