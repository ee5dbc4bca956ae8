"""tiger reconstruct: --resume never writes into a folder it cannot resume, Ctrl-C writes a
checkpoint and says which step it holds, --time-budget and --max-gaussians."""
from __future__ import annotations

import pytest
import torch

from tiger.cli.main import main

from .datasets import tabletop_dataset


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return tabletop_dataset(tmp_path_factory.mktemp("recon_data"), n_views=3, w=32, h=24)


def _reconstruct(data, out, *extra):
    return main(["reconstruct", str(data), "--out", str(out), "--steps", "30", "--init-points", "200",
                 "--test-every", "0", "--device", "cpu", "--checkpoint-every", "10", *extra])


def test_resume_without_checkpoint_refuses_a_non_empty_folder(data, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "scene.ply").write_bytes(b"precious")
    assert _reconstruct(data, out, "--resume") == 2
    err = capsys.readouterr().err
    assert "no record of a `tiger reconstruct` run" in err and "--force" in err and "scene.ply" in err
    assert (out / "scene.ply").read_bytes() == b"precious" and sorted(p.name for p in out.iterdir()) == ["scene.ply"]


def test_resume_into_an_empty_or_new_folder_starts_fresh(data, tmp_path):
    assert _reconstruct(data, tmp_path / "new", "--resume", "--steps", "10") == 0
    assert (tmp_path / "new" / "scene.ply").is_file()


def test_reconstruct_stores_the_capture_cameras_beside_the_scene(data, tmp_path):
    from tiger.scene.cameras_json import read_cameras_json
    from tiger.scene.dataset import load_dataset

    assert _reconstruct(data, tmp_path / "out", "--steps", "5") == 0
    cams = read_cameras_json(tmp_path / "out" / "cameras.json")
    ref = load_dataset(data).cameras  # every view, train and test, at full resolution
    assert [c.image_name for c in cams] == [c.image_name for c in ref]
    for a, b in zip(cams, ref):
        assert torch.allclose(a.viewmat.double(), b.viewmat.double(), atol=1e-9)
        assert torch.allclose(a.K.double(), b.K.double()) and (a.width, a.height) == (b.width, b.height)
    # the PLY stays a plain INRIA PLY
    assert b"cameras" not in (tmp_path / "out" / "scene.ply").read_bytes()[:4096]


def test_ctrl_c_names_the_checkpoint_step_and_resume_continues(data, tmp_path, capsys, monkeypatch):
    from tiger.recon.trainer import Trainer

    real = Trainer.train_step

    def interrupted_at_25(self, **kw):
        if self.step == 25:
            raise KeyboardInterrupt
        return real(self, **kw)

    out = tmp_path / "out"
    monkeypatch.setattr(Trainer, "train_step", interrupted_at_25)
    assert _reconstruct(data, out) == 130
    err = capsys.readouterr().err
    # the interrupt itself leaves a checkpoint of the last whole step (not the periodic one of step 20)
    assert "stopped at step 25 of 30" in err and "checkpoint.pt holds step 25" in err and "--resume" in err
    monkeypatch.setattr(Trainer, "train_step", real)
    assert _reconstruct(data, out, "--resume") == 0
    assert "resumed from" in capsys.readouterr().out and (out / "scene.ply").is_file()
    # the resumed scene is the uninterrupted one, bit for bit
    assert _reconstruct(data, tmp_path / "straight") == 0
    from tiger.scene import GaussianScene

    assert GaussianScene.load_ply(out / "scene.ply").equal(GaussianScene.load_ply(tmp_path / "straight" / "scene.ply"))


def test_resume_with_other_settings_is_refused_naming_them(data, tmp_path, capsys):
    out = tmp_path / "out"
    assert _reconstruct(data, out, "--steps", "10") == 0
    before = (out / "checkpoint.pt").read_bytes()
    assert _reconstruct(data, out, "--resume", "--sh-degree", "1") == 2
    err = capsys.readouterr().err
    assert "belongs to another reconstruction" in err and "config.sh_degree: 3 in the checkpoint, 1 now" in err
    assert (out / "checkpoint.pt").read_bytes() == before


def test_time_budget_stops_early_and_resume_continues(data, tmp_path, capsys):
    import json

    out = tmp_path / "out"
    assert _reconstruct(data, out, "--time-budget", "1e-9") == 0    # every step outlasts it: one step
    m = json.loads((out / "metrics.json").read_text())
    assert m["steps"] == 1 and m["stopped"] == "time budget"
    assert "time budget of 1e-09 s reached: stopped at step 1 of 30" in capsys.readouterr().out
    assert _reconstruct(data, out, "--resume") == 0                # no budget: runs to the end
    m = json.loads((out / "metrics.json").read_text())
    assert m["steps"] == 30 and m["stopped"] == "done"
    assert _reconstruct(data, tmp_path / "bad", "--time-budget", "0") == 2
    assert "--time-budget must be > 0" in capsys.readouterr().err


def test_max_gaussians_caps_densification(data, tmp_path, capsys):
    import json

    # 300 steps: INRIA's schedule scaled down densifies at steps 150 and 200
    assert _reconstruct(data, tmp_path / "free", "--steps", "300", "--init-points", "100") == 0
    free = json.loads((tmp_path / "free" / "metrics.json").read_text())["gaussians"]
    assert free > 110, free                                         # it does grow without a cap
    assert _reconstruct(data, tmp_path / "cap", "--steps", "300", "--init-points", "100",
                        "--max-gaussians", "110") == 0
    assert json.loads((tmp_path / "cap" / "metrics.json").read_text())["gaussians"] <= 110
    assert _reconstruct(data, tmp_path / "bad", "--max-gaussians", "0") == 2
    assert "--max-gaussians must be >= 1" in capsys.readouterr().err


def test_ctrl_c_before_the_first_checkpoint(data, tmp_path, capsys, monkeypatch):
    from tiger.recon.trainer import Trainer

    def interrupted(self, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(Trainer, "train_step", interrupted)
    assert _reconstruct(data, tmp_path / "out") == 130
    assert "stopped at step 0 of 30; this run wrote no checkpoint yet" in capsys.readouterr().err


def _with_missing_frames(data, tmp_path, gone):
    import shutil

    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    for i in gone:
        (copy / "images" / f"{i:03d}.png").unlink()
    return copy


@pytest.mark.parametrize("command", ["reconstruct", "features", "render"])
def test_missing_frames_name_the_flag_and_every_file(data, tmp_path, capsys, command):
    copy = _with_missing_frames(data, tmp_path, [0, 2])
    args = {"reconstruct": ["reconstruct", str(copy)],
            "features": ["features", str(copy)],
            "render": ["render", str(tmp_path / "none.ply"), "--data", str(copy)]}[command]
    if command == "render":  # a scene to render: any PLY
        from tiger.scene import GaussianScene
        import torch

        GaussianScene.random_in_box(5, [0, 0, 0], [1, 1, 1], generator=torch.Generator().manual_seed(0)) \
            .save_ply(tmp_path / "none.ply")
    assert main([*args, "--out", str(tmp_path / "out"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "2 of 3 images not found" in err and "000.png" in err and "002.png" in err
    assert "--skip-missing" in err and "skip_missing=True" not in err


def test_skip_missing_flag_drops_the_views(data, tmp_path, capsys):
    copy = _with_missing_frames(data, tmp_path, [2])
    assert _reconstruct(copy, tmp_path / "out", "--skip-missing", "--steps", "5") == 0
    assert "2 training views" in capsys.readouterr().out
