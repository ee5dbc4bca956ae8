"""Initial colours of random points: the mean pixel colour over the views that see them."""
from __future__ import annotations

import torch

from tiger.recon.init import colors_from_views
from tiger.render import Camera
from tiger.scene.cameras import intrinsics


def test_colors_from_views_samples_the_projected_pixels():
    W, H = 8, 6
    K = intrinsics(10.0, 10.0, W / 2, H / 2)
    cam = Camera(torch.eye(4, dtype=torch.float64), K, W, H)          # at the origin, looking down +z
    img = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0))
    img2 = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(1))
    # points on pixel centres (u, v) at depth 2: x = (u + 0.5 - cx) / fx * z
    pix = [(0, 0), (3, 2), (7, 5)]
    pts = torch.tensor([[(u + 0.5 - W / 2) / 10 * 2, (v + 0.5 - H / 2) / 10 * 2, 2.0] for u, v in pix]
                       + [[0.0, 0.0, -1.0], [50.0, 0.0, 1.0]])        # behind the camera, outside the image
    got = colors_from_views(pts, [cam, cam], [img, img2])
    for i, (u, v) in enumerate(pix):
        torch.testing.assert_close(got[i], (img[v, u] + img2[v, u]) / 2)
    assert torch.equal(got[3:], torch.full((2, 3), 0.5))
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[2, 3] = False                                               # pixel (3, 2) not valid in view 2
    got = colors_from_views(pts, [cam, cam], [img, img2], [torch.ones_like(mask), mask])
    torch.testing.assert_close(got[1], img[2, 3])
