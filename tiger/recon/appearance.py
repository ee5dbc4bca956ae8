"""Per-image appearance: an affine colour correction for each training image.

Phone captures change exposure and white balance from image to image; a scene fitted to
them bakes those changes into view-dependent colour (floaters and wrong colours in held-out
views). As recent 3DGS trainers do (e.g. the exposure compensation of INRIA's 2024 code),
each training image ``v`` gets ``c' = A_v c + b_v`` (``A_v`` [3, 3], ``b_v`` [3], identity at
the start) applied to the render before the loss. Only the mean of the transforms over the
training images is fixed by nothing (the scene's colours can absorb any common change):
:meth:`AffineAppearance.recentre` moves it into the scene's colours, so that the saved scene, which
held-out views are rendered with, shows the capture's average appearance.
"""
from __future__ import annotations

import torch

from tiger.render.reference import SH_C0


class AffineAppearance(torch.nn.Module):
    """``n_views`` affine colour transforms, identity at initialisation.

    Parameters: ``matrix`` [V, 3, 3], ``bias`` [V, 3].
    """

    def __init__(self, n_views: int, device: torch.device | str | None = None) -> None:
        super().__init__()
        if n_views <= 0:
            raise ValueError(f"tiger.recon: AffineAppearance needs n_views > 0, got {n_views}")
        self.matrix = torch.nn.Parameter(torch.eye(3, device=device).repeat(n_views, 1, 1))
        self.bias = torch.nn.Parameter(torch.zeros(n_views, 3, device=device))

    def forward(self, image: torch.Tensor, view: int) -> torch.Tensor:
        """[H, W, 3] render -> [H, W, 3] render as seen by training image ``view``."""
        if image.shape[-1] != 3:
            raise ValueError(f"tiger.recon: AffineAppearance expects [..., 3] colours, got {list(image.shape)}")
        if not 0 <= view < self.matrix.shape[0]:
            raise IndexError(f"tiger.recon: AffineAppearance has {self.matrix.shape[0]} views, not view {view}")
        return image @ self.matrix[view].T + self.bias[view]

    @torch.no_grad()
    def recentre(self, sh_dc: torch.Tensor, sh_rest: torch.Tensor) -> None:
        """Move the mean transform (A, b) over the views into the SH colours, in place.

        Args:
            sh_dc: [N, 3] degree-0 coefficients; sh_rest: [N, K, 3] higher bands (K may be 0).
        A Gaussian's colour ``c = 0.5 + C0 sh_dc + sum_k Y_k sh_k`` becomes ``A c + b``, and each
        view's transform ``T_v`` becomes ``T_v o T^-1``, so every training view renders as before
        (up to the clamp of negative colours; with a black background the blend is affine in
        the colours where the pixel is covered), while the plain render now shows the average
        appearance instead of an arbitrary one.
        """
        A, b = self.matrix.mean(0), self.bias.mean(0)
        if bool(torch.linalg.det(A).abs() < 1e-6):
            return  # a degenerate mean transform cannot be inverted: leave the gauge as it is
        A_inv = torch.linalg.inv(A)
        sh_dc.copy_(sh_dc @ A.T + (0.5 * A.sum(1) + b - 0.5) / SH_C0)
        if sh_rest.numel():
            sh_rest.copy_(sh_rest @ A.T)
        new_matrix = self.matrix @ A_inv
        self.bias.sub_(new_matrix @ b)
        self.matrix.copy_(new_matrix)


def fit_affine_colour(render: torch.Tensor, target: torch.Tensor,
                      mask: torch.Tensor | None = None) -> torch.Tensor:
    """The least-squares affine colour map from ``render`` to ``target`` ([H, W, 3] each):
    returns [H, W, 3] ``render @ A^T + b`` with (A, b) minimising the squared error over
    ``mask`` (default all pixels). A diagnostic ("colour-corrected PSNR"): how much of a
    held-out view's error a per-image colour change explains."""
    x = render.detach().reshape(-1, 3).double()
    y = target.detach().reshape(-1, 3).double()
    if mask is not None:
        keep = mask.reshape(-1).to(x.device)
        xs, ys = x[keep], y[keep]
    else:
        xs, ys = x, y
    X = torch.cat([xs, torch.ones_like(xs[:, :1])], 1)
    coef = torch.linalg.lstsq(X, ys).solution                              # [4, 3]
    out = torch.cat([x, torch.ones_like(x[:, :1])], 1) @ coef
    return out.reshape(render.shape).to(render.dtype)
