"""`--sam-precision` on `tiger features` and `tiger prepare`: one option, parsed the same, reaching
the feature config (prepare forwards it only when given)."""
from __future__ import annotations

import pytest
import torch

from tiger.cli.main import build_parser


class _Stop(Exception):
    pass


def test_parsed_on_features_and_prepare():
    parser = build_parser()
    assert parser.parse_args(["features", "d", "--out", "o"]).sam_precision == "auto"
    assert parser.parse_args(["features", "d", "--out", "o", "--sam-precision", "fp32"]).sam_precision == "fp32"
    with pytest.raises(SystemExit):
        parser.parse_args(["features", "d", "--out", "o", "--sam-precision", "fp16"])
    assert parser.parse_args(["prepare", "d", "--out", "o"]).sam_precision is None
    assert parser.parse_args(["prepare", "d", "--out", "o", "--sam-precision", "bf16"]).sam_precision == "bf16"
    from tiger.cli.prepare import _flag_args

    assert _flag_args({"--sam-precision": None}) == [] and _flag_args({"--sam-precision": "fp32"}) == [
        "--sam-precision", "fp32"]


@pytest.mark.parametrize("option, expected", [([], "auto"), (["--sam-precision", "fp32"], "fp32")])
def test_reaches_the_feature_config(tmp_path, monkeypatch, option, expected):
    from PIL import Image

    import tiger.cli.features as features_cli
    import tiger.language.extract as extract_mod

    data = tmp_path / "images"
    data.mkdir()
    Image.fromarray(torch.zeros(8, 8, 3, dtype=torch.uint8).numpy()).save(data / "a.png")
    seen = {}

    def spy(files, out, *, config, **kw):
        seen["config"] = config
        raise _Stop

    monkeypatch.setattr(features_cli, "_claim", lambda args: tmp_path / "out")
    monkeypatch.setattr(extract_mod, "extract_features", spy)
    args = build_parser().parse_args(["features", str(data), "--out", str(tmp_path / "out"), *option])
    with pytest.raises(_Stop):
        features_cli.run(args)
    assert seen["config"].sam.precision == expected
