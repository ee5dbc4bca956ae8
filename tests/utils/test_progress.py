"""tiger.utils.progress: tqdm's bar on a terminal, plain lines (no carriage returns) elsewhere."""
from __future__ import annotations

import io

from tiger.utils.progress import progress


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_plain_lines_when_not_a_terminal():
    log = io.StringIO()
    total = 0
    for x in progress(range(50), "rendering", file=log):
        total += x
    assert total == sum(range(50))
    text = log.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    assert 1 <= len(lines) <= 3, lines  # first and last line only (at most one every 30 s)
    assert lines[-1].startswith("rendering") and "50/50" in lines[-1]


def test_total_form_and_updates():
    log = io.StringIO()
    with progress(total=10, desc="training", file=log, mininterval=0, maxinterval=0) as bar:
        for _ in range(10):
            bar.update(1)
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and lines[-1].startswith("training") and "10/10" in lines[-1]
    log2 = io.StringIO()
    with progress(7, "steps", file=log2) as bar:  # an int is a total
        bar.update(7)
    assert "7/7" in log2.getvalue().splitlines()[-1]


def test_a_terminal_gets_the_usual_bar():
    tty = _Terminal()
    for _ in progress(range(5), "x", file=tty):
        pass
    assert "\r" in tty.getvalue()
