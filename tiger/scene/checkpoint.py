"""Training checkpoints: the scene, the optimizer state and the trainer's own state.

Files are ``torch.save`` dicts written atomically and read with ``weights_only=True``
(plain tensors, numbers, strings, lists and dicts only), so loading a checkpoint can
never run code.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional, Union

import torch

from tiger.utils.io import atomic_torch_save

from .errors import SceneFormatError
from .gaussian_scene import GaussianScene

PathLike = Union[str, os.PathLike]
FORMAT = "tiger.checkpoint/1"


def save_checkpoint(path: PathLike, scene: GaussianScene,
                    optimizer: Optional[torch.optim.Optimizer] = None, step: int = 0,
                    extra: Optional[dict[str, Any]] = None) -> None:
    """Write ``scene`` (+ optimizer state, step, trainer state ``extra``) atomically."""
    payload = {
        "format": FORMAT,
        "step": int(step),
        "scene": scene.state_dict(),
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "extra": extra or {},
    }
    atomic_torch_save(payload, path)


def load_checkpoint(path: PathLike, map_location: Union[str, torch.device] = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Returns a dict with ``scene`` (:class:`GaussianScene`), ``optimizer`` (state dict or
    None), ``step`` (int) and ``extra`` (dict). Raises :class:`SceneFormatError` when the
    file is missing, corrupt or not a TIGER checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, "checkpoint file not found")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # pickle/zip raise many types on corrupt input
        raise SceneFormatError(path, f"cannot read checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise SceneFormatError(path, f"not a TIGER checkpoint (expected format '{FORMAT}')", "format")
    try:
        scene = GaussianScene.from_state_dict(payload["scene"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneFormatError(path, f"invalid scene in checkpoint: {exc}", "scene") from None
    return {"scene": scene, "optimizer": payload.get("optimizer"), "step": int(payload.get("step", 0)),
            "extra": payload.get("extra") or {}}
