"""Replay a whole guidance step as one CUDA graph.

A guidance step (VAE encode, UNet passes, VAE backward) launches thousands of small kernels;
at the sizes used here the launches, not the arithmetic, bound the UNet passes. The step's
inputs are all tensors of fixed shape (renders, condition latents, noise, timesteps drawn by the
caller), so it can be captured once per input signature and replayed.
"""
from __future__ import annotations

import logging
import threading
import weakref
from typing import Callable, Sequence

import torch

logger = logging.getLogger(__name__)

StepFn = Callable[..., torch.Tensor]

_LOCK = threading.Lock()  # the registries below: the loop's thread and the pool's worker both capture
_POOLS: dict[tuple, object] = {}
_POOL_GRAPHS: "dict[tuple, weakref.WeakSet[torch.cuda.CUDAGraph]]" = {}


def capturing(t: torch.Tensor) -> bool:
    """Whether ``t``'s work would be recorded into a CUDA graph now (a CUDA tensor while the current
    stream captures): what a memo must not keep across the capture boundary."""
    return t.is_cuda and torch.cuda.is_current_stream_capturing()


def _stream_key(stream: "torch.cuda.Stream") -> tuple:
    return (stream.device_index, stream.stream_id)


def shared_graph_pool(stream: "torch.cuda.Stream | None" = None):
    """One CUDA-graph memory pool for the guidance steps replayed on ``stream`` (default: the
    current stream).

    Steps replayed on one stream run one after the other and each returns a copy of its output, so
    their intermediates can share memory: with both guidances graphed on one stream, the peak is
    the larger step's activations, not their sum (a graph's private pool is never released
    between replays). Steps on different streams may run at the same time (``CSDGuidance`` runs
    MVDream beside InstructPix2Pix), so each stream has its own pool.
    A pool lives only while a graph captured into it does: once every such graph is gone (the
    guidances of a finished edit were freed), the caching allocator has released the pool and
    capturing into its old handle fails an internal assertion, so a fresh handle is made."""
    key = _stream_key(torch.cuda.current_stream() if stream is None else stream)
    with _LOCK:
        graphs = _POOL_GRAPHS.setdefault(key, weakref.WeakSet())
        if key not in _POOLS or len(graphs) == 0:
            _POOLS[key] = torch.cuda.graph_pool_handle()
        return _POOLS[key]


_CAPTURE_STREAMS: dict[tuple, "torch.cuda.Stream"] = {}
_REPLAY_STREAMS: dict[tuple, int] = {}  # key -> raw handle of the replay streams seen


def capture_stream(replay_stream: "torch.cuda.Stream") -> "torch.cuda.Stream":
    """The stream on which the graphs replayed on ``replay_stream`` are warmed up and captured: one
    per replay stream, shared with no other replay stream.

    ``torch.cuda.graph`` captures on one process-wide stream by default, and a capture bakes in
    per-stream resources: cuBLAS's workspace is chosen by (handle, stream). Graphs captured on the
    same stream and replayed at the same time on different streams would share that workspace
    (wrong values, or a hang in the kernels that keep semaphores in it: both seen on an H100)."""
    key = _stream_key(replay_stream)
    with _LOCK:
        stream = _CAPTURE_STREAMS.get(key)
        if stream is None:
            _REPLAY_STREAMS[key] = replay_stream.cuda_stream
            taken = {s.cuda_stream for s in _CAPTURE_STREAMS.values()} | set(_REPLAY_STREAMS.values())
            for _ in range(256):  # torch hands out streams from a round-robin pool: skip ones in use
                stream = torch.cuda.Stream(device=replay_stream.device)
                if stream.cuda_stream not in taken:
                    break
            else:
                raise RuntimeError("tiger.edit: no free CUDA stream for graph capture")
            _CAPTURE_STREAMS[key] = stream
        return stream


class GraphedStep:
    """``fn(*tensors) -> tensor`` replayed from a CUDA graph captured per input signature.

    The first call with a new signature runs ``warmup`` eager calls on the replay stream's own
    capture stream (:func:`capture_stream`; cuDNN autotuning, lazy initialisation, torch.compile
    happen there), then captures on it. Later calls copy
    the inputs into the captured buffers and replay. ``fn`` must be free of host synchronisation
    (no ``.item()``, no data-dependent Python branches) and draw no random numbers itself.
    Returns a fresh tensor (a copy of the graph's output buffer). ``share_pool``: capture into the
    pool shared by all guidance steps replayed on the same stream (:func:`shared_graph_pool`).
    A graph is captured per input signature and per stream it is replayed on, so a step called on
    another stream never shares memory with the steps of the stream it was first captured for.
    Captures are "thread_local" (``torch.cuda.graph``'s ``capture_error_mode``): the edit loop's
    view-pool worker (:func:`tiger.utils.streams.run_beside`) captures InstructPix2Pix's condition
    encode while the loop's thread synchronises on its own stream, and the loop's thread captures
    the guidance steps while the worker runs; only the capturing thread's unsafe calls are errors.
    """

    def __init__(self, fn: StepFn, warmup: int = 3, share_pool: bool = True) -> None:
        self.fn = fn
        self.warmup = int(warmup)
        self.share_pool = share_pool
        self._graphs: dict[tuple, tuple[torch.cuda.CUDAGraph, list[torch.Tensor], torch.Tensor]] = {}

    @staticmethod
    def _signature(args: Sequence[torch.Tensor]) -> tuple:
        return (tuple((tuple(a.shape), a.dtype, a.device) for a in args),
                _stream_key(torch.cuda.current_stream(args[0].device)))

    def __call__(self, *args: torch.Tensor) -> torch.Tensor:
        if not all(isinstance(a, torch.Tensor) and a.is_cuda for a in args):
            raise ValueError("tiger.edit: GraphedStep takes CUDA tensors only")
        key = self._signature(args)
        entry = self._graphs.get(key)
        if entry is None:
            entry = self._capture(args)
            self._graphs[key] = entry
        graph, static_in, static_out = entry
        for dst, src in zip(static_in, args):
            dst.copy_(src)
        graph.replay()
        return static_out.clone()

    def _capture(self, args: Sequence[torch.Tensor]):
        static_in = [a.detach().clone() for a in args]
        replay_stream = torch.cuda.current_stream()
        cap = capture_stream(replay_stream)
        cap.wait_stream(replay_stream)
        with torch.cuda.stream(cap):
            for _ in range(self.warmup):
                self.fn(*static_in)
        replay_stream.wait_stream(cap)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=shared_graph_pool(replay_stream) if self.share_pool else None, stream=cap,
                              capture_error_mode="thread_local"):
            static_out = self.fn(*static_in)
        if self.share_pool:
            with _LOCK:
                _POOL_GRAPHS[_stream_key(replay_stream)].add(graph)
        logger.info("captured a CUDA graph for input shapes %s", [tuple(a.shape) for a in args])
        return graph, static_in, static_out

    def reset(self) -> None:
        """Forget the captured graphs (and free their memory pools)."""
        self._graphs.clear()
