"""tiger reconstruct: a stopped or refused run leaves nothing that blocks the next one; the image
cache and the checkpoint go once the scene is written (--keep-cache keeps them); --resume with
other settings is refused, naming them."""
from __future__ import annotations

import json

import pytest

from tiger.cli.main import main

from .datasets import tabletop_dataset as _dataset


@pytest.fixture(scope="module")
def distorted(tmp_path_factory):
    """A tiny capture whose cameras have lens distortion, so its images are undistorted and cached."""
    root = _dataset(tmp_path_factory.mktemp("recon_cache"), n_views=3, w=32, h=24)
    meta = json.loads((root / "transforms.json").read_text())
    meta["k1"] = 0.002
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def _reconstruct(data, out, *extra):
    return main(["reconstruct", str(data), "--out", str(out), "--steps", "12", "--init-points", "200",
                 "--test-every", "0", "--device", "cpu", "--checkpoint-every", "5", *extra])


def test_bad_steps_create_nothing(distorted, tmp_path, capsys):
    assert _reconstruct(distorted, tmp_path / "out", "--steps", "-1") == 2
    assert "--steps must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_early_ctrl_c_does_not_block_a_rerun(distorted, tmp_path, monkeypatch):
    from tiger.recon.trainer import Trainer

    real = Trainer.train_step

    def interrupted(self, **kw):
        raise KeyboardInterrupt

    out = tmp_path / "out"
    monkeypatch.setattr(Trainer, "train_step", interrupted)
    assert _reconstruct(distorted, out) == 130
    assert (out / "image_cache").is_dir()  # the undistorted images were cached before the stop
    monkeypatch.setattr(Trainer, "train_step", real)
    assert _reconstruct(distorted, out) == 0  # neither --force nor --resume needed
    assert (out / "scene.ply").is_file()


def test_a_corrupt_image_does_not_block_a_rerun(distorted, tmp_path, capsys):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(distorted, data)
    good = (data / "images" / "002.png").read_bytes()
    (data / "images" / "002.png").write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    out = tmp_path / "out"
    assert _reconstruct(data, out) != 0
    assert "002.png" in capsys.readouterr().err
    (data / "images" / "002.png").write_bytes(good)
    assert _reconstruct(data, out) == 0 and (out / "scene.ply").is_file()
    assert _reconstruct(data, tmp_path / "fresh", "--resume") == 0  # and --resume from nothing


def test_cache_and_checkpoint_removed_on_success_unless_kept(distorted, tmp_path, capsys):
    assert _reconstruct(distorted, tmp_path / "a") == 0
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert "image_cache" not in names and "checkpoint.pt" not in names and "scene.ply" in names
    assert "removed image_cache, checkpoint.pt" in capsys.readouterr().out
    assert _reconstruct(distorted, tmp_path / "b", "--keep-cache") == 0
    assert (tmp_path / "b" / "image_cache").is_dir() and (tmp_path / "b" / "checkpoint.pt").is_file()


def test_resume_with_other_settings_is_refused_naming_them(distorted, tmp_path, capsys):
    out = tmp_path / "out"
    assert _reconstruct(distorted, out, "--keep-cache") == 0
    before = (out / "scene.ply").read_bytes()
    capsys.readouterr()
    assert _reconstruct(distorted, out, "--resume", "--downscale", "2", "--steps", "8") == 2
    err = capsys.readouterr().err
    assert "--steps (was 12, now 8)" in err and "--downscale (was 1.0, now 2.0)" in err
    assert (out / "scene.ply").read_bytes() == before
    assert _reconstruct(distorted, out, "--resume", "--keep-cache") == 0  # the same settings resume
