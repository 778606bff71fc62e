"""ordered_map: results in order, progress in the caller's thread, failures raised."""

from __future__ import annotations

import threading
import time

import pytest

from workers.pipeline.threads import ordered_map, thread_count


def test_results_come_in_order_however_long_each_takes() -> None:
    def slow_first(x: int) -> tuple[int, str]:
        time.sleep(0.02 * (5 - x))
        return x * x, threading.current_thread().name

    out = ordered_map(slow_first, list(range(5)), threads=3)
    assert [v for v, _ in out] == [0, 1, 4, 9, 16]
    assert len({name for _, name in out}) > 1  # spread over threads
    assert ordered_map(slow_first, [], threads=3) == []


def test_done_is_called_in_order_from_the_callers_thread() -> None:
    calls: list[tuple[int, str]] = []
    ordered_map(
        lambda x: x,
        list(range(4)),
        threads=2,
        done=lambda k: calls.append((k, threading.current_thread().name)),
    )
    assert [k for k, _ in calls] == [1, 2, 3, 4]
    assert {name for _, name in calls} == {threading.current_thread().name}


@pytest.mark.parametrize("threads", [1, 2])
def test_a_failure_is_raised_and_the_calls_not_started_are_dropped(threads: int) -> None:
    started: list[int] = []

    def fn(x: int) -> int:
        started.append(x)
        time.sleep(0.01)
        if x == 1:
            raise ValueError("item 1 is bad")
        return x

    with pytest.raises(ValueError, match="item 1 is bad"):
        ordered_map(fn, list(range(40)), threads=threads)
    assert len(started) < 40


def test_a_cancel_from_done_stops_the_rest() -> None:
    started: list[int] = []

    def fn(x: int) -> int:
        started.append(x)
        time.sleep(0.01)
        return x

    def done(k: int) -> None:
        if k == 2:
            raise KeyboardInterrupt  # what a cancelled job's progress raises, in kind

    with pytest.raises(KeyboardInterrupt):
        ordered_map(fn, list(range(40)), threads=2, done=done)
    assert len(started) < 40


def test_zero_threads_is_one_per_core() -> None:
    assert thread_count(0) >= 1
    assert thread_count(3) == 3
