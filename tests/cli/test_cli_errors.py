"""What a new user meets on bad input: one line, one exit-code convention (2 bad input, 1 failure
while running, 130 interrupted, 141 reader gone), nothing written; and honest reports (timers,
the recolour's RGB, the missing PCA sidecar, every missing model)."""
from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from PIL import Image

from tiger.cli import common
from tiger.cli.main import build_parser, main

from .test_delete_cli import _scene_file


@pytest.fixture(scope="module")
def lang_scene(tmp_path_factory):
    """(PLY with lang_* + PCA sidecar, its text table) of the tabletop; the table knows 'mug', 'cup'
    and the canonical negatives."""
    root = tmp_path_factory.mktemp("lang")
    path, _, _ = _scene_file(root)
    table = torch.load(root / "text.pt")
    g = torch.Generator().manual_seed(1)
    for word in ("object", "things", "stuff", "texture"):  # LERF's canonical negatives (edit's weights)
        table[word] = torch.randn(512, generator=g)
    torch.save(table, root / "text.pt")
    return path, root / "text.pt"


def _last_line(err: str) -> str:
    lines = [l for l in err.strip().splitlines() if l.strip()]
    assert lines, "no message"
    assert "Traceback" not in err, err
    return lines[-1]


def test_summary_counts_the_whole_command(capsys):
    common.mark_command_start()
    time.sleep(0.3)  # the work, done before the summary object exists
    s = common.Summary("tiger x")
    s.print()
    out = capsys.readouterr().out
    assert float(out.split("done in ")[1].split(" s")[0]) >= 0.3


@pytest.mark.parametrize("args, needle", [
    (["render", "{scene}", "--size", "0", "0"], "--size must be two positive"),
    (["render", "{scene}", "--size", "-5", "10"], "--size must be two positive"),
    (["query", "{scene}", "mug", "--views", "-3", "--text-embeddings", "{table}"], "--views must be >= 0"),
    (["delete", "{scene}", "mug", "--background", "5,5,5", "--text-embeddings", "{table}"], "in [0, 1]"),
    (["render", "{scene}", "--orbit", "1", "--size", "100000", "100000"], "GiB"),
])
def test_bad_numbers_are_refused_in_one_line(lang_scene, tmp_path, capsys, args, needle):
    scene, table = lang_scene
    out = tmp_path / "out"
    t0 = time.perf_counter()
    code = main([a.format(scene=scene, table=table) for a in args] + ["--out", str(out), "--device", "cpu"])
    assert time.perf_counter() - t0 < 30  # refused up front, not after a 120 GB allocation
    assert code == 2
    assert needle in _last_line(capsys.readouterr().err)
    assert not out.exists() or not any(out.iterdir())


def test_text_embeddings_that_are_not_a_torch_file(lang_scene, tmp_path, capsys):
    scene, _ = lang_scene
    bad = tmp_path / "table.pt"
    bad.write_bytes(b"these are not pickled tensors\n" * 10)
    code = main(["query", str(scene), "mug", "--text-embeddings", str(bad), "--out", str(tmp_path / "q")])
    assert code == 2
    line = _last_line(capsys.readouterr().err)
    assert str(bad) in line and "is not a torch.save'd" in line
    assert not (tmp_path / "q").exists()


def test_unknown_text_lists_the_table_case_insensitive_and_short(tmp_path, capsys):
    from tiger.retrieval.text import EmbeddingTable, UnknownTextError

    table = EmbeddingTable({f"object {i:02d}": torch.randn(8) for i in range(25)} | {"Potted Plant": torch.ones(8)})
    assert torch.equal(table.encode_text(["potted plant"])[0], torch.ones(8))  # case and spaces ignored
    assert torch.equal(table.encode_text(["  POTTED   plant "])[0], torch.ones(8))
    with pytest.raises(UnknownTextError) as e:
        table.encode_text(["unicorn"])
    msg = str(e.value)
    assert "its 26 texts" in msg and all(f"object {i:02d}" in msg for i in range(25)) and "Potted Plant" in msg
    big = {f"t{i:03d}": torch.randn(8) for i in range(100)}
    with pytest.raises(UnknownTextError, match="and 40 more"):
        EmbeddingTable(big).encode_text(["x" * 100_000])
    with pytest.raises(UnknownTextError) as e:
        EmbeddingTable(big).encode_text(["x" * 100_000])
    assert len(str(e.value)) < 2000 and "(100000 characters)" in str(e.value)


def test_missing_pca_sidecar_is_named(lang_scene, tmp_path, capsys):
    import shutil

    scene, table = lang_scene
    lone = tmp_path / "copied.ply"
    shutil.copy(scene, lone)  # the PLY without its .lang_pca.npz
    code = main(["query", str(lone), "mug", "--text-embeddings", str(table), "--out", str(tmp_path / "q")])
    assert code == 2
    line = _last_line(capsys.readouterr().err)
    assert str(tmp_path / "copied.lang_pca.npz") in line and "missing" in line


def test_exit_codes_bad_input_two_failure_one(lang_scene, tmp_path, capsys, monkeypatch):
    bad_ply = tmp_path / "bad.ply"
    bad_ply.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    assert main(["info", str(bad_ply)]) == 2  # a malformed file is bad input
    assert "bad.ply" in _last_line(capsys.readouterr().err)
    scene, table = lang_scene
    assert main(["query", str(scene), "unicorn", "--text-embeddings", str(table), "--out", str(tmp_path / "u")]) == 2
    assert "no embedding for ['unicorn']" in _last_line(capsys.readouterr().err)

    import tiger.cli.info as info

    def crash(args):
        raise RuntimeError("CUDA error: an illegal memory access\n   (second line)")

    monkeypatch.setattr(info, "run", crash)
    assert main(["info", str(scene)]) == 1
    line = _last_line(capsys.readouterr().err)
    assert line.startswith("tiger info: error: RuntimeError: CUDA error") and "-v" in line


def test_exit_codes_are_documented():
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert "Exit codes" in readme and "| 2 |" in readme and "| 1 |" in readme
    assert "Exit codes" in build_parser().epilog


def test_info_into_a_closed_pipe_is_quiet(lang_scene):
    scene, _ = lang_scene
    proc = subprocess.Popen([sys.executable, "-m", "tiger.cli.main", "info", str(scene)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # `| head -0`: the reader is gone before the first line
    _, err = proc.communicate(timeout=300)
    assert b"Traceback" not in err and b"BrokenPipe" not in err, err.decode()
    assert proc.returncode == 141


def test_reconstruct_on_an_empty_folder_names_every_format(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["reconstruct", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    line = _last_line(capsys.readouterr().err)
    assert "transforms.json" in line and "COLMAP" in line


def test_models_config_with_an_unknown_key(tmp_path):
    from tiger.models.paths import REGISTRY, resolve_model_path

    cfg = tmp_path / "models.json"
    cfg.write_text(json.dumps({"clp": "/x"}))
    with pytest.raises(ValueError) as e:
        resolve_model_path("clip", config=str(cfg))
    assert "'clp'" in str(e.value) and all(k in str(e.value) for k in REGISTRY)
    assert set(REGISTRY) == {"clip", "sam", "featup_jbu", "ip2p", "mvdream", "lama"}


def test_missing_diffusion_weights_all_named_and_nothing_written(lang_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("TIGER_MODELS", raising=False)
    scene, table = lang_scene
    (tmp_path / "models").mkdir()
    out = tmp_path / "e"
    code = main(["edit", str(scene), "make it red", "--target", "mug", "--text-embeddings", str(table),
                 "--models", str(tmp_path / "models"), "--out", str(out), "--device", "cpu"])
    assert code == 2
    line = _last_line(capsys.readouterr().err)
    assert "model 'ip2p' not found" in line and "model 'mvdream' not found" in line
    assert "--guidance recolor" in line and "allow_download" not in line
    assert not out.exists()


def test_recolor_shades_negations_and_the_rgb_recorded(lang_scene, tmp_path, capsys):
    from tiger.edit.guidance.recolor import COLORS, parse_color

    green = torch.tensor(COLORS["green"], dtype=torch.float64)
    assert torch.allclose(parse_color("make it dark green"), green * 0.55)
    assert torch.allclose(parse_color("light green"), green + (1 - green) * 0.5)
    assert torch.allclose(parse_color("make the green mug red"), torch.tensor(COLORS["red"], dtype=torch.float64))
    with pytest.raises(ValueError, match="negates 'red'"):
        parse_color("make it not red")

    scene, table = lang_scene
    out = tmp_path / "e"
    code = main(["edit", str(scene), "make it dark green", "--target", "mug", "--text-embeddings", str(table),
                 "--guidance", "recolor", "--steps", "2", "--size", "16", "--tau", "0.5", "--video", "none",
                 "--out", str(out), "--device", "cpu"])
    assert code == 0
    printed = capsys.readouterr().out
    rep = json.loads((out / "edit.json").read_text())
    assert rep["recolor_rgb"] == pytest.approx((green * 0.55).tolist(), abs=1e-4)
    assert "RGB " + ", ".join(f"{v:.3f}" for v in rep["recolor_rgb"]) in printed
    # one edit time: the loop's (as its rounds record it), and the command's wall time beside it
    assert rep["time_s"] == rep["rounds"][-1]["time_s"] and rep["command_s"] >= rep["time_s"]
    assert float(printed.split("done in ")[1].split(" s")[0]) >= rep["time_s"]
    assert main(["edit", str(scene), "make it not red", "--target", "mug", "--text-embeddings", str(table),
                 "--guidance", "recolor", "--out", str(tmp_path / "e2")]) == 2
    assert not (tmp_path / "e2").exists()


def test_depth_pictures_carry_a_colour_bar(lang_scene, tmp_path):
    import matplotlib

    scene, _ = lang_scene
    out = tmp_path / "r"
    assert main(["render", str(scene), "--orbit", "1", "--size", "40", "30", "--what", "color", "depth",
                 "--out", str(out), "--device", "cpu"]) == 0
    color = np.asarray(Image.open(out / "orbit000_color.png"))
    depth = np.asarray(Image.open(out / "orbit000_depth.png"))[..., :3].astype(np.float64) / 255
    assert color.shape[:2] == (30, 40) and depth.shape[:2] == (30, 40 + 68)
    bar = depth[:, 40 + 4 + 6]  # the bar's middle column: turbo from far (top) to near (bottom)
    turbo = matplotlib.colormaps["turbo"](np.linspace(1, 0, 30))[:, :3]
    assert np.abs(bar - turbo).max() < 0.02


def test_render_relevancy_shows_the_score_query_uses():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    defaults = {name: {a.dest: a.default for a in sub.choices[name]._actions} for name in ("render", "query")}
    assert defaults["render"]["score"] == defaults["query"]["score"]


def test_a_default_edit_on_the_cpu_warns_with_the_expected_time(tmp_path, caplog):
    import logging

    with caplog.at_level(logging.WARNING, logger="tiger.cli.edit"):
        code = main(["edit", str(tmp_path / "missing.ply"), "make it red", "--target", "mug", "--guidance",
                     "recolor", "--out", str(tmp_path / "e"), "--device", "cpu"])
    assert code == 2  # the scene is missing; the warning came first, from the settings alone
    warned = [r.getMessage() for r in caplog.records if "edit on the CPU" in r.getMessage()]
    assert warned and "about 13 min" in warned[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="tiger.cli.edit"):
        main(["edit", str(tmp_path / "missing.ply"), "make it red", "--target", "mug", "--guidance", "recolor",
              "--steps", "20", "--size", "64", "--out", str(tmp_path / "e"), "--device", "cpu"])
    assert not [r for r in caplog.records if "edit on the CPU" in r.getMessage()]  # a short edit: quiet


def test_eval_edit_refusals_leave_no_folder(lang_scene, tmp_path, capsys):
    scene, table = lang_scene
    out = tmp_path / "ev"
    assert main(["eval-edit", str(scene), str(scene), "--target", "unicorn", "--text-embeddings", str(table),
                 "--out", str(out), "--device", "cpu"]) == 2
    assert "no embedding for ['unicorn']" in _last_line(capsys.readouterr().err)
    assert not out.exists()


def test_features_without_weights_names_every_missing_model(tmp_path, capsys, monkeypatch):
    from PIL import Image as PILImage

    monkeypatch.delenv("TIGER_MODELS", raising=False)
    (tmp_path / "imgs").mkdir()
    PILImage.new("RGB", (8, 8)).save(tmp_path / "imgs" / "a.png")
    out = tmp_path / "f"
    assert main(["features", str(tmp_path / "imgs"), "--out", str(out), "--models", str(tmp_path / "none"),
                 "--upsampler", "jbu"]) == 2
    line = _last_line(capsys.readouterr().err)
    assert "3 of 3 models not found" in line and all(f"model '{m}'" in line for m in ("clip", "sam", "featup_jbu"))
    assert not out.exists()


def test_edit_refuses_a_video_kind_it_cannot_write_before_any_work(tmp_path, capsys, monkeypatch):
    """--video mp4 on a machine without an H.264 encoder: one line before the scene is even read
    (not after a long edit), and no output folder."""
    from tiger.utils import video

    def broken(arrays, tmp, fps):
        raise RuntimeError("no encoder in this build")

    monkeypatch.setitem(video._ENCODERS, "mp4", (broken,))
    out = tmp_path / "e"
    code = main(["edit", str(tmp_path / "missing.ply"), "make it red", "--target", "mug", "--guidance", "recolor",
                 "--video", "mp4", "--out", str(out), "--device", "cpu"])
    assert code == 2
    assert _last_line(capsys.readouterr().err).startswith("tiger edit: error: --video mp4: cannot write MP4 (broken:")
    assert not out.exists()
