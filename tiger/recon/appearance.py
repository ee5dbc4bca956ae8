"""Per-image appearance: an affine colour correction for each training image.

Phone captures change exposure and white balance from image to image; a scene fitted to
them bakes those changes into view-dependent colour (floaters and wrong colours in held-out
views). As recent 3DGS trainers do (e.g. the exposure compensation of INRIA's 2024 code),
each training image ``v`` gets ``c' = A_v c + b_v`` (``A_v`` [3, 3], ``b_v`` [3], identity at
the start) applied to the render before the loss. Held-out views are rendered without it.
"""
from __future__ import annotations

import torch


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
