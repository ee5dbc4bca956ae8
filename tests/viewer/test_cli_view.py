"""`tiger view` on bad input: one clear line each; a scene without lang_* is served look-only."""
from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import pytest

from .conftest import demo_scene

pytest.importorskip("viser", reason="the viewer needs viser: pip install viser==1.1.1")


def _run(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "tiger.cli.main", "view", *args], capture_output=True, text=True,
                          timeout=timeout)


def _error_line(res) -> str:
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, (res.returncode, res.stderr)
    return lines[0]


@pytest.fixture(scope="module")
def ply(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli_view") / "scene.ply"
    demo_scene(0.05)[0].scene.save_ply(path)
    return path


def test_help_has_an_example():
    res = subprocess.run([sys.executable, "-m", "tiger.cli.main", "view", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "example: tiger view" in res.stdout and "--host" in res.stdout


def test_missing_scene(tmp_path):
    assert "does not exist" in _error_line(_run(str(tmp_path / "nope.ply")))


def test_unknown_device(ply):
    assert "--device 'gpu7' is not a device" in _error_line(_run(str(ply), "--device", "gpu7"))


def test_port_in_use(ply):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        line = _error_line(_run(str(ply), "--port", str(port), "--device", "cpu"))
    assert f"port {port} on 127.0.0.1 is in use" in line


def test_scene_without_language_is_served_look_only(ply, tmp_path):
    from tiger.scene import GaussianScene

    scene = GaussianScene.load_ply(ply)
    scene.lang = None
    bare = tmp_path / "bare.ply"
    scene.save_ply(bare)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "tiger.cli.main", "view", str(bare), "--port", str(port),
                             "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        first = proc.stdout.readline()
        assert "has no language features (lang_*): look only" in first, first
        t0 = time.time()
        while time.time() - t0 < 60:  # serving
            with socket.socket() as c:
                if c.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.2)
        else:
            raise AssertionError("the server did not start")
    finally:
        proc.send_signal(signal.SIGINT)  # Ctrl-C: a clean stop
        assert proc.wait(30) == 0
