"""The one lagged worker (``workers``): results are taken at the frame they are due, in the
order handed over, whatever the worker's speed; ``due(None)`` takes all; inline runs each
task at once; a task's error reaches whoever takes its result."""

from __future__ import annotations

import threading
import time

import pytest

from edgevo_jax.workers import Worker


def slow_square(x: int) -> int:
    time.sleep(0.02 * (3 - x % 3))  # later tasks finish no earlier than earlier ones anyway
    return x * x


@pytest.mark.parametrize("inline", [False, True])
def test_results_are_taken_at_their_frame_in_order(inline):
    worker = Worker("test", inline=inline)
    try:
        queue = worker.queue(lag=2)
        for frame in range(5):
            queue.submit(frame, f"k{frame}", slow_square, frame)
        assert queue.due(1) == []  # nothing is due before frame 0 + 2
        assert queue.due(3) == [("k0", 0), ("k1", 1)]
        assert queue.tags == ["k2", "k3", "k4"] and len(queue) == 3
        assert queue.due(None) == [("k2", 4), ("k3", 9), ("k4", 16)]
        assert queue.due(None) == []
    finally:
        worker.close()


def test_a_worker_runs_beside_the_caller_and_inline_runs_at_once():
    worker = Worker("beside")
    try:
        names = []
        worker.run(lambda: names.append(threading.current_thread().name)).result()
        assert names[0].startswith("edgevo-beside")
    finally:
        worker.close()
    inline = Worker("inline", inline=True)
    assert inline.inline
    assert inline.run(threading.current_thread).result() is threading.current_thread()


@pytest.mark.parametrize("inline", [False, True])
def test_an_error_is_raised_where_the_result_is_taken(inline):
    worker = Worker("error", inline=inline)
    try:
        queue = worker.queue(lag=0)
        queue.submit(0, "bad", lambda: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            queue.due(0)
    finally:
        worker.close()


def test_clear_drops_what_was_not_taken():
    worker = Worker("clear")
    try:
        queue = worker.queue(lag=1)
        queue.submit(0, "a", slow_square, 1)
        queue.clear()
        assert queue.due(None) == [] and queue.tags == []
    finally:
        worker.close()
