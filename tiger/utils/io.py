"""Atomic file writes: a temp file in the destination folder, fsync, then rename.

A crash or interruption leaves either the old file or the new one, never a torn one. ``fsync=False``
skips the flush to the disk (a file that a crash may only cost recomputing, such as a cache: the
rename stays atomic for the running system, but after a power loss the file may be missing or empty,
which its reader must treat as absent). Ctrl-C
during a write (in the main thread) is held until the file is in place, then raised: the
interrupted program ends with a complete file and a plain KeyboardInterrupt, not a serializer's
internal error. The new file gets the mode ``open()`` would have given it (0666 less the umask,
typically 0644), not the owner-only 0600 of :func:`tempfile.mkstemp`.
"""
from __future__ import annotations

import contextlib
import os
import signal
import tempfile
import threading
from pathlib import Path
from typing import IO, Any, Iterator, Optional, Sequence, Union

import torch

PathLike = Union[str, os.PathLike]


def _umask() -> int:
    """The process umask, read without changing it where Linux shows it (/proc/self/status)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)  # elsewhere reading it means setting it: put it straight back
    os.umask(mask)
    return mask


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) while the block runs and raise KeyboardInterrupt after it.

    Only where Python's default SIGINT handler is installed and in the main thread (elsewhere
    signals cannot be caught); otherwise the block runs unchanged. An exception raised by the
    block itself wins over the held interrupt.
    """
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    held: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if held:
        raise KeyboardInterrupt


@contextlib.contextmanager
def atomic_write(path: PathLike, mode: str = "wb", fsync: bool = True) -> Iterator[IO]:
    """Open a temporary file next to ``path``; on clean exit it replaces ``path``.

    The file's permissions follow the umask, like a plain ``open(path, "w")``. Ctrl-C inside the
    block is held until the file is in place (:func:`interrupts_deferred`). ``fsync=False``: no
    flush to the disk before the rename (see the module's note).
    """
    with interrupts_deferred():
        with _atomic_write(path, mode, fsync) as fh:
            yield fh


@contextlib.contextmanager
def _atomic_write(path: PathLike, mode: str, fsync: bool = True) -> Iterator[IO]:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            if fsync:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_torch_save(obj: object, path: PathLike, fsync: bool = True) -> None:
    """``torch.save`` through :func:`atomic_write` (``fsync``: as there)."""
    with atomic_write(path, "wb", fsync) as fh:
        torch.save(obj, fh)


def file_slug(text: str, default: str = "query", max_len: Optional[int] = 80, keep: str = "") -> str:
    """``text`` as a file-name part: every character that is not a letter, a digit or in ``keep``
    becomes '_', leading/trailing '_' dropped, at most ``max_len`` characters (None: no limit);
    ``default`` when nothing is left. The one slug rule of every file tiger names after a text."""
    return "".join(c if c.isalnum() or c in keep else "_" for c in text).strip("_")[:max_len] or default


def unique_file_slugs(texts: Sequence[str], defaults: Optional[Sequence[str]] = None, **slug: Any) -> list[str]:
    """:func:`file_slug` of each text (``defaults[i]`` when the i-th leaves nothing), a repeat
    made unique by ``_2``, ``_3``, ... in order; ``slug``: file_slug's ``max_len`` / ``keep``."""
    out: list[str] = []
    for i, text in enumerate(texts):
        stem = file_slug(text, **({} if defaults is None else {"default": defaults[i]}), **slug)
        base, k = stem, 2
        while stem in out:
            stem, k = f"{base}_{k}", k + 1
        out.append(stem)
    return out
