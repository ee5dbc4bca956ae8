"""Hyper-parameters of the 3DGS fit (INRIA's defaults) and shorter schedules."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional


@dataclass
class ReconConfig:
    """Settings of :class:`tiger.recon.Trainer`; defaults are INRIA's 30k-step recipe.

    Step counts (``*_from``, ``*_until``, ``*_interval``, ``*_every``) are in optimizer
    steps (one view per step). Learning rates are per parameter; the position rate decays
    exponentially from ``lr_means_init`` to ``lr_means_final`` and is multiplied by the
    scene extent.
    """

    iterations: int = 30_000
    sh_degree: int = 3
    sh_increase_every: int = 1000          # 0: start at full degree
    lambda_dssim: float = 0.2
    lr_means_init: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_means_delay_mult: float = 0.01
    lr_means_delay_steps: int = 0
    lr_means_max_steps: Optional[int] = None  # None: iterations
    lr_log_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    adam_eps: float = 1e-15
    densify: bool = True
    densify_from: int = 500
    densify_until: int = 15_000
    densify_interval: int = 100
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    opacity_reset_interval: int = 3000     # 0: never
    min_opacity: float = 0.005
    max_screen_size: Optional[float] = None  # px; INRIA's screen rule is inert in practice
    max_world_size: Optional[float] = 0.1    # x extent, after the first opacity reset
    max_gaussians: Optional[int] = None
    appearance: bool = False               # per-training-image affine colour correction
    lr_appearance: float = 1e-3
    background: tuple = (0.0, 0.0, 0.0)
    # a random colour behind every training render (the held-out evaluation stays on `background`);
    # `tiger reconstruct` turns it on for opaque images (tiger.recon.data.training_background)
    random_background: bool = False
    init_random_points: int = 100_000
    init_min_view_fraction: float = 0.5
    init_radius_fraction: float = 1.0      # random init within this x the camera distance
    init_opacity: float = 0.1
    # random init: "views" (each point's mean pixel colour over the views that see it; with the
    # undistortion-border masks it gave the fox 26.76 dB held-out at 7000 steps in
    # benchmarks/recon_fox.py, where the CLI's random colours and unmasked border gave 20.84 dB)
    # or "random" (INRIA)
    init_colors: str = "views"
    extent: Optional[float] = None         # None: from the cameras (INRIA's rule)
    seed: int = 0
    checkpoint_every: int = 0              # 0: only when asked / at the end with out_dir
    eval_every: int = 0                    # 0: only at the end
    time_budget_s: Optional[float] = None  # stop early once training took this long
    progress: bool = True

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise ValueError(f"tiger.recon: iterations must be >= 0, got {self.iterations}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"tiger.recon: sh_degree must be in 0..3, got {self.sh_degree}")
        if self.densify_interval <= 0:
            raise ValueError("tiger.recon: densify_interval must be positive")
        if self.init_colors not in ("random", "views"):
            raise ValueError(f"tiger.recon: init_colors must be 'random' or 'views', got {self.init_colors!r}")
        self.background = tuple(float(v) for v in self.background)

    @classmethod
    def scaled(cls, iterations: int, **overrides) -> "ReconConfig":
        """INRIA's schedule compressed to ``iterations`` steps (identical at 30000).

        The SH ramp and the end of densification scale with ``iterations / 30000``; the
        start of densification keeps a floor of 100 steps and the interval one of 50 (the
        first steps' gradients are large everywhere, and statistics over a handful of
        views are noise: without the floors every Gaussian doubles each interval); the
        opacity reset stays 30 intervals apart (none when that is past the window).
        """
        f = iterations / 30_000

        def s(v: int, lo: int) -> int:
            return max(lo, int(round(v * f)))

        interval = s(100, 50)
        start = s(500, 100)
        until = max(s(15_000, 2), start + 2 * interval)
        reset = 30 * interval
        kw = dict(iterations=iterations, sh_increase_every=s(1000, 1), densify_from=start,
                  densify_until=until, densify_interval=interval,
                  opacity_reset_interval=reset if reset < until else 0)
        kw.update(overrides)
        return cls(**kw)

    @classmethod
    def finetune(cls, iterations: int = 3000, **overrides) -> "ReconConfig":
        """Refit an existing scene to (edited / inpainted) images: all SH bands from the
        start, positions move 10x slower, no opacity reset; densification stays on in the
        first half to fill holes (used by deletion)."""
        kw = dict(iterations=iterations, sh_increase_every=0, lr_means_init=1.6e-5, lr_means_final=1.6e-6,
                  densify_from=max(1, iterations // 20), densify_until=iterations // 2,
                  densify_interval=max(1, iterations // 30), opacity_reset_interval=0)
        kw.update(overrides)
        return cls(**kw)

    def strategy(self, n: int, device, extent: float, finetune: bool = False):
        """The :class:`~tiger.recon.strategy.InriaStrategy` of these settings for ``n`` Gaussians
        in a scene of radius ``extent`` (INRIA densifies after, not at, ``densify_from``;
        ``finetune``: huge Gaussians are pruned from the first densification)."""
        from .strategy import DensifySchedule, InriaStrategy

        when = DensifySchedule(self.densify_interval if self.densify else 0, self.densify_from + 1, self.densify_until)
        return InriaStrategy(n, device, when, extent, grad_threshold=self.densify_grad_threshold,
                             percent_dense=self.percent_dense, min_opacity=self.min_opacity,
                             max_screen_size=self.max_screen_size, max_world_size=self.max_world_size,
                             max_gaussians=self.max_gaussians, opacity_reset_every=self.opacity_reset_interval,
                             prune_large_from_start=finetune)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ReconConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: (tuple(v) if k == "background" else v) for k, v in d.items() if k in names})


def expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int, delay_steps: int = 0,
             delay_mult: float = 1.0) -> float:
    """INRIA's log-linear learning-rate decay from ``lr_init`` (step 0) to ``lr_final``
    (step ``max_steps``), with an optional sine-eased warm-up over ``delay_steps``."""
    import math

    if step < 0 or (lr_init == 0 and lr_final == 0):
        return 0.0
    if delay_steps > 0:
        delay = delay_mult + (1 - delay_mult) * math.sin(0.5 * math.pi * min(max(step / delay_steps, 0), 1))
    else:
        delay = 1.0
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return delay * math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)
