"""Capturing a function in a CUDA graph the way capture requires: the one helper of the CUDA-graph tests."""
from __future__ import annotations

from typing import Callable, TypeVar

import torch

T = TypeVar("T")


def capture(fn: Callable[[], T], warmup: int = 1) -> tuple[torch.cuda.CUDAGraph, T]:
    """Run ``fn()`` ``warmup`` times on a side stream (lazy initialisations and the allocator's
    first blocks happen outside the capture), then capture one call of ``fn`` in a CUDA graph on
    the current device. Returns (graph, the captured call's outputs: static tensors that each
    ``graph.replay()`` overwrites)."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(warmup):
            fn()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = fn()
    return graph, out


__all__ = ["capture"]
