"""Side CUDA streams (one per device and priority) and work that runs beside the caller's on one,
driven by a worker thread (:func:`run_beside`)."""
from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, TypeVar

import torch

T = TypeVar("T")

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_streams: dict[tuple[torch.device, bool], torch.cuda.Stream] = {}


def _worker() -> ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tiger-beside")
        return _pool


def side_stream(device: torch.device | str, high_priority: bool = False) -> torch.cuda.Stream:
    """The process's side stream of ``device`` (a CUDA device) at default or high priority, made once.

    High-priority streams come from a pool of their own in torch, so that stream is never one of
    the default-priority streams made elsewhere (e.g. the streams CUDA graphs are captured on,
    :func:`tiger.edit.guidance.cuda_graph.capture_stream`)."""
    dev = torch.device(device)
    if dev.index is None:
        dev = torch.device("cuda", torch.cuda.current_device())
    key = (dev, bool(high_priority))
    with _lock:
        if key not in _streams:
            _streams[key] = torch.cuda.Stream(dev, priority=-1 if high_priority else 0)
        return _streams[key]


def run_beside(fn: Callable[[], T], device: torch.device | str, inputs: tuple[torch.Tensor, ...] = (),
               after: "torch.cuda.Event | None" = None) -> Callable[[], T]:
    """Start ``fn()`` beside the caller's work and return a function that waits for its result.

    On CUDA ``fn`` runs in a worker thread on a side stream of ``device`` (after everything queued
    on the caller's stream so far, so it may read ``inputs`` and anything else already computed;
    or, given ``after``, only after that event: for work that reads nothing the caller queued
    since, so that it can run while the caller's queued kernels do),
    so the GPU can overlap it with kernels that the caller launches meanwhile, e.g. SAM's masks
    while the implicit FeatUp fit replays its small steps. The returned function joins the thread
    and makes the caller's stream wait for the side stream; tensors in the result may then be used
    on the caller's stream. ``fn`` must not draw random numbers (the caller's generator state is
    not its own) and its tensors must not be captured by a CUDA graph of the caller (a graph
    captured meanwhile must use ``capture_error_mode="thread_local"``). Anywhere else (CPU) ``fn``
    runs when the result is asked for, in the caller's thread, as a plain call would.
    Grad mode is off inside ``fn``.
    """
    dev = torch.device(device)
    if dev.type != "cuda":
        def later() -> T:
            with torch.no_grad():
                return fn()
        return later
    if dev.index is None:
        dev = torch.device("cuda", torch.cuda.current_device())
    main = torch.cuda.current_stream(dev)
    side = side_stream(dev)
    if after is None:
        side.wait_stream(main)
    else:
        side.wait_event(after)
    for t in inputs:  # their memory must not be reused before the side stream is done with them
        t.record_stream(side)

    def work() -> T:
        with torch.no_grad(), torch.cuda.device(dev), torch.cuda.stream(side):
            return fn()

    future: Future = _worker().submit(work)

    def result() -> T:
        out = future.result()
        main.wait_stream(side)
        for t in _tensors(out):
            t.record_stream(main)
        return out

    return result


def _tensors(obj) -> list[torch.Tensor]:
    if torch.is_tensor(obj):
        return [obj]
    if isinstance(obj, (list, tuple)):
        return [t for o in obj for t in _tensors(o)]
    if isinstance(obj, dict):
        return [t for o in obj.values() for t in _tensors(o)]
    return []
