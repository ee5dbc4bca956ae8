"""Settings of one edit round (paper §3.2 and appendix; SPEC §6)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Optional

#: Learning rates of the editable parameters (Adam). ``means`` is multiplied by the object's
#: radius (half-diagonal of its robust box), as INRIA scales it by the scene's extent.
DEFAULT_EDIT_LRS = {
    "means": 1e-3,
    "log_scales": 5e-3,
    "quats": 1e-3,
    "opacity_logits": 2.5e-2,
    "sh_dc": 1e-2,
}

#: Camera sets of an edit's view pool by default (EditConfig.view_pool; 0 = fresh cameras every step).
DEFAULT_VIEW_POOL = 256


@dataclass
class EditConfig:
    """Hyper-parameters of :func:`tiger.edit.edit` (the guidance's own settings, e.g. the CSD λ
    schedule, belong to the guidance: :meth:`tiger.edit.guidance.base.Guidance.settings`).

    Attributes:
        steps: optimisation steps (the paper: 1200-3000).
        n_views: cameras per step (4) around the object (tiger.edit.views).
        view_pool: where a step's cameras come from. K > 0 (default :data:`DEFAULT_VIEW_POOL` =
            256): K sets of ``n_views`` cameras drawn at the start with the per-step rules (seeded
            by ``seed``); each step takes one set at random, its original renders and footprints
            rendered the first time it is drawn and kept (8-bit), so a pool never renders more
            originals than fresh views (at most min(K, steps) sets); guidances cache per-camera
            work by view id (InstructPix2Pix's image-condition latents, a VAE encode of 4 renders
            per step otherwise). 0: a fresh set every step (the paper). The rule, measured on the
            analytic guidance's known answer (``benchmarks/edit_view_pool.py``, demo scene, 4-8
            seeds, PSNR to the target on the object's pixels from held-out views, docs/EDITING.md):
            256 sets reach it as well as fresh cameras at 1200 steps (-0.14 +- 0.19 dB, worst
            held-out view +0.3; within the seeds' spread at 100 and 300 steps too; locality
            unchanged); fewer sets fall behind as each is reused more (at 1200 steps: 128 sets
            -0.35 +- 0.14 dB, 64 sets -0.6 dB and -1.4 dB on the worst view, 16 sets -1.1 dB). The
            pool's 1024 views leave no fresh camera more than ~6° from a pooled one (128 sets: 6.9°,
            64: 11°, 16: 19°). On the GPU a pool saves the originals' renders and condition encodes
            of the steps that reuse a set, and a new set's are prepared beside the step before it
            (``prefetch_views``): 1200 steps on an H100: 90.0 s fresh, 77.0-79.5 s with 256 sets,
            74.6-75.7 s with 64 (the spread is between machines, docs/BENCHMARKS.md).
            Memory: K x n_views x 4 x width x height bytes on the device (1 GiB at 256 x 4 x 512²).
        width, height, fov_deg: render size and vertical field of view of those cameras.
        elevation_deg: elevation range of the cameras for 360° captures.
        fill: margin of the camera distance (1 = the object's bounding sphere touches the frame).
        lrs: Adam learning rates by parameter (missing ones: :data:`DEFAULT_EDIT_LRS`).
        densify_every: densify every K steps (0: never); densify_from/until: step window.
        densify_fraction: at most this fraction of the editable Gaussians (top by accumulated
            screen-space gradient) is cloned or split per densification (the paper: 1 %).
        percent_dense: a Gaussian is split rather than cloned when its largest scale exceeds this
            fraction of the object's radius.
        min_opacity: editable Gaussians below this opacity are pruned at each densification.
        view_independent: edited Gaussians drop their higher SH bands (zeroed at the start of the
            round, not optimised), so every view sees the same colour (paper appendix).
        background: RGB behind the Gaussians in the edit renders.
        seed: seed of the view sampler.
        checkpoint_every: write the checkpoint every this many steps (0: only on interrupt/end).
        progress: show a progress bar.
        prefetch_views: with a view pool, render the next step's set and let the guidance cache its
            per-view work for it (:meth:`~tiger.edit.guidance.base.Guidance.prepare`) while the
            current step runs: on CUDA in a worker thread on a side stream, so a new set's original
            renders and InstructPix2Pix's condition encode overlap the step's guidance instead of
            delaying the next one. Changes no value (not recorded, like ``progress``).
    """

    steps: int = 1200
    n_views: int = 4
    view_pool: int = DEFAULT_VIEW_POOL
    width: int = 512
    height: int = 512
    fov_deg: float = 49.1
    elevation_deg: tuple[float, float] = (0.0, 30.0)
    fill: float = 1.1
    lrs: dict[str, float] = field(default_factory=dict)
    densify_every: int = 100
    densify_from: int = 100
    densify_until: Optional[int] = None
    densify_fraction: float = 0.01
    percent_dense: float = 0.05
    min_opacity: float = 0.005
    view_independent: bool = True
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0
    checkpoint_every: int = 100
    progress: bool = True
    prefetch_views: bool = True

    def __post_init__(self) -> None:
        if self.steps < 1 or self.n_views < 1 or self.width < 1 or self.height < 1:
            raise ValueError("tiger.edit: steps, n_views, width and height must be positive")
        if self.view_pool < 0:
            raise ValueError(f"tiger.edit: view_pool must be >= 0 (0 = fresh views every step), got {self.view_pool}")
        if not 0.0 < self.densify_fraction <= 1.0:
            raise ValueError(f"tiger.edit: densify_fraction must be in (0, 1], got {self.densify_fraction}")
        unknown = set(self.lrs) - set(DEFAULT_EDIT_LRS)
        if unknown:
            raise ValueError(f"tiger.edit: unknown learning-rate names {sorted(unknown)}; "
                             f"known: {sorted(DEFAULT_EDIT_LRS)}")

    def learning_rates(self) -> dict[str, float]:
        return {**DEFAULT_EDIT_LRS, **self.lrs}

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["elevation_deg"] = list(self.elevation_deg)
        d["background"] = list(self.background)
        d.pop("progress")
        d.pop("prefetch_views")
        return d


__all__ = ["DEFAULT_EDIT_LRS", "DEFAULT_VIEW_POOL", "EditConfig"]
