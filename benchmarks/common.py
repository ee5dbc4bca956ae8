"""Timing and table helpers shared by the benchmarks.

The scenes the rendering benchmarks draw live with the tests (:mod:`tests.render.standard_scenes`).
"""
from __future__ import annotations

import math
import time
from typing import Callable, Iterable, Optional

import torch
from torch import Tensor

# The rendering tests (tests/render/test_cuda.py, test_binning.py) still import these from here.
from tests.render.standard_scenes import heavy_tailed_scene, standard_camera, standard_scene  # noqa: F401


def _addmm_inplace_flops(self_shape, a_shape, b_shape, out_shape=None, **kwargs) -> int:
    return 2 * a_shape[0] * a_shape[1] * b_shape[1]


def count_flops(fn: Callable[[], object]) -> float:
    """FLOPs of one ``fn()`` call by ``torch.utils.flop_counter``, counting in-place ``addmm_``
    too (the fused transformer blocks accumulate their residual stream that way; torch's counter
    has no formula for it)."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False, custom_mapping={torch.ops.aten.addmm_: _addmm_inplace_flops}) as counter:
        fn()
    return float(counter.get_total_flops())


def cuda_kernel_names(fn: Callable[[], object], reps: int, warmup: int = 2) -> list[tuple[str, float]]:
    """(name, ms) of every CUDA kernel, memset and copy that ``reps`` calls of ``fn()`` ran, after
    ``warmup`` calls (torch.profiler; divide sums by ``reps`` for per-call figures)."""
    from torch.profiler import ProfilerActivity, profile

    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(reps):
            fn()
        torch.cuda.synchronize()
    return [(ev.name, ev.device_time / 1e3) for ev in prof.events()
            if ev.device_type == torch.autograd.DeviceType.CUDA]


def gpu_timeline(spans: Iterable[tuple[float, float, str]], min_gap: float = 0.0
                 ) -> tuple[float, list[tuple[float, float, str, str]]]:
    """The busy time of GPU activities ``(start, end, name)`` (the union of their intervals) and
    the idle gaps longer than ``min_gap`` between them, as ``(start, end, name of the activity that
    ended last before, name of the one after)``; same time unit as the spans."""
    busy, end, last = 0.0, -math.inf, ""
    gaps: list[tuple[float, float, str, str]] = []
    for a, b, name in sorted(spans):
        if end > -math.inf and a - end > min_gap:
            gaps.append((end, a, last, name))
        if b > end:
            busy += b - max(a, end)
            end, last = b, name
    return busy, gaps


def rel_err(a: Tensor, b: Tensor) -> float:
    """Norm-wise relative error ||a - b|| / ||b|| in float64."""
    a, b = a.detach().double(), b.detach().double().to(a.device)
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


def cuda_time_ms(fn: Callable[[], Optional[object]], iters: int = 20, warmup: int = 3,
                 setup: Optional[Callable[[], object]] = None) -> float:
    """Median wall time of ``fn`` in ms from CUDA events, after ``warmup`` calls.
    ``setup`` (untimed) runs before each call and its result is passed to ``fn``."""
    times = []
    for i in range(warmup + iters):
        arg = setup() if setup is not None else None
        torch.cuda.synchronize()
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn(arg) if setup is not None else fn()
        end.record()
        torch.cuda.synchronize()
        if i >= warmup:
            times.append(start.elapsed_time(end))
    times.sort()
    return times[len(times) // 2]


def cuda_graph_ms(fn: Callable[[], Optional[object]], calls: int = 1) -> float:
    """GPU ms per call of ``fn``: ``calls`` calls captured in one CUDA graph (after one eager call
    on the capture stream) and the graph's replays timed by :func:`cuda_time_ms` (as the guidance
    steps run: no host launch cost between the kernels)."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.stream(side):
        fn()
        with torch.cuda.graph(graph, stream=side):
            for _ in range(calls):
                fn()
    torch.cuda.current_stream().wait_stream(side)
    return cuda_time_ms(graph.replay) / calls


def cuda_copy_bandwidth(nbytes: int = 1 << 30) -> float:
    """Device copy bandwidth in bytes/s (bytes read plus written) of an ``nbytes`` buffer, the
    median of 10 copies (:func:`cuda_time_ms`)."""
    x = torch.empty(nbytes // 4, device="cuda")
    y = torch.empty_like(x)
    ms = cuda_time_ms(lambda: y.copy_(x), iters=10)
    del x, y
    return 2 * nbytes / (ms * 1e-3)


def cpu_time_ms(fn: Callable[..., object], iters: int = 3, warmup: int = 1,
                setup: Optional[Callable[[], object]] = None) -> float:
    """Median wall time of ``fn`` in ms (CPU). ``setup`` (untimed) runs before each call and
    its result is passed to ``fn``."""
    times = []
    for i in range(warmup + iters):
        arg = setup() if setup is not None else None
        t0 = time.perf_counter()
        fn(arg) if setup is not None else fn()
        if i >= warmup:
            times.append((time.perf_counter() - t0) * 1e3)
    times.sort()
    return times[len(times) // 2]


def table(rows: list[dict], cols: list[str]) -> str:
    """Plain-text table of ``rows`` (dicts) with the given column order."""
    cells = [[str(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(c), *(len(x[i]) for x in cells)) if cells else len(c) for i, c in enumerate(cols)]
    line = lambda xs: "  ".join(x.rjust(w) for x, w in zip(xs, widths))  # noqa: E731
    return "\n".join([line(cols), line(["-" * w for w in widths])] + [line(x) for x in cells])


def median_time(fn: Callable[..., object], repeats: int = 5, warmup: int = 1,
                cuda: bool = False, setup: Optional[Callable[[], object]] = None) -> float:
    """Median time of fn() in seconds (CUDA events when cuda=True, else wall clock); with
    ``setup``, fn(setup()) is timed and setup() is not."""
    if cuda:
        return cuda_time_ms(fn, iters=repeats, warmup=warmup, setup=setup) / 1e3
    return cpu_time_ms(fn, iters=repeats, warmup=warmup, setup=setup) / 1e3


def print_table(rows: list[dict], title: str = "") -> str:
    """Print (and return) ``rows`` as an aligned table; floats with 3 significant digits."""
    if not rows:
        return ""
    fmt = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)  # noqa: E731
    text = table([{k: fmt(v) for k, v in r.items()} for r in rows], list(rows[0].keys()))
    if title:
        text = title + "\n" + text
    print(text, flush=True)
    return text


def sync(device: torch.device) -> None:
    """Wait for ``device``'s queued work (CUDA); nothing on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], object], device: torch.device) -> tuple[object, float]:
    """(``fn()``'s result, its wall seconds) with the device's queue drained before and after."""
    sync(device)
    t = time.perf_counter()
    out = fn()
    sync(device)
    return out, time.perf_counter() - t
