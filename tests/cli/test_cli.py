"""The tiger command: help texts, one-line errors, the demo writes its pictures."""
from __future__ import annotations

import subprocess
import sys

import pytest

from tiger.cli.main import build_parser, main


def _run(*args):
    return subprocess.run([sys.executable, "-m", "tiger.cli.main", *args], capture_output=True,
                          text=True, timeout=600)


def test_every_subcommand_has_help_with_example():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert sub.choices, "no subcommands"
    for name in sub.choices:
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0


def test_demo_refuses_to_overwrite_then_runs(tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    r = _run("demo", "--out", str(out), "--width", "64", "--height", "48", "--views", "1")
    assert r.returncode == 2 and "--force" in r.stderr and "Traceback" not in r.stderr
    r = _run("demo", "--out", str(out), "--width", "64", "--height", "48", "--views", "1",
             "--steps", "40", "--queries", "ball", "--force")
    assert r.returncode == 0, r.stderr
    for kind in ("color", "depth", "alpha", "features_pca"):
        assert (out / f"view0_{kind}.png").stat().st_size > 100
    for name in ("highlight_ball.png", "retrieved_ball.png", "relevancy/ball_view0.png"):
        assert (out / name).stat().st_size > 100, name
    assert "-> ball" in r.stdout  # the query retrieved the ball


def test_bad_arguments_give_one_line_error():
    r = _run("demo", "--width", "-3", "--out", "/tmp/tiger-never", "--force")
    assert r.returncode == 2 and "must be positive" in r.stderr and "Traceback" not in r.stderr
