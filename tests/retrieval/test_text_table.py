"""The one text-embedding table: look-ups, files, case folding, errors that name the text."""
from __future__ import annotations

import pytest
import torch

from tiger.retrieval.text import EmbeddingTable, UnknownTextError


def test_lookup_save_load_round_trip(tmp_path):
    g = torch.Generator().manual_seed(0)
    vecs = {"red mug": torch.randn(8, generator=g, dtype=torch.float64), "floor": torch.randn(1, 8, generator=g)}
    t = EmbeddingTable(vecs)
    out = t.encode_text(["floor", "red mug", "floor"])
    assert out.dtype == torch.float32 and out.shape == (3, 8)
    assert torch.equal(out[1], vecs["red mug"].float()) and torch.equal(out[0], out[2])
    back = EmbeddingTable.load(t.save(tmp_path / "t.pt"))
    assert torch.equal(back.encode_text(["red mug"]), t.encode_text(["red mug"]))
    assert "floor" in back and "Floor" in back and " FLOOR " in back  # case and spaces do not matter
    assert "floors" not in back


def test_fold_case_and_unknown_text():
    t = EmbeddingTable({"Mug": torch.ones(3)}, fold_case=True, source="the demo", hint="; use CLIP")
    assert torch.equal(t.encode_text(["  mug "]), torch.ones(1, 3))
    with pytest.raises(UnknownTextError) as e:
        t.encode_text(["mug", "unicorn"])
    assert isinstance(e.value, KeyError) and isinstance(e.value, ValueError)
    assert str(e.value) == "no embedding for ['unicorn'] in the demo (its 1 texts: 'mug'); use CLIP"


def test_bad_tables_are_named(tmp_path):
    with pytest.raises(ValueError, match="is empty"):
        EmbeddingTable({})
    with pytest.raises(ValueError, match=r"mixes embedding sizes \[3, 4\]"):
        EmbeddingTable({"a": torch.zeros(3), "b": torch.zeros(4)})
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(ValueError, match="list.pt must hold a dict"):
        EmbeddingTable.load(tmp_path / "list.pt")
