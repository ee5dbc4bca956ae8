"""No command overwrites a finished result without --force, and a resume with other inputs or
settings is refused before anything is written, naming what differs."""
from __future__ import annotations

import json

import pytest
import torch

from tiger.cli.common import RUN_RECORD
from tiger.cli.main import main
from tiger.scene import GaussianScene

from .datasets import tabletop_dataset
from .test_delete_cli import _scene_file


def _snapshot(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return tabletop_dataset(tmp_path_factory.mktemp("resume_data"), n_views=3, w=32, h=24)


@pytest.fixture()
def scene_file(tmp_path):
    return _scene_file(tmp_path)[0]


def _delete(scene, out, text, *extra):
    return main(["delete", str(scene), text, "--text-embeddings", str(scene.parent / "text.pt"), "--out", str(out),
                 "--views", "2", "--size", "48x36", "--steps", "2", "--tau", "0.5", "--device", "cpu", *extra])


def test_delete_resume_of_another_deletion_is_refused_and_changes_nothing(scene_file, tmp_path, capsys):
    out = tmp_path / "del"
    assert _delete(scene_file, out, "mug") == 0
    assert json.loads((out / RUN_RECORD).read_text())["finished"] is True
    before = _snapshot(out)
    assert _delete(scene_file, out, "cup", "--resume") == 2
    err = capsys.readouterr().err
    assert "--text (was 'mug', now 'cup')" in err and "Traceback" not in err
    assert _delete(scene_file, out, "mug", "--resume", "--steps", "3") == 2
    assert "--steps (was 2, now 3)" in capsys.readouterr().err
    assert _delete(scene_file, out, "mug") == 2 and "--force" in capsys.readouterr().err
    assert _snapshot(out) == before
    assert _delete(scene_file, out, "mug", "--resume") == 0  # the same run resumes


def test_delete_guard_refuses_a_threshold_that_takes_the_scene(scene_file, tmp_path, capsys):
    out = tmp_path / "all"
    assert _delete(scene_file, out, "mug", "--tau", "-5") == 2
    err = capsys.readouterr().err
    assert "100% of the scene's Gaussians" in err and "--force" in err
    assert not out.exists()


def test_delete_library_refuses_an_empty_result(scene_file):
    from tiger.delete import delete
    from tiger.render.views import orbit_cameras_around

    scene = GaussianScene.load_ply(scene_file)
    cams = orbit_cameras_around(scene.means, 2, 32, 24)
    with pytest.raises(ValueError, match="empty scene"):
        delete(scene, torch.ones(len(scene), dtype=torch.bool), cams, progress=False)


def test_edit_resume_names_what_differs(scene_file, tmp_path, capsys):
    out = tmp_path / "edit"
    base = [str(scene_file), "make it red", "--target", "mug", "--guidance", "recolor", "--text-embeddings",
            str(scene_file.parent / "text.pt"), "--out", str(out), "--tau", "0.5", "--device", "cpu",
            "--video", "none", "--steps", "2", "--size", "16"]
    assert main(["edit", *base]) == 0
    before = _snapshot(out)
    assert main(["edit", *base, "--resume", "--size", "24"]) == 2
    assert "--size (was 16, now 24)" in capsys.readouterr().err
    assert main(["edit", *base, "--resume", "--steps", "3"]) == 2
    assert "--steps (was 2, now 3)" in capsys.readouterr().err
    other = tmp_path / "other.ply"
    scene = GaussianScene.load_ply(scene_file)
    scene.means = scene.means + 0.01
    scene.save_ply(other)
    assert main(["edit", str(other), *base[1:], "--resume"]) == 2
    assert "--scene (" in capsys.readouterr().err
    assert main(["edit", *base]) == 2 and "--force" in capsys.readouterr().err
    assert _snapshot(out) == before


def test_reconstruct_resume_with_other_settings_is_refused(data, tmp_path, capsys):
    out = tmp_path / "recon"
    run = ["reconstruct", str(data), "--out", str(out), "--init-points", "100", "--test-every", "0",
           "--device", "cpu"]
    assert main([*run, "--steps", "3"]) == 0
    before = _snapshot(out)
    assert main([*run, "--steps", "5", "--resume"]) == 2
    assert "--steps (was 3, now 5)" in capsys.readouterr().err
    assert main([*run, "--steps", "3"]) == 2 and "--force" in capsys.readouterr().err
    assert _snapshot(out) == before


def test_features_continues_only_its_own_run(data, tmp_path, capsys):
    out = tmp_path / "feat"
    out.mkdir()
    (out / RUN_RECORD).write_text(json.dumps({"command": "features", "settings": {"pca_dim": 32}}))
    assert main(["features", str(data), "--out", str(out), "--device", "cpu"]) == 2
    assert "--pca-dim (was 32, now 64)" in capsys.readouterr().err
    (out / RUN_RECORD).unlink()
    (out / "pca.pt").write_bytes(b"other")
    assert main(["features", str(data), "--out", str(out), "--device", "cpu"]) == 2
    assert "no record" in capsys.readouterr().err and (out / "pca.pt").read_bytes() == b"other"


def test_embed_continues_only_its_own_checkpoint(data, scene_file, tmp_path, capsys):
    feats = tmp_path / "features"
    feats.mkdir()
    out = tmp_path / "lang.ply"
    ckpt = tmp_path / "lang.ply.ckpt.pt"
    ckpt.write_bytes(b"checkpoint of another run")
    args = ["embed", str(scene_file), str(data), "--features", str(feats), "--out", str(out), "--device", "cpu"]
    (tmp_path / "lang.ply.ckpt.pt.run.json").write_text(json.dumps({"command": "embed", "settings": {"steps": 5}}))
    assert main(args) == 2
    from tiger.language.field import FieldConfig

    assert f"--steps (was 5, now {FieldConfig().steps})" in capsys.readouterr().err
    assert ckpt.read_bytes() == b"checkpoint of another run" and not out.exists()


@pytest.mark.parametrize("command", ["query", "render", "demo"])
def test_finished_outputs_need_force(scene_file, tmp_path, capsys, command):
    out = tmp_path / command
    out.mkdir()
    (out / "result.png").write_bytes(b"finished")
    args = {"query": ["query", str(scene_file), "mug", "--text-embeddings", str(scene_file.parent / "text.pt")],
            "render": ["render", str(scene_file)],
            "demo": ["demo"]}[command]
    assert main([*args, "--out", str(out)] + ([] if command == "demo" else ["--device", "cpu"])) == 2
    assert "--force" in capsys.readouterr().err
    assert (out / "result.png").read_bytes() == b"finished"


def test_tau_is_parsed_the_same_everywhere(scene_file, tmp_path, capsys):
    text = str(scene_file.parent / "text.pt")
    assert main(["query", str(scene_file), "mug", "--text-embeddings", text, "--tau", "otsu", "--views", "1",
                 "--out", str(tmp_path / "q"), "--device", "cpu"]) == 0
    for command in (["query", str(scene_file), "mug"], ["delete", str(scene_file), "mug"],
                    ["edit", str(scene_file), "make it red", "--target", "mug"]):
        with pytest.raises(SystemExit) as e:
            main([*command, "--tau", "often", "--out", str(tmp_path / "x")])
        assert e.value.code == 2
        assert "must be a number or one of auto, valley, kittler, otsu" in capsys.readouterr().err
