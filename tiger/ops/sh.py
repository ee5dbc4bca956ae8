"""``tiger::sh_to_color``: spherical-harmonics colour per Gaussian (public function, fake kernel,
autograd)."""
from __future__ import annotations

from typing import Any, Optional

import torch
from torch import Tensor

_OP = "tiger::sh_to_color"


def sh_to_color(dirs: Tensor, coeffs: Tensor, degree: int, visible: Optional[Tensor] = None,
                rest: Optional[Tensor] = None, *, trainable: Optional[Tensor] = None,
                _staged: bool = True) -> Tensor:
    """Real SH (INRIA order) evaluated per Gaussian for its view direction, differentiably.

    Args:
        dirs: [N, 3] view directions (Gaussian centre minus camera centre; any non-zero norm).
        coeffs: [N, K, 3] SH coefficients, DC first.
        degree: SH degree in 0..3 (bands used); the coefficients must hold (degree + 1)^2.
        visible: [N] bool; rows that are False are skipped (output 0, gradient 0). None: all.
        rest: [N, K1, 3] or None: the coefficients are then ``cat([coeffs, rest], 1)``, read in
            place (float32 on CUDA) -- a scene's DC band and higher bands without the copy.
        trainable: [N] bool or None: the rows whose gradients the backward computes; the others
            get zero gradients and cost no gradient work (an edit's frozen Gaussians). The values
            do not depend on it.
        _staged: test-only: False sends float32 rows on CUDA through the plain kernels (which
            float64 and very long rows always take) instead of the staged ones (coefficient rows
            through shared memory); the same arithmetic, bit for bit, kept for comparisons.
    Returns:
        [N, 3] ``SH(dirs)`` without the +0.5 offset and without clamping (same dtype as ``dirs``).

    Example:
        >>> dc = torch.tensor([[[1.0, 2.0, 3.0]]])  # one Gaussian, degree 0: Y_0 = 0.2820948
        >>> sh_to_color(torch.tensor([[0.0, 0.0, 1.0]]), dc, 0).tolist()  # doctest: +ELLIPSIS
        [[0.282..., 0.564..., 0.846...]]
    """
    return torch.ops.tiger.sh_to_color(dirs.contiguous(), coeffs, int(degree), visible, rest,
                                       bool(_staged), trainable)


@torch.library.register_fake(_OP)
def _sh_fake(dirs, coeffs, degree, visible, rest=None, _staged=True, trainable=None):
    return dirs.new_empty(dirs.shape[0], 3)


@torch.library.register_fake("tiger::sh_to_color_backward")
def _sh_backward_fake(dirs, coeffs, degree, visible, v_colors, rest=None, _staged=True, trainable=None):
    v_rest = rest.new_empty(rest.shape) if rest is not None else dirs.new_empty(0)
    return torch.empty_like(dirs), coeffs.new_empty(coeffs.shape), v_rest


def _setup(ctx: Any, inputs: tuple, output: torch.Tensor) -> None:
    dirs, coeffs, degree, visible = inputs[:4]
    rest = inputs[4] if len(inputs) > 4 else None
    trainable = inputs[6] if len(inputs) > 6 else None
    ctx.save_for_backward(dirs, coeffs, visible, rest, trainable)
    ctx.degree = degree
    ctx.staged = bool(inputs[5]) if len(inputs) > 5 else True


def _backward(ctx: Any, v_colors: torch.Tensor):
    dirs, coeffs, visible, rest, trainable = ctx.saved_tensors
    v_dirs, v_coeffs, v_rest = torch.ops.tiger.sh_to_color_backward(
        dirs, coeffs, ctx.degree, visible, v_colors.contiguous(), rest, ctx.staged, trainable)
    need = ctx.needs_input_grad
    return (v_dirs if need[0] else None, v_coeffs if need[1] else None, None, None,
            v_rest if rest is not None and need[4] else None) + (None,) * (len(need) - 5)


torch.library.register_autograd(_OP, _backward, setup_context=_setup)

__all__ = ["sh_to_color"]
