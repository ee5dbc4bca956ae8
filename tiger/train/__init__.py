"""The training skeleton every loop of TIGER runs on (reconstruction, language field, edit, refit).

* :class:`ViewSampler` (``views.py``): which view(s) a step trains on; seeded epochs of a random
  permutation, its state checkpointed for exact resume.
* ``checkpoint.py``: atomic checkpoint files with a format tag, a signature of the inputs and
  settings (a resume with other ones is refused, naming what differs) and the RNG states.
* :class:`StageTimer` (``timing.py``): seconds per named stage (CUDA events on CUDA, no syncs).
* :func:`progress_bar` (``progress.py``): the one progress bar.
* :func:`run_loop` (``loop.py``): steps until done or a time budget, periodic checkpoints, a
  checkpoint on Ctrl-C (taken between steps, so resume is exact), the progress display.

Densification strategies (what to densify and when) live with the rules in
:mod:`tiger.recon.strategy`. This package imports nothing of TIGER above :mod:`tiger.utils`.
"""
from __future__ import annotations

from .checkpoint import (CheckpointError, CheckpointMismatch, read_checkpoint, restore_rng, rng_state,
                         signature_differences, write_checkpoint)
from .loop import LoopOutcome, run_loop
from .progress import progress_bar
from .timing import StageTimer
from .views import ViewSampler

__all__ = ["CheckpointError", "CheckpointMismatch", "LoopOutcome", "StageTimer", "ViewSampler", "progress_bar",
           "read_checkpoint", "restore_rng", "rng_state", "run_loop", "signature_differences", "write_checkpoint"]
