"""Renders of frozen geometry with new per-Gaussian channels each step.

Training the language field (and lifting onto it) renders the same Gaussians from the same views
again and again; only the channels they carry change. The projection and the tile lists of a
view depend on the geometry alone, so :class:`FrozenViews` computes them once per view and every
later render runs only the compositing kernel (and, under autograd, its features-only backward):
no projection, no binning, no host synchronisation per step.

A render may cover a band of whole tile rows (``rows``): its tiles are a contiguous run of the
view's row-major tile lists, so the band is composited from a slice of ``tile_offsets`` into the
view's own ``gaussian_ids`` (no copy), with the 2D means moved up by the band's first pixel row.
Every pixel of the band is the full render's pixel (up to float32 rounding of that shift).
"""
from __future__ import annotations

import logging
from typing import NamedTuple, Optional, Sequence

import torch

from tiger.ops.raster import rasterize
from tiger.render import Camera
from tiger.render.rasterize import Projection, RasterSettings, bin_projection, project_for_raster
from tiger.scene import GaussianScene

log = logging.getLogger(__name__)
#: Device memory kept free when deciding whether one more view's tile lists are cached (bytes;
#: also at least an eighth of the device): the renders and their backward need room.
CACHE_RESERVE_BYTES = 2 << 30


class _Cached(NamedTuple):
    projection: Projection  # its features are a zero [N, 1] column: each render passes the embeddings
    tile_offsets: torch.Tensor
    gaussian_ids: torch.Tensor


class FrozenViews:
    """Each view's projection and tile lists, computed once, for renders of changing channels.

    Args:
        scene: the Gaussians [N]; only geometry and opacity are read (detached here).
        cameras: V views, each at the size it is rendered at.
        settings: the rasterizer's settings (``check_finite`` is ignored: inputs are checked once).
    """

    def __init__(self, scene: GaussianScene, cameras: Sequence[Camera],
                 settings: RasterSettings = RasterSettings(check_finite=False)) -> None:
        frozen = scene.detach()
        self.cameras = [c.to(device=frozen.device, dtype=frozen.dtype) for c in cameras]
        self.settings = settings
        self._geometry = (frozen.means, frozen.quats, frozen.scales, frozen.opacities)
        self._no_features = frozen.means.new_zeros((len(frozen), 1))
        self.count = len(frozen)  # N
        self._cache: dict[int, _Cached] = {}
        self._full = False  # the device ran short: views not cached yet are binned per render
        self.tile_size = int(settings.tile_size)

    def __len__(self) -> int:
        return len(self.cameras)

    def tile_rows(self, v: int) -> int:
        """Rows of tiles of view ``v``."""
        return -(-self.cameras[v].height // self.tile_size)

    def _prepare(self, v: int) -> _Cached:
        if v in self._cache:
            return self._cache[v]
        cam = self.cameras[v]
        with torch.no_grad():
            p = project_for_raster(*self._geometry, self._no_features, cam.viewmat, cam.K, cam.width, cam.height,
                                   settings=self.settings)
            offsets, ids = bin_projection(p, cam.width, cam.height, self.settings)
        entry = _Cached(p, offsets, ids)
        if not self._full and self._room(entry):
            self._cache[v] = entry
        return entry

    def _room(self, entry: _Cached) -> bool:
        if entry.gaussian_ids.device.type != "cuda":
            return True
        free, total = torch.cuda.mem_get_info(entry.gaussian_ids.device)
        if free > max(CACHE_RESERVE_BYTES, total // 8):
            return True
        self._full = True
        log.info("frozen views: device memory is short; the tile lists of %d of %d views are cached, the "
                 "others are binned again at every render", len(self._cache), len(self))
        return False

    def radii(self, v: int) -> torch.Tensor:
        """[N] int32 screen radius of every Gaussian in view ``v`` (0: culled)."""
        return self._prepare(v).projection.radii.amax(dim=1)

    def render(self, v: int, channels: torch.Tensor,
               rows: Optional[tuple[int, int]] = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(color [h, W, C], alpha [h, W]) of ``channels`` [N, C] seen from view ``v``.

        Args:
            channels: per-Gaussian channels (differentiable: the features-only backward).
            rows: ``(first, stop)`` tile rows: only pixel rows ``first * tile_size`` up to
                ``min(stop * tile_size, H)`` are rendered (``h`` of them); None: the whole view.
        """
        p, offsets, ids = self._prepare(v)
        cam, ts = self.cameras[v], self.tile_size
        means2d, height = p.means2d, cam.height
        if rows is not None:
            first, stop = int(rows[0]), int(rows[1])
            if not 0 <= first < stop <= self.tile_rows(v):
                raise ValueError(f"tiger.FrozenViews: tile rows {first}..{stop} outside view {v}'s "
                                 f"{self.tile_rows(v)}")
            tiles_x = -(-cam.width // ts)
            offsets = offsets[first * tiles_x: stop * tiles_x + 1]
            height = min(stop * ts, cam.height) - first * ts
            if first:
                means2d = means2d - means2d.new_tensor([0.0, float(first * ts)])
        s = self.settings
        color, alpha, _, _, _ = rasterize(means2d, p.conics, p.opacities, channels.contiguous(), p.depths,
                                          None, offsets, ids, cam.width, height, ts, s.alpha_max,
                                          s.alpha_threshold, s.t_min, s.kernels)
        return color, alpha


__all__ = ["FrozenViews"]
