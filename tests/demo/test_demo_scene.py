"""The procedural demo scene: labelled objects land where they were built and render."""
from __future__ import annotations

import torch

import tiger
from tiger.demo import DEMO_ORBIT, tabletop_scene
from tiger.render.views import orbit_viewmats, pinhole_K


def test_scene_labels_and_render():
    lab = tabletop_scene(density=0.2)
    scene = lab.scene
    assert set(lab.labels.unique().tolist()) == set(range(len(lab.names)))
    # Objects sit on the table top (y < 0 is above the table in this y-down world).
    for i, name in enumerate(lab.names[1:], start=1):
        assert float(scene.means[lab.labels == i][:, 1].max()) < 0.05, name
    K = pinhole_K(96, 72)
    V = orbit_viewmats(1, start_deg=20.0, **DEMO_ORBIT)[0]
    out = tiger.rasterize_gaussians(scene.means, scene.quats, scene.scales, scene.opacities,
                                    scene.rgb, V, K, 96, 72)
    cov = float((out["alpha"] > 0.5).float().mean())
    assert 0.1 < cov < 0.9  # the scene is in view and does not fill it
    # Each label, rendered alone as a one-hot channel, is visible from the orbit view.
    onehot = torch.nn.functional.one_hot(lab.labels, len(lab.names)).float()
    lab = tiger.rasterize_gaussians(scene.means, scene.quats, scene.scales, scene.opacities,
                                    onehot, V, K, 96, 72)["color"]
    assert bool((lab.amax(dim=(0, 1)) > 0.5).all())
