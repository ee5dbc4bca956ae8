"""Coherent Score Distillation: the λ schedule and the weighted sum of two guidances (paper §3.2).

``∇ = E_v[(λ1 g_ip2p + λ2 g_mvdream) ∂x_v/∂S]``. The schedule (paper appendix: "the initial weight
ratio of InstructPix2Pix to MVDream is 2:1; the weight of InstructPix2Pix gradually increases while
that of MVDream decreases until it reaches zero after 75 % of the steps") is, with progress
``p = step / total_steps`` (step 0-based) and ``p_end = mv_end`` (default 0.75):

    λ2(p) = λ2_0 · max(0, 1 − p / p_end)          λ2_0 = ratio_mv / (ratio_ip + ratio_mv) = 1/3
    λ1(p) = 1 − λ2(p)                             (2/3 at the start, 1 from p_end on)

so λ1:λ2 = 2:1 at step 0, λ2 falls linearly to 0 at 75 % of the steps, λ1 grows linearly to 1,
and the total weight λ1 + λ2 stays 1 (the gradient's scale does not drift with the mix).
When λ2 = 0 MVDream is not called at all (the last 25 % of the steps cost one model only); when a
guidance is missing its λ is 0 and the other's is 1.

On CUDA the two guidances are independent given the renders, so MVDream runs on a side stream
beside InstructPix2Pix (``concurrent``): MVDream's ~1,400 small kernels at 32² latents fill the
gaps and idle SMs of InstructPix2Pix's step. Each guidance's kernels are the same either way, so
the gradient is bit-identical to running them one after the other.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Optional

import torch

from tiger.utils.streams import side_stream

from .guidance.base import (Guidance, GuidanceInfo, ViewBatch, check_guidance, prepare_guidance,
                            unique_generators)


@dataclass(frozen=True)
class CSDSchedule:
    """λ1 (InstructPix2Pix) and λ2 (MVDream) over the edit (see the module docstring).

    Attributes:
        ratio: (ip2p, mvdream) weight ratio at step 0 (2:1).
        mv_end: fraction of the steps at which λ2 reaches 0 (0.75).
    """

    ratio: tuple[float, float] = (2.0, 1.0)
    mv_end: float = 0.75

    def __post_init__(self) -> None:
        object.__setattr__(self, "ratio", tuple(float(r) for r in self.ratio))
        a, b = self.ratio
        if a < 0 or b < 0 or a + b <= 0:
            raise ValueError(f"tiger.edit.csd: ratio must be two non-negative weights, got {self.ratio}")
        if not 0.0 < self.mv_end <= 1.0:
            raise ValueError(f"tiger.edit.csd: mv_end must be in (0, 1], got {self.mv_end}")

    def weights(self, step: int, total_steps: int) -> tuple[float, float]:
        """(λ1, λ2) at ``step`` (0-based) of ``total_steps``."""
        if total_steps <= 0:
            raise ValueError(f"tiger.edit.csd: total_steps must be positive, got {total_steps}")
        a, b = self.ratio
        lam2_0 = b / (a + b)
        p = step / total_steps
        lam2 = lam2_0 * max(0.0, 1.0 - p / self.mv_end)
        return 1.0 - lam2, lam2

    def to_dict(self) -> dict[str, Any]:
        """``{"ratio": [ip2p, mvdream], "mv_end": p_end}`` (records)."""
        return {"ratio": list(self.ratio), "mv_end": self.mv_end}


class CSDGuidance:
    """``λ1 g_ip2p + λ2 g_mvdream`` with λ from a :class:`CSDSchedule`; a Guidance itself.

    Args:
        ip2p: the image-editing guidance (or None: MVDream alone, λ2 = 1).
        mvdream: the multi-view guidance (or None: InstructPix2Pix alone, λ1 = 1).
        schedule: the λ schedule (its one home: the record of an edit is this guidance's
            :meth:`settings`).
        concurrent: run MVDream on a side CUDA stream beside InstructPix2Pix when both are called
            on CUDA renders (None, the default: on; False: one after the other on the caller's
            stream). Changes no value, so it is not part of :meth:`settings`.

    The instruction is InstructPix2Pix's (MVDream's prompt when there is no InstructPix2Pix).
    """

    name = "csd"

    def __init__(self, ip2p: Optional[Guidance], mvdream: Optional[Guidance],
                 schedule: CSDSchedule = CSDSchedule(), concurrent: Optional[bool] = None) -> None:
        if ip2p is None and mvdream is None:
            raise ValueError("tiger.edit.csd: needs at least one guidance")
        self.ip2p = None if ip2p is None else check_guidance(ip2p)
        self.mvdream = None if mvdream is None else check_guidance(mvdream)
        self.schedule = schedule
        self.concurrent = True if concurrent is None else bool(concurrent)
        self.instruction = (self.ip2p or self.mvdream).instruction

    def settings(self) -> dict[str, Any]:
        """The schedule and each part's name, instruction and settings (None for a missing part)."""
        parts = {key: None if g is None else {"name": g.name, "instruction": g.instruction, **g.settings()}
                 for key, g in (("ip2p", self.ip2p), ("mvdream", self.mvdream))}
        return {"schedule": self.schedule.to_dict(), **parts}

    def generators(self) -> list[torch.Generator]:
        """InstructPix2Pix's generators, then MVDream's (a shared one once)."""
        return unique_generators(*(g.generators() for g in (self.ip2p, self.mvdream) if g is not None))

    def reset_caches(self) -> None:
        for g in (self.ip2p, self.mvdream):
            if g is not None:
                g.reset_caches()

    def prepare(self, views: ViewBatch) -> list[torch.Tensor]:
        """Each part's :meth:`~tiger.edit.guidance.base.Guidance.prepare` (the optional member)."""
        return [t for g in (self.ip2p, self.mvdream) if g is not None for t in prepare_guidance(g, views)]

    def weights(self, step: int, total_steps: int) -> tuple[float, float]:
        if self.mvdream is None:
            return 1.0, 0.0
        if self.ip2p is None:
            return 0.0, 1.0
        return self.schedule.weights(step, total_steps)

    def grad(self, renders: torch.Tensor, views: ViewBatch) -> tuple[torch.Tensor, GuidanceInfo]:
        lam1, lam2 = self.weights(views.step, views.total_steps)
        info = GuidanceInfo(extra={"lambda_ip2p": lam1, "lambda_mvdream": lam2})
        parts = [(lam, g_mod, key) for lam, g_mod, key in ((lam1, self.ip2p, "ip2p"), (lam2, self.mvdream, "mvdream"))
                 if g_mod is not None and lam != 0.0]
        results = {}
        if len(parts) == 2 and self.concurrent and renders.is_cuda:
            main = torch.cuda.current_stream(renders.device)
            side = self._side_stream(renders.device)
            side.wait_stream(main)  # the renders
            with torch.cuda.stream(side):  # MVDream first: its launch must not wait for InstructPix2Pix's
                results["mvdream"] = self._timed(self.mvdream, renders, views)
            results["ip2p"] = self._timed(self.ip2p, renders, views)
            main.wait_stream(side)
            results["mvdream"][0].record_stream(main)  # used on main, allocated on the side stream
        else:
            for _, g_mod, key in parts:
                results[key] = self._timed(g_mod, renders, views)
        total = torch.zeros_like(renders)
        for lam, _, key in parts:
            g, gi, ms = results[key]
            info.timings_ms[key] = ms
            info.timings_ms.update({f"{key}.{k}": v for k, v in gi.timings_ms.items()})
            info.loss += lam * gi.loss
            info.extra[f"loss_{key}"] = gi.loss
            total.add_(g.to(total), alpha=lam)
        return total, info

    @staticmethod
    def _timed(g_mod: Guidance, renders: torch.Tensor, views: ViewBatch) -> tuple[torch.Tensor, GuidanceInfo, float]:
        t0 = time.perf_counter()
        g, gi = g_mod.grad(renders, views)
        return g, gi, 1e3 * (time.perf_counter() - t0)

    @staticmethod
    def _side_stream(device: torch.device) -> "torch.cuda.Stream":
        # The same stream for every call (the graphs are captured per stream), from the
        # high-priority pool: never one of the default-priority streams graphs are captured on,
        # whose per-stream cuBLAS workspace those graphs use (cuda_graph.capture_stream).
        return side_stream(device, high_priority=True)


__all__ = ["CSDGuidance", "CSDSchedule"]
