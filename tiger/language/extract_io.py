"""How ``extract_features`` moves its per-image records: kept on the device between the two
passes when they fit, written to the disk in the background, read back only when they did not fit.

A stage-1 record holds an image's 512-d features compactly (mask id map, per-mask means, and the
features of pixels in no mask, float16). For an image with few SAM masks that is most of a
full-resolution 512-d map (a 1080x1920 image: up to 2 GB), so writing it and reading it back costs
more than the models. :class:`KeptRecords` keeps records in device memory (host memory on the CPU)
for the projection pass, as many as fit next to the per-image working set; :class:`BackgroundSaver`
copies records to the host and writes them on a worker thread while the device goes on computing.
"""
from __future__ import annotations

import logging
import os
import shutil
import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import torch

from tiger.utils.io import atomic_torch_save

logger = logging.getLogger(__name__)


def record_bytes(record: dict[str, Any]) -> int:
    """Bytes of the tensors of a record (one level of nesting)."""
    total = 0
    for value in record.values():
        values = value.values() if isinstance(value, dict) else (value,)
        total += sum(v.numel() * v.element_size() for v in values if torch.is_tensor(v))
    return total


def _to_host(record: dict[str, Any]) -> dict[str, Any]:
    return {k: ({kk: vv.cpu() if torch.is_tensor(vv) else vv for kk, vv in v.items()} if isinstance(v, dict)
                else v.cpu() if torch.is_tensor(v) else v) for k, v in record.items()}


def load_mapped(path: Path) -> dict[str, Any] | None:
    """``torch.load`` of ``path`` memory-mapped (tensors are read only when touched), None when the
    file is missing or unreadable (a torn or foreign file is recomputed, never trusted)."""
    if not path.is_file():
        return None
    try:
        return torch.load(str(path), map_location="cpu", weights_only=True, mmap=True)
    except Exception as exc:  # noqa: BLE001
        logger.warning("ignoring unreadable file %s (%s)", path, exc)
        return None


class BackgroundSaver:
    """Atomic ``torch.save`` of records on worker threads: the device-to-host copy (on a side CUDA
    stream, after the work that produced the record) and the write overlap the computation.

    ``save(record, path, fsync=..., optional=False)`` queues a write and waits while
    ``max_pending`` required writes are unfinished (bounded host memory). An ``optional`` write
    (a record that stays in memory anyway; written so that a kill does not lose it) never waits,
    and is dropped if it has not started when a required write is queued or :meth:`drop_optional`
    is called: a slow disk never holds up the computation for a write that only guards against an
    interruption. An error of a write is raised by a later :meth:`save` or by :meth:`close`, which
    waits for every queued write.
    """

    def __init__(self, device: torch.device, max_pending: int = 2, workers: int = 2) -> None:
        self.device = device
        self.max_pending = max(1, max_pending)
        self._pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="tiger-features-save")
        self._required: deque[Future] = deque()
        self._optional: list[tuple[Future, Path]] = []
        self._local = threading.local()
        self.dropped: list[Path] = []

    def save(self, record: dict[str, Any], path: Path, *, fsync: bool, optional: bool = False) -> None:
        if not optional:
            self.drop_optional()
            while self._required and (self._required[0].done() or len(self._required) >= self.max_pending):
                self._required.popleft().result()
        event = None
        if self.device.type == "cuda":
            event = torch.cuda.Event()
            event.record(torch.cuda.current_stream(self.device))
        future = self._pool.submit(self._write, record, Path(path), fsync, event)
        if optional:
            self._optional.append((future, Path(path)))
        else:
            self._required.append(future)

    def drop_optional(self) -> None:
        """Cancel the optional writes that have not started (their paths go to ``dropped``)."""
        still = []
        for future, path in self._optional:
            if future.cancel():
                self.dropped.append(path)
            elif not future.done():
                still.append((future, path))
            else:
                future.result()
        self._optional = still

    def _write(self, record: dict[str, Any], path: Path, fsync: bool, event: Any) -> None:
        if event is None:
            host = _to_host(record)
        else:  # the copy waits for the producing kernels on this thread's own stream only
            stream = getattr(self._local, "stream", None)
            if stream is None:
                stream = self._local.stream = torch.cuda.Stream(self.device)
            with torch.cuda.stream(stream):
                stream.wait_event(event)
                host = _to_host(record)
        atomic_torch_save(host, path, fsync=fsync)

    def close(self, raise_errors: bool = True) -> None:
        """Wait for every queued write (the first error raised unless ``raise_errors`` is False)."""
        try:
            for future in [f for f, _ in self._optional] + list(self._required):
                if raise_errors:
                    future.result()
                else:
                    future.exception()
        finally:
            self._optional, self._required = [], deque()
            self._pool.shutdown(wait=True)


class KeptRecords:
    """Stage-1 records held in memory until the projection pass, as many as fit.

    On CUDA a record is kept while the device's free memory (the caching allocator's spare blocks
    included) stays above the largest per-image working set seen plus 5 % of the device, and the
    kept records stay under a quarter of the device (another process on the GPU, say the
    reconstruction that `tiger prepare` runs alongside, grows after this check); on the CPU
    while the kept records stay under ``budget`` bytes (default a quarter of the physical memory).
    ``budget=0`` keeps nothing (every record goes through the disk); a positive ``budget`` caps the
    kept bytes on any device.
    """

    def __init__(self, device: torch.device, budget: int | None = None) -> None:
        self.device = device
        self.budget = budget
        self.records: dict[str, dict[str, Any]] = {}
        self.kept_bytes = 0
        self._working = 0
        self._base = 0
        if budget is None and device.type == "cuda":
            self.budget = torch.cuda.get_device_properties(device).total_memory // 4
        elif budget is None:
            try:
                self.budget = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 4
            except (ValueError, OSError, AttributeError):
                self.budget = 1 << 30

    def start_image(self) -> None:
        """Call before an image's work: its peak memory is measured from here (CUDA)."""
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
            self._base = torch.cuda.memory_allocated(self.device)

    def offer(self, name: str, record: dict[str, Any]) -> bool:
        """Keep ``record`` (its tensors on ``device``) if it fits; True when kept."""
        size = record_bytes(record)
        if self.device.type == "cuda":
            self._working = max(self._working, torch.cuda.max_memory_allocated(self.device) - self._base)
            free, total = torch.cuda.mem_get_info(self.device)
            spare = free + torch.cuda.memory_reserved(self.device) - torch.cuda.memory_allocated(self.device)
            fits = spare >= self._working + total // 20
        else:
            fits = True
        if self.budget is not None:
            fits = fits and self.kept_bytes + size <= self.budget
        if fits:
            self.records[name] = record
            self.kept_bytes += size
        return fits

    def pop(self, name: str) -> dict[str, Any] | None:
        record = self.records.pop(name, None)
        if record is not None:
            self.kept_bytes -= record_bytes(record)
        return record


class DiskBudget:
    """Where stage-1 records may go on the disk: a write must leave 1 GiB and 5 % of the disk free
    beyond ``reserve`` bytes (the maps still to come), and the records written by this run stay
    under a tenth of the disk (a thin-provisioned disk may report more free space than it can
    hold). A record refused here is recomputed for the projection instead (at most a few seconds
    an image; reading 2 GB back costs as much)."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.written = 0

    def room(self, nbytes: int, reserve: int = 0) -> bool:
        probe = self.folder
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        usage = shutil.disk_usage(probe)
        return (usage.free - nbytes - reserve >= max(1 << 30, usage.total // 20)
                and self.written + nbytes <= usage.total // 10)

    def add(self, nbytes: int) -> None:
        self.written += nbytes
