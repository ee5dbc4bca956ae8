"""``tiger::bin_gaussians``: tile binning (public function, its kernel settings and fake kernel;
integer outputs, not differentiable; semantics in ``csrc/binning/binning.h``)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

__all__ = ["bin_gaussians", "BinningSettings"]

_PATHS = ("auto", "tiles", "global")


@dataclass(frozen=True)
class BinningSettings:
    """Kernel choices of the CUDA binning; every choice gives the same tile lists (the CPU kernel
    has one walk and only checks them). Defaults: the measured best on the H100
    (docs/BENCHMARKS.md), the same as the op schema's (``csrc/binning/binning_choices.h``).

    Attributes:
        path: ``"auto"`` (the per-tile sort for scenes of up to 2^18 Gaussians, the global sort
            beyond), ``"tiles"`` or ``"global"``.
        block_sort_keys: the longest tile list one block sorts in shared memory; longer lists
            are merged from sorted runs of this length (a power of two in [2, 4096]).
        warp_sort_keys: the longest tile list one warp sorts (in [1, 256]); longer ones by a block.
        giant_tiles: candidate tiles beyond which a Gaussian of the global-sort path is walked by
            a block instead of a warp (>= 1).
        _serial: test-only: every Gaussian walked by one thread (the former walk, for
            comparisons).
    """

    path: Literal["auto", "tiles", "global"] = "auto"
    block_sort_keys: int = 4096
    warp_sort_keys: int = 256
    giant_tiles: int = 512
    _serial: bool = False

    def op_args(self) -> tuple:
        """The op's trailing arguments, in schema order."""
        return (self.path, int(self.block_sort_keys), int(self.warp_sort_keys),
                int(self.giant_tiles), bool(self._serial))


_DEFAULT = BinningSettings()


def bin_gaussians(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor,
                  width: int, height: int, tile_size: int, alpha_threshold: float,
                  settings: BinningSettings = _DEFAULT, views: int = 1) -> tuple[Tensor, Tensor]:
    """Which Gaussians touch which tile, front to back (inputs from :func:`project_gaussians`).

    Args:
        means2d: [N, 2] px; conics: [N, 3]; opacities: [N]; depths: [N]; radii: [N, 2] int32
            (0 = culled); width, height: image size (px); tile_size: tile edge (px);
        alpha_threshold: a tile is kept only where the ellipse reaches o*G >= threshold.
        settings: the CUDA kernels' choices (:class:`BinningSettings`; the lists are the same).
        views: V images in one call (CPU and CUDA): the N Gaussians are V consecutive
            blocks of N / V, block v projected into image v (its own pixel coordinates); image
            v's tiles follow image v-1's and list only block v's Gaussians (the tile lists of
            ``rasterize(views=V)``; each image's lists are those of its block alone, ids offset
            by v * N / V).
    Returns:
        tile_offsets [views * tiles_y * tiles_x + 1] int64 (row-major tiles; tile t's list is
        ``gaussian_ids[tile_offsets[t]:tile_offsets[t + 1]]``), gaussian_ids [M] int32 sorted by
        (tile, depth, id).
    """
    return torch.ops.tiger.bin_gaussians(means2d.detach(), conics.detach(), opacities.detach(),
                                         depths.detach(), radii, int(width), int(height),
                                         int(tile_size), float(alpha_threshold), *settings.op_args(),
                                         int(views))


def _check_choices(path: str, block_sort_keys: int, warp_sort_keys: int, giant_tiles: int) -> None:
    """The kernels' checks of the choices (csrc/binning/ops.cpp), for tracing."""
    torch._check(path in _PATHS,
                 lambda: f"tiger.bin_gaussians: path must be 'auto', 'tiles' or 'global', got '{path}'")
    top = _DEFAULT.block_sort_keys  # the defaults are the maxima
    torch._check(2 <= block_sort_keys <= top and block_sort_keys & (block_sort_keys - 1) == 0,
                 lambda: f"tiger.bin_gaussians: block_sort_keys must be a power of two in [2, {top}], "
                         f"got {block_sort_keys}")
    torch._check(1 <= warp_sort_keys <= _DEFAULT.warp_sort_keys,
                 lambda: f"tiger.bin_gaussians: warp_sort_keys must be in [1, {_DEFAULT.warp_sort_keys}], "
                         f"got {warp_sort_keys}")
    torch._check(giant_tiles >= 1,
                 lambda: f"tiger.bin_gaussians: giant_tiles must be at least 1, got {giant_tiles}")


@torch.library.register_fake("tiger::bin_gaussians")
def _bin_fake(means2d, conics, opacities, depths, radii, width, height, tile_size, alpha_threshold,
              path=_DEFAULT.path, block_sort_keys=_DEFAULT.block_sort_keys,
              warp_sort_keys=_DEFAULT.warp_sort_keys, giant_tiles=_DEFAULT.giant_tiles,
              _serial=False, views=1):
    _check_choices(path, block_sort_keys, warp_sort_keys, giant_tiles)
    torch._check(views >= 1, lambda: f"tiger.bin_gaussians: views must be at least 1, got {views}")
    torch._check(means2d.shape[0] % views == 0,
                 lambda: f"tiger.bin_gaussians: views={views} must divide the number of Gaussians "
                         f"({means2d.shape[0]})")
    tiles = views * ((width + tile_size - 1) // tile_size) * ((height + tile_size - 1) // tile_size)
    m = torch.library.get_ctx().new_dynamic_size()
    return (means2d.new_empty(tiles + 1, dtype=torch.int64),
            means2d.new_empty(m, dtype=torch.int32))
