"""The progress bar of every loop: :func:`tiger.utils.progress.progress` (tqdm on a terminal or in a
notebook, plain lines otherwise) over a step count."""
from __future__ import annotations

from typing import Any

from tiger.utils.progress import progress


def progress_bar(total: int, desc: str, initial: int = 0, enabled: bool = True, **kw: Any):
    """A bar over ``total`` steps starting at ``initial`` (a resumed run), or a disabled one;
    extra keywords go to tqdm (e.g. ``unit``)."""
    return progress(total, desc, initial=min(initial, total), disable=not enabled, **kw)


__all__ = ["progress_bar"]
