"""atomic_write: files get the mode a plain open() gives them (0666 less the umask)."""
import os
import stat

import pytest
import torch

from tiger.utils.io import atomic_torch_save, atomic_write


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield lambda m: os.umask(m)
    os.umask(old)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077])
def test_mode_follows_the_umask_like_open(umask, tmp_path, mask):
    umask(mask)
    with open(tmp_path / "plain.txt", "w") as fh:  # the reference: what any program gets
        fh.write("x")
    with atomic_write(tmp_path / "atomic.txt", "w") as fh:
        fh.write("x")
    atomic_torch_save({"a": torch.zeros(2)}, tmp_path / "ckpt.pt")
    assert _mode(tmp_path / "plain.txt") == 0o666 & ~mask
    assert _mode(tmp_path / "atomic.txt") == _mode(tmp_path / "plain.txt")
    assert _mode(tmp_path / "ckpt.pt") == _mode(tmp_path / "plain.txt")
    assert os.umask(mask) == mask  # the writer left the umask as it found it


def test_outputs_of_the_cli_writers_are_world_readable(umask, tmp_path):
    from tiger.scene import GaussianScene
    from tiger.utils.images import save_png

    umask(0o022)
    save_png(tmp_path / "a.png", torch.rand(4, 5, 3))
    scene = GaussianScene.random_in_box(3, [0, 0, 0], [1, 1, 1], sh_degree=0,
                                        generator=torch.Generator().manual_seed(0))
    scene.save_ply(tmp_path / "scene.ply")
    assert _mode(tmp_path / "a.png") == 0o644
    assert _mode(tmp_path / "scene.ply") == 0o644
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left


def test_failed_write_leaves_the_old_file(tmp_path):
    target = tmp_path / "f.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(target, "w") as fh:
            fh.write("new")
            raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]


def test_file_slug_is_the_one_rule_and_unique_slugs_number_repeats():
    from tiger.utils.io import file_slug, unique_file_slugs

    assert file_slug("the red mug!") == "the_red_mug" and file_slug("???") == "query"
    assert file_slug("a" * 100) == "a" * 80 and file_slug("a" * 100, max_len=None) == "a" * 100
    assert file_slug("img-01.v2", keep="-") == "img-01_v2" and file_slug("img-01") == "img_01"
    assert unique_file_slugs(["cup", "cup", "c u p", "c?u?p", "!!"], ["v0", "v1", "v2", "v3", "v4"]) == [
        "cup", "cup_2", "c_u_p", "c_u_p_2", "v4"]


class _InterruptWhilePickled:
    """Sends Ctrl-C (SIGINT) to this process while torch.save is pickling it."""

    def __reduce__(self):
        import signal

        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):  # let Python deliver the signal inside the serializer
            pass
        return (dict, ())


def test_ctrl_c_during_a_checkpoint_write_finishes_the_file_then_interrupts(tmp_path):
    path = tmp_path / "checkpoint.pt"
    atomic_torch_save({"step": 1}, path)
    big = {"step": 2, "weights": torch.arange(1_000_000, dtype=torch.float32), "x": _InterruptWhilePickled()}
    with pytest.raises(KeyboardInterrupt):
        atomic_torch_save(big, path)
    # a plain KeyboardInterrupt after the write: the new file is complete and readable
    loaded = torch.load(path, weights_only=False)
    assert loaded["step"] == 2 and torch.equal(loaded["weights"], big["weights"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]  # no temporary left


def test_ctrl_c_outside_writes_is_immediate():
    import signal

    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored after writes


def test_fsync_is_skipped_only_when_asked(tmp_path, monkeypatch):
    synced = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real(fd)))
    atomic_torch_save({"x": torch.arange(3)}, tmp_path / "kept.pt")
    assert len(synced) == 1
    atomic_torch_save({"x": torch.arange(4)}, tmp_path / "cache.pt", fsync=False)
    assert len(synced) == 1  # no flush to the disk, still renamed into place whole
    assert torch.equal(torch.load(tmp_path / "cache.pt", weights_only=True)["x"], torch.arange(4))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache.pt", "kept.pt"]
