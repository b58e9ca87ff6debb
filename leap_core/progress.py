"""Progress reporting protocol shared by every long-running function."""

from __future__ import annotations

from typing import Protocol

from leap_core.errors import Cancelled


class ProgressFn(Protocol):
    """Called as ``progress(done, total)`` after each unit of work; may raise :class:`Cancelled`."""

    def __call__(self, done: int, total: int) -> None: ...


def report(progress: ProgressFn | None, done: int, total: int) -> None:
    """Call ``progress`` if given (keeps call sites free of ``if progress`` noise)."""
    if progress is not None:
        progress(done, total)


__all__ = ["Cancelled", "ProgressFn", "report"]
