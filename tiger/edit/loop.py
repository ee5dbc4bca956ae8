"""The edit loop: Coherent Score Distillation on the retrieved Gaussians only (paper §3.2, SPEC §6).

Each step: draw V cameras around the object (:class:`tiger.edit.views.ObjectViews`), render the
current scene and the original scene from them, ask the guidance for ``dL/drenders``, back-propagate
through the rasterizer, and take a relevance-scaled Adam step on the editable Gaussians.

* **Sparse parameters** (:class:`tiger.recon.step.SceneOptimizer` with a trainable mask): Gaussians
  of weight 0 are not parameters (no gradient tensor, no Adam state, no update) and come out
  bit-identical, in their original order.
* **Autograd over the editable rows only** (:class:`RenderLayout`): the step renders the frozen
  Gaussians first (their tensors and activations built once per layout, detached) and the
  editable leaves behind them, so the graph (activations, concatenation, the scatter of the
  screen-space gradients back to scene order) spans the editable rows, and the rasterizer's
  backward is told which rows are trainable (``RenderLayout.trainable``): frozen rows still shape
  every pixel's transmittance but get no gradient terms and no atomics.
* **No read-backs per step**: cameras go to the device in one asynchronous copy
  (:func:`device_cameras`; pooled ones once), statistics, Adam and the relevance scaling stay on
  the device, the history's losses are read back at checkpoints and at the end. Only a
  densification step (the scene's size changes) reads counts back.
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

import copy
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, Union

import torch

from tiger.ops.raster import RasterKernelSettings
from tiger.retrieval.text import TextEncoder
from tiger.recon.step import SceneOptimizer
from tiger.recon.strategy import DensifySchedule, RegionTopKStrategy
from tiger.render import Camera
from tiger.scene.gaussian_scene import GaussianScene, render_rgb, render_views
from tiger.train import StageTimer, read_checkpoint, restore_rng, run_loop, write_checkpoint
from tiger.utils.streams import run_beside

from .config import EditConfig
from .guidance.base import Guidance, ViewBatch, check_guidance, prepare_guidance
from .target import EditTarget, TargetLike, resolve_target
from .views import ObjectViews

log = logging.getLogger(__name__)
CHECKPOINT_FORMAT = "tiger.edit-checkpoint/1"
POOL_SEED_OFFSET = 7919  # the view pool's generator: seed + this, apart from the per-step draws
OPTIMISED = ("means", "log_scales", "quats", "opacity_logits", "sh_dc")
STAGES = ("view_pool", "render", "guidance", "backward", "optimizer", "densify")
# The edit's rasterizer kernels: one pixel per backward thread (8 warps a tile) instead of the
# default two (4 warps). An edit's backward walks long tile lists (the object's tiles, behind and
# in front of it) on few tiles, where more warps per tile hide more latency: on the H100 the
# raster backward of the demo edit's 4 views of 512² (317,600 Gaussians, 41,600 editable) takes
# 1.94 ms against 2.38 on the edit's own cameras, 2.55 against 3.34 on orbit cameras
# (`python -m benchmarks.render_views --edit ...`, docs/BENCHMARKS.md); a real capture's full
# backward (fox, 268 entries a tile) is faster with two (1.24 against 1.56 ms), so the library
# default stays 2.
EDIT_RASTER_KERNELS = RasterKernelSettings(backward_pixels_per_thread=1)


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
    step's set (float64 on the CPU, what the guidance sees), ``device_cameras[k]`` the same set
    on the scene's device and dtype (what the rasterizer reads); ``originals`` [K, V, 3, H, W]
    and ``masks`` [K, V, 1, H, W] are the unedited scene's renders and the object's footprint
    from them, in [0, 1] stored as 8-bit steps (uint8, value x 255, rounded: the precision of
    a photograph, a quarter of float32's memory), rendered when a set is first drawn
    (``rendered[k]``), so a pool costs no more renders than the sets an edit uses. ``order[s]``
    is the set step ``s`` takes (uniform, with replacement), fixed when the pool is drawn, so the
    next step's set is known a step ahead (:attr:`EditConfig.prefetch_views`)."""

    cameras: list[Sequence[Camera]]
    device_cameras: list[Sequence[Camera]]
    originals: torch.Tensor
    masks: torch.Tensor
    rendered: list[bool]
    order: list[int]  # the set each step takes, drawn with the pool


def _to_8bit(x: torch.Tensor) -> torch.Tensor:
    """[0, 1] values as uint8 steps of 1/255 (rounded)."""
    return (x.clamp(0, 1) * 255).round().to(torch.uint8)


def _from_8bit(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return x.to(dtype) / 255


#: Scene tensors the edit renders, and the activation the rasterizer input applies to each.
_RENDERED = {"means": "means", "quats": "quats", "log_scales": "scales", "opacity_logits": "opacities",
             "sh_dc": "sh_dc", "sh_rest": "sh_rest"}
_ACTIVATIONS = {"log_scales": torch.exp, "opacity_logits": torch.sigmoid}


class _RenderRows(GaussianScene):
    """A scene as the rasterizer reads it (means, quats, activated scales and opacities, SH), built
    from given rows without re-validation (they come from a validated scene); no ``log_scales`` /
    ``opacity_logits`` / ``lang``."""

    scales = None  # plain attributes here, not the base class's activations of the logits
    opacities = None

    def __init__(self, rows: dict[str, torch.Tensor]) -> None:  # noqa: D107 (no base __init__: no checks)
        self.__dict__.update(rows, log_scales=None, opacity_logits=None, lang=None, lang_pca_basis=None,
                             lang_pca_mean=None, metadata={})


@dataclass
class RenderLayout:
    """The row order the edit renders in, so that autograd works on the editable rows only.

    Render rows ``[0, frozen_rows)`` are the frozen Gaussians (constant: densification and pruning
    touch editable rows only), their tensors and activations built once per layout and detached;
    rows ``[frozen_rows, N)`` are the optimizer's editable leaves, concatenated behind them each
    step. So the step's autograd graph (activations, concatenation, the screen-space gradients'
    scatter back to scene order) spans the M editable rows, not N, and the rasterizer's backward
    skips the gradient work of the frozen head (``trainable``).

    Attributes:
        frozen_rows: F, the number of frozen Gaussians.
        order: [N] long, the scene row of each render row (frozen rows, then the editable ones,
            each in scene order).
        frozen: [F, ...] detached rasterizer inputs of the frozen rows by input name (``means``,
            ``quats``, ``scales``, ``opacities``, ``sh_dc``, ``sh_rest``).
        fixed: [N, ...] full render-order tensors of the inputs that are not optimised (``sh_rest``).
        trainable: [N] bool in render order, False on the frozen head: the rasterizer's backward
            does no gradient work for those rows.
    """

    frozen_rows: int
    order: torch.Tensor
    frozen: dict[str, torch.Tensor]
    fixed: dict[str, torch.Tensor]
    trainable: torch.Tensor

    @classmethod
    @torch.no_grad()
    def of(cls, opt: SceneOptimizer) -> "RenderLayout":
        """The layout of ``opt``'s current rows (no read-back: the frozen count is known on the host)."""
        s, idx, leaves = opt.scene, opt.trainable_index, opt.leaves
        n = len(s)
        if idx is None:
            idx = torch.arange(n, device=s.device)
        frozen_idx = torch.nonzero_static(~opt.trainable_mask(), size=n - int(idx.numel())).reshape(-1)
        order = torch.cat([frozen_idx, idx])
        frozen, fixed = {}, {}
        for name, key in _RENDERED.items():
            t = getattr(s, name).detach()
            act = _ACTIVATIONS.get(name, lambda v: v)
            if name in leaves:
                frozen[key] = act(t[frozen_idx])
            else:
                fixed[key] = act(t[order])
        trainable = torch.ones(n, dtype=torch.bool, device=s.device)
        trainable[: frozen_idx.numel()] = False
        return cls(int(frozen_idx.numel()), order, frozen, fixed, trainable)

    def scene(self, leaves: dict[str, torch.Tensor]) -> GaussianScene:
        """The scene to render: frozen rows, then ``leaves`` (the editable rows, by scene tensor name)."""
        rows = dict(self.fixed)
        for name, leaf in leaves.items():
            key = _RENDERED.get(name)
            if key is not None:
                rows[key] = torch.cat([self.frozen[key], _ACTIVATIONS.get(name, lambda v: v)(leaf)])
        return _RenderRows(rows)

    def to_scene_order(self, per_view_rows: torch.Tensor) -> torch.Tensor:
        """[V, N, ...] in render order -> the same in the scene's row order."""
        return torch.zeros_like(per_view_rows).index_copy_(1, self.order, per_view_rows)


def device_cameras(cameras: Sequence[Camera], device: torch.device, dtype: torch.dtype) -> list[Camera]:
    """``cameras`` on ``device`` in ``dtype`` with one host-to-device copy (from pinned memory,
    asynchronous on CUDA: a plain ``Camera.to`` per camera would copy from pageable memory and
    re-validate the values there, each waiting for the GPU). The values are the validated ones of
    ``cameras``; the rest of each camera (size, name, metadata) is shared."""
    cams = list(cameras)
    packed = torch.cat([torch.stack([c.viewmat for c in cams]).reshape(len(cams), 16),
                        torch.stack([c.K for c in cams]).reshape(len(cams), 9)], 1).to(dtype)
    if device.type == "cuda":
        packed = packed.pin_memory().to(device, non_blocking=True)
    else:
        packed = packed.to(device)
    out = []
    for cam, row in zip(cams, packed):
        moved = copy.copy(cam)  # no __post_init__: it would read the device values back
        moved.viewmat, moved.K = row[:16].view(4, 4), row[16:].view(3, 3)
        out.append(moved)
    return out



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
        self._pending: Optional[tuple[int, Callable[[], Any]]] = None  # (pool set, join) of a prefetch
        self._layout: Optional[RenderLayout] = None  # rebuilt after every change of rows
        guidance.reset_caches()  # view ids of an earlier round named other cameras
        self._pool_drawn: Optional[torch.cuda.Event] = None  # on CUDA: the pool's and originals' copies queued
        if config.view_pool:
            self.pool = self._build_pool(config.view_pool)
            if self.device.type == "cuda":
                self._pool_drawn = torch.cuda.Event()
                self._pool_drawn.record(torch.cuda.current_stream(self.device))

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
        """``sets`` camera sets drawn with the per-step rules from their own seeded generator,
        then the set of every step (a resumed run rebuilds the same pool and order); their
        original renders come when first drawn."""
        gen = torch.Generator().manual_seed(self.cfg.seed + POOL_SEED_OFFSET)
        cams = [self.views.sample(gen) for _ in range(sets)]
        order = torch.randint(sets, (self.cfg.steps,), generator=gen).tolist()
        on_device = [device_cameras(c, self.device, self.scene.dtype) for c in cams]
        V, H, W = self.cfg.n_views, self.cfg.height, self.cfg.width
        empty = lambda c: torch.zeros(sets, V, c, H, W, dtype=torch.uint8, device=self.device)  # noqa: E731
        return ViewPool(cams, on_device, empty(3), empty(1), [False] * sets, order)

    def _pool_set(self, step: int) -> Optional[int]:
        """The pool set step ``step`` (0-based) takes; None without a pool or past the last step."""
        if self.pool is None or step >= len(self.pool.order):
            return None
        return self.pool.order[step]

    def _pool_batch(self, k: int, step: int) -> ViewBatch:
        """The :class:`ViewBatch` of pool set ``k`` at step ``step`` (its originals must be rendered)."""
        v = len(self.pool.cameras[k])
        return ViewBatch(cameras=self.pool.cameras[k], originals=_from_8bit(self.pool.originals[k], self.scene.dtype),
                         masks=_from_8bit(self.pool.masks[k], self.scene.dtype),
                         view_ids=torch.arange(k * v, (k + 1) * v), step=step, total_steps=self.cfg.steps,
                         object_center=self.views.center, world_up=self.views.layout.up)

    def _prepare_set(self, k: int, step: int) -> list[torch.Tensor]:
        """Render pool set ``k``'s originals and footprints (8-bit, into the pool) and let the
        guidance cache its per-view work for them (:func:`prepare_guidance`); returns the tensors
        the guidance cached."""
        rgb, foot = self._render_originals(self.pool.device_cameras[k])
        self.pool.originals[k], self.pool.masks[k] = _to_8bit(rgb), _to_8bit(foot)
        if self.pool.originals.is_cuda:  # written on this stream: not reused before it is done, even if never joined
            stream = torch.cuda.current_stream(self.pool.originals.device)
            self.pool.originals.record_stream(stream)
            self.pool.masks.record_stream(stream)
        made = prepare_guidance(self.guidance, self._pool_batch(k, step))
        self.pool.rendered[k] = True
        return made

    def _prefetch_next(self) -> None:
        """Start preparing the next step's pool set if it is new (:attr:`EditConfig.prefetch_views`):
        on CUDA in a worker thread on a side stream (:func:`tiger.utils.streams.run_beside`), so its
        renders, their read-backs and the guidance's encodes overlap this step's queued work; on the
        CPU it runs when the next step asks for it."""
        k = self._pool_set(self.step)
        if k is None or not self.cfg.prefetch_views or self.pool.rendered[k] or self._pending is not None:
            return
        step = self.step
        # it reads only what existed when the pool was drawn (the original scene, the pool's
        # cameras), so it waits for that, not for this step's queued guidance
        self._pending = (k, run_beside(lambda: self._prepare_set(k, step), self.device, after=self._pool_drawn))

    def _ready_set(self, k: int) -> None:
        """Pool set ``k`` rendered and prepared before this step's guidance: the prefetch joined
        (the main stream waits for the side stream's work), or the work done now (stage ``view_pool``)."""
        if self._pending is None and self.pool.rendered[k]:
            return  # a set drawn before: nothing to wait for or time (two CUDA events per step fewer)
        with self.timer("view_pool"):
            self._join_prefetch()  # k's, normally (any other is done first: none may be left pending)
            if not self.pool.rendered[k]:
                self._prepare_set(k, self.step)

    def _join_prefetch(self, quiet: bool = False) -> None:
        """Wait for a started prefetch and forget it; its errors surface here, or are only logged
        (``quiet``: when the loop ends, perhaps on another error, whose place they must not take;
        the set is then prepared again when drawn)."""
        if self._pending is None:
            return
        k, result = self._pending
        self._pending = None
        if quiet and self.device.type != "cuda":
            return  # off CUDA the work only runs when joined: at the loop's end it is dropped, not done
        try:
            result()
        except Exception as exc:
            if not quiet:
                raise
            self.pool.rendered[k] = False
            log.warning("edit: preparing pool set %d beside the loop failed: %s", k, exc)

    def render_layout(self) -> RenderLayout:
        """The current :class:`RenderLayout` (built after the start, a densification or a resume)."""
        if self._layout is None:
            self._layout = RenderLayout.of(self.opt)
        return self._layout

    # -- one step -------------------------------------------------------------------------------
    def step_once(self) -> dict:
        """One CSD step (views, renders, guidance, backward, scaled Adam, densification); the
        record's ``loss`` may be a 0-d tensor (not read back, so the host need not wait).

        Apart from a densification step, the loop's own work reads nothing back from the device:
        cameras go up in one asynchronous copy, the screen-space statistics, Adam and the
        relevance scaling stay on the device (what the rasterizer and the guidance do is theirs).
        """
        cfg, T = self.cfg, self.timer
        k = self._pool_set(self.step)
        with T("render"):
            if k is None:  # fresh cameras: the originals are rendered with them
                cams = self.views.sample(self.gen)
                cams_on_device = device_cameras(cams, self.device, self.scene.dtype)
                originals, masks = self._render_originals(cams_on_device)
            else:
                cams, cams_on_device = self.pool.cameras[k], self.pool.device_cameras[k]
            layout = self.render_layout()
            out = render_views(layout.scene(self.opt.leaves), cams_on_device, "rgb", background=self.background,
                               check_finite=False, trainable=layout.trainable, kernels=EDIT_RASTER_KERNELS)
            out["means2d"].retain_grad()
            x = out["color"].permute(0, 3, 1, 2).clamp(0, 1)
        if k is None:
            batch = ViewBatch(cameras=cams, originals=originals, masks=masks, step=self.step, total_steps=cfg.steps,
                              object_center=self.views.center,
                              world_up=self.views.layout.up)  # float64 on the CPU, like the cameras
        else:  # after the render: a prefetch's side-stream work only has to be done before the guidance
            self._ready_set(k)
            batch = self._pool_batch(k, self.step)
        with T("guidance"):
            g, info = self.guidance.grad(x.detach(), batch)
        if g.shape != x.shape:
            raise ValueError(f"tiger.edit: guidance '{self.guidance.name}' returned a gradient "
                             f"of shape {list(g.shape)} for renders {list(x.shape)}")
        with T("backward"):
            x.backward(torch.nan_to_num(g.to(x), nan=0.0, posinf=0.0, neginf=0.0))
            if self.strategy.schedule.collecting(self.step + 1) and out["means2d"].grad is not None:
                self.strategy.observe_grad(self.step + 1, layout.to_scene_order(out["means2d"].grad),
                                           layout.to_scene_order(out["radii"]), cams[0].width,
                                           cams[0].height)  # one size for all views
        with T("optimizer"):
            self.opt.update()
        self.step += 1
        # the loss stays a (0-d) tensor: reading it here would wait for the GPU every step
        loss = info.loss.detach().float() if isinstance(info.loss, torch.Tensor) else float(info.loss)
        rec = {"step": self.step, "loss": loss, "gaussians": len(self.scene)}
        rec.update({k: (v.detach() if torch.is_tensor(v) else float(v)) for k, v in info.extra.items()
                    if k.startswith("lambda")})
        if self.strategy.schedule.due(self.step):
            with T("densify"):  # the scene's size changes: this step reads counts back
                editable_before = self.opt.num_trainable
                rec["densify"] = self.strategy.step_post_backward(self.opt, self.step, self.gen)
                rec["densify"].update(editable_before=editable_before, editable=self.opt.num_trainable)
                self._layout = None
        self._prefetch_next()  # last: this step's work is queued, the next set's overlaps it
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

    def settle_history(self) -> None:
        """Turn the 0-d device tensors kept in :attr:`history` into floats, in one read-back."""
        pending = [(r, k) for r in self.history for k, v in r.items() if torch.is_tensor(v)]
        if pending:
            values = torch.stack([r[k].reshape(()).float().to(self.device) for r, k in pending]).tolist()
            for (r, k), v in zip(pending, values):
                r[k] = v

    def save(self, path: Union[str, Path]) -> None:
        self.settle_history()
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
        self._join_prefetch()  # its set stays rendered and prepared: the pool is the same after a resume
        self.opt.load_state_dict(ck["optimizer"])
        self.strategy.load_state_dict(ck["strategy"], self.device)
        restore_rng(ck["rng"], self.generators())
        self.step, self.history, self.elapsed = int(ck["step"]), list(ck["history"]), float(ck["elapsed"])
        self._layout = None
        self.timer.load(ck.get("timings", {}))
        log.info("edit resumed from %s at step %d of %d", path, self.step, self.cfg.steps)

    # -- the loop -----------------------------------------------------------------------------------
    def run(self, checkpoint: Optional[Union[str, Path]] = None) -> None:
        """Step until ``config.steps``; checkpoints as configured and on Ctrl-C (re-raised)."""
        cfg = self.cfg

        def keep(rec: dict) -> None:
            if self.step % 10 == 0 or self.step == cfg.steps or "densify" in rec:
                self.history.append(rec)  # device values stay there until settle_history

        try:
            run_loop(self, cfg.steps, checkpoint=checkpoint, checkpoint_every=cfg.checkpoint_every,
                     progress=cfg.progress, desc=f"edit: {self.instruction}"[:40], after_step=keep)
        finally:
            self._join_prefetch(quiet=True)  # no worker left writing the pool after the loop (or an interrupt)
            self.settle_history()


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


__all__ = ["EditResult", "EditSession", "RenderLayout", "ViewPool", "device_cameras", "edit"]
