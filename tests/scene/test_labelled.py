"""LabelledScene: a GaussianScene plus one label per Gaussian; label pictures by rendering."""
from __future__ import annotations

import pytest
import torch

from tiger.render import Camera
from tiger.scene import GaussianScene
from tiger.scene.cameras import intrinsics
from tiger.scene import LabelledScene


def _two_blobs() -> LabelledScene:
    """Two opaque round Gaussians 3 units in front of the camera, left (label 1) and right (0)."""
    means = torch.tensor([[-0.5, 0.0, 3.0], [0.5, 0.0, 3.0]])
    quats = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    scene = GaussianScene.from_values(means, quats, torch.full((2, 3), 0.1), torch.tensor([0.9, 0.9]),
                                      torch.tensor([[1.0, 0, 0], [0, 0, 1.0]]))
    return LabelledScene(scene, torch.tensor([1, 0]), ["right", "left"])


def test_from_values_stores_the_parameters():
    s = _two_blobs().scene
    torch.testing.assert_close(s.scales, torch.full((2, 3), 0.1))
    torch.testing.assert_close(s.opacities, torch.tensor([0.9, 0.9]))
    torch.testing.assert_close(s.rgb, torch.tensor([[1.0, 0, 0], [0, 0, 1.0]]), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="scales > 0"):
        GaussianScene.from_values(s.means, s.quats, torch.zeros(2, 3), s.opacities, s.rgb)


def test_label_image_follows_the_geometry():
    lab = _two_blobs()
    cam = Camera(torch.eye(4), intrinsics(40.0, 40.0, 32.0, 16.0), 64, 32)
    label, alpha = lab.label_image(cam)
    # centres project to x = 32 -+ 40 * 0.5 / 3 px, y = 16 px
    assert int(label[16, 25]) == 1 and int(label[16, 38]) == 0
    assert float(alpha[16, 25]) > 0.8 and float(alpha[0, 0]) == 0.0


def test_subset_concat_and_checks():
    lab = _two_blobs()
    both = LabelledScene.concat([lab, lab.subset(torch.tensor([True, False]))], lab.names)
    assert len(both) == 3 and both.labels.tolist() == [1, 0, 1]
    assert torch.equal(both.scene.means[2], lab.scene.means[0])
    assert both.one_hot().tolist() == [[0, 1], [1, 0], [0, 1]]
    with pytest.raises(ValueError, match="must index the 2 names"):
        LabelledScene(lab.scene, torch.tensor([0, 2]), lab.names)
    with pytest.raises(ValueError, match=r"labels must be \[N=2\] int64"):
        LabelledScene(lab.scene, torch.tensor([0.0, 1.0]), lab.names)
