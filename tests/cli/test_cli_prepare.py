"""`tiger prepare` on a tiny rendered capture with tiny random models: all three stages, the
record in prepare.json, skipping finished stages, continuing an unfinished one, refusing
changed inputs, and `tiger query` on the prepared folder."""
from __future__ import annotations

import json

from .datasets import tabletop_dataset as _dataset
from .test_cli_pipeline import _run, _tiny_models

TINY = ["--recon-steps", "40", "--init-points", "500", "--test-every", "3", "--upsampler", "bilinear",
        "--long-side", "32", "--clip-long-side", "64", "--pca-dim", "16", "--embed-steps", "10", "--device", "cpu"]


def test_prepare_resume_and_query(tmp_path):
    data = _dataset(tmp_path / "data")
    cfg = _tiny_models(tmp_path / "models")
    out = tmp_path / "prep"
    r = _run("prepare", str(data), "--out", str(out), "--models", str(cfg), *TINY)
    assert r.returncode == 0, r.stderr[-3000:]
    rec = json.loads((out / "prepare.json").read_text())
    stages = rec["stages"]
    assert [s for s in stages] == ["reconstruct", "features", "embed"]
    assert all(s["done"] and s["seconds"] > 0 for s in stages.values())
    assert stages["reconstruct"]["quality"]["gaussians"] > 0
    assert "held_out_psnr_db" in stages["reconstruct"]["quality"]
    assert stages["features"]["quality"]["maps"] == 6
    assert stages["embed"]["quality"]["field_loss"] > 0
    # the field loss reported is the embed's loss over every view (printed by `tiger embed`), not
    # the last training step's own loss (a band or a pooled view)
    printed = float(r.stdout.split("loss over every pixel of every view ")[1].split()[0].rstrip(";"))
    assert abs(stages["embed"]["quality"]["field_loss"] - printed) <= 1e-4 * max(printed, 1e-6) + 5e-5
    assert (out / "scene_lang.ply").is_file() and (out / "recon" / "scene.ply").is_file()
    for word in ("reconstruct", "features", "embed", "total"):
        assert word in r.stdout

    # an unfinished stage continues; finished ones are skipped without being run again
    stages["embed"]["done"] = False
    (out / "prepare.json").write_text(json.dumps(rec))
    mtime = (out / "recon" / "scene.ply").stat().st_mtime_ns
    r = _run("prepare", str(data), "--out", str(out), "--models", str(cfg), *TINY)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "[1/3] reconstruct: done before" in r.stdout and "[2/3] features: done before" in r.stdout
    assert "[3/3] embed: continuing" in r.stdout
    assert (out / "recon" / "scene.ply").stat().st_mtime_ns == mtime
    assert json.loads((out / "prepare.json").read_text())["stages"]["embed"]["done"]

    # an unfinished stage with other inputs (say a wrong option made it fail) starts afresh
    rec = json.loads((out / "prepare.json").read_text())
    rec["stages"]["embed"]["done"] = False
    (out / "prepare.json").write_text(json.dumps(rec))
    changed = [a if a != "10" else "11" for a in TINY]
    r = _run("prepare", str(data), "--out", str(out), "--models", str(cfg), *changed)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "[3/3] embed: unfinished run had other inputs (steps: 10 -> 11); starting it afresh" in r.stdout
    embed = json.loads((out / "prepare.json").read_text())["stages"]["embed"]
    assert embed["done"] and embed["inputs"]["steps"] == 11

    # other inputs for a finished stage: one line naming the stage and the setting
    changed = [a if a != "10" else "12" for a in TINY]
    r = _run("prepare", str(data), "--out", str(out), "--models", str(cfg), *changed)
    assert r.returncode == 2 and "stage 'embed' finished with other inputs (steps: 11 -> 12)" in r.stderr
    assert "--force" in r.stderr and (out / "scene_lang.ply").is_file()

    # the prepared folder stands for its scene
    r = _run("query", str(out), "mug", "--models", str(cfg), "--views", "1", "--out", str(tmp_path / "q"),
             "--device", "cpu")
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "q" / "selection.json").is_file()


def test_prepare_refuses_a_foreign_folder(tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    data = tmp_path / "data"
    data.mkdir()
    r = _run("prepare", str(data), "--out", str(out))
    assert r.returncode == 2 and "holds no prepare.json" in r.stderr
    assert (out / "notes.txt").read_text() == "mine"


def test_features_alongside_the_reconstruction_give_the_same_maps(tmp_path):
    """--alongside (the default on one GPU) runs `tiger features` in a second process while the
    scene is reconstructed: the same feature files byte for byte as one stage after the other, the
    stage recorded as run alongside, its output in features.log, and the wall clock in the table."""
    data = _dataset(tmp_path / "data")
    cfg = _tiny_models(tmp_path / "models")
    outs = {}
    for mode in ("--sequential", "--alongside"):
        out = tmp_path / mode.strip("-")
        r = _run("prepare", str(data), "--out", str(out), "--models", str(cfg), *TINY, mode)
        assert r.returncode == 0, r.stderr[-3000:]
        outs[mode] = (out, r)
    seq, (alo, r) = outs["--sequential"][0], outs["--alongside"]
    assert "features: running alongside the reconstruction" in r.stdout and "wall clock" in r.stdout
    rec = json.loads((alo / "prepare.json").read_text())["stages"]["features"]
    assert rec["done"] and rec["quality"]["alongside"] == "reconstruct" and rec["quality"]["maps"] == 6
    assert list(json.loads((alo / "prepare.json").read_text())["stages"]) == ["reconstruct", "features", "embed"]
    assert (alo / "features.log").stat().st_size > 0 and not (seq / "features.log").exists()
    files = sorted(p.relative_to(seq / "features") for p in (seq / "features" / "features").glob("*.pt"))
    assert len(files) == 6
    for f in files + [p.relative_to(seq / "features") for p in (seq / "features").glob("pca.*")]:
        assert (seq / "features" / f).read_bytes() == (alo / "features" / f).read_bytes(), f
