"""The demo tabletop with per-object language features, built fast (no field training)."""
from __future__ import annotations

import pytest
import torch

from tiger.demo.run import label_features
from tiger.demo.scene import tabletop_scene
from tiger.retrieval.text import EmbeddingTable


def demo_scene(density: float = 0.3):
    """(LabelledScene with ``scene.lang`` set, text encoder): each object's text is the mean
    language feature of its Gaussians (so 'ball' retrieves the ball)."""
    lab = tabletop_scene(density)
    lab.scene.lang = label_features(lab)
    table = {name: lab.scene.lang[lab.labels == i].mean(0) for i, name in enumerate(lab.names)}
    g = torch.Generator().manual_seed(1)  # LERF's canonical negatives, as the demo's table has them
    table.update({w: torch.randn(64, generator=g) for w in ("object", "things", "stuff", "texture")})
    return lab, EmbeddingTable(table, source="the test tabletop's labels", fold_case=True)


@pytest.fixture(scope="module")
def tabletop():
    return demo_scene()


@pytest.fixture(scope="module")
def tabletop_camera():
    from tiger.render.views import orbit_cameras

    return orbit_cameras(1, 160, 120, center=(0.0, -0.1, 0.0), radius=2.2, elevation_deg=30.0, start_deg=20.0,
                         up=(0.0, -1.0, 0.0))[0]
