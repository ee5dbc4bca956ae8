"""thread_map: results in the items' order on named worker threads; one worker stays in the caller's thread. in_background: one job beside the caller, its result or error handed back."""
import threading
import time

import pytest

from tiger.utils.threads import thread_map


def test_thread_map_keeps_the_order_and_uses_worker_threads():
    seen, done = [], []

    def slow_first(i):
        time.sleep(0.02 * (5 - i))  # the first items finish last
        seen.append(threading.current_thread().name)
        return i * i

    assert thread_map(slow_first, range(5), 8, "tiger-maps", on_done=lambda: done.append(1)) == [0, 1, 4, 9, 16]
    assert all(name.startswith("tiger-maps") for name in seen) and len(done) == 5


def test_one_worker_runs_in_the_callers_thread_and_errors_propagate():
    names = thread_map(lambda _: threading.current_thread().name, [1, 2], 1)
    assert names == [threading.current_thread().name] * 2

    def fail(i):
        if i == 2:
            raise ValueError("item 2")
        return i

    with pytest.raises(ValueError, match="item 2"):
        thread_map(fail, range(4), 4)


def test_in_background_runs_beside_the_caller_and_hands_back_result_or_error():
    import threading
    import time

    import torch

    from tiger.utils.threads import in_background

    started, release = threading.Event(), threading.Event()

    def job():
        started.set()
        release.wait(5)  # the caller goes on meanwhile
        return threading.current_thread().name, torch.is_grad_enabled()

    with torch.no_grad():  # the job runs with the caller's grad mode
        result = in_background(job, "tiger-test-job")
    assert started.wait(5)
    release.set()
    name, grad = result()
    assert name == "tiger-test-job" and grad is False
    assert result() == (name, grad)  # asking again returns the same result

    def failing():
        time.sleep(0.01)
        raise ValueError("tiger.test: the model file is broken")

    with pytest.raises(ValueError, match="model file is broken"):
        in_background(failing)()
