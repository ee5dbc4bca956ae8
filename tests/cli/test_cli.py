"""The tiger command: help texts, one-line errors, the demo writes its pictures."""
from __future__ import annotations

import subprocess
import sys

import pytest

import tiger.scene
from tiger.cli.main import build_parser, main


def _run(*args):
    return subprocess.run([sys.executable, "-m", "tiger.cli.main", *args], capture_output=True,
                          text=True, timeout=600)


def test_every_subcommand_has_help_with_example(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert set(sub.choices) >= {"reconstruct", "features", "embed", "query", "render",
                                "eval-lerf", "info", "demo", "edit", "eval-edit"}
    for name in sub.choices:
        try:
            code = main([name, "--help"])
        except SystemExit as e:
            code = e.code
        assert code == 0, name
        assert "example: tiger " + name in capsys.readouterr().out, name


def test_demo_refuses_to_overwrite_then_runs(tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    r = _run("demo", "--out", str(out), "--width", "64", "--height", "48", "--views", "1")
    assert r.returncode == 2 and "--force" in r.stderr and "Traceback" not in r.stderr
    r = _run("demo", "--out", str(out), "--width", "64", "--height", "48", "--views", "1",
             "--steps", "40", "--queries", "ball", "--edit-steps", "10", "--force")
    assert r.returncode == 0, r.stderr
    assert (out / "edit_before_after.png").stat().st_size > 100 and (out / "scene_ball_red.ply").is_file()
    for kind in ("color", "depth", "alpha", "features_pca"):
        assert (out / f"view0_{kind}.png").stat().st_size > 100
    for name in ("highlight_ball.png", "retrieved_ball.png"):
        assert (out / name).stat().st_size > 100, name
    assert len(list((out / "relevancy").glob("ball_view*.png"))) == 2
    assert "-> ball" in r.stdout  # the query retrieved the ball
    assert (out / "scene.ply").is_file() and (out / "text_embeddings.pt").is_file()

    # The other commands work on what the demo wrote.
    r = _run("info", str(out / "scene.ply"))
    assert r.returncode == 0 and "64-d, with PCA basis" in r.stdout, r.stderr
    q = tmp_path / "query"
    r = _run("query", str(out / "scene.ply"), "ball", "cup", "--text-embeddings",
             str(out / "text_embeddings.pt"), "--out", str(q), "--views", "1", "--tau", "0.5")
    assert r.returncode == 0, r.stderr
    import json

    sel = json.loads((q / "selection.json").read_text())
    assert sel["ball"]["selected"] > 0 and sel["cup"]["selected"] > 0
    assert (q / "ball.ply").is_file() and (q / "ball_highlight_0.png").is_file()
    rd = tmp_path / "render"
    r = _run("render", str(out / "scene.ply"), "--orbit", "2", "--size", "64", "48", "--what",
             "color", "depth", "features", "--video", "--out", str(rd))
    assert r.returncode == 0, r.stderr
    assert len(list(rd.glob("*_features.png"))) == 2 and list(rd.glob("turntable.*"))
    # tiger edit (recolor, no weights) and tiger eval-edit on the demo's scene
    ed = tmp_path / "edit"
    emb = str(out / "text_embeddings.pt")
    r = _run("edit", str(out / "scene.ply"), "make it red", "--target", "ball", "--guidance", "recolor",
             "--text-embeddings", emb, "--tau", "0.5", "--steps", "12", "--size", "48", "--video", "gif",
             "--device", "cpu", "--out", str(ed))
    assert r.returncode == 0, r.stderr
    rep = json.loads((ed / "edit.json").read_text())
    assert rep["selected"] > 0 and rep["metrics"]["locality"]["psnr"] > 30 and rep["settings"]["steps"] == 12
    assert rep["guidance_settings"] == {"color": [0.86, 0.08, 0.08], "strength": 1.0}  # "red", as it ran
    assert (ed / "before_after.png").stat().st_size > 100 and (ed / "turntable.gif").is_file()
    edited = tiger.scene.GaussianScene.load_ply(ed / "edited.ply")
    assert edited.lang is not None and edited.metadata["tiger_edits"][-1]["instruction"] == "make it red"
    r = _run("eval-edit", str(out / "scene.ply"), str(ed / "edited.ply"), "--target", "ball", "--text-embeddings",
             emb, "--tau", "0.5", "--views", "3", "--size", "48", "--out", str(tmp_path / "ev"))
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "ev" / "metrics.json").read_text())["locality"]["psnr"] > 30
    r = _run("edit", str(out / "scene.ply"), "make it red", "--target", "ball", "--guidance", "ip2p",
             "--text-embeddings", emb, "--tau", "0.5", "--models", str(tmp_path / "no_models"),
             "--out", str(tmp_path / "e2"))
    assert r.returncode != 0 and "Traceback" not in r.stderr and "instruct-pix2pix" in r.stderr.lower(), r.stderr
    r = _run("edit", str(out / "scene.ply"), "make it red", "--target", "ball", "--cuda-graph", "--device", "cpu",
             "--text-embeddings", emb, "--out", str(tmp_path / "e3"))
    assert r.returncode != 0 and "--cuda-graph needs a CUDA --device" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "e3").exists()  # refused before anything was written
    r = _run("query", str(out / "scene.ply"), "unicorn", "--text-embeddings",
             str(out / "text_embeddings.pt"), "--out", str(tmp_path / "q2"))
    assert r.returncode != 0 and "no embedding for ['unicorn']" in r.stderr
    assert "Traceback" not in r.stderr


def test_bad_arguments_give_one_line_error(tmp_path):
    r = _run("demo", "--width", "-3", "--out", "/tmp/tiger-never", "--force")
    assert r.returncode == 2 and "must be positive" in r.stderr and "Traceback" not in r.stderr
    for args in (["info", str(tmp_path / "missing.ply")],
                 ["reconstruct", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")],
                 ["render", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "r")],
                 ["eval-lerf", "--labels", str(tmp_path)]):
        r = _run(*args)
        assert r.returncode != 0, args
        assert "Traceback" not in r.stderr and r.stderr.strip(), args
        assert "error" in r.stderr.strip().splitlines()[-1], (args, r.stderr)
