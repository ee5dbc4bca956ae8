"""The training skeleton: view sampling, signed checkpoints, stage timing, the loop (time budget,
Ctrl-C between steps, interrupted steps redone) and the densification schedule."""
from __future__ import annotations

import signal
import time

import pytest
import torch

from tiger.recon.strategy import DensifySchedule
from tiger.train import (CheckpointError, CheckpointMismatch, StageTimer, ViewSampler, read_checkpoint, restore_rng,
                         run_loop, write_checkpoint)


def test_view_sampler_is_inria_order_and_resumes():
    g = torch.Generator().manual_seed(5)
    s = ViewSampler(7, g)
    got = [s.next() for _ in range(21)]
    ref_gen, ref, order = torch.Generator().manual_seed(5), [], []
    for _ in range(21):                                   # the order INRIA's trainer draws
        if not order:
            order = torch.randperm(7, generator=ref_gen).tolist()
        ref.append(order.pop())
    assert got == ref
    for e in range(3):
        assert sorted(got[7 * e:7 * e + 7]) == list(range(7))   # each epoch visits every view once
    s.take(3)
    state, gstate = s.state_dict(), g.get_state()
    ahead = s.take(9)
    g2 = torch.Generator()
    g2.set_state(gstate)
    t = ViewSampler(7, g2)
    t.load_state_dict(state)
    assert t.take(9) == ahead
    sub = ViewSampler([2, 5, 9], torch.Generator().manual_seed(0))
    assert sorted(sub.take(3)) == [2, 5, 9]
    with pytest.raises(ValueError, match=r"views \[4\] outside"):
        sub.load_state_dict({"order": [4]})


def test_peek_does_not_change_the_sequence():
    a, b = ViewSampler(5, torch.Generator().manual_seed(1)), ViewSampler(5, torch.Generator().manual_seed(1))
    seq_a, seq_b = [], []
    for _ in range(12):
        nxt = a.peek(2)
        step = a.take(2)
        assert step == nxt
        seq_a += step
        seq_b += b.take(2)
    assert seq_a == seq_b


def test_checkpoint_signature_rng_and_errors(tmp_path):
    p = tmp_path / "ck.pt"
    g = torch.Generator().manual_seed(3)
    sig = {"views": 4, "config": {"lr": 0.1, "size": (8, 6)}}
    write_checkpoint(p, "tiger.test/1", {"step": 7, "x": torch.arange(3)}, signature=sig, generators=[g])
    assert [f.name for f in tmp_path.iterdir()] == ["ck.pt"]
    expected_g, expected_global = torch.rand(4, generator=g), torch.rand(4)
    ck = read_checkpoint(p, "tiger.test/1", signature={"views": 4, "config": {"lr": 0.1, "size": [8, 6]}})
    assert ck["step"] == 7 and torch.equal(ck["x"], torch.arange(3))
    g2 = torch.Generator()
    restore_rng(ck["rng"], [g2])
    assert torch.equal(torch.rand(4, generator=g2), expected_g) and torch.equal(torch.rand(4), expected_global)
    with pytest.raises(CheckpointMismatch) as e:
        read_checkpoint(p, "tiger.test/1", signature={"views": 5, "config": {"lr": 0.2, "size": [8, 6]}},
                        what="test run")
    msg = str(e.value)
    assert "belongs to another test run" in msg
    assert "config.lr: 0.1 in the checkpoint, 0.2 now" in msg and "views: 4 in the checkpoint, 5 now" in msg
    assert [k for k, _, _ in e.value.differences] == ["config.lr", "views"]
    with pytest.raises(CheckpointError, match="not a tiger.other/1 checkpoint .it is tiger.test/1"):
        read_checkpoint(p, "tiger.other/1")
    p.write_bytes(p.read_bytes()[:50])
    with pytest.raises(CheckpointError, match="cannot read checkpoint") as e:
        read_checkpoint(p, "tiger.test/1")
    assert e.value.reason == "unreadable"
    with pytest.raises(ValueError, match="may not use the keys"):
        write_checkpoint(p, "tiger.test/1", {"rng": 1})


def test_stage_timer_on_the_cpu():
    seen = []
    t = StageTimer(on_stage=lambda n, s: seen.append(n), stages=("a", "never"))
    for _ in range(2):
        with t.stage("b"):
            time.sleep(0.02)
    with t("a"):
        time.sleep(0.01)
    s = t.summary()
    assert list(s) == ["a", "never", "b"] and s["never"] == 0.0
    assert 0.035 < s["b"] < 1.0 and 0.008 < s["a"] < 1.0 and seen == ["b", "b", "a"]
    t2 = StageTimer()
    t2.load(s)
    with t2.stage("a"):
        pass
    assert t2.summary()["a"] >= s["a"] and t2.total == pytest.approx(sum(t2.summary().values()))
    assert "total" in t.table()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_stage_timer_on_cuda_uses_events():
    t = StageTimer("cuda")
    x = torch.randn(2048, 2048, device="cuda")
    with t.stage("matmul"):
        for _ in range(10):
            x = x @ x.T / 2048
    assert t._pending and t.summary()["matmul"] > 0 and not t._pending


class Walker:
    """A toy session: w moves toward a random draw each step."""

    def __init__(self, seed: int = 0, interrupt_at=None, signal_at=None) -> None:
        self.gen = torch.Generator().manual_seed(seed)
        self.w = torch.zeros(3)
        self.step, self.elapsed = 0, 0.0
        self.interrupt_at, self.signal_at, self.saves = interrupt_at, signal_at, []

    def generators(self):
        return [self.gen]

    def step_once(self) -> dict:
        x = torch.rand(3, generator=self.gen)
        if self.step == self.interrupt_at:
            raise KeyboardInterrupt             # before the step changed anything
        if self.step == self.signal_at:
            signal.raise_signal(signal.SIGINT)  # as Ctrl-C would, in the middle of the step
        self.w = self.w + 0.5 * (x - self.w)
        self.step += 1
        return {"loss": self.w.sum()}

    def save(self, path) -> None:
        self.saves.append(self.step)
        write_checkpoint(path, "tiger.walker/1", {"w": self.w, "step": self.step}, generators=self.generators())

    def load(self, path) -> None:
        ck = read_checkpoint(path, "tiger.walker/1")
        self.w, self.step = ck["w"], ck["step"]
        restore_rng(ck["rng"], self.generators())


def _straight(steps: int) -> torch.Tensor:
    w = Walker()
    run_loop(w, steps, progress=False)
    return w.w


@pytest.mark.parametrize("how", ["signal", "raised"])
def test_ctrl_c_leaves_a_checkpoint_that_resumes_exactly(tmp_path, how):
    ck = tmp_path / "ck.pt"
    w = Walker(**({"signal_at": 4} if how == "signal" else {"interrupt_at": 4}))
    with pytest.raises(KeyboardInterrupt):
        run_loop(w, 10, checkpoint=ck, checkpoint_every=3, progress=False)
    # SIGINT is held until the step ends (step 5 is whole); a raised interrupt drops step 5
    assert w.saves == [3, 5] if how == "signal" else w.saves == [3, 4]
    r = Walker()
    r.load(ck)
    run_loop(r, 10, progress=False)
    assert torch.equal(r.w, _straight(10))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handler given back


def test_no_checkpoint_when_interrupted_before_any_step(tmp_path):
    w = Walker(interrupt_at=0)
    with pytest.raises(KeyboardInterrupt):
        run_loop(w, 10, checkpoint=tmp_path / "ck.pt", progress=False)
    assert w.saves == [] and not (tmp_path / "ck.pt").exists()


def test_time_budget_and_end_checkpoint(tmp_path):
    w = Walker()
    out = run_loop(w, 50, checkpoint=tmp_path / "ck.pt", time_budget_s=1e-9, progress=False)
    assert (out.stopped, out.steps_run, w.step, w.saves) == ("time budget", 1, 1, [1])
    w.elapsed = 0.0
    out = run_loop(w, 50, progress=False, after_step=lambda rec: None)
    assert (out.stopped, out.steps_run) == ("done", 49) and torch.equal(w.w, _straight(50))


def test_densify_schedule_edges():
    inria = DensifySchedule(every=100, first=501, last=15_000)    # INRIA: after step 500
    assert [s for s in range(1, 16_001) if inria.due(s)][:2] == [600, 700]
    assert max(s for s in range(1, 16_001) if inria.due(s)) == 15_000
    assert inria.collecting(15_000) and not inria.collecting(15_001)
    edit = DensifySchedule(every=2, first=2, last=6)
    assert [s for s in range(1, 10) if edit.due(s)] == [2, 4, 6]
    off = DensifySchedule(every=0)
    assert not any(off.due(s) or off.collecting(s) for s in range(1, 50))
