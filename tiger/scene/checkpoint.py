"""Scene checkpoints: the scene, the optimizer state and the trainer's own state.

A thin layer over :mod:`tiger.train.checkpoint` (atomic write, ``weights_only`` read, format
tag, signature, RNG states) that stores a :class:`GaussianScene` and reports bad files as
:class:`SceneFormatError`.
"""
from __future__ import annotations

import os
from typing import Any, Optional, Sequence, Union

import torch

from tiger.train.checkpoint import CheckpointError, read_checkpoint, write_checkpoint

from .errors import SceneFormatError
from .gaussian_scene import GaussianScene

PathLike = Union[str, os.PathLike]
FORMAT = "tiger.checkpoint/1"


def save_checkpoint(path: PathLike, scene: GaussianScene,
                    optimizer: Optional[torch.optim.Optimizer] = None, step: int = 0,
                    extra: Optional[dict[str, Any]] = None, *, signature: Optional[dict] = None,
                    generators: Sequence[torch.Generator] = ()) -> None:
    """Write ``scene`` (+ optimizer state, step, trainer state ``extra``, the ``signature`` of the
    run and the RNG states of ``generators`` and torch) atomically."""
    state = {"step": int(step), "scene": scene.state_dict(),
             "optimizer": None if optimizer is None else optimizer.state_dict(), "extra": extra or {}}
    write_checkpoint(path, FORMAT, state, signature=signature, generators=generators)


def load_checkpoint(path: PathLike, map_location: Union[str, torch.device] = "cpu",
                    signature: Optional[dict] = None, what: str = "run") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Returns a dict with ``scene`` (:class:`GaussianScene`), ``optimizer`` (state dict or
    None), ``step`` (int), ``extra`` (dict) and ``rng`` (for :func:`tiger.train.restore_rng`).
    Raises :class:`SceneFormatError` when the file is missing, corrupt or not a TIGER
    checkpoint, and :class:`tiger.train.CheckpointMismatch` naming what differs when
    ``signature`` is given and the file's is another.
    """
    try:
        payload = read_checkpoint(path, FORMAT, signature=signature, map_location=map_location, what=what)
    except CheckpointError as exc:
        if exc.reason == "signature":
            raise
        if exc.reason == "missing":
            raise SceneFormatError(path, "checkpoint file not found") from None
        if exc.reason == "format":
            raise SceneFormatError(path, f"not a TIGER checkpoint (expected format '{FORMAT}')", "format") from None
        raise SceneFormatError(path, str(exc).split(": ", 1)[-1]) from None
    try:
        scene = GaussianScene.from_state_dict(payload["scene"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneFormatError(path, f"invalid scene in checkpoint: {exc}", "scene") from None
    return {"scene": scene, "optimizer": payload.get("optimizer"), "step": int(payload.get("step", 0)),
            "extra": payload.get("extra") or {}, "rng": payload.get("rng") or {}}
