"""Background runs: a FIFO queue across projects, worker threads, one child process per run.

Life of a run: ``start_run`` snapshots the project (dataset, schema, pipeline parameters, active
corrections) into a new ``queued`` row and folder, then a worker thread takes it, marks it ``running``
and executes it in a child process (:mod:`app.jobs.worker`) while relaying the child's progress into a
:class:`~app.jobs.progress.ProgressTracker` that API requests read. At most one queued-or-running run
exists per project; ``max_parallel_runs`` runs execute at once, the rest wait in arrival order.

Crash safety: stage states are written to SQLite at every stage change (and every few seconds), the
pipeline writes its outputs atomically and records finished stages in ``run_dir/stages.json``. When the
server starts, runs still marked queued/running are marked ``interrupted``; ``resume_run`` queues the
same run again in the same folder with the same snapshot, so finished stages and frames are reused.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import json
import logging
import os
import select
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app import crud, services
from app.advice import ADVICE
from app.core.config import Settings
from app.core.db import open_db, transaction, utcnow
from app.core.errors import Conflict, InsufficientStorage, InvalidField, disk_full_message
from app.core.security import resolve_in_roots
from app.demo import demo_exists
from app.jobs import worker
from app.jobs.folders import migrate_run_folders
from app.jobs.messages import (
    CancelRun,
    FromWorker,
    LogLine,
    MessageError,
    RunOutcome,
    RunSpec,
    StageProgress,
    decode_from_worker,
)
from app.jobs.notify import ChangeNotifier
from app.jobs.poses import needs_estimate
from app.jobs.progress import TERMINAL_STATUSES, ProgressTracker
from app.jobs.stages import run_stages, skipped_stages
from app.models import ACTIVE_STATUSES, RESUMABLE_STATUSES
from app.rows import ProjectRow, RunParams, RunRow, RunSequence
from leap_core.corrections import ERASE, ScanCorrections
from leap_core.errors import LeapError
from leap_core.fusion import last_per_key
from leap_core.io_utils import atomic_write_json, link_or_copy, remove_tree
from leap_core.labelers import LABELERS
from leap_core.pipeline import STAGES, read_run_metrics
from leap_core.pipeline.apply import RunCorrections
from leap_core.pipeline.metrics_file import RunMetrics
from leap_core.run_layout import SequenceLayout

log = logging.getLogger("leap.jobs")

PERSIST_EVERY_S = 0.5
"""Longest time between two writes of a running run's stage states to SQLite."""
FINISHED_KEPT = 256
"""Finished trackers kept in memory so progress polls of recent runs never touch the database."""
CANCEL_GRACE_S = 10.0
"""After a cancel request, seconds the child gets to stop by itself before it is terminated."""
RETRY_STORE_S = 2.0
"""Seconds between two attempts to store a run's end that the database refused (e.g. a full disk)."""
MIB = 1 << 20


class _RunRefused(Exception):
    """A queued run cannot start (the message says why)."""


@dataclass
class _Live:
    """A queued or running run in this process."""

    tracker: ProgressTracker
    label: str
    """How logs name the run: the number the UI shows, its project and its id."""
    process: subprocess.Popen[bytes] | None = None
    """The worker process (None until started)."""
    cancel_requested: bool = False
    cancel_at: float | None = None
    done_event: threading.Event = field(default_factory=threading.Event)


@dataclass
class _Worker:
    """A worker process and the read end of its message pipe."""

    process: subprocess.Popen[bytes]
    read_fd: int
    closed: bool = False

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(5.0)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            os.close(self.read_fd)
            with contextlib.suppress(OSError):
                if self.process.stdin is not None:
                    self.process.stdin.close()


class JobManager:
    """Owns the run queue and the worker threads of one server process."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self._queue: collections.deque[int] = collections.deque()
        self._live: dict[int, _Live] = {}
        self._finished: collections.OrderedDict[int, ProgressTracker] = collections.OrderedDict()
        self._threads: list[threading.Thread] = []
        self._stopping = False
        self.stages: list[str] = list(STAGES)
        """The pipeline's ordered stages (a run of a demo project not generated yet adds one before)."""
        self.changes = ChangeNotifier()
        """Progress streams wait on this; every tracker change notifies it."""
        self._payloads: dict[int, tuple[int, str, str]] = {}
        self._unsaved: dict[int, dict[str, Any]] = {}
        """Final columns of ended runs that the database refused (full disk); retried until stored."""
        self._store_error: str | None = None
        """Why the last refused write failed (for /health)."""
        self._started = False
        self._done_hooks: list[Callable[[int], None]] = []

    def on_run_done(self, hook: Callable[[int], None]) -> None:
        """Call ``hook(project_id)`` after each run that ends ``done`` (on the worker thread, after its row
        is stored): the app's "apply corrections" job uses it, since corrections made while a run worked
        are newer than the ones the run fused (:mod:`app.jobs.apply`)."""
        self._done_hooks.append(hook)

    # ------------------------------------------------------------------------------------- lifecycle
    def start(self) -> list[int]:
        """Mark runs left over by a previous server as interrupted, move run folders of earlier versions
        into today's layout (:func:`~app.jobs.folders.migrate_run_folders`) and start the workers."""
        with open_db(self.settings.database) as db:
            interrupted = crud.mark_stale_runs_interrupted(db)
            for run_id in interrupted:
                run = crud.get_run(db, run_id)
                if run is not None:
                    log.warning(
                        "run #%d of project %d (id %d) was interrupted by a server stop; it can be resumed",
                        run.number,
                        run.project_id,
                        run_id,
                    )
        migrate_run_folders(self.settings.database)
        with self._lock:
            self._stopping = False
            self._started = True
            for i in range(self.settings.max_parallel_runs):
                t = threading.Thread(target=self._worker_loop, name=f"leap-run-worker-{i}", daemon=True)
                t.start()
                self._threads.append(t)
        _set_current(self)
        return interrupted

    def stop(self, timeout: float = 15.0) -> None:
        """Stop the workers; running runs are asked to stop and end ``interrupted`` (resumable)."""
        with self._lock:
            self._stopping = True
            for live in self._live.values():
                self._send_cancel(live)
            self._wake.notify_all()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.1, deadline - time.monotonic()))
        with self._lock:
            for live in self._live.values():
                if live.process is not None and live.process.poll() is None:
                    live.process.kill()
        for t in self._threads:
            t.join(2.0)
        self._threads.clear()
        self._flush_unsaved()
        try:
            with open_db(self.settings.database) as db:
                crud.mark_stale_runs_interrupted(db)
        except Exception:  # a full disk must not stop the shutdown; the next start marks them instead
            log.exception("could not mark the runs left active as interrupted")
        with self._lock:
            self._started = False
        _set_current(None)

    # ------------------------------------------------------------------------------------- requests
    def start_run(self, project_id: int, *, frames: tuple[int, int] | None = None) -> RunRow:
        """Queue a new run of the project's current settings.

        Raises:
            NotFound: unknown project.
            Conflict: the project already has a queued or running run.
            InsufficientStorage: less free disk space than ``min_free_disk_mb``.
        """
        self._refuse_when_disk_low()
        # The write transaction (not the manager lock, which progress readers on the event loop share)
        # makes "check for an active run, then insert" atomic across requests.
        with open_db(self.settings.database) as db:
            with transaction(db):
                project = crud.require_project(db, project_id)
                for seq in project.sequences:
                    self._confine_dataset(project.dataset_kind, seq.dataset_path)
                _refuse_without_poses(project)
                if frames is not None and len(project.sequences) > 1:
                    raise InvalidField(
                        ["body", "frames"],
                        f"project {project_id} has {len(project.sequences)} sequences: its runs label "
                        "every frame of each (frames are for a project of one sequence)",
                    )
                active = crud.active_run(db, project_id)
                if active is not None:
                    # Inside this transaction a retry of the stored end would wait for its own lock.
                    self._refuse_when_unsaved(active.id, flush=False)
                    raise Conflict(
                        f"Project {project_id} already has run {active.number} (id {active.id}) "
                        f"{active.status}; cancel it or wait for it to finish"
                    )
                params = self._snapshot(db, project, frames)
                run = crud.create_run(
                    db, project_id=project_id, params=params, runs_dir=self.settings.runs_dir
                )
            self._prepare_run_dir(db, run)
            expected = self._expected_seconds(db, project_id)
        with self._lock:
            self._enqueue(run, expected)
        return run

    def resume_run(self, run_id: int) -> RunRow:
        """Queue an interrupted, cancelled or failed run again in its own folder with its own snapshot.

        Raises:
            NotFound: unknown run.
            Conflict: the run is not resumable or its project has another active run.
            InsufficientStorage: less free disk space than ``min_free_disk_mb``.
        """
        self._refuse_when_disk_low()
        self._refuse_when_unsaved(run_id)
        with open_db(self.settings.database) as db:
            with transaction(db):
                run = crud.require_run(db, run_id)
                for seq in run.params.sequences:
                    self._confine_dataset(run.params.dataset_kind, str(seq.dataset))
                if run.status not in RESUMABLE_STATUSES:
                    raise Conflict(
                        f"Run {run.number} (id {run_id}) is {run.status}; "
                        f"only {', '.join(RESUMABLE_STATUSES)} runs resume"
                    )
                active = crud.active_run(db, run.project_id)
                if active is not None:
                    raise Conflict(
                        f"Project {run.project_id} already has run {active.number} (id {active.id}) "
                        f"{active.status}"
                    )
                crud.update_run(db, run_id, status="queued", error=None, finished_at=None)
                run = crud.require_run(db, run_id)
            expected = self._expected_seconds(db, run.project_id)
        with self._lock:
            previous = self._finished.pop(run_id, None)
            self._payloads.pop(run_id, None)
            self._enqueue(run, expected, after_version=0 if previous is None else previous.version)
        return run

    def cancel_run(self, run_id: int) -> RunRow:
        """Cancel a queued run at once, or ask a running one to stop at its next progress report.

        Raises:
            NotFound: unknown run.
            Conflict: the run already ended.
        """
        self._refuse_when_unsaved(run_id)
        with open_db(self.settings.database) as db:
            run = crud.require_run(db, run_id)
            if run.status not in ACTIVE_STATUSES:
                raise Conflict(
                    f"Run {run.number} (id {run_id}) is {run.status}; "
                    "only queued or running runs can be cancelled"
                )
            # queued -> cancelled and queued -> running (_execute) are both conditional updates, so
            # exactly one of them wins.
            if crud.transition_run(db, run_id, "queued", status="cancelled", finished_at=utcnow()):
                with self._lock:
                    if run_id in self._queue:
                        self._queue.remove(run_id)
                    live = self._live.get(run_id)
                    if live is not None:
                        live.tracker.set_status("cancelled", utcnow())
                        self._retire(run_id)
            else:
                with self._lock:
                    live = self._live.get(run_id)
                    if live is not None:
                        live.cancel_requested = True
                        live.cancel_at = time.monotonic()
                        self._send_cancel(live)  # or _execute sends it once the process exists
                if live is None:
                    # A row left running by a process that no longer exists.
                    crud.transition_run(db, run_id, "running", status="cancelled", finished_at=utcnow())
            return crud.require_run(db, run_id)

    def run_status(self, run_id: int) -> dict[str, Any]:
        """The run's progress (an :class:`app.models.RunProgress` as a dict), live or from the database.

        Raises:
            NotFound: unknown run.
        """
        live = self.progress(run_id)
        if live is not None:
            return live
        with open_db(self.settings.database) as db:
            return services.run_progress(crud.require_run(db, run_id), None).model_dump()

    def as_stored(self, run: RunRow) -> RunRow:
        """``run`` with the end the database has refused so far laid over it, so that readers see the run
        as it will be stored (e.g. ``failed`` with its reason), not the stale ``running`` row."""
        with self._lock:
            pending = self._unsaved.get(run.id)
        return run if pending is None else dataclasses.replace(run, **pending)

    def progress(self, run_id: int) -> dict[str, Any] | None:
        """Live (or recently finished) progress snapshot; None when the run is not in memory."""
        with self._lock:
            live = self._live.get(run_id)
            if live is not None:
                return live.tracker.snapshot()
            finished = self._finished.get(run_id)
            return None if finished is None else finished.snapshot()

    def progress_payload(self, run_id: int) -> tuple[int, str, str] | None:
        """``(version, status, JSON text)`` of the run's progress, serialised once per version and shared
        by every stream and poll; None when the run is not in memory."""
        with self._lock:
            tracker = self._live[run_id].tracker if run_id in self._live else self._finished.get(run_id)
            if tracker is None:
                return None
            cached = self._payloads.get(run_id)
            if cached is not None and cached[0] == tracker.version:
                return cached
            entry = (tracker.version, tracker.status, json.dumps(tracker.snapshot(), separators=(",", ":")))
            self._payloads[run_id] = entry
            return entry

    def counts(self) -> tuple[int, int]:
        """(queued, running) runs in this process."""
        with self._lock:
            running = sum(1 for v in self._live.values() if v.tracker.status == "running")
            return len(self._queue), running

    def wait(self, run_id: int, timeout: float | None = None) -> bool:
        """Block until a run queued in this process ends; False on timeout."""
        with self._lock:
            live = self._live.get(run_id)
        return True if live is None else live.done_event.wait(timeout)

    # ------------------------------------------------------------------------------------- internals
    def _confine_dataset(self, kind: str, path: str) -> None:
        """Check a folder dataset against the server's data roots as they are NOW: they may have narrowed
        since the project was created, or a folder on the way, or an entry the pipeline reads
        (``velodyne/``, ``labels/``, ...), may have become a link out of them.

        Raises:
            Forbidden: naming the path (or the entry) and the allowed roots.
            InvalidField: an entry became a symlink loop.
        """
        if kind != "demo":
            folder = resolve_in_roots(path, self.settings.data_roots, what="dataset path")
            services.refuse_escaping_entries(folder, self.settings.data_roots, shown=path)

    def _snapshot(self, db: Any, project: ProjectRow, frames: tuple[int, int] | None) -> RunParams:
        """What a new run of ``project`` labels (``frames`` only for a project of one sequence), the
        corrections it gets and the progress stages it will go through."""
        demo = project.dataset_kind == "demo"
        generate = [s.name for s in project.sequences if demo and not demo_exists(Path(s.dataset_path))]
        estimate = [
            s.name
            for s in project.sequences
            if project.estimate_poses and s.name not in generate and needs_estimate(Path(s.dataset_path))
        ]
        joint = services.project_config(project).consistency.enabled
        return RunParams(
            sequences=tuple(RunSequence(s.name, Path(s.dataset_path), frames) for s in project.sequences),
            dataset_kind=project.dataset_kind,
            schema=project.schema,
            pipeline=project.pipeline,
            estimate_poses=project.estimate_poses,
            stages=tuple(
                run_stages(project.names, self.stages, joint_3dcn=joint, estimate=estimate, generate=generate)
            ),
            corrections=active_correction_ids(db, project),
        )

    def _prepare_run_dir(self, db: Any, run: RunRow) -> None:
        """Write the parameter snapshot into the new run folder, and into each sequence's folder its active
        corrections and the stage outputs of the finished run it starts from (:func:`seed_source`)."""
        # Ids are never handed out twice (crud._new_id), but a database restored from a backup, or one whose
        # rows were deleted by an older version, may give p<P>/r<R> whose folder holds another run's files:
        # stale stage outputs must never leak into this run.
        remove_tree(run.run_dir)
        run.run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_json(run.layout.params, run.params.to_dict())
        previous = seed_source(db, run.project_id, run.params)
        linked = 0
        for seq in run.params.sequences:
            lay = run.sequence_layout(seq.name)
            lay.folder.mkdir(parents=True, exist_ok=True)
            corrections = snapshot_corrections(db, run.project_id, run.params, seq.name)
            run_corrections(corrections, run.params, self.settings.work_dir).write_run(lay)
            if previous is not None:
                linked += seed_sequence(previous.sequence_layout(seq.name), lay)
        if previous is not None:
            # The 3D-CN's checkpoints and staged rounds, reused while their fingerprints match.
            linked += link_tree(previous.layout.cn_dir, run.layout.cn_dir)
            log.info(
                "run #%d of project %d starts from run #%d's stage outputs (%d files linked)",
                run.number,
                run.project_id,
                previous.number,
                linked,
            )

    def _expected_seconds(self, db: Any, project_id: int) -> dict[str, float]:
        last = crud.last_finished_run(db, project_id)
        if last is None:
            return {}
        stages = (last.stages or {}).get("stages") or {}
        return {k: float(v["seconds"]) for k, v in stages.items() if v.get("seconds") is not None}

    def _enqueue(self, run: RunRow, expected: dict[str, float], after_version: int = 0) -> None:
        labeler = LABELERS.get(str((run.params.pipeline or {}).get("labeler") or "simulated"))
        tracker = ProgressTracker.create(
            run.id,
            run.project_id,
            run.params.stages or self.stages,
            expected_seconds=expected,
            labeler_input=None if labeler is None else labeler.needs,
        )
        tracker.version = after_version  # a resumed run's versions continue, so streams see only news
        tracker.on_change = self.changes.notify
        tracker.set_status("queued", utcnow())
        label = f"run #{run.number} of project {run.project_id} (id {run.id})"
        self._live[run.id] = _Live(tracker=tracker, label=label)
        self._queue.append(run.id)
        self._wake.notify()

    def _retire(self, run_id: int) -> None:
        live = self._live.pop(run_id, None)
        if live is None:
            return
        self._finished[run_id] = live.tracker
        while len(self._finished) > FINISHED_KEPT:
            old_id, _ = self._finished.popitem(last=False)
            self._payloads.pop(old_id, None)
        live.done_event.set()
        self.changes.notify(run_id)

    def _spawn_worker(self) -> _Worker:
        """Start a worker process; it imports the pipeline, then waits for a run spec on stdin.

        Worker threads spawn their own processes, so the kernel's parent-death signal (tied to the
        spawning thread) fires only when the server itself goes away.
        """
        self.settings.work_dir.mkdir(parents=True, exist_ok=True)
        read_fd, write_fd = os.pipe()
        try:
            with open(self.settings.work_dir / "worker.log", "ab") as errlog:
                process = subprocess.Popen(
                    worker_command(write_fd),
                    env=worker_env(),
                    stdin=subprocess.PIPE,
                    stdout=errlog,
                    stderr=errlog,
                    pass_fds=(write_fd,),
                    close_fds=True,
                )
        except BaseException:
            os.close(read_fd)
            raise
        finally:
            os.close(write_fd)
        return _Worker(process, read_fd)

    def _worker_loop(self) -> None:
        """A worker thread's body. No error ends it: a dead thread would leave its run ``running`` for
        good, turn Cancel into a no-op and keep every later run ``queued``."""
        while True:
            try:
                self._serve_queue()
                return
            except Exception:
                name = threading.current_thread().name
                log.exception("job manager: unexpected error in %s; the thread goes on", name)
                time.sleep(1.0)

    def _serve_queue(self) -> None:
        spare: _Worker | None = None
        try:
            if self.settings.prewarm_workers:
                spare = self._spawn_spare()
            while True:
                with self._lock:
                    while not self._queue and not self._stopping:
                        if self._unsaved:
                            self._wake.wait(RETRY_STORE_S)
                            break
                        self._wake.wait()
                    if self._stopping:
                        return
                    run_id = self._queue.popleft() if self._queue else None
                self._flush_unsaved()
                if run_id is None:
                    continue
                worker_proc, spare = spare, None
                self._run_one(run_id, worker_proc)
                with self._lock:
                    stopping = self._stopping
                if not stopping:
                    # Ready for the next run: its imports happen now, while nothing else runs.
                    spare = self._spawn_spare()
        finally:
            if spare is not None:
                spare.kill()
                spare.close()

    def _run_one(self, run_id: int, proc: _Worker | None) -> None:
        """Execute a run taken from the queue in ``proc`` (a pre-started worker, or a new one)."""
        try:
            low = self._low_disk_message()
            if low is not None:
                raise _RunRefused(f"not started: {low}")
            if proc is None or proc.process.poll() is not None:
                if proc is not None:
                    proc.close()
                proc = self._spawn_worker()
            self._execute(run_id, proc)
        except Exception as exc:  # a broken run must not end the worker thread
            self._fail_run(run_id, exc, proc)
        finally:
            if proc is not None:
                proc.close()

    def _spawn_spare(self) -> _Worker | None:
        """A pre-started worker, or None when it cannot be started now (the next run tries again)."""
        try:
            return self._spawn_worker()
        except Exception:
            log.exception("could not start a worker process")
            return None

    def _fail_run(self, run_id: int, exc: Exception, proc: _Worker | None) -> None:
        """End a run the job manager could not carry through: kill its process, store and publish
        ``failed`` with the reason (a full disk, a refused start, or an internal error)."""
        with self._lock:
            live = self._live.get(run_id)
        label = live.label if live is not None else f"run id {run_id}"
        reason = str(exc) if isinstance(exc, _RunRefused) else disk_full_message(exc)
        if reason is None:
            log.exception("%s: unexpected error in the job manager", label)
            reason = f"internal error in the job manager ({type(exc).__name__}: {exc}); see the server log"
        else:
            log.error("%s failed: %s", label, reason)
        if proc is not None:
            proc.kill()
        if live is None:
            return
        with self._lock:
            final = live.tracker.clone()
        final.set_status("failed", utcnow(), reason)
        self._store_final(
            run_id,
            {"status": "failed", "error": reason, "finished_at": utcnow(), "stages": final.stages_record()},
        )
        with self._lock:
            live.tracker.set_status("failed", utcnow(), reason)
            self._retire(run_id)

    def _store_final(self, run_id: int, fields: dict[str, Any]) -> bool:
        """Write a run's final columns; when the database refuses, keep them and retry every
        ``RETRY_STORE_S`` (until then /health reports it). True when stored now."""
        try:
            with open_db(self.settings.database) as db:
                crud.update_run(db, run_id, **fields)
        except Exception as exc:
            why = disk_full_message(exc) or f"{type(exc).__name__}: {exc}"
            log.error("run id %d: its end (%s) not stored, will retry: %s", run_id, fields["status"], why)
            with self._lock:
                self._unsaved[run_id] = fields
                self._store_error = why
                self._wake.notify()
            return False
        return True

    def _flush_unsaved(self) -> None:
        """Retry storing the ends the database refused before."""
        with self._lock:
            pending = list(self._unsaved.items())
        for run_id, fields in pending:
            try:
                with open_db(self.settings.database) as db:
                    crud.update_run(db, run_id, **fields)
            except Exception as exc:
                with self._lock:
                    self._store_error = disk_full_message(exc) or f"{type(exc).__name__}: {exc}"
                continue
            log.info("run id %d: its end (%s) is stored now", run_id, fields["status"])
            with self._lock:
                if self._unsaved.get(run_id) is fields:
                    del self._unsaved[run_id]

    def _refuse_when_unsaved(self, run_id: int, *, flush: bool = True) -> None:
        """A run whose end is not stored yet cannot be cancelled or resumed (its row still says running);
        ``flush`` first tries to store it once more."""
        if run_id not in self._unsaved:
            return
        if flush:
            self._flush_unsaved()
        with self._lock:
            fields = self._unsaved.get(run_id)
            why = self._store_error
        if fields is not None:
            raise InsufficientStorage(
                f"Run id {run_id} already ended ({fields['status']}: {fields.get('error')}), but the "
                f"database cannot store that yet: {why}"
            )

    # ----------------------------------------------------------------------------------- disk space
    def free_disk_bytes(self) -> int | None:
        """Free bytes on the work folder's file system (None when it cannot be read)."""
        try:
            return shutil.disk_usage(self.settings.work_dir).free
        except OSError:
            return None

    def _low_disk_message(self, free: int | None = None) -> str | None:
        """Why no run may start now (free space below ``min_free_disk_mb``), or None."""
        need = self.settings.min_free_disk_mb
        if need <= 0:
            return None
        free = self.free_disk_bytes() if free is None else free
        if free is None or free >= need * MIB:
            return None
        return (
            f"only {free / MIB:.0f} MiB free on the disk of {self.settings.work_dir}, and a run needs at "
            f"least {need:g} MiB (setting min_free_disk_mb); free some space, then start the run again"
        )

    def _refuse_when_disk_low(self) -> None:
        low = self._low_disk_message()
        if low is not None:
            raise InsufficientStorage(f"Run not started: {low}")

    def health(self) -> dict[str, Any]:
        """The job manager's state for ``/health``: worker threads alive, ends waiting to be stored, free
        disk space; ``problems`` lists what needs attention (empty when all is well)."""
        with self._lock:
            expected = len(self._threads) if self._started else 0
            alive = sum(1 for t in self._threads if t.is_alive())
            unsaved = sorted(self._unsaved)
            store_error = self._store_error
        free = self.free_disk_bytes()
        problems: list[str] = []
        if alive < expected:
            problems.append(f"{expected - alive} of {expected} job threads stopped; restart the server")
        if unsaved:
            ids = ", ".join(str(i) for i in unsaved)
            problems.append(f"the end of run id(s) {ids} is not stored yet: {store_error}")
        low = self._low_disk_message(free)
        if low is not None:
            problems.append(low)
        return {
            "workers": expected,
            "workers_alive": alive,
            "unsaved_runs": unsaved,
            "disk_free_mb": None if free is None else round(free / MIB, 1),
            "min_free_disk_mb": self.settings.min_free_disk_mb,
            "problems": problems,
        }

    def _execute(self, run_id: int, proc: _Worker) -> None:
        with open_db(self.settings.database) as db:
            run = crud.get_run(db, run_id)
            started = run is not None and crud.transition_run(
                db, run_id, "queued", status="running", started_at=utcnow(), attempts=run.attempts + 1
            )
        if not started:  # cancelled (or deleted) while it waited
            with self._lock:
                self._retire(run_id)
            proc.kill()
            return
        assert run is not None
        spec = self._spec(run)
        run.run_dir.mkdir(parents=True, exist_ok=True)
        process = proc.process
        with self._lock:
            live = self._live[run_id]
            live.process = process
            live.tracker.set_status("running", utcnow())
            assert process.stdin is not None
            try:
                process.stdin.write(spec.to_line())
                process.stdin.flush()
            except OSError:
                pass  # it died while waiting; _relay reports the exit code
            if self._stopping or live.cancel_requested:
                self._send_cancel(live)
        outcome = self._relay(run_id, live, proc.read_fd, process)
        with contextlib.suppress(OSError):
            process.stdin.close()
        try:
            process.wait(5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        self._finish(run_id, outcome)

    @staticmethod
    def _send_cancel(live: _Live) -> None:
        process = live.process
        if process is None or process.stdin is None:
            return
        with contextlib.suppress(OSError, ValueError):
            process.stdin.write(CancelRun().to_line())
            process.stdin.flush()

    def _spec(self, run: RunRow) -> RunSpec:
        params = run.params
        return RunSpec(
            run_id=run.id,
            run_dir=run.run_dir,
            sequences=[(s.name, s.dataset, s.frames) for s in params.sequences],
            demo=params.dataset_kind == "demo",
            demo_synth=dict(self.settings.demo_synth),
            schema=params.schema,
            pipeline=params.pipeline,
            models_dir=self.settings.models_dir,
            cache_dir=self.settings.cache_dir / f"p{run.project_id}",
            progress_interval_s=self.settings.progress_interval_s,
            allow_download=self.settings.allow_download,
            estimate_poses=params.estimate_poses,
            poses_cache=self.settings.cache_dir,
            ray_address=self.settings.ray_address,
        )

    def _on_progress(self, run_id: int, live: _Live, message: StageProgress, last_persist: float) -> float:
        """Apply a progress report; stage states reach SQLite on a stage change or every
        ``PERSIST_EVERY_S``. Returns the time of the last write."""
        with self._lock:
            changed = live.tracker.update(
                message.stage, message.done, message.total, time.monotonic(), utcnow(), message.skipped
            )
        if changed or time.monotonic() - last_persist > PERSIST_EVERY_S:
            self._persist_stages(run_id, live)
            return time.monotonic()
        return last_persist

    def _on_log(self, live: _Live, message: LogLine) -> None:
        """A pipeline warning: into the server log, and into the run's warnings the UI shows."""
        log.log(message.level, "%s: %s: %s", live.label, message.logger, message.message)
        if message.level >= logging.WARNING:
            with self._lock:
                live.tracker.add_warning(message.message, utcnow())

    def _relay(self, run_id: int, live: _Live, fd: int, process: subprocess.Popen[bytes]) -> RunOutcome:
        """Feed the child's messages into the tracker until it reports a result or dies."""
        last_persist = time.monotonic()
        outcome: RunOutcome | None = None
        buffer = b""
        eof = False
        while outcome is None and not eof:
            ready, _, _ = select.select([fd], [], [], 0.2)
            if ready:
                chunk = os.read(fd, 65536)
                if not chunk:
                    eof = True
                buffer += chunk
                *lines, buffer = buffer.split(b"\n")
                for line in lines:
                    if not line.strip():
                        continue
                    try:
                        message = decode_from_worker(line)
                    except MessageError as exc:
                        log.warning("%s: unreadable worker message: %s", live.label, exc)
                        continue
                    if isinstance(message, StageProgress):
                        last_persist = self._on_progress(run_id, live, message, last_persist)
                    elif isinstance(message, LogLine):
                        self._on_log(live, message)
                    else:
                        outcome = message
            if (
                live.cancel_at is not None
                and outcome is None
                and time.monotonic() - live.cancel_at > CANCEL_GRACE_S
            ):
                log.warning(
                    "%s did not stop within %.0f s of its cancel; killing it", live.label, CANCEL_GRACE_S
                )
                process.kill()
                outcome = RunOutcome("cancelled")
        if outcome is None:
            try:
                code = process.wait(2.0)
            except subprocess.TimeoutExpired:
                code = None
            outcome = RunOutcome("failed", f"the worker process stopped unexpectedly (exit code {code})")
        return outcome

    def _persist_stages(self, run_id: int, live: _Live) -> None:
        with self._lock:
            record = live.tracker.stages_record()
        with open_db(self.settings.database) as db:
            crud.update_run(db, run_id, stages=record)

    def _finish(self, run_id: int, outcome: RunOutcome) -> None:
        """Store the outcome, then publish it: a client that sees the end in the progress stream and
        reads the run right after finds the final row (status, metrics) in the database.

        A run whose end the database refuses for lack of space ends ``failed`` with that reason (its
        outputs stay on disk: a resume finds them); any other error propagates to :meth:`_fail_run`."""
        status: str = outcome.status
        error = outcome.error
        with open_db(self.settings.database) as db:
            row = crud.require_run(db, run_id)
        run_dir, project_id = row.run_dir, row.project_id
        skipped = skipped_stages(run_dir, row.params.names)
        with self._lock:
            live = self._live[run_id]
            if status != "done" and self._stopping and not live.cancel_requested:
                status, error = "interrupted", "the server stopped during this run; resume it to continue"
            final = live.tracker.clone()
        final.set_status(status, utcnow(), error)
        final.mark_skipped(skipped)
        metrics = None if status != "done" else read_metrics(run_dir)
        try:
            with open_db(self.settings.database) as db:
                crud.update_run(
                    db,
                    run_id,
                    status=status,
                    error=error,
                    finished_at=utcnow(),
                    stages=final.stages_record(),
                    **({"metrics": metrics} if metrics is not None else {}),
                )
        except Exception as exc:
            reason = disk_full_message(exc)
            if reason is None:
                raise
            status, error = "failed", f"the run's end could not be stored: {reason}; then resume the run"
            with self._lock:
                final = live.tracker.clone()
            final.set_status(status, utcnow(), error)
            final.mark_skipped(skipped)
            self._store_final(
                run_id,
                {"status": status, "error": error, "finished_at": utcnow(), "stages": final.stages_record()},
            )
        with self._lock:
            live.tracker.set_status(status, utcnow(), error)
            live.tracker.mark_skipped(skipped)
            self._retire(run_id)
        log.info("%s %s%s", live.label, status, f": {error}" if error else "")
        if status == "done":
            for hook in self._done_hooks:
                try:
                    hook(project_id)
                except Exception:  # a hook's failure must not fail the run that already ended
                    log.exception("after run %d: a run-done hook failed", run_id)

    # ------------------------------------------------------------------------------ synchronous use
    def run_now(self, run_id: int, on_progress: Callable[[str, int, int], None] | None = None) -> str:
        """Execute a queued run in this thread and process (the ``leap demo`` command); returns its status.

        The run must have been created with :meth:`start_run` on a manager that was not started, so no
        worker thread competes for it.
        """
        with self._lock:
            if run_id in self._queue:
                self._queue.remove(run_id)
            live = self._live[run_id]
        with open_db(self.settings.database) as db:
            run = crud.require_run(db, run_id)
            crud.update_run(db, run_id, status="running", started_at=utcnow(), attempts=run.attempts + 1)
        live.tracker.set_status("running", utcnow())

        def emit(message: FromWorker) -> None:
            if not isinstance(message, StageProgress):
                return
            stage, done, total = message.stage, message.done, message.total
            if live.tracker.update(stage, done, total, time.monotonic(), utcnow(), message.skipped):
                self._persist_stages(run_id, live)
            if on_progress is not None:
                on_progress(stage, done, total)

        outcome = worker.execute(self._spec(run), emit, lambda: False)
        self._finish(run_id, outcome)
        return outcome.status


_CODE_ROOT = Path(__file__).resolve().parents[2]
"""The folder holding the ``app`` and ``leap_core`` packages this server runs."""


def _refuse_without_poses(project: ProjectRow) -> None:
    """Refuse a run that would fail at its first 3D stage: a sequence folder without ``poses.txt`` in a
    project that does not estimate poses (as ``leap run`` refuses one before any work).

    Raises:
        Conflict: naming the sequence, its missing poses file and the fixes in the app's words.
    """
    if project.dataset_kind == "demo" or project.estimate_poses:
        return  # the demo street is generated with its poses; estimated poses are made by the run
    missing = [s for s in project.sequences if needs_estimate(Path(s.dataset_path))]
    if missing:
        seq = missing[0]
        which = f"sequence {seq.name!r}: " if len(project.sequences) > 1 else ""
        raise Conflict(
            f"{which}{Path(seq.dataset_path) / 'poses.txt'}: no poses, and the 3D stages need one pose per "
            f"scan; {ADVICE['poses_missing'].app} (through the API: PATCH /api/v1/projects/{project.id} "
            'with {"estimate_poses": true}), then start the run again'
        )


def worker_command(message_fd: int) -> list[str]:
    """The worker's command line. ``-P`` keeps the server's current folder off the worker's import path:
    a stray ``numbers.py`` there would otherwise shadow the standard library's and fail every run."""
    return [sys.executable, "-P", "-m", "app.jobs.worker", str(message_fd), str(os.getpid())]


def worker_env() -> dict[str, str]:
    """The server's environment, with the server's own code first on ``PYTHONPATH`` (``-P`` removed the
    current folder, the worker must still import the same ``app`` and ``leap_core`` as the server)."""
    env = dict(os.environ)
    parts = [str(_CODE_ROOT), *(p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p)]
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(parts))
    return env


def seed_sequence(previous: SequenceLayout, folder: SequenceLayout) -> int:
    """Hard-link a finished run's stage outputs and ``stages.json`` of one sequence into the same
    sequence's folder of a new run.

    The pipeline then skips every stage whose fingerprint still matches (a class colour or a prompt the
    simulated labeler does not read changes nothing; a smoothing ``k`` edit reruns ``smooth`` onwards)
    and clears the outputs of the stages that changed. Sharing inodes is safe because leap_core writes
    results only through ``atomic_write`` (a new file renamed over the old name): a stage that reruns
    replaces the link in the new run and never writes into the previous run's file. Files that cannot
    be linked (another file system) are copied.

    Returns:
        Number of files linked or copied.
    """
    if not previous.state.is_file():
        return 0

    def stage_output(rel: Path) -> bool:
        # Hidden files are a run's temporaries (spills, partial writes); the run's own files
        # (corrections, counts) belong to the run that wrote them.
        if any(part.startswith(".") for part in rel.parts):
            return False
        return not (len(rel.parts) == 1 and rel.name in SequenceLayout.RUN_OWN_FILES)

    return link_tree(previous.folder, folder.folder, keep=stage_output)


def read_metrics(run_dir: Path) -> RunMetrics | None:
    """The run's stored result tables (None when no sequence has ground truth or they are unreadable)."""
    try:
        return read_run_metrics(run_dir)
    except LeapError:
        return None


def seed_source(db: Any, project_id: int, params: RunParams) -> RunRow | None:
    """The finished run a new run with ``params`` starts from: the project's latest finished run when it
    labeled the same sequences on the same folders and frames (its stage outputs are linked in and reused
    where the fingerprints still match); None when there is none."""
    previous = crud.last_finished_run(db, project_id)
    if previous is None or previous.params.sequences != params.sequences:
        return None
    return previous


def link_tree(source: Path, target: Path, keep: Callable[[Path], bool] | None = None) -> int:
    """Hard-link (else copy) every file under ``source`` that ``target`` lacks to the same place under
    ``target`` (only those whose relative path ``keep`` accepts, when given); returns how many. Safe for
    pipeline outputs, which are only ever replaced through ``atomic_write``."""
    if not source.is_dir():
        return 0
    count = 0
    for src in sorted(source.rglob("*")):
        rel = src.relative_to(source)
        if not src.is_file() or src.is_symlink() or (keep is not None and not keep(rel)):
            continue
        dst = target / rel
        if dst.exists():
            continue
        link_or_copy(src, dst)
        count += 1
    return count


def active_correction_ids(db: Any, project: ProjectRow) -> dict[str, tuple[int, ...]]:
    """Per sequence of ``project``, the ids of its active corrections in the order they were made (what a
    run queued now gets, :attr:`RunParams.corrections`)."""
    return {
        s.name: tuple(c.id for c in crud.list_corrections(db, project.id, active_only=True, sequence=s.name))
        for s in project.sequences
    }


def snapshot_corrections(db: Any, project_id: int, params: RunParams, sequence: str) -> list[crud.Correction]:
    """The corrections of ``sequence`` that a run with ``params`` gets: those its snapshot names (the active
    ones when it was queued, so one made in between is not half in), else the active ones now."""
    if params.corrections is None:
        return crud.list_corrections(db, project_id, active_only=True, sequence=sequence)
    wanted = set(params.corrections.get(sequence, ()))
    every = crud.list_corrections(db, project_id, active_only=False, sequence=sequence)
    return [c for c in every if c.id in wanted]


def run_corrections(
    corrections: Sequence[crud.Correction], params: RunParams, work_dir: Path
) -> RunCorrections:
    """The active corrections of a project's sequence as a run with ``params`` (its ``schema`` and
    ``pipeline``) applies them: map scope flattened by :func:`corrections_for_run`, scan scope by
    :meth:`ScanCorrections.merge` (later corrections win on the same voxel / point), object scope with
    each object's identity read from its file under ``work_dir`` (in the order they were made).

    Raises:
        DatasetError: an object correction's identity file is missing or unreadable (naming it).
    """
    keys, classes = corrections_for_run(corrections, params.schema, params.pipeline)
    names = [c["name"] for c in params.schema["classes"]]
    scan = ScanCorrections.merge(
        (c.frame_id, c.points, index)
        for c in corrections
        if c.scope == "scan"
        and c.frame_id
        and c.points is not None
        and (index := _class_index(c.class_name, names)) != -2
    )
    objects = services.object_corrections(corrections, names, work_dir)
    return RunCorrections(keys, classes, scan, objects)


def _class_index(name: str, names: list[str]) -> int:
    """A correction's class index in a run's schema: -1 (erase) for ``""``, -2 when the class is gone."""
    if name == "":
        return ERASE
    return names.index(name) if name in names else -2


def corrections_for_run(
    corrections: Sequence[crud.Correction], schema: dict[str, Any], pipeline: dict[str, Any]
) -> tuple[np.ndarray, np.ndarray]:
    """Flatten a project's active map-scope corrections into the arrays the pipeline applies.

    Later corrections override earlier ones on the same voxel; an erase (class ``""``) becomes class -1.
    Corrections whose class is no longer in the schema, or whose voxel size differs from the run's, are
    dropped.

    Returns:
        ``keys (K,) int64`` sorted unique voxel keys and ``class_idx (K,) int16`` class indices of the
        run's schema (-1 = erase).
    """
    names = [c["name"] for c in schema["classes"]]
    voxel_size = pipeline_voxel_size(pipeline)
    key_parts: list[np.ndarray] = []
    cls_parts: list[np.ndarray] = []
    for c in corrections:
        index = _class_index(c.class_name, names)
        if c.scope != "map" or index == -2:
            continue
        if voxel_size is not None and not np.isclose(c.voxel_size, voxel_size, rtol=0, atol=1e-9):
            continue
        key_parts.append(c.keys)
        cls_parts.append(np.full(c.keys.shape[0], index, dtype=np.int16))
    if not key_parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int16)
    keys, classes = last_per_key(np.concatenate(key_parts), np.concatenate(cls_parts))
    return keys, classes.astype(np.int16)


def pipeline_voxel_size(pipeline: dict[str, Any]) -> float | None:
    """The voxel size in a pipeline config dict (``fusion.voxel_size``), if present."""
    fusion = pipeline.get("fusion")
    if isinstance(fusion, dict) and isinstance(fusion.get("voxel_size"), (int, float)):
        return float(fusion["voxel_size"])
    value = pipeline.get("voxel_size")
    return float(value) if isinstance(value, (int, float)) else None


# ------------------------------------------------------------------------------- process-wide access
_current: JobManager | None = None


def _set_current(manager: JobManager | None) -> None:
    global _current  # noqa: PLW0603  # the one manager of this process: set by start(), cleared by stop()
    _current = manager


def current_manager() -> JobManager:
    """The manager of the running server (for the viewer and other in-process callers)."""
    if _current is None:
        raise RuntimeError("no job manager is running (the app is not started)")
    return _current


def is_terminal(status: str) -> bool:
    return status in TERMINAL_STATUSES
