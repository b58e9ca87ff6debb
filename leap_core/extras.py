"""The optional stacks (pyproject.toml's extras) and the one-line error a command gives without one.

``leap run --ray``, ``leap import rosbag``, ``leap import nuscenes`` and the memory benchmarks import their
stack only when they run. Without it they stop with :class:`MissingExtra`, whose message names the extra
that installs it; every other command works without any extra. The ``fast`` extra (numba) only speeds the
fusion up: without it the fusion runs its numpy path, which gives the same bytes.
"""

from __future__ import annotations

from dataclasses import dataclass

from leap_core.errors import LeapError

NUSCENES_DEVKIT = "nuscenes-devkit==1.2.0"
"""The devkit release scripts/install.sh installs, with ``--no-deps``: its metadata pins numpy<2, so its
imports are the ``nuscenes`` extra instead (pyproject.toml)."""


@dataclass(frozen=True)
class _Stack:
    label: str
    """What the message calls the stack when its own package is the one missing."""
    module: str
    """The stack's own top-level module."""
    users: str
    """What needs the stack's other modules (named when one of those is the missing one)."""
    install: str
    """The command that installs the extra."""


STACKS: dict[str, _Stack] = {
    "ray": _Stack("Ray", "ray", "Ray", "pip install 'leap-studio[ray]'"),
    "ros": _Stack("rosbags", "rosbags", "rosbags", "pip install 'leap-studio[ros]'"),
    "nuscenes": _Stack(
        "nuscenes-devkit",
        "nuscenes",
        "nuscenes-devkit",
        f"pip install 'leap-studio[nuscenes]' && pip install --no-deps '{NUSCENES_DEVKIT}'",
    ),
    "bench": _Stack("psutil", "psutil", "the benchmarks", "pip install 'leap-studio[bench]'"),
    # Never missing in the sense of the others: without numba the fusion runs its numpy path, same bytes.
    "fast": _Stack("numba", "numba", "the fusion's compiled kernels", "pip install 'leap-studio[fast]'"),
}
"""The extras by name (pyproject.toml's ``[project.optional-dependencies]``, less ``test``)."""


class MissingExtra(LeapError):
    """An optional stack is not installed: ``Ray is not installed: pip install 'leap-studio[ray]'``.

    Args:
        extra: the extra that installs it (a key of :data:`STACKS`).
        module: the module that failed to import (``ModuleNotFoundError.name``); when it is not the stack's
            own (a dependency of the devkit, say), the message names it and what needs it.
    """

    def __init__(self, extra: str, module: str | None = None) -> None:
        stack = STACKS[extra]
        top = (module or stack.module).partition(".")[0]
        what = stack.label if top == stack.module else f"{top} (needed by {stack.users})"
        super().__init__(f"{what} is not installed: {stack.install}")
        self.extra, self.module = extra, module

    def __reduce__(self) -> tuple[object, ...]:
        # Exceptions pickle as ``cls(*args)`` (the message), which is not this constructor's signature.
        return (MissingExtra, (self.extra, self.module))


__all__ = ["NUSCENES_DEVKIT", "STACKS", "MissingExtra"]
