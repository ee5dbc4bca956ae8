"""The analytic guidance for tests (SPEC §8): score distillation with the ideal denoiser of known targets.

For a target image x* the ideal noise prediction at noise level t is

    ε̂(x_t, t) = (x_t − √ᾱ_t x*) / √(1 − ᾱ_t),   x_t = √ᾱ_t x + √(1 − ᾱ_t) ε,

so the SDS gradient ``w(t) (ε̂ − ε)`` equals ``w(t) √(ᾱ_t / (1 − ᾱ_t)) (x − x*)``: it pulls every
render toward its target, and its optimum is exactly x*. This module runs the real SDS path
(noise drawn, x_t formed, ε̂ computed from x_t), so it exercises the same arithmetic a diffusion
guidance does, in image space ([0, 1] mapped to [-1, 1]) with Stable Diffusion's noise schedule
(:class:`~tiger.edit.guidance.noise_schedule.NoiseSchedule`, t drawn as the diffusion guidances draw it).
``w(t) = 1 − ᾱ_t`` (DreamFusion). The targets are rendered by a callable from the step's views,
typically the renders of a ground-truth edited scene from the same cameras.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Optional

import torch

from tiger.edit.guidance.base import GuidanceInfo, ViewBatch, check_renders
from tiger.edit.guidance.noise_schedule import NoiseSchedule, check_t_range
from tiger.scene import GaussianScene, render_rgb


class IdealDenoiserGuidance:
    """SDS with the ideal denoiser of per-view target images (see the module docstring).

    Args:
        targets: ``views -> [V, 3, H, W]`` target images in [0, 1] for the step's cameras.
        t_range: (lo, hi) noise levels as fractions of the 1000 training steps (default [0.02, 0.2]).
        seed: seed of the guidance's own generator (noise and t); its state is checkpointed by the
            edit loop through :meth:`generators`.
        instruction: the text recorded as the edit's instruction (the targets are the edit).
    """

    name = "analytic"

    def __init__(self, targets: Callable[[ViewBatch], torch.Tensor],
                 t_range: tuple[float, float] = (0.02, 0.2), seed: int = 0, *,
                 instruction: str = "match the target renders") -> None:
        self.targets, self.t_range = targets, check_t_range(t_range)
        self.instruction = instruction
        self.schedule = NoiseSchedule.from_betas(0.00085, 0.012)  # Stable Diffusion's
        self.generator = torch.Generator().manual_seed(seed)

    def settings(self) -> dict[str, Any]:
        """The noise range (fractions of the 1000 training steps)."""
        return {"t_range": list(self.t_range)}

    def generators(self) -> list[torch.Generator]:
        """The one generator of t and the noise."""
        return [self.generator]

    def reset_caches(self) -> None:
        """Nothing is cached across steps."""

    def grad(self, renders: torch.Tensor, views: ViewBatch) -> tuple[torch.Tensor, GuidanceInfo]:
        t0 = time.perf_counter()
        check_renders(renders, self.name)
        target = self.targets(views)
        if target.shape != renders.shape:
            raise ValueError(f"tiger.edit.analytic: targets {list(target.shape)} must match renders "
                             f"{list(renders.shape)}")
        V = renders.shape[0]
        t = self.schedule.sample(V, self.t_range, self.generator)
        a = self.schedule.alphas_cumprod[t].to(renders).view(V, 1, 1, 1)
        x = renders * 2 - 1
        x_star = target.to(renders) * 2 - 1
        eps = torch.randn(renders.shape, generator=self.generator, dtype=renders.dtype).to(renders.device)
        x_t = a.sqrt() * x + (1 - a).sqrt() * eps
        eps_hat = (x_t - a.sqrt() * x_star) / (1 - a).sqrt()
        g = (1 - a) * (eps_hat - eps) * 2  # d/drenders of the [-1, 1] image
        g = torch.where(torch.isfinite(g), g, torch.zeros_like(g))
        loss = 0.5 * float(((renders - target.to(renders)) ** 2).mean())
        return g, GuidanceInfo(loss=loss, t=t.float() / self.schedule.num_steps,
                               timings_ms={"analytic": 1e3 * (time.perf_counter() - t0)})


def render_targets(target_scene: GaussianScene, background: Optional[torch.Tensor] = None
                   ) -> Callable[[ViewBatch], torch.Tensor]:
    """Targets = renders [V, 3, H, W] of ``target_scene`` (full SH colour, :func:`tiger.scene.render_rgb`)
    from the step's cameras."""
    def fn(views: ViewBatch) -> torch.Tensor:
        return render_rgb(target_scene, views.cameras, background).permute(0, 3, 1, 2)

    return fn


__all__ = ["IdealDenoiserGuidance", "render_targets"]
