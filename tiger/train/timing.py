"""Seconds per named stage of a loop or a pipeline."""
from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Callable, Iterator, Optional, Sequence, Union

import torch

#: CUDA stage events kept before they are resolved (one host sync) to bound their number.
MAX_PENDING = 512


class StageTimer:
    """Totals of seconds per stage, in the order the stages first ran.

    On CUDA each stage is bracketed by CUDA events that are read only when the totals are asked
    for (:meth:`summary`), so timing adds no host synchronisation (a sync per stage would leave
    the GPU idle while the next stage's launches are prepared); the stages' ranges are also named
    for a profiler. On the CPU it is ``time.perf_counter``.

    Args:
        device: where the timed work runs (``"cuda"``: events; anything else: wall clock).
        on_stage: called as ``on_stage(name, seconds)`` when a stage ends (e.g. to print it); with
            CUDA events this waits for the stage, so use it for pipelines, not per-step stages.
        prefix: of the profiler range names.
        stages: names listed (at 0 s) in the summary even if they never run, in this order.
    """

    def __init__(self, device: Union[str, torch.device, None] = None,
                 on_stage: Optional[Callable[[str, float], None]] = None, prefix: str = "tiger",
                 stages: Sequence[str] = ()) -> None:
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.on_stage, self.prefix = on_stage, prefix
        self._done: dict[str, float] = {name: 0.0 for name in stages}
        self._pending: list[tuple[str, torch.cuda.Event, torch.cuda.Event]] = []

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the block as stage ``name`` (totals add up over repeated entries)."""
        self._done.setdefault(name, 0.0)
        if self.device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            with torch.profiler.record_function(f"{self.prefix}::{name}"):
                yield
            end.record()
            self._pending.append((name, start, end))
            if self.on_stage is not None:
                end.synchronize()
                self.on_stage(name, 1e-3 * start.elapsed_time(end))
            if len(self._pending) >= MAX_PENDING or self.on_stage is not None:
                self._resolve()
        else:
            t0 = time.perf_counter()
            yield
            dt = time.perf_counter() - t0
            self._done[name] += dt
            if self.on_stage is not None:
                self.on_stage(name, dt)

    __call__ = stage

    def _resolve(self) -> None:
        if self._pending:
            self._pending[-1][2].synchronize()
            for name, start, end in self._pending:
                self._done[name] += 1e-3 * start.elapsed_time(end)
            self._pending.clear()

    def summary(self) -> dict[str, float]:
        """{stage: seconds} so far, in first-run order (waits for stages still on the GPU)."""
        self._resolve()
        return dict(self._done)

    @property
    def total(self) -> float:
        """Seconds of all stages together."""
        return sum(self.summary().values())

    def load(self, totals: dict[str, float]) -> None:
        """Continue from the totals of an earlier (checkpointed) run."""
        self._resolve()
        for k, v in totals.items():
            self._done[k] = float(v)

    def table(self, width: int = 40) -> str:
        """One ``name  seconds`` line per stage and a total line."""
        rows = self.summary()
        return "\n".join([f"{n:<{width}s} {t:7.2f} s" for n, t in rows.items()] +
                         [f"{'total':<{width}s} {sum(rows.values()):7.2f} s"])


__all__ = ["StageTimer"]
