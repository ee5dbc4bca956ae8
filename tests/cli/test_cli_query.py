"""tiger query with several texts: every text is checked before anything is written,
selection.json names every text, a refused query leaves nothing behind."""
from __future__ import annotations

import json

import pytest
import torch

from tiger.cli.main import main
from tiger.retrieval import CANONICAL_NEGATIVES
from tiger.scene import GaussianScene

F, D = 8, 4


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A scene whose lang features are the PCA projections of two embeddings (ball, cup), and the
    {text: embedding} table of those, another known text and the canonical negatives."""
    root = tmp_path_factory.mktemp("query")
    g = torch.Generator().manual_seed(0)
    n = 120
    scene = GaussianScene.random_in_box(n, [-1, -1, -1], [1, 1, 1], sh_degree=0, generator=g)
    basis = torch.linalg.qr(torch.randn(F, D, generator=g))[0]
    mean = torch.zeros(F)
    table = {t: torch.randn(F, generator=g) for t in ["ball", "cup", "fox ears", *CANONICAL_NEGATIVES]}
    lang = torch.where((torch.arange(n) < n // 2)[:, None], table["ball"] @ basis, table["cup"] @ basis)
    scene.lang, scene.lang_pca_basis, scene.lang_pca_mean = lang + 0.01 * torch.randn(n, D, generator=g), basis, mean
    scene.save_ply(root / "scene.ply")
    GaussianScene.random_in_box(5, [0, 0, 0], [1, 1, 1], generator=g).save_ply(root / "plain.ply")
    torch.save(table, root / "table.pt")
    return root


def _query(files, out, *texts):
    return main(["query", str(files / "scene.ply"), *texts, "--text-embeddings", str(files / "table.pt"),
                 "--out", str(out), "--views", "1", "--device", "cpu"])


def test_every_text_is_checked_before_anything_is_written(files, tmp_path, capsys):
    out = tmp_path / "q"
    assert _query(files, out, "ball", "unicorn", "cup") == 2
    err = capsys.readouterr().err
    assert "no embedding for ['unicorn']" in err and "nothing was written" in err
    assert not out.exists()


def test_refused_query_leaves_no_folder(files, tmp_path, capsys):
    out = tmp_path / "q"
    assert main(["query", str(files / "plain.ply"), "ball", "--text-embeddings", str(files / "table.pt"),
                 "--out", str(out)]) == 2
    assert "no language features" in capsys.readouterr().err
    assert not out.exists()


def test_several_texts_all_written_with_selection_json(files, tmp_path):
    out = tmp_path / "q"
    assert _query(files, out, "ball", "cup", "fox ears") == 0
    sel = json.loads((out / "selection.json").read_text())
    assert list(sel) == ["ball", "cup", "fox ears"]
    assert sel["ball"]["selected"] > 0 and sel["cup"]["selected"] > 0
    for text in sel:
        slug = sel[text]["files"]
        assert (out / f"{slug}_highlight_0.png").is_file(), text
    assert (out / "fox_ears_highlight_0.png").is_file()
    assert len(list((out / "relevancy").glob("*.png"))) == 3
