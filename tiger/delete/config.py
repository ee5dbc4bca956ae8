"""What a deletion takes and gives: :class:`DeleteConfig` (its settings, the CLI's defaults) and
:class:`DeleteResult` (the new scene, the stages' images and masks, counts and timings)."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import torch

from tiger.retrieval.select import Tau
from tiger.scene.gaussian_scene import GaussianScene
from tiger.utils.io import file_slug

from .removal import Removal

PathLike = Union[str, os.PathLike]


@dataclass
class DeleteConfig:
    """Parameters of :func:`tiger.delete.delete` (defaults are the CLI's).

    Removal: ``score``/``tau`` of the retrieval; ``floater_fraction``, ``box_margin`` of the floater
    rule, ``unseen_norm`` of the unseen rule, ``appearance_margin`` of the appearance rule (None:
    off), ``attach_k`` of the attachment rule bounding all three (0: off; see
    :mod:`tiger.delete.removal`). Holes: ``visible_alpha``, ``thin_alpha``, ``dilate`` (pixels). Inpainting:
    ``inpaint_margin`` (pixels of context around a hole given to the inpainter; None: the whole
    view); ``depth_source_alpha`` (pixels at least this opaque give the depth filled into the
    holes for the seeds). Refit: ``steps`` (one view each), ``near_weight`` and ``hole_share`` (a remaining
    Gaussian is trainable when its summed compositing weight inside the holes is at least
    ``near_weight`` and at least ``hole_share`` of its weight over all the views, so changing it
    changes mostly hole pixels), ``window_margin`` (pixels around a view's
    hole rendered for the loss; views without a hole are not refitted on), seeds (``seed_stride`` px, ``seed_min_change``,
    ``seed_opacity``, ``seed_depth_tolerance``, ``seed_slack``: a seed may show in another view
    only inside that view's hole grown by this many pixels; see :mod:`tiger.delete.seeds`), ``densify_every`` / ``densify_fraction`` (top fraction of the trainable
    Gaussians by screen-space gradient, split or cloned), ``lambda_dssim``, learning rates ``lrs``
    (GaussianScene parameter names; means in world units), ``background`` (RGB behind the scene).
    """

    score: str = "cosine"
    tau: Tau = "auto"
    floater_fraction: float = 0.5
    unseen_norm: float = 0.1
    appearance_margin: Optional[float] = 0.5
    attach_k: int = 8
    box_margin: float = 0.1
    visible_alpha: float = 0.3
    thin_alpha: float = 0.9
    dilate: int = 3
    inpaint_margin: Optional[int] = 32
    depth_source_alpha: float = 0.95
    steps: int = 150
    near_weight: float = 0.05
    hole_share: float = 0.5
    window_margin: int = 16
    seed_stride: int = 2
    seed_min_change: float = 0.05
    seed_opacity: float = 0.5
    seed_depth_tolerance: float = 0.05
    seed_slack: int = 4
    densify_every: int = 50
    densify_fraction: float = 0.1
    lambda_dssim: float = 0.2
    lrs: dict = field(default_factory=lambda: {"means": 1e-3, "log_scales": 5e-3, "quats": 1e-3,
                                                 "opacity_logits": 5e-2, "sh_dc": 1e-2, "sh_rest": 5e-4})
    background: tuple = (0.0, 0.0, 0.0)
    seed: int = 0
    checkpoint_every: int = 50


@dataclass
class DeleteResult:
    """What :func:`tiger.delete.delete` did. Images are [V, H, W, 3] in [0, 1], masks [V, H, W] bool.

    Attributes:
        scene: the scene without the object, refitted.
        removal: the removed Gaussians (masks over the input scene) and the rule's thresholds.
        cameras: the V views used.
        before, remaining, targets, after: renders of the input scene, of the scene right after
            removal, the inpainted views, and renders of the result.
        holes: the (dilated) hole masks; footprint: where the removed part was visible (dilated).
        trainable: [N_out] bool, which Gaussians of ``scene`` the refit could change (the seeds
            and their children included); the others are bit-identical to the input's, in order.
        near: [N_rest] bool over the Gaussians kept after removal: those made trainable.
        counts: Gaussians retrieved / floaters / removed / trainable / seeded / added / final.
        timings: seconds per stage (remove, render, inpaint, refit, total).
        losses: refit loss per step.
        metrics: empty from :func:`~tiger.delete.delete` (the library call does no evaluation);
            :func:`tiger.eval.reprojection.evaluate_delete` fills it (locality and hole PSNRs,
            multi-view consistency) and :meth:`save` writes what it holds.
    """

    scene: GaussianScene
    removal: Removal
    cameras: list
    before: torch.Tensor
    remaining: torch.Tensor
    targets: torch.Tensor
    after: torch.Tensor
    holes: torch.Tensor
    footprint: torch.Tensor
    trainable: torch.Tensor
    near: torch.Tensor
    counts: dict
    timings: dict
    losses: list
    metrics: dict = field(default_factory=dict)

    def save(self, folder: PathLike, n_pairs: int = 4, extra: Optional[dict] = None) -> list[Path]:
        """Write ``scene.ply``, ``before_k.png``/``after_k.png`` for the ``n_pairs`` views that saw
        most of the object, every view's hole mask (``holes/``) and inpainted view
        (``inpainted/``), and ``delete.json`` (:meth:`report` plus ``extra``), atomically.
        Returns the before/after paths."""
        import json

        from tiger.utils.images import save_png
        from tiger.utils.io import atomic_write

        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        self.scene.save_ply(out / "scene.ply")
        paths = []
        for k, i in enumerate(self.best_views(n_pairs)):
            paths.append(save_png(out / f"before_{k}.png", self.before[i]))
            paths.append(save_png(out / f"after_{k}.png", self.after[i]))
        for i, cam in enumerate(self.cameras):
            stem = file_slug(Path(cam.image_name or f"view{i}").stem, default=f"view{i}", keep="-_", max_len=None)
            save_png(out / "holes" / f"{i:03d}_{stem}.png", self.holes[i].float())
            save_png(out / "inpainted" / f"{i:03d}_{stem}.png", self.targets[i])
        with atomic_write(out / "delete.json", "w") as fh:
            json.dump({**(extra or {}), **self.report()}, fh, indent=2, default=str)
        return paths

    def best_views(self, n: int = 4) -> list[int]:
        """Indices of the ``n`` views that saw most of the removed object."""
        return torch.argsort(self.footprint.flatten(1).sum(1), descending=True)[:n].tolist()

    def report(self) -> dict:
        """JSON-ready summary: counts, timings, metrics, thresholds."""
        return {"counts": self.counts, "timings_s": self.timings, "metrics": self.metrics,
                "tau": self.removal.tau, "floater_tau": self.removal.floater_tau,
                "box_min": self.removal.box_min.tolist(), "box_max": self.removal.box_max.tolist(),
                "views": len(self.cameras), "hole_pixels": int(self.holes.sum())}


__all__ = ["DeleteConfig", "DeleteResult"]
