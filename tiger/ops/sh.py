"""``tiger::sh_to_color``: spherical-harmonics colour per Gaussian (public function, fake kernel,
autograd)."""
from __future__ import annotations

from typing import Any, Optional

import torch
from torch import Tensor

_OP = "tiger::sh_to_color"


def sh_to_color(dirs: Tensor, coeffs: Tensor, degree: int, visible: Optional[Tensor] = None) -> Tensor:
    """Real SH (INRIA order) evaluated per Gaussian for its view direction, differentiably.

    Args:
        dirs: [N, 3] view directions (Gaussian centre minus camera centre; any non-zero norm).
        coeffs: [N, K, 3] SH coefficients, K >= (degree + 1)^2, DC first.
        degree: SH degree in 0..3 (bands used).
        visible: [N] bool; rows that are False are skipped (output 0, gradient 0). None: all.
    Returns:
        [N, 3] ``SH(dirs)`` without the +0.5 offset and without clamping (same dtype as ``dirs``).
    """
    return torch.ops.tiger.sh_to_color(dirs.contiguous(), coeffs.contiguous(), int(degree), visible)


@torch.library.register_fake(_OP)
def _sh_fake(dirs, coeffs, degree, visible):
    return dirs.new_empty(dirs.shape[0], 3)


@torch.library.register_fake("tiger::sh_to_color_backward")
def _sh_backward_fake(dirs, coeffs, degree, visible, v_colors):
    return torch.empty_like(dirs), torch.empty_like(coeffs)


def _setup(ctx: Any, inputs: tuple, output: torch.Tensor) -> None:
    dirs, coeffs, degree, visible = inputs
    ctx.save_for_backward(dirs, coeffs, visible)
    ctx.degree = degree


def _backward(ctx: Any, v_colors: torch.Tensor):
    dirs, coeffs, visible = ctx.saved_tensors
    v_dirs, v_coeffs = torch.ops.tiger.sh_to_color_backward(
        dirs, coeffs, ctx.degree, visible, v_colors.contiguous())
    need = ctx.needs_input_grad
    return (v_dirs if need[0] else None, v_coeffs if need[1] else None, None, None)


torch.library.register_autograd(_OP, _backward, setup_context=_setup)

__all__ = ["sh_to_color"]
