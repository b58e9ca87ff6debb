"""Wake asyncio tasks (progress streams) when a run changes; notified from the job manager's threads."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections import defaultdict


def _wake(futures: list[asyncio.Future[None]]) -> None:
    for fut in futures:
        if not fut.done():
            fut.set_result(None)


class ChangeNotifier:
    """Per-run wait/notify across threads and event loops.

    ``notify`` costs one ``call_soon_threadsafe`` per event loop with waiters, however many streams wait,
    so a run followed by many browsers stays cheap.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._waiters: dict[int, list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]]] = defaultdict(
            list
        )
        self._events: list[threading.Event] = []

    def add_event(self, event: threading.Event) -> None:
        """Set ``event`` at every change of any run (a thread that follows runs waits on it instead of
        reading the database on a timer); :meth:`remove_event` stops it."""
        with self._lock:
            self._events.append(event)

    def remove_event(self, event: threading.Event) -> None:
        with self._lock:
            self._events = [e for e in self._events if e is not event]

    def notify(self, run_id: int) -> None:
        with self._lock:
            waiters = self._waiters.pop(run_id, None)
            events = list(self._events)
        for event in events:
            event.set()
        if not waiters:
            return
        by_loop: dict[asyncio.AbstractEventLoop, list[asyncio.Future[None]]] = defaultdict(list)
        for loop, fut in waiters:
            by_loop[loop].append(fut)
        for loop, futures in by_loop.items():
            with contextlib.suppress(RuntimeError):  # that loop has closed
                loop.call_soon_threadsafe(_wake, futures)

    def register(self, run_id: int) -> asyncio.Future[None]:
        """A future that completes at the run's next change (register, then check, then await)."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        with self._lock:
            self._waiters[run_id].append((loop, fut))
        return fut

    def discard(self, run_id: int, fut: asyncio.Future[None]) -> None:
        with self._lock:
            waiters = self._waiters.get(run_id)
            if waiters:
                waiters[:] = [w for w in waiters if w[1] is not fut]
                if not waiters:
                    del self._waiters[run_id]
