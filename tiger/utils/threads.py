"""Work on host threads: the one ordered thread map of the package, and one job in the background."""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import nullcontext
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


def in_background(fn: Callable[[], T], name: str = "tiger-background") -> Callable[[], T]:
    """Start ``fn()`` in a daemon thread now and return a function that waits for its result (and
    raises its error). For host-bound work to overlap with the caller's: reading and building
    models while a scene loads, encoding a video while metrics render. ``fn`` runs with the
    caller's grad mode and on the caller's current CUDA stream (the same stream, so tensors pass
    between the threads without stream bookkeeping; GPU work of the two is not overlapped). A
    daemon thread: an error in the caller ends the process without waiting for it."""
    import torch

    grad = torch.is_grad_enabled()
    stream = torch.cuda.current_stream() if torch.cuda.is_available() and torch.cuda.is_initialized() else None
    box: dict = {}

    def work() -> None:
        try:
            with torch.set_grad_enabled(grad), (torch.cuda.stream(stream) if stream is not None else nullcontext()):
                box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller by result()
            box["error"] = exc

    thread = threading.Thread(target=work, name=name, daemon=True)
    thread.start()

    def result() -> T:
        thread.join()
        if "error" in box:
            raise box["error"]
        return box["value"]

    return result


__all__ = ["in_background", "thread_map"]
