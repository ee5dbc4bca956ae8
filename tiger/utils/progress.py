"""Progress bars that suit where the output goes: ``tqdm.auto`` on a terminal or in a notebook,
plain lines (no carriage returns, at most one every ``LOG_INTERVAL_S`` seconds, plus the last)
when stderr is a file or a pipe, so logs of long runs stay readable.

Every stage's progress goes through :func:`progress`::

    for view in progress(views, "rendering"):
        ...
    with progress(total=steps, desc="training") as bar:
        bar.update(1)
"""
from __future__ import annotations

import io
import sys
from typing import Any, Iterable, Optional, TextIO, Union

#: Seconds between two plain progress lines when the output is not a terminal.
LOG_INTERVAL_S = 30.0


class _LineWriter(io.TextIOBase):
    """A file for tqdm that turns its in-place updates ("\\r" + status) into one line per update."""

    def __init__(self, stream: TextIO) -> None:
        super().__init__()
        self.stream, self.last = stream, ""

    def write(self, text: str) -> int:
        for part in text.split("\r"):
            line = part.replace("\x1b[A", "").rstrip()
            if line and line != self.last:
                self.stream.write(line + "\n")
                self.last = line
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


def is_terminal(stream: Optional[TextIO] = None) -> bool:
    """Whether ``stream`` (default: stderr) is an interactive terminal."""
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress(iterable: Union[Iterable, int, None] = None, desc: str = "", *, total: Optional[int] = None,
             file: Optional[TextIO] = None, **kwargs: Any):
    """A ``tqdm.auto`` bar over ``iterable`` (or over ``total`` steps when given an int or None).

    On a terminal or in a notebook this is tqdm's own bar; otherwise the bar is written as plain
    lines, at most one every :data:`LOG_INTERVAL_S` seconds and the final one. Other keyword
    arguments go to tqdm (``disable``, ``unit``, ``initial``, ``leave``, ...).
    """
    from tqdm.auto import tqdm

    if isinstance(iterable, int) and not isinstance(iterable, bool):
        iterable, total = None, iterable
    stream = sys.stderr if file is None else file
    notebook = any(cls.__module__ == "tqdm.notebook" for cls in tqdm.__mro__)  # Jupyter widgets
    if not notebook and not is_terminal(stream):
        kwargs.setdefault("mininterval", LOG_INTERVAL_S)
        kwargs.setdefault("maxinterval", max(LOG_INTERVAL_S, kwargs["mininterval"]))
        kwargs["dynamic_ncols"] = False
        kwargs.setdefault("ncols", 100)
        kwargs.setdefault("ascii", True)
        stream = _LineWriter(stream)
    return tqdm(iterable, desc=desc, total=total, file=stream, **kwargs)
