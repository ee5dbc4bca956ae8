"""`tiger features` and `tiger prepare` under torchrun (2 CPU processes, gloo): each rank extracts
its share of the images, and every file of the features folder equals the one-process run's."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

from benchmarks.prepare import compare_folders

from .datasets import tabletop_dataset
from .test_cli_pipeline import _run, _tiny_models

FEATURES = ["--upsampler", "bilinear", "--long-side", "32", "--clip-long-side", "64", "--pca-dim", "8",
            "--device", "cpu"]

pytestmark = pytest.mark.skipif(not torch.distributed.is_available(), reason="needs torch.distributed")


def _torchrun(*args, timeout=900):
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "tiger.cli.main", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("torchrun")
    return tabletop_dataset(root / "data", n_views=4), _tiny_models(root / "models")


def test_features_sharded_equal_one_process(tmp_path, capture):
    data, cfg = capture
    one, two = tmp_path / "one", tmp_path / "two"
    r = _run("features", str(data), "--out", str(one), "--models", str(cfg), *FEATURES)
    assert r.returncode == 0, r.stderr[-3000:]
    r = _torchrun("features", str(data), "--out", str(two), "--models", str(cfg), *FEATURES)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.count("feature maps in") == 1 and "(2 ranks)" in r.stdout  # one summary, by rank 0
    cmp = compare_folders(one, two)
    assert cmp["files"] >= 4 + 4 + 1 and not cmp["differ"], cmp
    # a bad folder stops both ranks with rank 0's one line
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "mine.txt").write_text("keep")
    r = _torchrun("features", str(data), "--out", str(tmp_path / "busy"), "--models", str(cfg), *FEATURES)
    assert r.returncode != 0 and (tmp_path / "busy" / "mine.txt").read_text() == "keep"
    assert "tiger features: error:" in r.stderr


def test_prepare_shards_the_feature_stage(tmp_path, capture):
    data, cfg = capture
    tiny = ["--recon-steps", "30", "--init-points", "400", "--test-every", "3", "--embed-steps", "5", *FEATURES]
    one = tmp_path / "one"
    r = _run("prepare", str(data), "--out", str(one), "--models", str(cfg), *tiny)
    assert r.returncode == 0, r.stderr[-3000:]
    two = tmp_path / "two"
    scene = one / "recon" / "scene.ply"
    r = _torchrun("prepare", str(data), "--out", str(two), "--scene", str(scene), "--models", str(cfg), *tiny)
    assert r.returncode == 0, r.stderr[-3000:]
    stages = json.loads((two / "prepare.json").read_text())["stages"]
    assert all(s["done"] for s in stages.values()) and stages["features"]["quality"]["maps"] == 4
    assert r.stdout.count("tiger prepare:") == 1  # rank 0's table only
    cmp = compare_folders(one / "features", two / "features")
    assert not cmp["differ"], cmp
    # a re-run under torchrun: every stage done before, nothing runs on any rank
    r = _torchrun("prepare", str(data), "--out", str(two), "--scene", str(scene), "--models", str(cfg), *tiny)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "[2/3] features: done before" in r.stdout and "[3/3] embed: done before" in r.stdout
