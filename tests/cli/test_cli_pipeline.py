"""The pipeline commands end to end on a tiny rendered dataset with tiny random models:
reconstruct -> features -> embed -> query/render/info. Checks files, shapes and exit codes
(the models are random, so retrieval quality is not asserted here; tests/language covers it)."""
from __future__ import annotations

import json
import math
import subprocess
import sys

from .datasets import tabletop_dataset


def _run(*args, timeout=900):
    return subprocess.run([sys.executable, "-m", "tiger.cli.main", *args], capture_output=True,
                          text=True, timeout=timeout)


def _tiny_models(root):
    from tiger.testing.random_models import save_random_clip, save_random_sam

    clip = save_random_clip(root / "clip")
    sam = save_random_sam(root / "sam")
    cfg = root / "models.json"
    cfg.write_text(json.dumps({"clip": str(clip), "sam": str(sam)}))
    return cfg


def test_reconstruct_features_embed_query(tmp_path):
    data = tabletop_dataset(tmp_path / "data")
    out = tmp_path / "recon"
    r = _run("reconstruct", str(data), "--out", str(out), "--steps", "60", "--init-points", "800",
             "--test-every", "3", "--device", "cpu", "--keep-cache")  # keeps checkpoint.pt
    assert r.returncode == 0, r.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["gaussians"] > 0 and math.isfinite(metrics["psnr"])
    assert "test views: PSNR" in r.stdout
    # --resume continues from the checkpoint instead of refusing the existing folder
    r = _run("reconstruct", str(data), "--out", str(out), "--steps", "60", "--init-points", "800",
             "--test-every", "3", "--resume")
    assert r.returncode == 0, r.stderr[-2000:]

    cfg = _tiny_models(tmp_path / "models")
    feats = tmp_path / "features"
    r = _run("features", str(data), "--out", str(feats), "--models", str(cfg), "--upsampler",
             "bilinear", "--long-side", "32", "--clip-long-side", "64", "--pca-dim", "16")
    assert r.returncode == 0, r.stderr[-2000:]
    assert (feats / "pca.pt").is_file() and len(list((feats / "features").glob("*.pt"))) == 6

    lang = tmp_path / "scene_lang.ply"
    r = _run("embed", str(out / "scene.ply"), str(data), "--features", str(feats), "--out",
             str(lang), "--steps", "20")
    assert r.returncode == 0, r.stderr[-2000:]
    stages = r.stdout.split("seconds by stage: ")[1].splitlines()[0]  # where the embed's time went
    assert [part.rsplit(" ", 1)[0] for part in stages.split(", ")][:2] == ["read maps", "project and bin"]
    r = _run("info", str(lang))
    assert r.returncode == 0 and "with PCA basis" in r.stdout, r.stdout + r.stderr

    q = tmp_path / "query"
    r = _run("query", str(lang), "mug", "--models", str(cfg), "--data", str(data), "--views", "2",
             "--out", str(q))
    assert r.returncode == 0, r.stderr[-2000:]
    sel = json.loads((q / "selection.json").read_text())
    assert set(sel) == {"mug"} and len(list((q / "relevancy").glob("*.png"))) == 2
    r = _run("render", str(lang), "--data", str(data), "--what", "color", "features", "--out",
             str(tmp_path / "render"))
    assert r.returncode == 0, r.stderr[-2000:]
    assert len(list((tmp_path / "render").glob("*_features.png"))) == 6
