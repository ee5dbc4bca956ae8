"""``tiger delete`` end to end on the demo tabletop (built-in OpenCV inpainting, no weights)."""
from __future__ import annotations

import json

import torch

from tiger.cli.main import main
from tiger.scene import GaussianScene

from ..delete.test_pipeline import _tabletop
from .datasets import tabletop_dataset


def _scene_file(tmp_path):
    """The tabletop as a PLY with 64-d lang and a 512 -> 64 PCA basis, and a text table whose
    'mug' entry projects onto the mug's language features."""
    scene, is_mug, query = _tabletop(density=0.3)
    g = torch.Generator().manual_seed(0)
    basis, _ = torch.linalg.qr(torch.randn(512, 64, generator=g))  # orthonormal columns
    scene.lang_pca_basis, scene.lang_pca_mean = basis.contiguous(), torch.zeros(512)
    path = tmp_path / "scene.ply"
    scene.save_ply(path)
    torch.save({"mug": basis @ query, "cup": basis @ query}, tmp_path / "text.pt")
    return path, int(is_mug.sum()), len(scene)


def test_cli_delete_writes_scene_pictures_and_report(tmp_path, capsys):
    path, n_mug, n = _scene_file(tmp_path)
    out = tmp_path / "out"
    args = [str(path), "mug", "--text-embeddings", str(tmp_path / "text.pt"), "--out", str(out),
            "--views", "4", "--size", "96x72", "--steps", "4", "--tau", "0.5", "--background", "1,1,1",
            "--device", "cpu"]
    assert main(["delete", *args]) == 0
    rep = json.loads((out / "delete.json").read_text())
    assert rep["counts"]["retrieved"] == n_mug and rep["counts"]["total"] == n
    assert set(rep["timings_s"]) == {"remove", "render", "inpaint", "refit", "total"}
    assert rep["metrics"]["locality_psnr"] > 30
    result = GaussianScene.load_ply(out / "scene.ply")
    assert len(result) == rep["counts"]["final"] and result.lang is not None
    for k in range(4):
        assert (out / f"before_{k}.png").is_file() and (out / f"after_{k}.png").is_file()
    assert len(list((out / "holes").glob("*.png"))) == 4 == len(list((out / "inpainted").glob("*.png")))
    assert "tiger delete done" in capsys.readouterr().out
    # the output folder is not overwritten without --force; --resume continues the refit
    assert main(["delete", *args]) == 2
    assert main(["delete", *args, "--resume"]) == 0


def test_cli_delete_errors(tmp_path, capsys):
    path, _, _ = _scene_file(tmp_path)
    base = [str(path), "--text-embeddings", str(tmp_path / "text.pt"), "--device", "cpu"]
    assert main(["delete", *base[:1], "ball", *base[1:], "--out", str(tmp_path / "a")]) == 2  # bad input
    assert "no embedding for ['ball']" in capsys.readouterr().err
    cfg = tmp_path / "models.json"
    cfg.write_text(json.dumps({"lama": str(tmp_path / "lama" / "big-lama.pt")}))
    assert main(["delete", *base[:1], "mug", *base[1:], "--out", str(tmp_path / "b"),
                 "--inpainter", "lama", "--models", str(cfg)]) == 2  # missing weights: bad setup
    err = capsys.readouterr().err
    assert "model 'lama' not found" in err and "big-lama.pt" in err


def test_cli_delete_on_a_capture(tmp_path):
    """--data: the capture's views (every other of 6, named after its images) and its images as
    the inpainter's context."""
    path, _, _ = _scene_file(tmp_path)
    data = tabletop_dataset(tmp_path / "data", n_views=6)
    out = tmp_path / "out"
    assert main(["delete", str(path), "cup", "--text-embeddings", str(tmp_path / "text.pt"), "--out", str(out),
                 "--data", str(data), "--views", "3", "--steps", "2", "--tau", "0.5", "--device", "cpu"]) == 0
    rep = json.loads((out / "delete.json").read_text())
    assert rep["views"] == 3 and rep["data"] == str(data)
    assert sorted(p.name for p in (out / "holes").glob("*.png")) == ["000_000.png", "001_002.png", "002_004.png"]
