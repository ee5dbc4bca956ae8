"""Per-image appearance: moving the mean transform into the scene's colours changes no training
view's colours (checked with the reference SH evaluation) and makes the mean transform identity."""
from __future__ import annotations

import torch

from tiger.recon.appearance import AffineAppearance
from tiger.render.reference import sh_to_color_ref


def _colours(sh_dc: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    coeffs = torch.cat([sh_dc[:, None], sh_rest], 1)
    return sh_to_color_ref(dirs, coeffs, 3) + 0.5          # [N, 3], unclamped


def test_recentre_keeps_every_view_and_centres_the_mean():
    g = torch.Generator().manual_seed(0)
    n, views = 50, 4
    sh_dc = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5
    sh_rest = torch.randn(n, 15, 3, generator=g, dtype=torch.float64) * 0.1
    dirs = torch.randn(n, 3, generator=g, dtype=torch.float64)
    app = AffineAppearance(views).double()
    with torch.no_grad():
        app.matrix.add_(0.2 * torch.randn(views, 3, 3, generator=g, dtype=torch.float64))
        app.bias.add_(0.1 * torch.randn(views, 3, generator=g, dtype=torch.float64))
    before = [app(_colours(sh_dc, sh_rest, dirs), v) for v in range(views)]
    mean_a, mean_b = app.matrix.mean(0).clone(), app.bias.mean(0).clone()
    plain = _colours(sh_dc, sh_rest, dirs) @ mean_a.T + mean_b   # the average appearance

    app.recentre(sh_dc, sh_rest)

    after = [app(_colours(sh_dc, sh_rest, dirs), v) for v in range(views)]
    for v in range(views):
        torch.testing.assert_close(after[v], before[v], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(app.matrix.mean(0), torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-9)
    torch.testing.assert_close(app.bias.mean(0), torch.zeros(3, dtype=torch.float64), rtol=0, atol=1e-9)
    torch.testing.assert_close(_colours(sh_dc, sh_rest, dirs), plain, rtol=1e-9, atol=1e-9)


def test_recentre_of_identity_changes_nothing():
    sh_dc, sh_rest = torch.randn(7, 3), torch.zeros(7, 0, 3)
    ref = sh_dc.clone()
    AffineAppearance(3).recentre(sh_dc, sh_rest)
    torch.testing.assert_close(sh_dc, ref)
