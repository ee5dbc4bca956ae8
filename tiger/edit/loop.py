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
* **Densification** every ``densify_every`` steps from ``densify_from`` to ``densify_until``
  (:class:`tiger.recon.strategy.RegionTopKStrategy`): the top ``densify_fraction`` (1 %) of the
  editable Gaussians by mean accumulated screen-space gradient are cloned (largest scale ≤
  ``percent_dense`` × object radius) or split; editable Gaussians below ``min_opacity`` are pruned.
  Children inherit every attribute of their parent: ``lang``, the relevance weight, trainability.
* **Checkpoints**: every ``checkpoint_every`` steps and on Ctrl-C (then the interrupt is re-raised);
  ``resume=True`` continues bit-for-bit (views, guidance noise, Adam, densification statistics).
  The loop itself (progress, checkpoints, Ctrl-C) is :func:`tiger.train.run_loop`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import torch

from tiger.retrieval.text import TextEncoder
from tiger.recon.step import SceneOptimizer
from tiger.recon.strategy import DensifySchedule, RegionTopKStrategy
from tiger.render import Camera
from tiger.scene.gaussian_scene import GaussianScene, render_rgb, render_views
from tiger.train import StageTimer, read_checkpoint, restore_rng, run_loop, write_checkpoint

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
        self.timer = StageTimer(self.device, prefix="edit", stages=STAGES)
        until = config.densify_until if config.densify_until is not None else int(0.9 * config.steps)
        self.strategy = RegionTopKStrategy(len(work), self.device,
                                           DensifySchedule(config.densify_every, config.densify_from, until),
                                           extent=max(self.radius, 1e-6), top_percent=100.0 * config.densify_fraction,
                                           percent_dense=config.percent_dense, min_opacity=config.min_opacity)
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
            self.strategy.observe(self.step + 1, out, cams[0].width, cams[0].height)  # one size for all views
        with T("optimizer"):
            self.opt.update()
        self.step += 1
        # the loss stays a (0-d) tensor: reading it here would wait for the GPU every step
        loss = info.loss.detach().float() if isinstance(info.loss, torch.Tensor) else float(info.loss)
        rec = {"step": self.step, "loss": loss, "gaussians": len(self.scene)}
        rec.update({k: float(v) for k, v in info.extra.items() if k.startswith("lambda")})
        if self.strategy.schedule.due(self.step):
            with T("densify"):
                editable_before = self.opt.num_trainable
                rec["densify"] = self.strategy.step_post_backward(self.opt, self.step, self.gen)
                rec["densify"].update(editable_before=editable_before, editable=self.opt.num_trainable)
        return rec

    def generators(self) -> list[torch.Generator]:
        """The view sampler's generator and the guidance's (set back when a step is interrupted)."""
        return [self.gen] + list(self.guidance.generators())

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
        state = {"step": self.step, "optimizer": self.opt.state_dict(), "strategy": self.strategy.state_dict(),
                 "history": self.history, "elapsed": self.elapsed, "timings": self.timer.summary()}
        write_checkpoint(path, CHECKPOINT_FORMAT, state, signature=self.signature(), generators=self.generators())

    def load(self, path: Union[str, Path]) -> None:
        """Continue from :meth:`save`'s checkpoint; one of another edit (instruction, target,
        guidance, settings) is refused naming what differs."""
        try:
            ck = read_checkpoint(path, CHECKPOINT_FORMAT, signature=self.signature(), map_location=self.device,
                                 what="edit")
        except ValueError as exc:
            raise ValueError(f"tiger.edit: {exc}") from None
        self.opt.load_state_dict(ck["optimizer"])
        self.strategy.load_state_dict(ck["strategy"], self.device)
        restore_rng(ck["rng"], self.generators())
        self.step, self.history, self.elapsed = int(ck["step"]), list(ck["history"]), float(ck["elapsed"])
        self.timer.load(ck.get("timings", {}))
        log.info("edit resumed from %s at step %d of %d", path, self.step, self.cfg.steps)

    # -- the loop -----------------------------------------------------------------------------------
    def run(self, checkpoint: Optional[Union[str, Path]] = None) -> None:
        """Step until ``config.steps``; checkpoints as configured and on Ctrl-C (re-raised)."""
        cfg = self.cfg

        def keep(rec: dict) -> None:
            if self.step % 10 == 0 or self.step == cfg.steps or "densify" in rec:
                rec["loss"] = float(rec["loss"])  # one read-back per logged step
                self.history.append(rec)

        run_loop(self, cfg.steps, checkpoint=checkpoint, checkpoint_every=cfg.checkpoint_every,
                 progress=cfg.progress, desc=f"edit: {self.instruction}"[:40], after_step=keep)


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
                      timings_s=session.timer.summary())


__all__ = ["EditResult", "EditSession", "edit"]
