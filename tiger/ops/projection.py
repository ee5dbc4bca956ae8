"""``tiger::project_gaussians``: EWA projection of 3D Gaussians (public function, fake kernel,
autograd; semantics in ``csrc/projection/projection.h``)."""
from __future__ import annotations

from typing import Any, Optional

import torch
from torch import Tensor

from tiger.ops._eager_autograd import eager_autograd

_OP = "tiger::project_gaussians"

__all__ = ["project_gaussians"]


def project_gaussians(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                      viewmat: Tensor, K: Tensor, width: int, height: int, eps2d: float,
                      near: float, far: float, alpha_threshold: float,
                      antialiased: bool, trainable: Optional[Tensor] = None
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Project N Gaussians into one pinhole camera, differentiably (viewmat and K included).

    Args:
        means: [N, 3] world centres; quats: [N, 4] (w, x, y, z), any non-zero norm;
        scales: [N, 3] linear standard deviations; opacities: [N] in [0, 1];
        viewmat: [4, 4] world→camera (OpenCV axes); K: [3, 3] intrinsics (px); one float dtype.
        width, height: image size (px); eps2d: dilation of the 2D covariance diagonal (px^2);
        near, far: camera-z range kept; alpha_threshold: opacity-aware extent rule;
        antialiased: scale opacity by sqrt(det Σ2d / det(Σ2d + eps2d I)).
        trainable: [N] bool or None: the rows whose gradients the backward computes; the others
            (an edit's frozen Gaussians) get zero gradients, cost no gradient work and add nothing
            to viewmat's and K's. The values do not depend on it.
    Returns:
        means2d [N, 2] px, conics [N, 3] (a, b, c of the inverse dilated 2D covariance),
        depths [N] camera z, opacities [N] (after the antialiasing factor), radii [N, 2] int32
        half extents in px (0 = culled; not differentiable).
    """
    return _project_eager(
        means.contiguous(), quats.contiguous(), scales.contiguous(), opacities.contiguous(),
        viewmat.contiguous(), K.contiguous(), int(width), int(height), float(eps2d), float(near),
        float(far), float(alpha_threshold), bool(antialiased), trainable)


@torch.library.register_fake(_OP)
def _project_fake(means, quats, scales, opacities, viewmat, K, width, height, eps2d, near_plane,
                  far_plane, alpha_threshold, antialiased, trainable=None):
    n = means.shape[0]
    return (means.new_empty(n, 2), means.new_empty(n, 3), means.new_empty(n),
            means.new_empty(n), means.new_empty(n, 2, dtype=torch.int32))


@torch.library.register_fake("tiger::project_gaussians_backward")
def _project_backward_fake(means, quats, scales, opacities, viewmat, K, radii, width, height, eps2d,
                           antialiased, v_means2d, v_conics, v_depths, v_opacities_out, camera_grad):
    return (torch.empty_like(means), torch.empty_like(quats), torch.empty_like(scales),
            torch.empty_like(opacities), means.new_empty(4, 4), means.new_empty(3, 3))


def _setup(ctx: Any, inputs: tuple, output: tuple) -> None:
    means, quats, scales, opacities, viewmat, K, width, height, eps2d, _, _, _, antialiased = inputs[:13]
    trainable = inputs[13] if len(inputs) > 13 else None
    ctx.save_for_backward(means, quats, scales, opacities, viewmat, K, output[4], trainable)
    ctx.args = (width, height, eps2d, antialiased)
    ctx.mark_non_differentiable(output[4])
    ctx.set_materialize_grads(False)  # no zero fills for unused outputs (radii, ...): see _backward


def _backward(ctx: Any, v_means2d, v_conics, v_depths, v_opac, _v_radii):
    means, quats, scales, opacities, viewmat, K, radii, trainable = ctx.saved_tensors
    width, height, eps2d, antialiased = ctx.args
    if trainable is not None:  # the kernels skip the other rows as they skip culled ones
        radii = radii.masked_fill(~trainable[:, None], 0)
    n = means.shape[0]
    zeros = lambda *s: means.new_zeros(*s)  # noqa: E731
    v_means2d = zeros(n, 2) if v_means2d is None else v_means2d
    v_conics = zeros(n, 3) if v_conics is None else v_conics
    v_depths = zeros(n) if v_depths is None else v_depths
    v_opac = zeros(n) if v_opac is None else v_opac
    need = ctx.needs_input_grad
    camera_grad = bool(need[4] or need[5])
    g = torch.ops.tiger.project_gaussians_backward(
        means, quats, scales, opacities, viewmat, K, radii, width, height, eps2d, antialiased,
        v_means2d, v_conics, v_depths, v_opac, camera_grad)  # both glues take strided rows
    grads = [gi if need[i] else None for i, gi in enumerate(g)]
    return (*grads, *[None] * (len(need) - len(grads)))


torch.library.register_autograd(_OP, _backward, setup_context=_setup)
_project_eager = eager_autograd(torch.ops.tiger.project_gaussians, _setup, _backward)
