"""The DDPM noise schedule and the SDS noise draws shared by every score-distillation guidance
(InstructPix2Pix, MVDream and the analytic ideal denoiser). Pure torch: no diffusers needed.

Conventions (Stable Diffusion, ε-prediction): ``x_t = √ᾱ_t·x_0 + √(1−ᾱ_t)·ε``; the SDS gradient is
``w(t)(ε̂ − ε)`` with ``w(t) = 1 − ᾱ_t``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch


@dataclass
class NoiseSchedule:
    """ᾱ_t of a discrete DDPM schedule ([T] float32 tensor, t = 0 … T−1)."""

    alphas_cumprod: torch.Tensor

    @classmethod
    def from_betas(cls, beta_start: float, beta_end: float, num_train_timesteps: int = 1000,
                   beta_schedule: str = "scaled_linear") -> "NoiseSchedule":
        """The Stable Diffusion schedules: ``scaled_linear`` (linear in √β, LDM's "linear") or ``linear``."""
        if beta_schedule == "scaled_linear":
            betas = torch.linspace(beta_start ** 0.5, beta_end ** 0.5, num_train_timesteps, dtype=torch.float64) ** 2
        elif beta_schedule == "linear":
            betas = torch.linspace(beta_start, beta_end, num_train_timesteps, dtype=torch.float64)
        else:
            raise ValueError(f"tiger.edit: unsupported beta_schedule {beta_schedule!r} (scaled_linear or linear)")
        return cls(torch.cumprod(1.0 - betas, dim=0).float())

    @classmethod
    def from_scheduler_config(cls, config: dict) -> "NoiseSchedule":
        """From a diffusers ``scheduler_config.json`` (beta_start, beta_end, beta_schedule, num_train_timesteps)."""
        if config.get("prediction_type", "epsilon") != "epsilon":
            raise ValueError(f"tiger.edit: only ε-prediction models are supported, scheduler says "
                             f"prediction_type={config.get('prediction_type')!r}")
        return cls.from_betas(float(config.get("beta_start", 0.00085)), float(config.get("beta_end", 0.012)),
                              int(config.get("num_train_timesteps", 1000)),
                              str(config.get("beta_schedule", "scaled_linear")))

    @property
    def num_steps(self) -> int:
        return int(self.alphas_cumprod.shape[0])

    def to(self, device: torch.device | str) -> "NoiseSchedule":
        return NoiseSchedule(self.alphas_cumprod.to(device))

    def step_range(self, t_range: tuple[float, float]) -> tuple[int, int]:
        """Integer timesteps [lo, hi] (inclusive) for fractions of the schedule, as threestudio does."""
        lo, hi = check_t_range(t_range)
        return int(self.num_steps * lo), min(int(self.num_steps * hi), self.num_steps - 1)

    def sample(self, n: int, t_range: tuple[float, float], generator: Optional[torch.Generator] = None,
               device: torch.device | str = "cpu") -> torch.Tensor:
        """[n] int64 timesteps drawn uniformly from ``step_range(t_range)``."""
        lo, hi = self.step_range(t_range)
        t = torch.randint(lo, hi + 1, (n,), generator=generator, device="cpu" if generator is None else generator.device)
        return t.to(device)

    def coefficients(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(√ᾱ_t, √(1−ᾱ_t)) as [n, 1, 1, 1] float32 for [n] timesteps."""
        a = self.alphas_cumprod.to(t.device)[t].view(-1, 1, 1, 1)
        return a.sqrt(), (1.0 - a).sqrt()

    def add_noise(self, z0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        s, n = self.coefficients(t)
        return (s * z0.float() + n * noise.float()).to(z0.dtype)

    def predict_x0(self, z_t: torch.Tensor, eps: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """x0 = (z_t − √(1−ᾱ_t)·ε) / √ᾱ_t (float32)."""
        s, n = self.coefficients(t)
        return (z_t.float() - n * eps.float()) / s

    def sds_weight(self, t: torch.Tensor) -> torch.Tensor:
        """w(t) = 1 − ᾱ_t as [n, 1, 1, 1] float32."""
        return 1.0 - self.alphas_cumprod.to(t.device)[t].view(-1, 1, 1, 1)


def finite_clamped(g: torch.Tensor, clip: Optional[float]) -> torch.Tensor:
    """Non-finite entries zeroed, then clamped to [−clip, clip] when ``clip`` is set."""
    g = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
    return g.clamp(-clip, clip) if clip is not None else g


def draw_noise(given: Optional[torch.Tensor], shape: tuple[int, ...], name: str,
               generator: Optional[torch.Generator], device: torch.device) -> torch.Tensor:
    """``given`` checked against ``shape`` (ValueError naming ``name``), or standard normal noise."""
    if given is not None:
        if tuple(given.shape) != tuple(shape):
            raise ValueError(f"tiger.edit.{name} must be {list(shape)}, got {list(given.shape)}")
        return given.to(device, torch.float32)
    gen_dev = generator.device if generator is not None else device
    return torch.randn(shape, generator=generator, device=gen_dev).to(device)


def check_t_range(t_range: tuple[float, float]) -> tuple[float, float]:
    """The (lo, hi) fractions of the schedule as floats, or a ValueError."""
    lo, hi = float(t_range[0]), float(t_range[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi <= 1.0):
        raise ValueError(f"tiger.edit: t_range must satisfy 0 <= lo <= hi <= 1, got {t_range}")
    return lo, hi


__all__ = ["NoiseSchedule", "check_t_range", "draw_noise", "finite_clamped"]
