import threading

import pytest
import torch

from tiger.utils.streams import run_beside


def test_cpu_runs_when_asked_in_the_callers_thread_without_grad():
    calls = []
    x = torch.ones(3, requires_grad=True)

    def fn():
        calls.append(threading.current_thread())
        return x * 2

    later = run_beside(fn, "cpu", (x,))
    assert calls == []  # nothing ran yet: on the CPU the work is a plain call, made when asked for
    out = later()
    assert calls == [threading.current_thread()]
    assert torch.equal(out, torch.full((3,), 2.0)) and not out.requires_grad


def test_errors_reach_the_caller():
    def fn():
        raise ValueError("tiger.test: boom")

    with pytest.raises(ValueError, match="boom"):
        run_beside(fn, "cpu")()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_side_stream_result_equals_a_plain_call_beside_a_captured_graph():
    dev = torch.device("cuda")
    g = torch.Generator(device=dev).manual_seed(0)
    a = torch.randn(2048, 2048, device=dev, generator=g)
    b = torch.randn(2048, 2048, device=dev, generator=g)
    expected = (a @ b).relu().sum(0)
    torch.cuda.synchronize()
    later = run_beside(lambda: [(a @ b).relu().sum(0) for _ in range(20)][-1], dev, (a, b))
    # meanwhile the caller captures and replays a graph, as the implicit FeatUp fit does
    x = torch.zeros(1024, device=dev)
    side = torch.cuda.Stream(dev)
    side.wait_stream(torch.cuda.current_stream(dev))
    with torch.cuda.stream(side):
        x.add_(1)
    torch.cuda.current_stream(dev).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph, capture_error_mode="thread_local"):
        x.mul_(2).add_(1)
    for _ in range(5):
        graph.replay()
    out = later()
    assert torch.equal(out, expected)
    assert threading.current_thread() is threading.main_thread()
    assert float(x[0]) == 63.0  # 1, then five replays of x = 2x + 1 (a capture itself runs nothing)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_after_an_event_runs_while_the_callers_queue_does():
    """``after=event``: the side work waits for that event only, not for the kernels the caller
    queued since (here a ~1 s sleep kernel), and its result is still ordered before the caller's
    later work once joined."""
    dev = torch.device("cuda")
    a = torch.randn(512, 512, device=dev)

    def fn():
        out = (a @ a).sum(0)
        done = torch.cuda.Event()
        done.record()
        return out, done

    run_beside(fn, dev)()  # the worker's first use: its cuBLAS handle and memory, which may synchronise
    torch.cuda.synchronize()
    ready = torch.cuda.Event()
    ready.record(torch.cuda.current_stream(dev))
    torch.cuda._sleep(2_000_000_000)  # ~1 s of GPU clock on the caller's stream
    main_done = torch.cuda.Event()
    main_done.record(torch.cuda.current_stream(dev))
    later = run_beside(fn, dev, after=ready)
    import time

    start = time.perf_counter()
    out, side_done = later()
    while not side_done.query() and time.perf_counter() - start < 5.0:
        time.sleep(0.001)
    assert side_done.query() and not main_done.query()  # done while the caller's sleep still runs
    torch.cuda.synchronize()
    torch.testing.assert_close(out, (a @ a).sum(0))
