"""The per-view feature maps the language field trains on, read once and kept resident.

:class:`ResidentMaps` reads every view's map once (from a sequence, a callable or a
``FeatureSet`` on disk) and keeps it where a training step can take it without touching the disk:
on the training device when all maps fit in its free memory, otherwise in pinned host memory,
copied to the device asynchronously on a side stream one step ahead (:meth:`prefetch`). Maps
keep their stored dtype (float16 from ``tiger features``); the loss reads them in float32. On CUDA
the maps are copied over on :data:`READ_THREADS` threads.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Optional, Protocol, Sequence, Union

import torch

from tiger.render import Camera
from tiger.utils.threads import thread_map

log = logging.getLogger(__name__)
#: One view's target: features [H, W, D], (features, valid [H, W]) or {"features", "valid"}.
FeatureMap = Union[torch.Tensor, tuple[torch.Tensor, Optional[torch.Tensor]], Mapping[str, torch.Tensor]]
#: Device memory left free beside the maps when deciding whether they fit (bytes; also at least
#: a quarter of the device): the render, its backward and the allocator's slack need room.
DEVICE_RESERVE_BYTES = 4 << 30
PLACEMENTS = ("auto", "device", "host")


class FeatureStore(Protocol):
    """Feature maps on disk by image name (``tiger.language.FeatureSet``)."""

    names: Sequence[str]

    def load(self, name: str) -> FeatureMap: ...


FeatureSource = Union[Sequence[FeatureMap], Callable[[int], FeatureMap], FeatureStore]


def as_map(item: FeatureMap, index: int) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """(features [H, W, D], valid [H, W] bool or None) from a tensor, a pair or a dict."""
    if isinstance(item, dict):
        feats, valid = item.get("features"), item.get("valid", item.get("mask"))
    elif isinstance(item, (tuple, list)) and len(item) == 2:
        feats, valid = item
    else:
        feats, valid = item, None
    if not torch.is_tensor(feats) or feats.dim() != 3:
        raise ValueError(f"tiger.train_field: feature map {index} must be [H, W, D], got "
                         f"{list(feats.shape) if torch.is_tensor(feats) else type(feats).__name__}")
    if valid is not None:
        valid = torch.as_tensor(valid)
        if valid.shape != feats.shape[:2]:
            raise ValueError(f"tiger.train_field: valid mask {index} is {list(valid.shape)}, its feature "
                             f"map is {list(feats.shape[:2])}")
        valid = valid.bool()
    return feats, valid


def map_loader(feature_maps: FeatureSource, cameras: Sequence[Camera]) -> Callable[[int], FeatureMap]:
    """index -> raw map item. Accepts a sequence, a callable, or a store with ``names``/``load(name)``
    (``tiger.language.FeatureSet``), matched to cameras by image name (or its stem)."""
    n = len(cameras)
    if hasattr(feature_maps, "load") and hasattr(feature_maps, "names"):
        names = list(feature_maps.names)
        by_name = {nm: nm for nm in names}
        by_name.update({Path(nm).stem: nm for nm in names})
        chosen = []
        for i, cam in enumerate(cameras):
            img = cam.image_name
            key = img if img in by_name else Path(img).stem if Path(img).stem in by_name else None
            if key is None:
                if len(names) != n:
                    raise ValueError(f"tiger.train_field: camera {i} ('{img}') has no feature map among "
                                     f"{len(names)} names, and the counts differ ({n} cameras)")
                chosen.append(names[i])
            else:
                chosen.append(by_name[key])
        return lambda i: feature_maps.load(chosen[i])
    if callable(feature_maps):
        return feature_maps
    if len(feature_maps) != n:
        raise ValueError(f"tiger.train_field: {len(feature_maps)} feature maps for {n} cameras")
    return lambda i: feature_maps[i]


@dataclass
class ViewMap:
    """One view's target on the device: features [H, W, D], valid [H, W] bool or None, and the
    number of valid pixels (counted once on the host)."""

    features: torch.Tensor
    valid: Optional[torch.Tensor]
    n_valid: int


def pooled(m: ViewMap, factor: int) -> ViewMap:
    """``m`` averaged over ``factor`` x ``factor`` blocks (rows and columns past the last whole
    block dropped): the mean of each block's valid pixels, valid where at least half of the
    block is; features keep their dtype, the valid pixels are counted here (one read-back)."""
    f = m.features
    h, w = f.shape[0] // factor, f.shape[1] // factor
    f = f[:h * factor, :w * factor]
    valid = None if m.valid is None else m.valid[:h * factor, :w * factor]
    x = f.float() if valid is None else f.float() * valid.unsqueeze(-1)
    feats = torch.nn.functional.avg_pool2d(x.permute(2, 0, 1).unsqueeze(0), factor)[0].permute(1, 2, 0)
    if valid is None:
        return ViewMap(feats.to(f.dtype).contiguous(), None, h * w)
    share = torch.nn.functional.avg_pool2d(valid[None, None].float(), factor)[0, 0]
    feats = feats / share.clamp_min(1.0 / factor ** 2).unsqueeze(-1)
    keep = share >= 0.5
    return ViewMap(feats.to(f.dtype).contiguous(), keep, int(keep.sum()))


#: Threads that copy the maps to the GPU at once, each through its own pinned buffer (a 1080p
#: 64-d float16 map is 265 MB); a memory-mapped source (``FeatureSet.load``) is read by these
#: threads. Eager loads one file after another took 12.3 s of the fox's 50 maps inside
#: ``tiger prepare`` on the H100 machine, the embed stage's largest part.
READ_THREADS = 8


def _to_device(t: torch.Tensor, device: torch.device) -> torch.Tensor:
    """``t`` on ``device`` through a pinned copy: the (possibly memory-mapped) bytes are read by the
    calling thread and the transfer is asynchronous on the current stream, so threads overlap."""
    staged = torch.empty(t.shape, dtype=t.dtype, pin_memory=True)
    staged.copy_(t)
    return staged.to(device, non_blocking=True)  # the pinned block is reused once the copy is done


class ResidentMaps:
    """Every view's map read once (module docstring).

    Args:
        load: index -> map item (:func:`map_loader`); called once per view here, never again.
        count: V, the number of views.
        dim: D the maps must have (None: the first map's).
        device: the training device.
        placement: ``"device"``, ``"host"`` (pinned, streamed, on CUDA) or ``"auto"`` (device when
            the maps fit beside :data:`DEVICE_RESERVE_BYTES`, else host).
    """

    def __init__(self, load: Callable[[int], FeatureMap], count: int, dim: Optional[int], device: torch.device,
                 placement: str = "auto") -> None:
        if placement not in PLACEMENTS:
            raise ValueError(f"tiger.train_field: map_placement must be one of {PLACEMENTS}, got {placement!r}")
        self.device = torch.device(device)
        self._host: list[tuple[torch.Tensor, Optional[torch.Tensor]]] = []
        self.n_valid: list[int] = []
        self._valid_rows: list[torch.Tensor] = []
        for i in range(count):
            feats, valid = as_map(load(i), i)
            dim = dim or int(feats.shape[2])
            if feats.shape[2] != dim:
                raise ValueError(f"tiger.train_field: feature map {i} has {feats.shape[2]} channels, L has {dim}")
            if not feats.is_floating_point():
                feats = feats.float()
            per_row = (valid.sum(1) if valid is not None
                       else torch.full((feats.shape[0],), feats.shape[1])).to("cpu", torch.int64)
            self._valid_rows.append(torch.cat([per_row.new_zeros(1), per_row.cumsum(0)]))
            self.n_valid.append(int(self._valid_rows[-1][-1]))
            self._host.append((feats, valid))
        self.dim = int(dim)
        self.sizes = [(int(f.shape[0]), int(f.shape[1])) for f, _ in self._host]
        self.bytes = sum(f.numel() * f.element_size() + (v.numel() if v is not None else 0) for f, v in self._host)
        self.on_device = self._decide(placement)
        self._stream = None
        self._inflight: dict[int, tuple[ViewMap, torch.cuda.Event]] = {}
        if self.device.type == "cuda":  # on the device, or pinned for streaming (CPU: the maps as read)
            move = (lambda t: _to_device(t, self.device)) if self.on_device else torch.Tensor.pin_memory
            self._host = thread_map(lambda fv: tuple(None if t is None else move(t) for t in fv), self._host,
                                    READ_THREADS, "tiger-maps")
        if self.on_device:
            self._maps = [ViewMap(f, v, n) for (f, v), n in zip(self._host, self.n_valid)]
            self._host = []
        elif self.device.type == "cuda":
            self._stream = torch.cuda.Stream(self.device)
        log.info("train_field: %d feature maps, %.2f GB, %s", count, self.bytes / 1e9,
                 "on the device" if self.on_device else
                 "in pinned host memory, streamed" if self._stream is not None else "in host memory")

    def _decide(self, placement: str) -> bool:
        if self.device.type != "cuda" or placement == "host":
            return self.device.type != "cuda"  # CPU training: host memory is the device
        if placement == "device":
            return True
        free, total = torch.cuda.mem_get_info(self.device)
        return self.bytes <= free - max(DEVICE_RESERVE_BYTES, total // 4)

    def __len__(self) -> int:
        return len(self.sizes)

    def valid_rows(self, i: int) -> torch.Tensor:
        """[H + 1] int64 on the host: valid pixels of view ``i`` above each row (so rows a..b
        hold ``valid_rows[b] - valid_rows[a]``), counted once when the map was read."""
        return self._valid_rows[i]

    def _copy(self, i: int) -> ViewMap:
        f, v = self._host[i]
        return ViewMap(f.to(self.device, non_blocking=True),
                       None if v is None else v.to(self.device, non_blocking=True), self.n_valid[i])

    def prefetch(self, views: Sequence[int]) -> None:
        """Start copying ``views``' maps to the device on the side stream (streamed maps only)."""
        if self._stream is None:
            return
        for i in views:
            if i in self._inflight:
                continue
            with torch.cuda.stream(self._stream):
                m = self._copy(i)
                ev = torch.cuda.Event()
                ev.record(self._stream)
            self._inflight[i] = (m, ev)

    def get(self, i: int) -> ViewMap:
        """View ``i``'s map on the training device (waits for its prefetch, if any)."""
        if self.on_device:
            return self._maps[i]
        if self._stream is None:  # CPU training
            f, v = self._host[i]
            return ViewMap(f, v, self.n_valid[i])
        if i in self._inflight:
            m, ev = self._inflight.pop(i)
            torch.cuda.current_stream(self.device).wait_event(ev)
            for t in (m.features, m.valid):  # used on the compute stream: not freed under it
                if t is not None:
                    t.record_stream(torch.cuda.current_stream(self.device))
            return m
        return self._copy(i)


__all__ = ["FeatureMap", "FeatureSource", "FeatureStore", "ResidentMaps", "ViewMap", "as_map", "map_loader",
           "pooled"]
