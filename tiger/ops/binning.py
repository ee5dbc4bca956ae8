"""Fake kernel of ``tiger::bin_gaussians`` (integer outputs: not differentiable)."""
from __future__ import annotations

import torch


@torch.library.register_fake("tiger::bin_gaussians")
def _bin_fake(means2d, conics, opacities, depths, radii, width, height, tile_size, alpha_threshold):
    tiles = ((width + tile_size - 1) // tile_size) * ((height + tile_size - 1) // tile_size)
    m = torch.library.get_ctx().new_dynamic_size()
    return (means2d.new_empty(tiles + 1, dtype=torch.int64),
            means2d.new_empty(m, dtype=torch.int32))
