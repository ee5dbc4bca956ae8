"""The edit loop: Coherent Score Distillation on the retrieved Gaussians only (paper §3.2, SPEC §6).

Each step: draw V cameras around the object (:class:`tiger.edit.views.ObjectViews`), render the
current scene and the original scene from them, ask the guidance for ``dL/drenders``, back-propagate
through the rasterizer, and take a relevance-scaled Adam step on the editable Gaussians.

* **Sparse parameters** (:class:`tiger.recon.step.SceneOptimizer` with a trainable mask): Gaussians
  of weight 0 are not parameters (no gradient tensor, no Adam state, no update) and come out
  bit-identical, in their original order. (The rasterizer's backward still visits every Gaussian
  in a tile; only the editable rows are kept from it.)
* **Score-based updating.** Adam normalises gradients, so scaling a gradient would not scale the
  update; the optimizer scales each Adam *update*: ``p ← p_old + w_i · (p_adam − p_old)``, with
  ``w_i`` the Gaussian's relevance (:mod:`tiger.edit.target`).
* **View-independent colour.** Editable Gaussians' higher SH bands are zeroed at the start of the
  round and not optimised (``sh_rest`` is not a parameter), so they render ``max(C0 · dc + 0.5, 0)``
  from every direction.
* **Densification** every ``densify_every`` steps (:func:`tiger.recon.strategy.region_topk_densify`):
  the top ``densify_fraction`` (1 %) of the editable Gaussians by mean accumulated screen-space
  gradient are cloned (largest scale ≤ ``percent_dense`` × object radius) or split; editable
  Gaussians below ``min_opacity`` are pruned (:func:`~tiger.recon.strategy.prune_transparent`).
  Children inherit every attribute of their parent: ``lang``, the relevance weight, trainability.
* **Checkpoints**: every ``checkpoint_every`` steps and on Ctrl-C (then the interrupt is re-raised);
  ``resume=True`` continues bit-for-bit (views, guidance noise, Adam, densification statistics).
"""
from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence, Union

import torch

from tiger.retrieval.text import TextEncoder
from tiger.recon.step import SceneOptimizer
from tiger.recon.strategy.rules import DensifyStats, prune_transparent, region_topk_densify
from tiger.render import Camera
from tiger.scene.gaussian_scene import GaussianScene, render_rgb, render_views
from tiger.utils.io import atomic_torch_save

from .config import EditConfig
from .guidance.base import Guidance, ViewBatch, check_guidance
from .target import EditTarget, TargetLike, resolve_target
from .views import ObjectViews

log = logging.getLogger(__name__)
CHECKPOINT_FORMAT = "tiger.edit-checkpoint/1"
POOL_SEED_OFFSET = 7919  # the view pool's generator: seed + this, apart from the per-step draws
OPTIMISED = ("means", "log_scales", "quats", "opacity_logits", "sh_dc")
STAGES = ("view_pool", "render", "guidance", "backward", "optimizer", "densify")


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
        timings_s: total seconds per stage (view_pool, render, guidance, backward, optimizer, densify).
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


@dataclass
class ViewPool:
    """Camera sets pre-sampled for an edit (``EditConfig.view_pool``): ``cameras[k]`` is one
    step's set; ``originals`` [K, V, 3, H, W] and ``masks`` [K, V, 1, H, W] (float16) are the
    unedited scene's renders and the object's footprint from them."""

    cameras: list[Sequence[Camera]]
    originals: torch.Tensor
    masks: torch.Tensor


class _Timer:
    """Seconds per stage. On CUDA each stage is bracketed by CUDA events, read back only when the
    totals are asked for, so timing adds no host synchronisation to the loop (a sync per stage
    would leave the GPU idle while the next stage's launches are prepared)."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self._done = {k: 0.0 for k in STAGES}
        self._pending: list[tuple[str, torch.cuda.Event, torch.cuda.Event]] = []

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        if self.device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            with torch.profiler.record_function(f"edit::{stage}"):  # named ranges for a profiler, if one runs
                yield
            end.record()
            self._pending.append((stage, start, end))
            if len(self._pending) >= 512:  # bounded: resolve (one sync) now and then
                self._resolve()
        else:
            t0 = time.perf_counter()
            yield
            self._done[stage] = self._done.get(stage, 0.0) + time.perf_counter() - t0

    def _resolve(self) -> None:
        if self._pending:
            self._pending[-1][2].synchronize()
            for stage, start, end in self._pending:
                self._done[stage] = self._done.get(stage, 0.0) + 1e-3 * start.elapsed_time(end)
            self._pending.clear()

    @property
    def total(self) -> dict[str, float]:
        """{stage: seconds} so far (reading it waits for the stages still running on the GPU)."""
        self._resolve()
        return self._done

    def load(self, totals: dict[str, float]) -> None:
        self._resolve()
        self._done.update(totals)


class EditSession:
    """The state of one edit round (built by :func:`edit`; usable directly for step-wise control).

    Sits on :class:`tiger.recon.step.SceneOptimizer` (trainable mask = the editable Gaussians,
    update weight = their relevance, extras ``weight`` following every row) and the region rules
    of :mod:`tiger.recon.strategy`.
    """

    def __init__(self, scene: GaussianScene, target: EditTarget, guidance: Guidance,
                 cameras: Optional[Sequence[Camera]], config: EditConfig) -> None:
        self.cfg, self.guidance, self.target = config, check_guidance(guidance), target
        self.instruction = guidance.instruction
        self.device = scene.device
        self.input_len = len(scene)
        w = target.weights.to(self.device, scene.dtype)
        editable = w > 0
        self.original = scene.detach()
        self.orig_indicator = editable.to(scene.dtype)
        work = scene.clone()
        if config.view_independent:  # editable Gaussians keep only their base colour
            work.sh_rest[editable] = 0
        self.radius = 0.5 * float((target.bbox_max - target.bbox_min).norm())
        self.opt = SceneOptimizer(work, self._lrs(), trainable=editable, update_weight=w, extras={"weight": w})
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
        self.stats = DensifyStats.zeros(len(work), self.device)
        self.pool: Optional[ViewPool] = None
        guidance.reset_caches()  # view ids of an earlier round named other cameras
        if config.view_pool:
            with self.timer("view_pool"):
                self.pool = self._build_pool(config.view_pool)

    def _lrs(self) -> dict[str, float]:
        lrs = self.cfg.learning_rates()
        return {**{n: lrs[n] for n in OPTIMISED}, "means": lrs["means"] * max(self.radius, 1e-6)}

    @property
    def scene(self) -> GaussianScene:
        """The scene being edited (frozen rows in place, children appended)."""
        return self.opt.scene

    @property
    def weights(self) -> torch.Tensor:
        """[N'] relevance weight of every Gaussian (0 = frozen); children inherit their parent's."""
        return self.opt.extras["weight"]

    @property
    def optimizer_state_numel(self) -> int:
        """Elements held in Adam's state (both moments of every editable parameter)."""
        return sum(v.numel() for st in self.opt.optimizer.state.values() for v in st.values()
                   if torch.is_tensor(v) and v.dim() > 0)

    # -- rendering ------------------------------------------------------------------------------
    def _render_originals(self, cams: Sequence[Camera]) -> tuple[torch.Tensor, torch.Tensor]:
        """Original renders [V, 3, H, W] (full SH) and the object's footprint [V, 1, H, W], in one pass."""
        rgb, foot = render_rgb(self.original, cams, self.background, footprint=self.orig_indicator)
        return rgb.permute(0, 3, 1, 2), foot[:, None]

    def _build_pool(self, sets: int) -> "ViewPool":
        """``sets`` camera sets drawn with the per-step rules from their own seeded generator
        (a resumed run rebuilds the same pool), with their original renders and footprints."""
        gen = torch.Generator().manual_seed(self.cfg.seed + POOL_SEED_OFFSET)
        cams = [self.views.sample(gen) for _ in range(sets)]
        rendered = [self._render_originals(c) for c in cams]
        return ViewPool(cams, torch.stack([o for o, _ in rendered]).half(),
                        torch.stack([m for _, m in rendered]).half())

    def _views(self) -> tuple[Sequence[Camera], torch.Tensor, torch.Tensor, Optional[torch.Tensor]]:
        """This step's cameras, original renders [V,3,H,W], footprints [V,1,H,W] and pool ids."""
        if self.pool is None:
            cams = self.views.sample(self.gen)
            return (cams, *self._render_originals(cams), None)
        k = int(torch.randint(len(self.pool.cameras), (1,), generator=self.gen))
        v = len(self.pool.cameras[k])
        return (self.pool.cameras[k], self.pool.originals[k].float(), self.pool.masks[k].float(),
                torch.arange(k * v, (k + 1) * v))

    # -- one step -------------------------------------------------------------------------------
    def step_once(self) -> dict:
        """One CSD step (views, renders, guidance, backward, scaled Adam, densification); the
        record's ``loss`` may be a 0-d tensor (not read back, so the host need not wait)."""
        cfg, T = self.cfg, self.timer
        self._rng_at_start = (self.gen.get_state(), [g.get_state() for g in self.guidance.generators()])
        with T("render"):
            cams, originals, masks, view_ids = self._views()
            out = render_views(self.opt.render_scene(), cams, "rgb", background=self.background, check_finite=False)
            out["means2d"].retain_grad()
            x = out["color"].permute(0, 3, 1, 2).clamp(0, 1)
        batch = ViewBatch(cameras=cams, originals=originals, masks=masks, view_ids=view_ids, step=self.step,
                          total_steps=cfg.steps, object_center=self.views.center,
                          world_up=self.views.layout.up)  # float64 on the CPU, like the cameras
        with T("guidance"):
            g, info = self.guidance.grad(x.detach(), batch)
        if g.shape != x.shape:
            raise ValueError(f"tiger.edit: guidance '{self.guidance.name}' returned a gradient "
                             f"of shape {list(g.shape)} for renders {list(x.shape)}")
        with T("backward"):
            x.backward(torch.nan_to_num(g.to(x), nan=0.0, posinf=0.0, neginf=0.0))
            if cfg.densify_every and out["means2d"].grad is not None:
                self.stats.add(out["means2d"].grad, out["radii"], cams[0].width, cams[0].height)  # one size
        with T("optimizer"):
            self.opt.update()
        self.step += 1
        self._rng_at_start = None  # from here on an interrupt keeps this step
        # the loss stays a (0-d) tensor: reading it here would wait for the GPU every step
        loss = info.loss.detach().float() if isinstance(info.loss, torch.Tensor) else float(info.loss)
        rec = {"step": self.step, "loss": loss, "gaussians": len(self.scene)}
        rec.update({k: float(v) for k, v in info.extra.items() if k.startswith("lambda")})
        until = cfg.densify_until if cfg.densify_until is not None else int(0.9 * cfg.steps)
        if (cfg.densify_every and self.step >= cfg.densify_from and self.step <= until
                and self.step % cfg.densify_every == 0):
            with T("densify"):
                rec["densify"] = self.densify()
        return rec

    def densify(self) -> dict:
        """Clone/split the top ``densify_fraction`` of the editable Gaussians, prune transparent ones."""
        editable_before = self.opt.num_trainable
        info = region_topk_densify(self.opt, self.stats, extent=max(self.radius, 1e-6),
                                   top_percent=100.0 * self.cfg.densify_fraction,
                                   percent_dense=self.cfg.percent_dense, generator=self.gen)
        info["pruned"] = prune_transparent(self.opt, self.cfg.min_opacity, state=self.stats.rows())
        info["total"] = len(self.scene)
        info["editable_before"], info["editable"] = editable_before, self.opt.num_trainable
        return info

    # -- result -----------------------------------------------------------------------------------
    def result_scene(self) -> tuple[GaussianScene, torch.Tensor]:
        """(the edited scene, detached, [N'] weights) in the documented order."""
        out = self.scene.detach().clone()
        out.metadata = dict(self.original.metadata)
        return out, self.weights.detach().float().clone()

    # -- checkpoints ------------------------------------------------------------------------------
    def signature(self) -> dict:
        """What a checkpoint must match to resume: instruction, target, input size, the guidance's
        name and settings (what runs), the edit settings."""
        return {"instruction": self.instruction, "target": self.target.description, "gaussians": self.input_len,
                "guidance": self.guidance.name, "guidance_settings": self.guidance.settings(),
                "config": self.cfg.to_dict()}

    def save(self, path: Union[str, Path]) -> None:
        payload = {
            "format": CHECKPOINT_FORMAT, "signature": self.signature(), "step": self.step,
            "optimizer": self.opt.state_dict(), "stats": self.stats.state_dict(), "view_rng": self.gen.get_state(),
            "guidance_rng": [g.get_state() for g in self.guidance.generators()],
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
            mine = self.signature()
            differ = sorted(k for k in set(mine) | set(ck["signature"]) if mine.get(k) != ck["signature"].get(k))
            raise ValueError(f"tiger.edit: checkpoint {path} belongs to another edit "
                             f"({ck['signature'].get('instruction')!r} on {ck['signature'].get('target')!r}; "
                             f"differs in {', '.join(differ)}); use another output folder or start without --resume")
        self.opt.load_state_dict(ck["optimizer"])
        self.stats = DensifyStats.from_state_dict({k: v.to(self.device) for k, v in ck["stats"].items()})
        self.gen.set_state(ck["view_rng"].cpu())
        for g, st in zip(self.guidance.generators(), ck.get("guidance_rng", [])):
            g.set_state(st.cpu())
        self.step, self.history, self.elapsed = int(ck["step"]), list(ck["history"]), float(ck["elapsed"])
        self.timer.load(ck.get("timings", {}))
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
                    rec["loss"] = float(rec["loss"])  # one read-back per logged step
                    self.history.append(rec)
                    bar.set_postfix(loss=f"{float(ema):.4g}", N=rec["gaussians"], refresh=False)
                bar.update(1)
                if checkpoint and cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0:
                    self.save(checkpoint)
        except KeyboardInterrupt:
            if self._rng_at_start is not None:  # the step did not finish: it is redone on resume
                self.gen.set_state(self._rng_at_start[0])
                for g, st in zip(self.guidance.generators(), self._rng_at_start[1]):
                    g.set_state(st)
            if checkpoint:
                self.save(checkpoint)
                log.warning("edit interrupted at step %d; resumable checkpoint in %s", self.step, checkpoint)
            raise
        finally:
            bar.close()
        if checkpoint:
            self.save(checkpoint)


def edit(scene: GaussianScene, target: TargetLike, guidance: Guidance, *,
         cameras: Optional[Sequence[Camera]] = None, config: Optional[EditConfig] = None,
         encoder: Optional[TextEncoder] = None, tau: Union[float, str] = "auto", checkpoint: Optional[Union[str, Path]] = None,
         resume: bool = False, **overrides: Any) -> EditResult:
    """Edit the Gaussians ``target`` names so that renders follow ``guidance`` (paper §3.2).

    Args:
        scene: the scene (with ``lang`` for a text target); not modified.
        target: text (retrieved with ``encoder``/``tau``), Retrieval, [N] bool mask or [N] weights.
        guidance: any :class:`~tiger.edit.guidance.base.Guidance` (``RecolorGuidance``,
            ``CSDGuidance(ip2p, mvdream)``, the analytic ``IdealDenoiserGuidance``, ...); it carries
            the instruction (recorded as ``guidance.instruction``) and its settings (the CSD
            schedule, dtypes, ...), recorded with the round and checked on resume.
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
    check_guidance(guidance)
    tgt = resolve_target(scene, target, encoder=encoder, tau=tau)
    session = EditSession(scene, tgt, guidance, cameras, cfg)
    if resume and checkpoint and Path(checkpoint).exists():
        session.load(checkpoint)
    log.info("edit '%s': %d of %d Gaussians editable (%s), %s views, %d steps", session.instruction, tgt.count, len(scene),
             tgt.description, "360°" if session.views.is_360 else "forward-facing", cfg.steps)
    session.run(checkpoint)
    out, w = session.result_scene()
    record = {"instruction": session.instruction, "target": tgt.description, "guidance": guidance.name,
              "guidance_settings": guidance.settings(),
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
