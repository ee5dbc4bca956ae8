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
