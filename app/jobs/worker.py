"""Executes one run of the pipeline, in a child process started by :class:`app.jobs.manager.JobManager`.

The child (``python -m app.jobs.worker``) is a separate process so the pipeline's CPU work never competes
with the server for the GIL, and so a cancel that the pipeline does not honour quickly can still be
enforced by killing it. It reports to the parent as JSON lines on a pipe:

- ``["stage", name, done, total]``: progress (throttled per stage; first and last reports always sent);
- ``["result", outcome]`` last: ``{"status": "done" | "failed" | "cancelled", "error": str | None}``.

The run's log (stage timings, errors with tracebacks) goes to ``run_dir/run.log``.

The parent sends ``cancel`` lines on the child's stdin. A run folder is locked (``flock`` on
``run_dir/.lock``) while a process works in it, and the child dies with its parent (``PR_SET_PDEATHSIG``,
end of stdin, and a parent-pid watchdog), so after a ``kill -9`` of the server no orphan keeps writing into
a run that is about to be resumed.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import fcntl
import logging
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from leap_core.errors import Cancelled, LeapError

LOG_NAME = "run.log"
LOCK_NAME = ".lock"

Emit = Callable[[tuple[Any, ...]], None]


class RunDirBusy(RuntimeError):
    """Another process holds the run folder's lock."""


@contextlib.contextmanager
def run_dir_lock(run_dir: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``run_dir/.lock`` (released when the process dies, even by kill -9)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(run_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunDirBusy(f"{run_dir}: another process is working in this run folder") from None
        yield
    finally:
        os.close(fd)


def _die_with_parent(parent_pid: int) -> None:
    """Make the kernel kill this process when the server dies; a watchdog covers non-Linux systems."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    if os.getppid() != parent_pid:
        os._exit(3)

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent_pid:
                os._exit(3)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


def _run_logger(run_dir: Path) -> logging.Logger:
    logger = logging.getLogger(f"leap.run.{run_dir.name}")
    logger.setLevel(logging.INFO)
    logger.propagate = False
    handler = logging.FileHandler(run_dir / LOG_NAME, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%Y-%m-%d %H:%M:%S"))
    logger.addHandler(handler)
    return logger


class _Reporter:
    """The pipeline's progress callback: throttles messages and turns a cancel request into ``Cancelled``."""

    def __init__(self, emit: Emit, should_cancel: Callable[[], bool], interval: float, log: logging.Logger):
        self.emit = emit
        self.should_cancel = should_cancel
        self.interval = interval
        self.log = log
        self._last: dict[str, float] = {}
        self._started: dict[str, float] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.should_cancel():
            raise Cancelled(f"cancelled during stage {stage}")
        now = time.monotonic()
        first = stage not in self._last
        finished = total > 0 and done >= total
        if first:
            self._started[stage] = now
        if first or finished or now - self._last[stage] >= self.interval:
            self._last[stage] = now
            self.emit(("stage", stage, int(done), int(total)))
        if finished and stage in self._started:
            seconds = now - self._started.pop(stage)
            self.log.info("stage %s done (%d units) in %.2f s", stage, total, seconds)


def execute(spec: Mapping[str, Any], emit: Emit, should_cancel: Callable[[], bool]) -> dict[str, Any]:
    """Run the pipeline described by ``spec`` (built by ``JobManager._spec``) in ``spec['run_dir']``.

    Returns:
        ``{"status": "done" | "failed" | "cancelled", "error": message or None}``. Errors in the user's
        data (``LeapError``) give their one-line message; unexpected ones add the exception type and
        the traceback goes to the run log.
    """
    run_dir = Path(spec["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    log = _run_logger(run_dir)
    try:
        with run_dir_lock(run_dir):
            log.info("run started in %s (pid %d)", run_dir, os.getpid())
            wall0, cpu0 = time.perf_counter(), time.process_time()
            reporter = _Reporter(emit, should_cancel, float(spec.get("progress_interval_s", 0.1)), log)
            try:
                _run(spec, reporter, log)
            except Cancelled:
                log.info("run cancelled")
                return {"status": "cancelled", "error": None}
            except LeapError as exc:
                log.error("run failed: %s", exc)
                return {"status": "failed", "error": str(exc)}
            except Exception as exc:  # noqa: BLE001 - any failure must end as a readable failed run
                log.error("run failed:\n%s", traceback.format_exc())
                return {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
            log.info(
                "run finished in %.2f s wall, %.2f s cpu",
                time.perf_counter() - wall0,
                time.process_time() - cpu0,
            )
            return {"status": "done", "error": None}
    except RunDirBusy as exc:
        return {"status": "failed", "error": str(exc)}
    finally:
        for handler in list(log.handlers):
            handler.close()
            log.removeHandler(handler)


def _run(spec: Mapping[str, Any], reporter: _Reporter, log: logging.Logger) -> None:
    from leap_core.config import config_from_dict
    from leap_core.pipeline import run_pipeline
    from leap_core.runtime import Runtime
    from leap_core.schema import Schema

    dataset = Path(spec["dataset"])
    if spec.get("demo"):
        from app.demo import ensure_demo_sequence

        ensure_demo_sequence(dataset, spec.get("demo_synth") or {}, progress=reporter, log=log)
    schema = Schema.from_dict(spec["schema"], source="project schema")
    config = config_from_dict(spec["pipeline"])
    if spec.get("models_dir") and config.grounded_sam.models_dir is None:
        # The server's models folder applies to projects that do not name their own.
        config = dataclasses.replace(
            config, grounded_sam=dataclasses.replace(config.grounded_sam, models_dir=spec["models_dir"])
        )
    frames = spec.get("frames")
    run_pipeline(
        dataset,
        schema,
        config,
        Path(spec["run_dir"]),
        progress=reporter,
        frames=None if frames is None else range(int(frames[0]), int(frames[1])),
        runtime=Runtime(cache_dir=None if spec.get("cache_dir") is None else Path(spec["cache_dir"])),
    )


def _read_commands(stream: Any, cancel: threading.Event) -> None:
    """Parent → child commands on stdin: ``cancel``. End of input means the parent is gone: exit at once."""
    for line in stream:
        if line.strip() == b"cancel":
            cancel.set()
    os._exit(3)


def child_main(argv: list[str] | None = None) -> None:
    """Entry point of the worker process: ``python -m app.jobs.worker MESSAGE_FD PARENT_PID``.

    The run spec arrives as one JSON line on stdin; further stdin lines are commands. Messages go out as
    JSON lines on file descriptor MESSAGE_FD (not stdout, which libraries may print to).
    """
    import json
    import sys

    args = sys.argv[1:] if argv is None else argv
    message_fd, parent_pid = int(args[0]), int(args[1])
    _die_with_parent(parent_pid)
    # The server handles Ctrl-C; the child stops through a cancel command or a kill.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Import the pipeline before the run arrives: a pre-started worker then starts computing at once.
    import leap_core.pipeline  # noqa: F401

    stdin = sys.stdin.buffer
    line = stdin.readline()
    if not line:
        os._exit(0)  # the server stopped before giving this worker a run
    spec = json.loads(line)
    cancel = threading.Event()
    threading.Thread(target=_read_commands, args=(stdin, cancel), name="commands", daemon=True).start()
    out = os.fdopen(message_fd, "wb", buffering=0)
    lock = threading.Lock()

    def emit(message: tuple[Any, ...]) -> None:
        data = (json.dumps(list(message), separators=(",", ":")) + "\n").encode()
        with lock:
            out.write(data)

    try:
        outcome = execute(spec, emit, cancel.is_set)
    except BaseException as exc:  # noqa: BLE001 - report anything, including import errors
        outcome = {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
    with contextlib.suppress(OSError):
        emit(("result", outcome))
    out.close()
    logging.shutdown()
    # The stdin reader thread is blocked in a read; a normal interpreter shutdown would trip over its lock.
    os._exit(0)


if __name__ == "__main__":
    child_main()
