"""``leap_core.prefetch.prefetched``: the same items in the same order, produced ahead on one other
thread, errors raised where the item was due, and nothing left running when the consumer stops."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest

from leap_core.prefetch import prefetched


def _draws(rng: np.random.Generator, n: int, log: list[tuple[int, str]]) -> Iterator[float]:
    for i in range(n):
        log.append((i, threading.current_thread().name))
        yield float(rng.random())


def test_items_come_in_order_from_one_thread_ahead_of_the_consumer() -> None:
    log: list[tuple[int, str]] = []
    plain = list(_draws(np.random.default_rng(3), 6, []))
    got = []
    for item in prefetched(_draws(np.random.default_rng(3), 6, log)):
        got.append(item)
    assert got == plain  # a random source draws in the same order as unprefetched
    assert {name for _, name in log} == {"prefetch"}
    assert [i for i, _ in log] == list(range(6))


def test_the_next_item_is_made_while_the_consumer_holds_this_one() -> None:
    made = [threading.Event() for _ in range(4)]

    def items() -> Iterator[int]:
        for i in range(4):
            made[i].set()
            yield i

    for item in prefetched(items()):
        if item < 3:
            assert made[item + 1].wait(10), f"item {item + 1} was not made while item {item} was in hand"


def test_an_error_is_raised_where_its_item_was_due() -> None:
    def failing() -> Iterator[int]:
        yield 1
        yield 2
        raise ValueError("scan 3: broken file")

    got = []
    with pytest.raises(ValueError, match="scan 3: broken file"):
        for item in prefetched(failing()):
            got.append(item)
    assert got == [1, 2]


def test_stopping_early_stops_and_closes_the_producer() -> None:
    produced: list[int] = []
    closed = threading.Event()

    def endless() -> Iterator[int]:
        try:
            i = 0
            while True:
                produced.append(i)
                yield i
                i += 1
        finally:
            closed.set()

    for item in prefetched(endless(), depth=2):
        if item == 3:
            break
    assert closed.is_set()  # the generator's cleanup ran before the loop's exit returned
    # The producer has ended (counted by name: other tests' threads may come and go meanwhile).
    assert not any(t.name == "prefetch" for t in threading.enumerate())
    assert len(produced) <= 3 + 1 + 2 + 1  # consumed, in hand, the queue's depth, one being made


def test_depth_zero_iterates_on_the_callers_thread() -> None:
    log: list[tuple[int, str]] = []
    assert list(prefetched(_draws(np.random.default_rng(0), 2, log), depth=0)) == list(
        _draws(np.random.default_rng(0), 2, [])
    )
    assert {name for _, name in log} == {threading.current_thread().name}
