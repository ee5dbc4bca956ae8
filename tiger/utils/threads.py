"""Work spread over a few host threads: the one ordered thread map of the package."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Callable, Iterable, Optional, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def thread_map(fn: Callable[[T], R], items: Iterable[T], max_workers: int, name: str = "tiger",
               on_done: Optional[Callable[[], None]] = None) -> list[R]:
    """``[fn(x) for x in items]`` on up to ``max_workers`` threads named ``name``, results in the
    items' order whatever order the threads finish in. For work that releases the GIL (file
    reads and decoding, host copies, numpy). ``on_done()`` is called in the caller's thread after
    each item (e.g. a progress bar's update). With one item or one worker everything runs in
    the caller's thread. The first error raised by ``fn`` is raised here."""
    items = list(items)
    workers = max(1, min(max_workers, len(items)))
    out: list = [None] * len(items)
    if workers == 1:
        for i, x in enumerate(items):
            out[i] = fn(x)
            if on_done is not None:
                on_done()
        return out
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name) as pool:
        jobs = {pool.submit(fn, x): i for i, x in enumerate(items)}
        for job in as_completed(jobs):
            out[jobs[job]] = job.result()
            if on_done is not None:
                on_done()
    return out


__all__ = ["thread_map"]
