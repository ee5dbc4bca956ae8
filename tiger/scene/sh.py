"""Spherical-harmonics bookkeeping shared by the scene, its files and the trainer.

Colours follow the INRIA convention: RGB = SH·basis + 0.5, and the degree-0 basis
function is the constant ``SH_C0``.
"""
from __future__ import annotations

import torch

from tiger.render.reference import SH_C0
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree`` (1, 4, 9, 16)."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"tiger: SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def sh_degree_from_rest(num_rest: int) -> int:
    """SH degree whose higher bands hold ``num_rest`` coefficients per channel.

    Raises ValueError when ``num_rest`` is not 0, 3, 8 or 15.
    """
    for d in range(MAX_SH_DEGREE + 1):
        if num_sh_bases(d) - 1 == num_rest:
            return d
    raise ValueError(
        f"tiger: {num_rest} higher-order SH coefficients per channel match no degree 0..3 "
        "(expected 0, 3, 8 or 15)"
    )


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient giving colour ``rgb`` (any shape, values in [0, 1])."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    """View-independent colour of the DC coefficient (any shape; not clamped)."""
    return sh_dc * SH_C0 + 0.5
