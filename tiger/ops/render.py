"""``tiger::render_forward``: projection, SH colour, tile binning and compositing of one view in one
call, for renders without gradients (fake kernel and public function; the chained ops are those of
:mod:`tiger.ops.projection`, :mod:`tiger.ops.sh`, :mod:`tiger.ops.binning` and
:mod:`tiger.ops.raster`; C++ in ``csrc/render/ops.cpp``)."""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from tiger.ops.binning import BinningSettings
from tiger.ops.raster import RasterKernelSettings

__all__ = ["render_forward"]


def render_forward(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                   sh_rest: Optional[Tensor], sh_degree: Optional[int], background: Optional[Tensor],
                   viewmat: Tensor, K: Tensor, width: int, height: int, eps2d: float, near: float,
                   far: float, alpha_threshold: float, antialiased: bool, tile_size: int, alpha_max: float,
                   t_min: float, binning: BinningSettings = BinningSettings(),
                   kernels: RasterKernelSettings = RasterKernelSettings()) -> tuple[Tensor, ...]:
    """One view rendered without recording gradients: the values of the op-by-op render.

    Args: those of :func:`tiger.rasterize_gaussians` (checked there), ``sh_degree=None`` for
        per-Gaussian channels ``colors`` [N, C].
    Returns:
        color [H, W, C], alpha [H, W], depth [H, W] (expected depth, 0 where alpha == 0),
        depth_accum [H, W], radii [N] int32 (the larger of the two extents), means2d [N, 2],
        conics [N, 3], depths [N], gaussian_ids [M] int32 (the tile lists' entries).
    """
    return torch.ops.tiger.render_forward(
        means, quats, scales, opacities, colors, sh_rest, -1 if sh_degree is None else int(sh_degree),
        background, viewmat, K, int(width), int(height), float(eps2d), float(near), float(far),
        float(alpha_threshold), bool(antialiased), int(tile_size), float(alpha_max), float(t_min),
        *binning.op_args(), int(kernels.forward_channel_block), *kernels.launch_args())


@torch.library.register_fake("tiger::render_forward")
def _render_forward_fake(means, quats, scales, opacities, colors, sh_rest, sh_degree, background, viewmat,
                         K, width, height, eps2d, near_plane, far_plane, alpha_threshold, antialiased,
                         tile_size, alpha_max, t_min, path=BinningSettings.path,
                         block_sort_keys=BinningSettings.block_sort_keys,
                         warp_sort_keys=BinningSettings.warp_sort_keys, giant_tiles=BinningSettings.giant_tiles,
                         _serial=False, channel_block=RasterKernelSettings.forward_channel_block,
                         tile_order=RasterKernelSettings().tile_order_arg(),
                         warp_cull=RasterKernelSettings.warp_cull):
    n = means.shape[0]
    c = 3 if sh_degree >= 0 else colors.shape[1]
    m = torch.library.get_ctx().new_dynamic_size()
    return (means.new_empty(height, width, c), means.new_empty(height, width), means.new_empty(height, width),
            means.new_empty(height, width), means.new_empty(n, dtype=torch.int32), means.new_empty(n, 2),
            means.new_empty(n, 3), means.new_empty(n), means.new_empty(m, dtype=torch.int32))
