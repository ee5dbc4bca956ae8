"""Checkpoint files of every training loop: atomic, tagged, signed, with the RNG states.

A checkpoint is a ``torch.save`` dict written through :func:`tiger.utils.io.atomic_torch_save`
(an interruption leaves the old file or the new one, never a torn one) and read with
``weights_only=True`` (tensors, numbers, strings, lists, dicts: loading never runs code). Its
keys: ``format`` (what wrote it, e.g. ``"tiger.edit-checkpoint/1"``), ``signature`` (a plain
dict of the inputs and settings the state belongs to), ``rng`` (:func:`rng_state`) and the
loop's own state. A resume whose signature differs from the file's is refused with
:class:`CheckpointMismatch`, which names every differing entry.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import torch

from tiger.utils.io import atomic_torch_save

PathLike = Union[str, os.PathLike]
#: How many differing signature entries a refusal spells out (the rest are counted).
SHOWN_DIFFERENCES = 8


class CheckpointError(ValueError):
    """A checkpoint file that is missing, cannot be read or was written by something else;
    ``reason`` is ``"missing"``, ``"unreadable"``, ``"format"`` or ``"signature"``."""

    def __init__(self, message: str, reason: str = "unreadable") -> None:
        super().__init__(message)
        self.reason = reason


class CheckpointMismatch(CheckpointError):
    """A checkpoint of other inputs or settings than the run that wants to resume from it.

    ``differences`` lists ``(key, in the file, now)`` for every differing signature entry.
    """

    def __init__(self, path: PathLike, differences: list[tuple[str, Any, Any]], what: str = "run") -> None:
        self.path, self.differences = str(path), differences
        shown = "; ".join(f"{k}: {_short(a)} in the checkpoint, {_short(b)} now"
                          for k, a, b in differences[:SHOWN_DIFFERENCES])
        more = f"; and {len(differences) - SHOWN_DIFFERENCES} more" if len(differences) > SHOWN_DIFFERENCES else ""
        super().__init__(f"checkpoint {path} belongs to another {what} ({shown}{more}); use another output "
                         "or start without resuming", "signature")


def _short(v: Any, limit: int = 60) -> str:
    s = repr(v)
    return s if len(s) <= limit else s[:limit - 3] + "..."


def _plain(v: Any) -> Any:
    """Tuples as lists, nested: what a signature looks like after a save/load round trip."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix or "signature": d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        out.update(_flat(v, key) if isinstance(v, dict) else {key: v})
    return out


def signature_differences(saved: dict, current: dict) -> list[tuple[str, Any, Any]]:
    """``(dotted key, saved value, current value)`` for every entry that differs (missing = None)."""
    a, b = _flat(_plain(saved)), _flat(_plain(current))
    return [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def rng_state(generators: Sequence[torch.Generator] = ()) -> dict:
    """The loop's own generators' states, torch's global CPU state and (when CUDA is in use) every
    device's global CUDA state."""
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() and torch.cuda.is_initialized() else []
    return {"generators": [g.get_state() for g in generators], "torch_cpu": torch.get_rng_state(), "cuda": cuda}


def restore_rng(state: dict, generators: Sequence[torch.Generator] = ()) -> None:
    """Set ``generators`` (in the order given to :func:`rng_state`) and torch's global states."""
    saved = list(state.get("generators", []))
    if len(saved) != len(generators):
        raise CheckpointError(f"checkpoint holds {len(saved)} generator states, the run has {len(generators)}",
                              "signature")
    for g, st in zip(generators, saved):
        g.set_state(st.cpu())
    if "torch_cpu" in state:
        torch.set_rng_state(state["torch_cpu"].cpu())
    cuda = list(state.get("cuda", []))
    if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all([s.cpu() for s in cuda])


def write_checkpoint(path: PathLike, format: str, state: dict, *, signature: Optional[dict] = None,
                     generators: Sequence[torch.Generator] = ()) -> None:
    """Write ``state`` (tensors, numbers, strings, lists, dicts) atomically with ``format``,
    ``signature`` and the RNG states of ``generators`` and torch (see :func:`rng_state`)."""
    reserved = {"format", "signature", "rng"} & set(state)
    if reserved:
        raise ValueError(f"tiger.train: checkpoint state may not use the keys {sorted(reserved)}")
    payload = {"format": format, "signature": _plain(signature or {}), "rng": rng_state(generators), **state}
    atomic_torch_save(payload, path)


def read_checkpoint(path: PathLike, format: str, *, signature: Optional[dict] = None,
                    map_location: Union[str, torch.device, None] = "cpu", what: str = "run") -> dict:
    """Read a checkpoint written by :func:`write_checkpoint` with the same ``format``.

    With ``signature`` the file's must be equal (else :class:`CheckpointMismatch` naming every
    difference; ``what`` names the kind of run in that message). Returns the whole payload; pass
    ``payload["rng"]`` to :func:`restore_rng`. Raises :class:`CheckpointError` when the file is
    missing, unreadable or of another format.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} not found", "missing")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # pickle/zip raise many types on corrupt input
        raise CheckpointError(f"{path}: cannot read checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(payload, dict) or payload.get("format") != format:
        found = payload.get("format") if isinstance(payload, dict) else None
        raise CheckpointError(f"{path}: not a {format} checkpoint"
                              + (f" (it is {found})" if isinstance(found, str) else ""), "format")
    if signature is not None:
        diff = signature_differences(payload.get("signature") or {}, signature)
        if diff:
            raise CheckpointMismatch(path, diff, what)
    return payload


__all__ = ["CheckpointError", "CheckpointMismatch", "read_checkpoint", "restore_rng", "rng_state",
           "signature_differences", "write_checkpoint"]
