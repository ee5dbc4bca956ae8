"""The progress bar of every loop: :func:`tiger.utils.progress.progress` (tqdm on a terminal or in a
notebook, plain lines otherwise) over a step count."""
from __future__ import annotations

from typing import Any

import torch

from tiger.utils.progress import progress


def progress_bar(total: int, desc: str, initial: int = 0, enabled: bool = True, **kw: Any):
    """A bar over ``total`` steps starting at ``initial`` (a resumed run), or a disabled one;
    extra keywords go to tqdm (e.g. ``unit``)."""
    return progress(total, desc, initial=min(initial, total), disable=not enabled, **kw)


class LaggedScalars:
    """Named scalars (0-d device tensors or numbers) read back without waiting for the device.

    :meth:`push` starts a copy of the values to host memory (pinned, asynchronous on CUDA) and
    :meth:`latest` returns the newest pushed values whose copy has finished: a progress display a
    few steps behind instead of a host synchronisation at every update. CPU values are ready at once.
    """

    def __init__(self) -> None:
        self._pending: list[tuple[dict[str, float], list[str], torch.Tensor, torch.cuda.Event]] = []
        self._latest: dict[str, float] = {}

    def push(self, values: dict[str, Any]) -> None:
        numbers = {k: float(v) for k, v in values.items() if not torch.is_tensor(v)}
        on_gpu = {k: v for k, v in values.items() if torch.is_tensor(v) and v.is_cuda}
        numbers.update({k: float(v) for k, v in values.items() if torch.is_tensor(v) and not v.is_cuda})
        if not on_gpu:
            self._latest = numbers
            self._pending.clear()
            return
        stacked = torch.stack([v.detach().reshape(()).float() for v in on_gpu.values()])
        host = torch.empty(stacked.shape, dtype=stacked.dtype, pin_memory=True)
        host.copy_(stacked, non_blocking=True)
        done = torch.cuda.Event()
        done.record()
        self._pending.append((numbers, list(on_gpu), host, done))

    def latest(self, wait: bool = False) -> dict[str, float]:
        """The newest values whose copy has finished (``wait``: the last pushed, waiting for it)."""
        while self._pending and (wait or self._pending[0][3].query()):
            numbers, names, host, done = self._pending.pop(0)
            done.synchronize()  # returns at once unless waiting
            self._latest = {**numbers, **dict(zip(names, host.tolist()))}
        return dict(self._latest)


__all__ = ["LaggedScalars", "progress_bar"]
