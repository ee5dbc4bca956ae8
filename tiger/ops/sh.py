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
    """Real SH (INRIA order) evaluated per Gaussian for its view direction, differentiably; for
    one view or for V views of the same Gaussians in one call.

    With ``dirs`` [V, N, 3] each coefficient row is read once for all V views, and the backward
    sums the V views' coefficient gradients inside the kernel (in view order) into one [N, K, 3]
    gradient, instead of V per-view gradients summed by autograd. View v of the result equals
    the one-view call with ``dirs[v]`` and ``visible[v]`` bit for bit.

    Args:
        dirs: [N, 3] view directions (Gaussian centre minus camera centre; any non-zero norm),
            or [V, N, 3]: V views' directions to the same N Gaussians.
        coeffs: [N, K, 3] SH coefficients, DC first (shared by the views).
        degree: SH degree in 0..3 (bands used); the coefficients must hold (degree + 1)^2.
        visible: bool of ``dirs``' leading shape, [N] or [V, N]; (view, row) pairs that are False
            are skipped (output 0, gradient 0). None: all.
        rest: [N, K1, 3] or None: the coefficients are then ``cat([coeffs, rest], 1)``, read in
            place (float32 on CUDA) -- a scene's DC band and higher bands without the copy.
        trainable: [N] bool or None (shared by the views): the rows whose gradients the backward
            computes; the others get zero gradients and cost no gradient work (an edit's frozen
            Gaussians). The values do not depend on it.
        _staged: test-only: False sends float32 rows on CUDA through the plain kernels (which
            float64 and very long rows always take) instead of the staged ones (coefficient rows
            through shared memory); the same arithmetic, bit for bit, kept for comparisons.
    Returns:
        ``SH(dirs)`` of ``dirs``' shape, [N, 3] or [V, N, 3], without the +0.5 offset and without
        clamping (same dtype as ``dirs``).

    Example:
        >>> dc = torch.tensor([[[1.0, 2.0, 3.0]]])  # one Gaussian, degree 0: Y_0 = 0.2820948
        >>> sh_to_color(torch.tensor([[0.0, 0.0, 1.0]]), dc, 0).tolist()  # doctest: +ELLIPSIS
        [[0.282..., 0.564..., 0.846...]]
    """
    return torch.ops.tiger.sh_to_color(dirs.contiguous(), coeffs, int(degree), visible, rest,
                                       bool(_staged), trainable)


def _check_shapes(op: str, dirs: Tensor, coeffs: Tensor, visible: Optional[Tensor], rest: Optional[Tensor],
                  trainable: Optional[Tensor], v_colors: Optional[Tensor] = None) -> None:
    """The fake kernels' shape checks (the C++ kernels check the same, and more): dirs [N, 3] or
    [V, N, 3]; coeffs, rest [N, *, 3]; visible of dirs' leading shape; trainable [N]; v_colors of
    dirs' shape."""
    torch._check(dirs.dim() in (2, 3) and dirs.shape[-1] == 3,
                 lambda: f"{op}: dirs must have shape [N, 3] (one view) or [V, N, 3] (V views), got "
                         f"{list(dirs.shape)}")
    n = dirs.shape[-2]
    for name, t in (("coeffs", coeffs), ("rest", rest)):
        if t is not None:
            torch._check(t.dim() == 3 and t.shape[0] == n and t.shape[2] == 3,
                         lambda: f"{op}: {name} must have shape [{n}, *, 3], got {list(t.shape)}")
    if visible is not None:
        torch._check(visible.shape == dirs.shape[:-1],
                     lambda: f"{op}: visible must have shape {list(dirs.shape[:-1])} (like dirs "
                             f"{list(dirs.shape)}), got {list(visible.shape)}")
    if trainable is not None:
        torch._check(trainable.shape == (n,),
                     lambda: f"{op}: trainable must have shape [{n}], got {list(trainable.shape)}")
    if v_colors is not None:
        torch._check(v_colors.shape == dirs.shape,
                     lambda: f"{op}: v_colors must have shape {list(dirs.shape)} (like dirs), got "
                             f"{list(v_colors.shape)}")


@torch.library.register_fake(_OP)
def _sh_fake(dirs, coeffs, degree, visible, rest=None, _staged=True, trainable=None):
    _check_shapes("tiger.sh_to_color", dirs, coeffs, visible, rest, trainable)
    return dirs.new_empty(dirs.shape)  # [N, 3] or [V, N, 3]


@torch.library.register_fake("tiger::sh_to_color_backward")
def _sh_backward_fake(dirs, coeffs, degree, visible, v_colors, rest=None, _staged=True, trainable=None):
    _check_shapes("tiger.sh_to_color_backward", dirs, coeffs, visible, rest, trainable, v_colors)
    v_rest = rest.new_empty(rest.shape) if rest is not None else dirs.new_empty(0)
    # the coefficient gradients once, summed over the views; v_dirs per view
    return dirs.new_empty(dirs.shape), coeffs.new_empty(coeffs.shape), v_rest


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
