"""Executes one run of the pipeline, in a child process started by :class:`app.jobs.manager.JobManager`.

The child (``python -m app.jobs.worker``) is a separate process so the pipeline's CPU work never competes
with the server for the GIL, and so a cancel that the pipeline does not honour quickly can still be
enforced by killing it. Both directions carry the messages of :mod:`app.jobs.messages`, one JSON line
each: the parent writes a :class:`~app.jobs.messages.RunSpec` and later
:class:`~app.jobs.messages.CancelRun` commands on the child's stdin; the child reports
:class:`~app.jobs.messages.StageProgress` (throttled per stage; first and last reports always sent) and
:class:`~app.jobs.messages.LogLine` (the pipeline's warnings) on a pipe, and one
:class:`~app.jobs.messages.RunOutcome` last.

The run's log (stage timings, errors with tracebacks) goes to ``run_dir/run.log``.

A run folder is locked (``flock`` on ``run_dir/.lock``) while a process works in it, and the child dies with
its parent (``PR_SET_PDEATHSIG``, end of stdin, and a parent-pid watchdog), so after a ``kill -9`` of the
server no orphan keeps writing into a run that is about to be resumed.
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import logging
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

from app.core.errors import disk_full_message
from app.demo import ensure_demo_sequence
from app.jobs.messages import (
    CancelRun,
    FromWorker,
    LogLine,
    MessageError,
    RunOutcome,
    RunSpec,
    StageProgress,
    decode_to_worker,
)
from app.jobs.poses import prepare_run_poses
from app.jobs.stages import POSES, SYNTH, stage_folder, stage_name
from leap_core.config import config_from_dict
from leap_core.errors import Cancelled, LeapError, ModelLoadError, PosesMissingError
from leap_core.run_layout import RunLayout
from leap_core.runtime import Runtime
from leap_core.schema import Schema

LOG_NAME = RunLayout.LOG
LOCK_NAME = RunLayout.LOCK

worker_log = logging.getLogger("leap.worker")
"""The worker process's own messages (stderr, i.e. the server's worker.log); a run logs to its run.log."""

Emit = Callable[[FromWorker], None]
"""Sends one message to the server."""


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


def _run_logger(run_dir: Path) -> tuple[logging.Logger, logging.Handler]:
    """The run's own logger, and the handler writing to its ``run.log`` (the pipeline's warnings, e.g.
    frames without a camera image, go there too: the UI shows that log)."""
    logger = logging.getLogger(f"leap.run.{run_dir.name}")
    logger.setLevel(logging.INFO)
    logger.propagate = False
    handler = logging.FileHandler(run_dir / LOG_NAME, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%Y-%m-%d %H:%M:%S"))
    logger.addHandler(handler)
    return logger, handler


class _Reporter:
    """The pipeline's progress callback: throttles messages and turns a cancel request into ``Cancelled``."""

    def __init__(
        self,
        emit: Emit,
        should_cancel: Callable[[], bool],
        interval: float,
        log: logging.Logger,
        run_dir: Path | None = None,
    ):
        self.emit = emit
        self.should_cancel = should_cancel
        self.interval = interval
        self.log = log
        self.run_dir = run_dir
        """The run folder: a stage's completion is checked in its sequence's ``stages.json`` for a skip
        (stage names are ``<sequence>/<stage>``, :mod:`app.jobs.stages`)."""
        self.since = time.time()
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
        skipped = None
        where = self._stage_record(stage) if finished and first else None
        if where is not None:
            # The pipeline reports a stage it skips as complete at once, after recording why. (Imported
            # here: a run has loaded the pipeline by now; the server importing this module must not.)
            from leap_core.pipeline.runner import skip_reason  # noqa: PLC0415  see the comment above

            skipped = skip_reason(where[0], where[1], self.since)
        if first or finished or now - self._last[stage] >= self.interval:
            self._last[stage] = now
            self.emit(StageProgress(stage, int(done), int(total), skipped))
        if finished and stage in self._started:
            seconds = now - self._started.pop(stage)
            if skipped is not None:
                self.log.info("stage %s skipped (%s)", stage, skipped)
            else:
                self.log.info("stage %s done (%d units) in %.2f s", stage, total, seconds)

    def _stage_record(self, stage: str) -> tuple[Path, str] | None:
        """(sequence folder, stage name) whose ``stages.json`` records the progress stage ``stage``."""
        return None if self.run_dir is None else stage_folder(self.run_dir, stage)


def execute(spec: RunSpec, emit: Emit, should_cancel: Callable[[], bool]) -> RunOutcome:
    """Run the pipeline described by ``spec`` (built by ``JobManager._spec``) in ``spec.run_dir``.

    Returns:
        How it ended. Errors in the user's data (``LeapError``) give their one-line message; unexpected
        ones add the exception type and the traceback goes to the run log.
    """
    run_dir = spec.run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    log, handler = _run_logger(run_dir)
    pipeline_warnings = logging.FileHandler(run_dir / LOG_NAME, encoding="utf-8")
    pipeline_warnings.setLevel(logging.WARNING)
    pipeline_warnings.setFormatter(handler.formatter)
    logging.getLogger("leap_core").addHandler(pipeline_warnings)
    try:
        with run_dir_lock(run_dir):
            log.info("run started in %s (pid %d)", run_dir, os.getpid())
            wall0, cpu0 = time.perf_counter(), time.process_time()
            reporter = _Reporter(emit, should_cancel, spec.progress_interval_s, log, run_dir)
            try:
                _run(spec, reporter, log)
            except Cancelled:
                log.info("run cancelled")
                return RunOutcome("cancelled")
            except LeapError as exc:
                log.error("run failed: %s", exc)
                return RunOutcome("failed", _in_app_words(exc))
            except OSError as exc:
                full = disk_full_message(exc)
                log.error("run failed:\n%s", traceback.format_exc())
                return RunOutcome("failed", full or f"{type(exc).__name__}: {exc}")
            except Exception as exc:
                log.error("run failed:\n%s", traceback.format_exc())
                return RunOutcome("failed", f"{type(exc).__name__}: {exc}")
            log.info(
                "run finished in %.2f s wall, %.2f s cpu",
                time.perf_counter() - wall0,
                time.process_time() - cpu0,
            )
            return RunOutcome("done")
    except RunDirBusy as exc:
        return RunOutcome("failed", str(exc))
    finally:
        logging.getLogger("leap_core").removeHandler(pipeline_warnings)
        pipeline_warnings.close()
        for h in list(log.handlers):
            h.close()
            log.removeHandler(h)


def _in_app_words(exc: LeapError) -> str:
    """A run's error as the app shows it. A missing model's own advice is for the command line (`hf
    download`, `--models`); the app's users get the server's side of it (the dataset check's wording). A
    dataset without poses names only the file; the app adds its own option."""
    from app.advice import ADVICE  # noqa: PLC0415  a run has loaded the pipeline by now

    if isinstance(exc, ModelLoadError):
        return f"{str(exc).split('; ')[0]}; {ADVICE['models_missing'].app}"
    if isinstance(exc, PosesMissingError):
        return f"{exc}; {ADVICE['poses_missing'].app}"
    return str(exc)


def _run(spec: RunSpec, reporter: _Reporter, log: logging.Logger) -> None:
    """The run: each sequence generated (the demo's) and its poses put in place, then the pipeline over
    every sequence, each report named ``<sequence>/<stage>``."""
    # Imported here, not at the top: the worker process must load the pipeline (torch) only once it dies
    # with the server (child_main), and the server imports this module for execute() and LOG_NAME.
    from leap_core.pipeline import SequenceSpec, run_pipeline  # noqa: PLC0415  # loaded by a run only
    from leap_core.pipeline.run import open_run_folder  # noqa: PLC0415

    # Deployment values come from the server's settings only (the spec), never from the project.
    runtime = Runtime(
        models_dir=spec.models_dir,
        cache_dir=spec.cache_dir,
        allow_download=spec.allow_download,
        ray_address=spec.ray_address,
    )
    specs = [
        SequenceSpec(name, dataset, None if frames is None else range(*frames))
        for name, dataset, frames in spec.sequences
    ]
    layout = open_run_folder(spec.run_dir, specs)

    for seq in specs:
        if spec.demo:
            generated = _Named(reporter, seq.name, SYNTH)
            ensure_demo_sequence(seq.dataset, spec.demo_synth, progress=generated.staged, log=log)
        prepare_run_poses(
            seq.dataset,
            layout.sequence(seq.name).folder,
            estimate=spec.estimate_poses,
            cache_root=spec.poses_cache,
            progress=_Named(reporter, seq.name, POSES),
        )
    schema = Schema.from_dict(spec.schema, source="project schema")
    config = config_from_dict(spec.pipeline)  # the run spec stores config_to_dict(); parsed once, here
    run_pipeline(
        specs,
        schema,
        config,
        spec.run_dir,
        progress=lambda sequence, stage, done, total: reporter(stage_name(sequence, stage), done, total),
        runtime=runtime,
    )


class _Named:
    """The progress callback of one sequence's step before its pipeline (the demo's generation, the pose
    estimation): reports ``<sequence>/<stage>`` to the run's reporter."""

    def __init__(self, reporter: _Reporter, sequence: str, stage: str) -> None:
        self.reporter = reporter
        self.name = stage_name(sequence, stage)

    def __call__(self, done: int, total: int) -> None:
        self.reporter(self.name, done, total)

    def staged(self, _stage: str, done: int, total: int) -> None:
        """The demo generator's ``progress(stage, done, total)``."""
        self(done, total)


class _ForwardLogs(logging.Handler):
    """Sends the pipeline's warnings and errors to the server as :class:`LogLine` messages."""

    def __init__(self, send: Emit) -> None:
        super().__init__(logging.WARNING)
        self.send = send

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.send(LogLine(record.levelno, record.name, record.getMessage()))
        except Exception:
            self.handleError(record)


def _read_commands(stream: IO[bytes], cancel: threading.Event) -> None:
    """Parent → child commands on stdin (:class:`CancelRun`). End of input means the parent is gone: exit
    at once."""
    for line in stream:
        if not line.strip():
            continue
        try:
            command = decode_to_worker(line)
        except MessageError as exc:
            worker_log.warning("ignored a malformed command from the server: %s", exc)
            continue
        if isinstance(command, CancelRun):
            cancel.set()
        else:
            worker_log.warning("ignored a second run spec (a worker executes one run)")
    os._exit(3)


def _first_spec(line: bytes) -> RunSpec:
    message = decode_to_worker(line)
    if not isinstance(message, RunSpec):
        raise MessageError(f"expected a run spec first, got {message.type!r}")
    return message


def child_main(argv: list[str] | None = None) -> None:
    """Entry point of the worker process: ``python -m app.jobs.worker MESSAGE_FD PARENT_PID``.

    The run spec arrives as the first line on stdin; further stdin lines are commands. Messages go out on
    file descriptor MESSAGE_FD (not stdout, which libraries may print to).
    """
    args = sys.argv[1:] if argv is None else argv
    message_fd, parent_pid = int(args[0]), int(args[1])
    _die_with_parent(parent_pid)
    # The server handles Ctrl-C; the child stops through a cancel command or a kill.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Import the pipeline (torch included) only now, once this process dies with the server, but before
    # the run arrives: a pre-started worker then starts computing at once.
    import leap_core.pipeline  # noqa: F401, PLC0415  # pre-warm only in the child, see the comment above

    stdin = sys.stdin.buffer
    line = stdin.readline()
    if not line:
        os._exit(0)  # the server stopped before giving this worker a run
    cancel = threading.Event()
    threading.Thread(target=_read_commands, args=(stdin, cancel), name="commands", daemon=True).start()
    out = os.fdopen(message_fd, "wb", buffering=0)
    lock = threading.Lock()

    def emit(message: FromWorker) -> None:
        data = message.to_line()
        with lock:
            out.write(data)

    logging.getLogger("leap_core").addHandler(_ForwardLogs(emit))
    try:
        outcome = execute(_first_spec(line), emit, cancel.is_set)
    except BaseException as exc:
        outcome = RunOutcome("failed", f"{type(exc).__name__}: {exc}")
    with contextlib.suppress(OSError):
        emit(outcome)
    out.close()
    logging.shutdown()
    # The stdin reader thread is blocked in a read; a normal interpreter shutdown would trip over its lock.
    os._exit(0)


if __name__ == "__main__":
    child_main()
