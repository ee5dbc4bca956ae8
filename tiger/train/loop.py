"""The loop every trainer runs: steps, progress, time budget, checkpoints, Ctrl-C.

A trainer ("session") owns its state and one step of its recipe; :func:`run_loop` owns the rest:

* stops at ``steps`` or once ``time_budget_s`` of training time have passed (counting the time of
  the runs a resumed one continues);
* a checkpoint every ``checkpoint_every`` steps, at the end, and on Ctrl-C;
* Ctrl-C in the main thread is taken at the end of the running step (SIGINT is held while a step
  runs), so the checkpoint holds a whole step and ``resume`` continues exactly; a second Ctrl-C
  interrupts at once. A ``KeyboardInterrupt`` raised inside a step anyway (another thread, a
  second Ctrl-C) counts as "the step did not happen": the session's generators and torch's global
  CPU generator are set back to where the step began and the step is redone on resume;
* one progress bar whose figures (running means of the step records' ``show`` keys) are copied
  from the device every ``log_every`` steps without waiting for it (:class:`LaggedScalars`: the
  bar shows the newest copy that has arrived; the last step's is awaited), and not at all when the
  bar is off.
"""
from __future__ import annotations

import logging
import os
import signal
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Optional, Protocol, Sequence, Union

import torch

from .progress import LaggedScalars, progress_bar

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]


class Session(Protocol):
    """What :func:`run_loop` drives."""

    step: int        # steps done (a resumed session starts at its checkpoint's)
    elapsed: float   # seconds of training so far, earlier runs included

    def step_once(self) -> dict:
        """One training step; returns its record (values may be 0-d device tensors)."""

    def save(self, path: PathLike) -> None:
        """Write a checkpoint from which the session resumes exactly."""

    def generators(self) -> Sequence[torch.Generator]:
        """The generators a step draws from (set back when a step is interrupted)."""


@dataclass
class LoopOutcome:
    """stopped: ``"done"`` (reached ``steps``) or ``"time budget"``; steps_run: steps of this call."""

    stopped: str
    steps_run: int


class _HeldInterrupt:
    requested = False


@contextmanager
def _hold_sigint() -> Iterator[_HeldInterrupt]:
    """While active (main thread, default handler only): the first SIGINT is noted, not raised;
    a second one raises KeyboardInterrupt at once."""
    held = _HeldInterrupt()
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield held
        return

    def note(signum, frame):
        if held.requested:
            raise KeyboardInterrupt
        held.requested = True
        log.warning("interrupt: stopping after this step (Ctrl-C again to stop at once)")

    previous = signal.signal(signal.SIGINT, note)
    try:
        yield held
    finally:
        signal.signal(signal.SIGINT, previous)


def run_loop(session: Session, steps: int, *, checkpoint: Optional[PathLike] = None, checkpoint_every: int = 0,
             time_budget_s: Optional[float] = None, progress: bool = True, desc: str = "train",
             show: Optional[dict[str, str]] = None, log_every: int = 10,
             after_step: Optional[Callable[[dict], None]] = None) -> LoopOutcome:
    """Run ``session.step_once()`` until ``session.step == steps`` (module docstring).

    Args:
        steps: the step count to reach (a resumed session has done some already).
        checkpoint: file for ``session.save``; None: no checkpoints.
        checkpoint_every: steps between checkpoints (0: only at the end and on Ctrl-C).
        time_budget_s: stop once ``session.elapsed`` reaches this (None: no budget).
        show: record keys shown on the bar as running means, with their format spec; the record's
            ``gaussians`` (an int) is shown as N. Default: ``{"loss": ".4g"}``.
        after_step: called with each step's record (e.g. to keep a history).
    Returns:
        :class:`LoopOutcome`. Ctrl-C re-raises KeyboardInterrupt after the checkpoint is written.
    """
    path = Path(checkpoint) if checkpoint is not None else None
    show = {"loss": ".4g"} if show is None else show
    first = session.step
    bar = progress_bar(steps, desc, initial=session.step, enabled=progress)
    means: dict[str, Any] = {}
    shown = LaggedScalars()
    t0, before = time.perf_counter(), session.elapsed
    stopped = "done"
    try:
        with _hold_sigint() as held:
            while session.step < steps:
                gens = list(session.generators())
                at_start = [g.get_state() for g in gens]
                global_at_start = torch.get_rng_state()
                step_before = session.step
                try:
                    rec = session.step_once()
                except KeyboardInterrupt:
                    if session.step == step_before:  # not finished: redo it on resume
                        for g, st in zip(gens, at_start):
                            g.set_state(st)
                        torch.set_rng_state(global_at_start)
                    raise
                session.elapsed = before + time.perf_counter() - t0
                if progress:
                    for k in show:
                        if k in rec:
                            means[k] = rec[k] if k not in means else 0.9 * means[k] + 0.1 * rec[k]
                if progress and (session.step % log_every == 0 or session.step == steps):
                    if means:
                        shown.push(means)
                    post = {k: format(v, show[k]) for k, v in shown.latest(wait=session.step == steps).items()}
                    if "gaussians" in rec:
                        post["N"] = rec["gaussians"]
                    bar.set_postfix(post, refresh=False)
                bar.update(1)
                if after_step is not None:
                    after_step(rec)
                if path is not None and checkpoint_every and session.step % checkpoint_every == 0:
                    session.save(path)
                if held.requested:
                    raise KeyboardInterrupt
                if time_budget_s is not None and session.elapsed >= time_budget_s and session.step < steps:
                    log.info("%s: time budget of %.0f s reached at step %d of %d", desc, time_budget_s,
                             session.step, steps)
                    stopped = "time budget"
                    break
    except KeyboardInterrupt:
        if path is not None and session.step != first:
            session.save(path)
            log.warning("%s interrupted at step %d of %d; %s holds it (resume continues exactly)", desc,
                        session.step, steps, path)
        raise
    finally:
        bar.close()
    if path is not None:
        session.save(path)
    return LoopOutcome(stopped, session.step - first)


__all__ = ["LoopOutcome", "Session", "run_loop"]
