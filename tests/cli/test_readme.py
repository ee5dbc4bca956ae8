"""The README's table of shared options says what each command's parser has."""
from __future__ import annotations

import re
from pathlib import Path

from tiger.cli.main import build_parser
from tiger.eval import lerf

README = Path(__file__).resolve().parents[2] / "README.md"
OPTIONS = ("--device", "--out", "--force", "--models")


def _parsers():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return {name: (lerf.build_parser() if name == "eval-lerf" else p) for name, p in sub.choices.items()}


def test_readme_option_table_matches_the_parsers():
    text = README.read_text()
    rows = {}
    for line in text.splitlines():
        m = re.match(r"\| ([a-z-]+) \| (.*) \|$", line)
        if m and m.group(1) in _parsers():
            cells = [c.strip() for c in m.group(2).split("|")]
            if len(cells) == len(OPTIONS) and all(c[:1] in "✓–" for c in cells):
                rows[m.group(1)] = [c.startswith("✓") for c in cells]
    parsers = _parsers()
    assert set(rows) == set(parsers), "every command has a row in the README's option table"
    for name, p in parsers.items():
        have = {o for a in p._actions for o in a.option_strings}
        assert rows[name] == [o in have for o in OPTIONS], name


def test_readme_says_up_front_that_make_installs_eigen_as_root():
    head = README.read_text()[:800]
    assert "libeigen3-dev" in head and "root" in head


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_readme_api_tour_runs_as_written(tmp_path, monkeypatch):
    """Every ```python block of the README, in order, in one namespace (as a reader pastes them),
    from a fresh folder: no undefined names, no missing weights, no errors."""
    import time

    blocks = _python_blocks(README.read_text())
    assert len(blocks) >= 6, "the API tour's blocks"
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("TIGER_MODELS", raising=False)
    namespace: dict = {"__name__": "readme_tour"}
    t0 = time.perf_counter()
    for k, block in enumerate(blocks):
        try:
            exec(compile(block, f"README.md python block {k}", "exec"), namespace)
        except Exception as exc:  # name the block that failed
            raise AssertionError(f"README python block {k} failed: {type(exc).__name__}: {exc}\n{block}") from exc
    assert time.perf_counter() - t0 < 600
    hit, tabletop = namespace["hit"], namespace["tabletop"]
    on_ball = tabletop.labels[hit.mask] == tabletop.names.index("ball")
    assert hit.count > 0 and float(on_ball.float().mean()) > 0.9  # the tour's query finds the ball
    for f in ("scene.ply", "edited.ply", "deleted/scene.ply", "scene.spz"):
        assert (tmp_path / "outputs" / "tour" / f).is_file(), f
