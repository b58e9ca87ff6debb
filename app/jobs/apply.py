"""The light "apply corrections" job: a correction added or toggled reaches the latest finished run's point
labels and ``.label`` / ``.conf`` export at once, without starting a run.

One background thread per project at most; requests made while it works coalesce into one more pass (the
job always applies the project's corrections as they are when it reads them, so nothing is lost). The work
itself is :func:`leap_core.pipeline.apply.apply_to_run`: only the frames whose points a changed correction
touches are rewritten, atomically per file; the run's cached export zips and counts are then dropped
(:func:`app.exports.invalidate`). The run's final grid and its voxel → frames index are kept in memory for
the project's latest run (the index is also saved in the run folder, ``frame_voxels.npz``), so after the
first pass a job costs about the rewritten frames only. :meth:`CorrectionApplier.warm` loads them ahead
(the viewer calls it when it opens a project), on the same thread as the passes.

The grid is held for one run row (its id and creation time, and the sequence folder), never for a project
id and folder alone: a project and its runs may be deleted, and whatever held their grid must not relabel
another run's points with it. :meth:`CorrectionApplier.forget` drops everything of a deleted project and
makes sure no pass writes into its folders afterwards.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from app import crud, exports
from app.core.config import Settings
from app.core.db import open_db, utcnow
from app.core.errors import AppError
from app.jobs.manager import run_corrections
from app.rows import Labeled, RunRow, labeled_sequences
from app.services import pipeline_config
from leap_core.errors import LeapError
from leap_core.io_utils import remove_tree
from leap_core.pipeline.apply import RunCache, RunCorrections, apply_to_run, load_run_cache
from leap_core.schema import Schema

log = logging.getLogger("leap.corrections")


@dataclass(frozen=True)
class ApplyState:
    """Where a project's "apply corrections" job stands (served to the web UI)."""

    status: str = "idle"
    """``idle`` (nothing asked since the server started), ``running``, ``done``, ``failed`` or ``no_run``
    (the project has no finished run to apply to)."""
    run_id: int | None = None
    """The run the last pass applied to."""
    run_number: int | None = None
    """Its number within the project."""
    frames: int = 0
    """Scans the last pass rewrote."""
    changed_voxels: int = 0
    """Map-scope voxels whose correction changed in the last pass."""
    baked_reverts: int = 0
    """Undone voxels the run had already fused: they keep their class until the next run."""
    seconds: float = 0.0
    """Wall time of the last pass (request to written files)."""
    error: str | None = None
    """Why the last pass failed."""
    finished_at: str | None = None
    """ISO UTC time the last pass ended."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


CacheKey = tuple[int, str, Path]
"""(run id, the run row's ``created_at``, sequence folder) a held grid belongs to."""


class CorrectionApplier:
    """The "apply corrections" jobs of one database (one per app process: :func:`applier`)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._lock = threading.Lock()
        self._states: dict[int, ApplyState] = {}
        self._wanted: dict[int, float] = {}
        """project → time.perf_counter() of the oldest request not yet taken by a pass."""
        self._warm: set[int] = set()
        """Projects whose grid a viewer asked to load ahead."""
        self._threads: dict[int, threading.Thread] = {}
        """The one thread per project that runs its passes and warm-ups, while it has any."""
        self._caches: dict[int, tuple[CacheKey, RunCache]] = {}
        self._deleted: set[int] = set()
        """Projects :meth:`forget` was told of (ids are never handed out again: app.crud)."""
        self._orphans: dict[int, list[Path]] = {}
        """Folders of a deleted project to remove again once the pass in flight at the delete has ended."""
        self._idle = threading.Condition(self._lock)

    # ---------------------------------------------------------------------------------------- requests
    def request(self, project_id: int) -> None:
        """Ask for a pass (returns at once; the work runs on the project's background thread)."""
        with self._lock:
            if project_id in self._deleted:
                return
            self._wanted.setdefault(project_id, time.perf_counter())
            thread = self._thread(project_id)
        if thread is not None:
            thread.start()

    def warm(self, project_id: int) -> None:
        """Load the latest run's grid and voxel → frames index in the background (on the project's thread,
        after any pass asked for; it may write the index into the run folder)."""
        with self._lock:
            if project_id in self._deleted:
                return
            self._warm.add(project_id)
            thread = self._thread(project_id)
        if thread is not None:
            thread.start()

    def forget(self, project_id: int, folders: Sequence[Path]) -> None:
        """The project was deleted: drop its queued passes, its grid and its state, ignore requests for it
        from now on, and remove ``folders`` (its run and cache folders) now and again once a pass or
        warm-up in flight has ended (it may write into them until then)."""
        with self._lock:
            self._deleted.add(project_id)
            self._wanted.pop(project_id, None)
            self._warm.discard(project_id)
            self._caches.pop(project_id, None)
            self._states.pop(project_id, None)
            if project_id in self._threads:
                self._orphans.setdefault(project_id, []).extend(folders)
        for folder in folders:
            remove_tree(folder)

    def _thread(self, project_id: int) -> threading.Thread | None:
        """The project's worker thread to start (registered, not started), or None when it has one.
        Call with the lock held."""
        if project_id in self._threads:
            return None
        thread = threading.Thread(
            target=self._loop, args=(project_id,), name=f"leap-apply-p{project_id}", daemon=True
        )
        self._threads[project_id] = thread
        return thread

    def state(self, project_id: int) -> ApplyState:
        with self._lock:
            state = self._states.get(project_id, ApplyState())
            busy = project_id in self._threads
        return replace(state, status="running") if busy else state

    def wait(self, project_id: int, timeout: float = 30.0) -> ApplyState:
        """Block until no pass is queued or running for the project (tests, benchmarks)."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while project_id in self._threads:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"apply-corrections job of project {project_id} still running")
                self._idle.wait(left)
        return self.state(project_id)

    # ------------------------------------------------------------------------------------------- work
    def _loop(self, project_id: int) -> None:
        try:
            while True:
                with self._lock:
                    # Passes first, then a warm-up, then what a delete left to remove; nothing left: the
                    # thread ends, decided under the lock, so a request made from now on starts a new one.
                    asked = self._wanted.pop(project_id, None)
                    warm = asked is None and project_id in self._warm
                    self._warm.discard(project_id)
                    orphans = self._orphans.pop(project_id, []) if asked is None and not warm else []
                    if asked is None and not warm and not orphans:
                        del self._threads[project_id]
                        self._idle.notify_all()
                        return
                if orphans:
                    for folder in orphans:
                        remove_tree(folder)
                elif warm:
                    self._warm_cache(project_id)
                else:
                    assert asked is not None
                    state = self._guarded_pass(project_id, asked)
                    with self._lock:
                        if project_id not in self._deleted:
                            self._states[project_id] = state
        except BaseException:
            with self._lock:
                if self._threads.get(project_id) is threading.current_thread():
                    del self._threads[project_id]
                self._idle.notify_all()
            raise

    def _guarded_pass(self, project_id: int, asked: float) -> ApplyState:
        """:meth:`_pass`, its failure as a state (the thread must go on and say why)."""
        try:
            return self._pass(project_id, asked)
        except (LeapError, AppError, OSError, ValueError, KeyError) as exc:
            log.warning("applying corrections of project %d failed: %s", project_id, exc)
            return ApplyState(status="failed", error=str(exc), finished_at=utcnow())
        except Exception as exc:
            log.exception("applying corrections of project %d failed", project_id)
            return ApplyState(status="failed", error=f"internal error: {exc}", finished_at=utcnow())

    def _latest(self, project_id: int) -> tuple[RunRow | None, list[tuple[Labeled, list[crud.Correction]]]]:
        """The latest finished run and, per sequence of it, its folder and dataset with the sequence's
        active corrections. Only the project's sequences the run labeled
        (:func:`~app.rows.labeled_sequences`): one added since has no results there, one removed since
        keeps the export it had."""
        with open_db(self.settings.database) as db:
            run = crud.last_finished_run(db, project_id)
            if run is None:
                return None, []
            targets = [
                (seq, crud.list_corrections(db, project_id, active_only=True, sequence=seq.name))
                for seq in labeled_sequences(run, crud.list_sequences(db, project_id))
            ]
        return run, targets

    def _cache(self, project_id: int, run: RunRow, seq: Labeled) -> RunCache:
        # One cache per project (its latest run; of several sequences, the one applied last): the grid
        # and index of a large sequence take much memory. Keyed by the run row, not the folder alone.
        key: CacheKey = (run.id, run.created_at, seq.layout.folder)
        with self._lock:
            held = self._caches.get(project_id)
        if held is not None and held[0] == key:
            return held[1]
        sequence = seq.layout.open_sequence(seq.dataset)
        cache = load_run_cache(seq.layout, sequence, sequence.select(seq.frames), _voxel_size(run))
        with self._lock:
            if project_id not in self._deleted:
                self._caches[project_id] = (key, cache)
        return cache

    def _warm_cache(self, project_id: int) -> None:
        try:
            run, targets = self._latest(project_id)
            if run is not None and targets and targets[0][0].layout.export_dir.is_dir():
                self._cache(project_id, run, targets[0][0])
        except (LeapError, AppError, OSError, ValueError, KeyError) as exc:
            log.info("could not prepare corrections of project %d: %s", project_id, exc)
        except Exception:  # the project's thread must go on to its next pass
            log.exception("could not prepare corrections of project %d", project_id)

    def _pass(self, project_id: int, asked: float) -> ApplyState:
        run, targets = self._latest(project_id)
        if run is None or not targets or not all(seq.layout.export_dir.is_dir() for seq, _ in targets):
            return ApplyState(status="no_run", finished_at=utcnow())
        schema = Schema.from_dict(run.params.schema, source=f"run {run.id} schema")
        frames = changed = baked = 0
        for seq, corrections in targets:
            new = run_corrections(corrections, run.params, self.settings.work_dir)
            if not new.differs(RunCorrections.applied(seq.layout, schema.num_classes)):
                # The usual case after a run ends (the hook of app.main): nothing to load or rewrite.
                continue
            sequence = seq.layout.open_sequence(seq.dataset)
            cache = self._cache(project_id, run, seq)
            result = apply_to_run(
                seq.layout,
                sequence,
                sequence.select(seq.frames),
                _voxel_size(run),
                schema.export_ids(),
                new=new,
                cache=cache,
                moving_export_ids=schema.moving_export_ids(),
                things_mask=schema.things(),
            )
            if result.frames:
                exports.invalidate(run.run_dir)
            frames += len(result.frames)
            changed += result.changed_voxels
            baked += result.baked_reverts
        seconds = time.perf_counter() - asked
        if frames:
            log.info("corrections applied to run %s: %d scans in %.2f s", run.number, frames, seconds)
        return ApplyState(
            status="done",
            run_id=run.id,
            run_number=run.number,
            frames=frames,
            changed_voxels=changed,
            baked_reverts=baked,
            seconds=round(seconds, 4),
            finished_at=utcnow(),
        )


def _voxel_size(run: RunRow) -> float:
    return pipeline_config(run.params.pipeline, loc=("run", "params", "pipeline")).fusion.voxel_size


_appliers: dict[Path, CorrectionApplier] = {}
_appliers_lock = threading.Lock()


def applier(settings: Settings) -> CorrectionApplier:
    """The process's applier for ``settings.database`` (created on first use)."""
    with _appliers_lock:
        found = _appliers.get(settings.database)
        if found is None:
            found = _appliers[settings.database] = CorrectionApplier(settings)
        return found


__all__ = ["ApplyState", "CorrectionApplier", "applier"]
