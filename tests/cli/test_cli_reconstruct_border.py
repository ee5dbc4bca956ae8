"""tiger reconstruct on a capture with lens distortion: the black border of undistortion is left
out of the loss and of the held-out PSNR, and metrics.json says which pixels the PSNR counts."""
from __future__ import annotations

import json
import math

import torch

from tiger.cli.main import main
from tiger.recon.data import load_views, masked_fraction, valid_pixel_masks
from tiger.scene import GaussianScene
from tiger.scene.dataset import load_dataset

from .datasets import tabletop_dataset as _dataset


def test_masks_only_for_distorted_cameras(tmp_path):
    data = _dataset(tmp_path / "plain", n_views=2, w=32, h=24)
    assert valid_pixel_masks(load_dataset(data).cameras) is None
    meta = json.loads((data / "transforms.json").read_text())
    meta["k1"] = 0.3
    (data / "transforms.json").write_text(json.dumps(meta))
    cams = load_dataset(data).cameras
    masks = valid_pixel_masks(cams, 2.0)
    assert len(masks) == 2 and masks[0].shape == (12, 16) and masks[0].dtype == torch.bool
    assert not masks[0][0, 0] and masks[0][6, 8]  # corner in the border, centre kept
    assert 0.0 < masked_fraction(masks) < 0.5


def test_psnr_counts_the_undistorted_pixels_only(tmp_path, capsys):
    data = _dataset(tmp_path / "data", n_views=4, w=48, h=36)
    meta = json.loads((data / "transforms.json").read_text())
    meta["k1"] = 0.25  # corners undistort to outside the file: a black border
    (data / "transforms.json").write_text(json.dumps(meta))
    out = tmp_path / "out"
    assert main(["reconstruct", str(data), "--out", str(out), "--steps", "30", "--init-points", "300",
                 "--test-every", "2", "--device", "cpu"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert "border left out" in metrics["psnr_pixels"] and "border left out" in capsys.readouterr().out
    # the definition it states is the one recomputed below: clamped render, black background, mean of views
    assert all(w in metrics["psnr_definition"] for w in ("10 log10(1 / MSE)", "black background",
                                                         "clamped to [0, 1]", "mean over the held-out views"))

    # the same number from the saved scene, the undistorted test images and the border masks
    ds = load_dataset(data)
    _, test = ds.split(2)
    cams, imgs = load_views(test)
    masks = valid_pixel_masks(test)
    scene = GaussianScene.load_ply(out / "scene.ply")
    per_view, unmasked = [], []
    for cam, img, m in zip(cams, imgs, masks):
        with torch.no_grad():
            pred = scene.render(cam, background=torch.zeros(3))["color"].clamp(0, 1)
        err = (pred.double() - img.double().clamp(0, 1)) ** 2
        per_view.append(-10 * math.log10(float(err[m].mean())))
        unmasked.append(-10 * math.log10(float(err.mean())))
    assert abs(metrics["psnr"] - sum(per_view) / len(per_view)) < 1e-3
    assert abs(metrics["psnr"] - sum(unmasked) / len(unmasked)) > 1e-2


def test_appearance_run_reports_the_saved_scene(tmp_path):
    # with per-image colour correction the held-out PSNR is still that of scene.ply as saved
    # (the mean correction is moved into its colours before the evaluation)
    data = _dataset(tmp_path / "data", n_views=4, w=32, h=24)
    out = tmp_path / "out"
    assert main(["reconstruct", str(data), "--out", str(out), "--steps", "30", "--init-points", "200",
                 "--test-every", "2", "--device", "cpu", "--appearance"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    _, test = load_dataset(data).split(2)
    cams, imgs = load_views(test)
    scene = GaussianScene.load_ply(out / "scene.ply")
    per_view = []
    for cam, img in zip(cams, imgs):
        with torch.no_grad():
            pred = scene.render(cam, background=torch.zeros(3))["color"].clamp(0, 1)
        per_view.append(-10 * math.log10(float(((pred.double() - img.double()) ** 2).mean())))
    assert abs(metrics["psnr"] - sum(per_view) / len(per_view)) < 1e-3


def _add_transparency(image_file) -> None:
    """Rewrite a dataset image as RGBA with its left column see-through."""
    import numpy as np
    from PIL import Image

    rgb = np.asarray(Image.open(image_file).convert("RGB"))
    alpha = np.full(rgb.shape[:2], 255, np.uint8)
    alpha[:, 0] = 0
    Image.fromarray(np.dstack([rgb, alpha]), "RGBA").save(image_file)


def test_colour_options_reach_the_training(tmp_path, monkeypatch):
    from tiger.recon import trainer as trainer_module

    seen = []
    real_init = trainer_module.Trainer.__init__

    def spy(self, *a, **kw):
        real_init(self, *a, **kw)
        seen.append((self.cfg.appearance, self.cfg.random_background))

    monkeypatch.setattr(trainer_module.Trainer, "__init__", spy)
    opaque = _dataset(tmp_path / "opaque", n_views=3, w=24, h=16)
    seethrough = _dataset(tmp_path / "seethrough", n_views=3, w=24, h=16)
    _add_transparency(seethrough / "images" / "001.png")
    # (data, flags) -> (appearance, random background) the trainer got, and what metrics.json says
    cases = [(opaque, [], (False, True), "random colour each training step (no image has transparent"),
             (opaque, ["--no-random-background"], (False, False), "black (asked for)"),
             (opaque, ["--appearance", "--random-background"], (True, True),
              "random colour each training step (asked for)"),
             (seethrough, [], (False, False), "black (1 image with transparent pixels, e.g. images/001.png"),
             (seethrough, ["--random-background"], (False, True), "asked for; 1 image with transparent pixels")]
    for data, flags, want, note in cases:
        out = tmp_path / f"o{len(seen)}"
        assert main(["reconstruct", str(data), "--out", str(out), "--steps", "3",
                     "--init-points", "50", "--test-every", "0", "--device", "cpu", *flags]) == 0
        assert seen[-1] == want, flags
        assert note in json.loads((out / "metrics.json").read_text())["training_background"], flags
