"""thread_map: results in the items' order on named worker threads; one worker stays in the caller's thread."""
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
