"""``tiger::bin_gaussians``: tile binning (public function and fake kernel; integer outputs,
not differentiable; semantics in ``csrc/binning/binning.h``)."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["bin_gaussians"]


def bin_gaussians(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor,
                  width: int, height: int, tile_size: int,
                  alpha_threshold: float) -> tuple[Tensor, Tensor]:
    """Which Gaussians touch which tile, front to back (inputs from :func:`project_gaussians`).

    Args:
        means2d: [N, 2] px; conics: [N, 3]; opacities: [N]; depths: [N]; radii: [N, 2] int32
            (0 = culled); width, height: image size (px); tile_size: tile edge (px);
        alpha_threshold: a tile is kept only where the ellipse reaches o*G >= threshold.
    Returns:
        tile_offsets [tiles_y * tiles_x + 1] int64 (row-major tiles; tile t's list is
        ``gaussian_ids[tile_offsets[t]:tile_offsets[t + 1]]``), gaussian_ids [M] int32 sorted by
        (tile, depth, id).
    """
    return torch.ops.tiger.bin_gaussians(means2d.detach(), conics.detach(), opacities.detach(),
                                         depths.detach(), radii, int(width), int(height),
                                         int(tile_size), float(alpha_threshold))


@torch.library.register_fake("tiger::bin_gaussians")
def _bin_fake(means2d, conics, opacities, depths, radii, width, height, tile_size, alpha_threshold):
    tiles = ((width + tile_size - 1) // tile_size) * ((height + tile_size - 1) // tile_size)
    m = torch.library.get_ctx().new_dynamic_size()
    return (means2d.new_empty(tiles + 1, dtype=torch.int64),
            means2d.new_empty(m, dtype=torch.int32))
