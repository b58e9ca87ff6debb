"""Iterate with the next items computed ahead on a background thread.

Used where a loop alternates CPU-side preparation with work that releases the GIL (a torch training step
or forward pass, a kd-tree query): the preparation of item i + 1 runs while item i is consumed.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import TypeVar, cast

T = TypeVar("T")

_POLL_S = 0.05
"""How often a producer blocked on a full queue looks whether the consumer has stopped."""


def prefetched(items: Iterable[T], depth: int = 1) -> Iterator[T]:
    """``items``, in order, computed ahead by one background thread: up to ``depth`` of them wait for the
    consumer, and one more is being computed (so ``depth + 1`` items besides the consumer's are in memory).

    The thread alone iterates ``items``, so a generator that draws from a random source draws in the same
    order as it would unprefetched. An exception raised while producing an item is raised here, in the
    consumer, where that item would have been. When the consumer stops early (``break``, an exception,
    ``close()``), the thread stops after the item it is computing and ``items`` is closed; the call that
    stops waits for it, so nothing of the producer outlives the loop. ``depth`` 0 iterates ``items``
    directly on the caller's thread.
    """
    if depth <= 0:
        yield from items
        return
    slots: queue.Queue[tuple[bool, object]] = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def put(entry: tuple[bool, object]) -> bool:
        while not stop.is_set():
            try:
                slots.put(entry, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        source = iter(items)
        try:
            for item in source:
                if not put((True, item)):
                    return
            put((True, done))
        except BaseException as exc:  # handed to the consumer, which raises it where the item was due
            put((False, exc))
        finally:
            close = getattr(source, "close", None)
            if close is not None:
                close()

    worker = threading.Thread(target=produce, name="prefetch", daemon=True)
    worker.start()
    try:
        while True:
            ok, item = slots.get()
            if not ok:
                assert isinstance(item, BaseException)
                raise item
            if item is done:
                return
            yield cast("T", item)  # every entry but the two markers is an item of ``items``
    finally:
        stop.set()
        worker.join()


__all__ = ["prefetched"]
