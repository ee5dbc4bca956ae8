"""The progress bar of every loop (tqdm.auto)."""
from __future__ import annotations

from typing import Any


def progress_bar(total: int, desc: str, initial: int = 0, enabled: bool = True, **kw: Any):
    """A ``tqdm.auto`` bar over ``total`` steps starting at ``initial`` (a resumed run), or a
    disabled one; extra keywords go to tqdm (e.g. ``unit``)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=min(initial, total), desc=desc, disable=not enabled, dynamic_ncols=True, **kw)


__all__ = ["progress_bar"]
