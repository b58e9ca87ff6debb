"""Starting and stopping review viewers inside the app process: per project, one session per browser tab.

:class:`AppBackend` adapts the app's SQLite store (:mod:`app.crud`, :mod:`app.services`) and job manager
(:mod:`app.jobs.manager`) to the viewer's :class:`~app.viewer.session.ProjectBackend`, so the viewer edits
exactly the data the web UI edits and its re-runs queue like any other run.

:class:`ProjectViewer` is a project's viewer: a :class:`~app.viewer.session.ReviewSession` per browser tab
(each with its own viser server, so its own scan, camera, selection, focus and panel) over what the tabs
share: one loaded copy of each shown run (grid and scans), the corrected labels
(:class:`~app.viewer.corrections.OverlayCache`), and the project's runs, which it follows on one thread.
A correction, undo or review mark in one tab is pushed to the others at once (their scene and panel update
over their own websockets); a run that starts anywhere shows its progress in every tab, and every tab
loads it when it ends unless it ticked "Stay on run N".
"""

from __future__ import annotations

import copy
import functools
import logging
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app import crud, models, reviewers, services
from app.core.config import Settings
from app.core.db import open_db
from app.core.errors import Conflict, NotFound
from app.jobs.apply import applier
from app.jobs.manager import JobManager, current_manager
from app.rows import ProjectRow, RunRow, labeled_sequences
from app.viewer.corrections import OverlayCache
from app.viewer.data import ReviewGrid, RunOutputs
from app.viewer.lod import LodConfig
from app.viewer.panel import ReviewPanel
from app.viewer.records import ObjectAction
from app.viewer.session import (
    CorrectionRecord,
    ProjectBackend,
    ReviewMarkRecord,
    ReviewSession,
    RunInfo,
    Scope,
    SessionConfig,
    read_run,
)
from leap_core.errors import LeapError, SchemaError
from leap_core.pipeline.object_corrections import ObjectCorrections
from leap_core.schema import Schema

log = logging.getLogger("leap.viewer")


def _schema_or_none(doc: dict[str, Any] | None) -> Schema | None:
    if not doc:
        return None
    try:
        return Schema.from_dict(doc, source="run schema")
    except SchemaError:
        return None


class AppBackend:
    """The viewer's view of one project in the app's database and job queue.

    Args:
        settings: app settings (database path, work dir).
        project_id: the project.
        jobs: the running job manager; None uses the process-wide one when a run is started.
        sequence: which of the project's sequences it shows (None: the first); its run folder, dataset,
            corrections and review marks are that sequence's.
    """

    def __init__(
        self, settings: Settings, project_id: int, jobs: JobManager | None = None, sequence: str | None = None
    ) -> None:
        self.settings = settings
        self.project_id = project_id
        self._jobs = jobs
        self.reviewer: str | None = None
        """The reviewer's name the tab was given: stored with its corrections and review marks."""
        with open_db(settings.database) as db:
            project = crud.require_project(db, project_id)
            self.sequence = crud.sequence_name(db, project_id, sequence, loc=("body", "sequence"))
            self.several = len(project.sequences) > 1
        # Corrections made in this viewer reach the export at once: load what that needs now.
        applier(settings).warm(project_id)

    def jobs_manager(self) -> JobManager | None:
        """The given job manager, else the running server's, else None (no server: read the DB only)."""
        if self._jobs is not None:
            return self._jobs
        try:
            return current_manager()
        except RuntimeError:
            return None

    def _project(self) -> ProjectRow:
        with open_db(self.settings.database) as db:
            return crud.require_project(db, self.project_id)

    def project_name(self) -> str:
        name = self._project().name
        return f"{name} · {self.sequence}" if self.several else name

    def dataset_path(self) -> Path:
        seq = self._project().sequence(self.sequence)
        if seq is None:
            raise NotFound(f"Project {self.project_id} has no sequence {self.sequence!r}")
        return Path(seq.dataset_path)

    def load_schema(self) -> Schema:
        return Schema.from_dict(self._project().schema, source=f"project {self.project_id} schema")

    def save_schema(self, schema: Schema) -> None:
        with open_db(self.settings.database) as db:
            services.save_classes(db, self.project_id, schema.to_dict()["classes"], loc=("viewer",))

    def _info(self, run: RunRow) -> RunInfo:
        status, percent, stage, error = str(run.status), 0.0, None, run.error
        manager = self.jobs_manager()
        if manager is not None:
            progress = manager.run_status(run.id)
            status = str(progress.get("status", status))
            percent = float(progress.get("percent") or 0.0)
            stage = progress.get("stage")
            error = progress.get("error") or error
        if status == "done":
            percent = 100.0
        return RunInfo(
            run_id=run.id,
            number=run.number,
            status=status,
            percent=percent,
            stage=stage,
            error=error,
            run_dir=run.sequence_layout(self.sequence).folder,
            schema=_schema_or_none(run.params.schema),
            pipeline=run.params.pipeline,
        )

    def _covers(self, run: RunRow) -> bool:
        """Whether the run labeled this sequence (it may predate the sequence's addition)."""
        return any(s.name == self.sequence for s in labeled_sequences(run, self._project().sequences))

    def run_info(self, run_id: int) -> RunInfo:
        with open_db(self.settings.database) as db:
            run = crud.require_run(db, run_id)
        if run.project_id != self.project_id:
            raise NotFound(f"Run {run_id} not found in project {self.project_id}")
        if not self._covers(run):
            raise Conflict(
                f"Run {run_id} did not label sequence {self.sequence!r} (added since); run the "
                "pipeline to label it"
            )
        return self._info(run)

    def latest_finished_run(self) -> RunInfo | None:
        """The newest finished run that labeled this sequence."""
        with open_db(self.settings.database) as db:
            runs = [r for r in crud.list_runs(db, self.project_id) if r.status == "done"]
        run = next((r for r in runs if self._covers(r)), None)
        return None if run is None else self._info(run)

    def finished_run_before(self, run_id: int) -> RunInfo | None:
        with open_db(self.settings.database) as db:
            runs = crud.list_runs(db, self.project_id)
        number = next((r.number for r in runs if r.id == run_id), None)
        if number is None:
            return None
        earlier = [r for r in runs if r.status == "done" and r.number < number and self._covers(r)]
        run = max(earlier, key=lambda r: r.number, default=None)
        return None if run is None else self._info(run)

    def active_run(self) -> RunInfo | None:
        with open_db(self.settings.database) as db:
            run = crud.active_run(db, self.project_id)
        return None if run is None else self._info(run)

    def start_run(self) -> int:
        manager = self.jobs_manager()
        if manager is None:
            raise RuntimeError("runs can only be started while the app's job manager is running")
        return manager.start_run(self.project_id).id

    def labeler(self) -> str:
        return services.project_config(self._project()).labeler

    def set_labeler(self, name: str) -> None:
        with open_db(self.settings.database) as db:
            services.update_project(db, self.project_id, models.ProjectUpdate(form={"labeler": name}))

    def corrections(self) -> list[CorrectionRecord]:
        with open_db(self.settings.database) as db:
            rows = crud.list_corrections(db, self.project_id, active_only=False, sequence=self.sequence)
        return [
            CorrectionRecord(
                c.id,
                c.class_name,
                c.voxel_size,
                c.keys,
                c.active,
                c.created_at,
                scope=c.scope,
                frame_id=c.frame_id,
                points=c.points,
                run_id=c.run_id,
                track_id=c.track_id,
            )
            for c in rows
        ]

    def add_correction(
        self,
        class_name: str,
        voxel_size: float,
        keys: npt.NDArray[np.int64],
        *,
        scope: Scope = "map",
        frame_id: str | None = None,
        points: npt.NDArray[np.int64] | None = None,
    ) -> int:
        """Store a correction made in the viewer (author "viewer", with the tab's reviewer) and apply it to
        the latest run's export in the background (:mod:`app.jobs.apply`)."""
        with open_db(self.settings.database) as db:
            cid = crud.add_correction(
                db,
                project_id=self.project_id,
                class_name=class_name,
                voxel_size=voxel_size,
                keys=keys,
                scope=scope,
                frame_id=frame_id,
                points=points,
                author="viewer",
                sequence=self.sequence,
                reviewer=self.reviewer,
            )
        applier(self.settings).request(self.project_id)
        return cid

    def add_object_correction(
        self,
        class_name: str,
        run_id: int,
        track_id: int,
        *,
        action: ObjectAction = "relabel",
        other_track_id: int | None = None,
        frame: str | None = None,
    ) -> int:
        """Store an object-scope correction made in the viewer (author "viewer", the tab's reviewer):
        object ``track_id`` of run ``run_id`` relabelled, merged with ``other_track_id`` or split at
        ``frame`` (checked and kept as identity files by :func:`app.services.object_ref`), and apply it to
        the latest run's export in the background."""
        with open_db(self.settings.database) as db:
            run = crud.require_run(db, run_id)
            obj = services.object_ref(
                db,
                self.settings,
                self.project_id,
                run_id,
                self.sequence,
                track_id,
                action=action,
                other_track_id=other_track_id,
                frame=frame,
            )
            cid = crud.add_correction(
                db,
                project_id=self.project_id,
                class_name=class_name,
                voxel_size=services.pipeline_config(run.params.pipeline, loc=("run",)).fusion.voxel_size,
                keys=[],
                scope="object",
                author="viewer",
                sequence=self.sequence,
                reviewer=self.reviewer,
                obj=obj,
            )
        applier(self.settings).request(self.project_id)
        return cid

    def object_corrections(self, names: list[str]) -> ObjectCorrections:
        """The sequence's active object corrections for a run with the classes ``names``
        (:func:`app.services.object_corrections`); none, with a warning in the log, when an identity file
        is unreadable (the export's apply job reports it)."""
        with open_db(self.settings.database) as db:
            rows = crud.list_corrections(db, self.project_id, active_only=True, sequence=self.sequence)
        try:
            return services.object_corrections(rows, names, self.settings.work_dir)
        except LeapError as exc:
            log.warning("object corrections not shown: %s", exc)
            return ObjectCorrections()

    def set_correction_active(self, correction_id: int, active: bool) -> None:
        with open_db(self.settings.database) as db:
            if crud.get_correction(db, correction_id).project_id != self.project_id:
                raise NotFound(f"Correction {correction_id} not found in project {self.project_id}")
            crud.set_correction_active(db, correction_id, active)
        applier(self.settings).request(self.project_id)

    def review_marks(self) -> dict[str, ReviewMarkRecord]:
        with open_db(self.settings.database) as db:
            marks = crud.list_review_marks(db, self.project_id, self.sequence)
        return {k: ReviewMarkRecord(m.signature, m.state) for k, m in marks.items()}

    def set_review_mark(self, region: str, signature: str, state: str, run_id: int | None) -> None:
        with open_db(self.settings.database) as db:
            crud.set_review_mark(
                db,
                self.project_id,
                region=region,
                signature=signature,
                state=state,
                run_id=run_id,
                sequence=self.sequence,
                reviewer=self.reviewer,
            )

    def claimed_by_others(self) -> set[str]:
        """Regions other reviewers hold unexpired claims on (an unnamed tab: every claimed region)."""
        with open_db(self.settings.database) as db:
            claims = reviewers.active_claims(db, self.project_id, self.sequence)
        return {r for r, c in claims.items() if c.reviewer != self.reviewer}

    def save_review_queue(self, kind: str, run_id: int | None, regions: list[tuple[str, str]]) -> None:
        with open_db(self.settings.database) as db:
            crud.save_review_queue(db, self.project_id, kind, run_id, regions, self.sequence)


TAB_PATTERN = r"^[A-Za-z0-9_-]{8,32}$"
"""What a tab id looks like (:func:`secrets.token_urlsafe`); routes check it before any lookup."""


@dataclass(frozen=True)
class ViewerInfo:
    """Where one tab of a project's viewer listens."""

    project_id: int
    """The project under review."""
    run_id: int | None
    """Run shown (None until the project has a finished run)."""
    port: int
    """Port the tab's viser server bound on 127.0.0.1."""
    sequence: str | None = None
    """The project sequence shown."""
    tab: str = ""
    """The tab's id (its page is ``/viewer/tabs/<tab>/client/``)."""


@dataclass
class _Tab:
    session: ReviewSession
    seen: float
    """When a browser was last seen connected (monotonic seconds; creation counts)."""


class ProjectViewer:
    """One project's viewer: a review session per browser tab over one shared copy of each shown run.

    Args:
        settings: app settings.
        project_id: the project.
        jobs: job manager for re-runs.
        sequence: the project sequence shown (None: the first).
        config: session tunables.
        tab_idle_s: a tab no browser has been connected to for this long is closed (a reload reconnects
            within seconds; a closed browser tab frees its server, threads and share of memory).
    """

    def __init__(
        self,
        settings: Settings,
        project_id: int,
        jobs: JobManager | None,
        sequence: str | None,
        config: SessionConfig,
        tab_idle_s: float,
    ) -> None:
        self.backend = AppBackend(settings, project_id, jobs, sequence)
        self.config = config
        self.tab_idle_s = tab_idle_s
        self.overlays = OverlayCache()
        self._tabs: dict[str, _Tab] = {}
        self._latest: str | None = None
        self._lock = threading.Lock()
        self._runs: dict[int, tuple[ReviewGrid, RunOutputs]] = {}
        self._runs_lock = threading.Lock()
        self._stop = threading.Event()
        self._followed: int | None = None
        latest = self.backend.latest_finished_run()
        self._finished: int | None = None if latest is None else latest.run_id
        self._changed = threading.Event()
        """Set when any run changes (the job manager's :class:`~app.jobs.notify.ChangeNotifier`)."""
        manager = self.backend.jobs_manager()
        same_db = manager is not None and manager.settings.database == settings.database
        self._notifier = manager.changes if manager is not None and same_db else None
        if self._notifier is not None:
            self._notifier.add_event(self._changed)
        self.looks = 0
        """How many times the follower has read the project's runs (tests count its wakeups)."""
        self._thread = threading.Thread(target=self._follow_loop, name="viewer-project", daemon=True)
        self._thread.start()

    @property
    def sequence(self) -> str:
        return self.backend.sequence

    # ------------------------------------------------------------------------------------------ tabs
    def open_tab(self, run_id: int | None, reviewer: str | None, port: int) -> tuple[str, ReviewSession]:
        """A new tab's session showing ``run_id`` (None: the latest finished run)."""
        backend = copy.copy(self.backend)
        backend.reviewer = reviewer
        tab = secrets.token_urlsafe(12)
        session = ReviewSession(
            backend,
            panel=ReviewPanel,
            run_id=run_id,
            host="127.0.0.1",
            port=port,
            config=self.config,
            data=self.run_data,
            overlays=self.overlays,
        )
        session.queue.claimed_by_others = backend.claimed_by_others
        session.on_event(functools.partial(self._on_event, tab))
        with self._lock:
            self._tabs[tab] = _Tab(session, time.monotonic())
            self._latest = tab
        return tab, session

    def tab(self, tab: str | None = None) -> ReviewSession | None:
        """The tab's session (None: the tab opened last that is still open)."""
        with self._lock:
            key = self._latest if tab is None else tab
            entry = None if key is None else self._tabs.get(key)
            return None if entry is None else entry.session

    def tab_id(self, session: ReviewSession) -> str:
        """The id of ``session``'s tab ("" when it is closed)."""
        with self._lock:
            return next((k for k, t in self._tabs.items() if t.session is session), "")

    def tabs(self) -> list[ReviewSession]:
        with self._lock:
            return [t.session for t in self._tabs.values()]

    def set_reviewer(self, tab: str, name: str | None) -> bool:
        """Name the reviewer of ``tab``; False when no such tab is open."""
        session = self.tab(tab)
        if session is None:
            return False
        backend = session.backend
        assert isinstance(backend, AppBackend)
        backend.reviewer = name
        return True

    def close_tab(self, tab: str) -> bool:
        with self._lock:
            entry = self._tabs.pop(tab, None)
            if self._latest == tab:
                self._latest = next(reversed(self._tabs), None)
        if entry is None:
            return False
        entry.session.close()
        self._prune_runs()
        return True

    def close(self) -> None:
        """Close every tab and stop following the project."""
        self._stop.set()
        self._changed.set()
        if self._notifier is not None:
            self._notifier.remove_event(self._changed)
        with self._lock:
            tabs = list(self._tabs.values())
            self._tabs.clear()
            self._latest = None
        for entry in tabs:
            try:
                entry.session.close()
            except Exception:  # closing: close the others regardless
                log.exception("closing a viewer tab failed")
        self._thread.join(timeout=5)

    # ----------------------------------------------------------------------------------- shared data
    def run_data(self, run: RunInfo) -> tuple[ReviewGrid, RunOutputs]:
        """The run's grid and scans, read once for every tab (tabs loading it meanwhile wait for it)."""
        with self._runs_lock:
            data = self._runs.get(run.run_id)
            if data is None:
                data = read_run(run, self.backend.dataset_path())
                self._runs[run.run_id] = data
            return data

    def _prune_runs(self) -> None:
        """Forget the runs no tab shows (their arrays are freed with the last tab that showed them)."""
        shown = {s.run.run_id for s in self.tabs() if s.run is not None}
        with self._runs_lock:
            for run_id in [r for r in self._runs if r not in shown]:
                # A run read moments ago for a tab still loading it is read again then: rare and harmless.
                del self._runs[run_id]

    # ------------------------------------------------------------------------------ pushes between tabs
    def _on_event(self, origin: str, name: str) -> None:
        if name == "corrected":
            self.push_corrections(skip=origin)
        elif name == "marked":
            self.push_marks(skip=origin)
        elif name == "loaded":
            self._prune_runs()

    def _others(self, skip: str | None) -> list[ReviewSession]:
        with self._lock:
            return [t.session for k, t in self._tabs.items() if k != skip]

    def push_corrections(self, skip: str | None = None) -> None:
        """Show the project's corrections again in every tab but ``skip`` (on threads: the tab that made the
        change answers at once)."""
        for session in self._others(skip):
            threading.Thread(target=_guarded(session.corrections.refresh), daemon=True).start()

    def push_marks(self, skip: str | None = None) -> None:
        """Re-read the review marks in every tab but ``skip``, and show its queue's progress with them."""
        for session in self._others(skip):
            marks = session.backend.review_marks()
            queue = session.queue
            with session.shared.lock:
                queue.marks = marks
                shown = queue.queue_built and not queue.queue_building
            if shown:
                session.notify.panel.on_queue(False)

    # --------------------------------------------------------------------------------- following runs
    def _idle_wait_s(self) -> float:
        """Longest wait between two looks at the runs and the tabs' browsers: with the job manager's
        notifier a look follows each run change, so the timer only has to find tabs whose browser left
        (within a quarter of ``tab_idle_s``, at most 30 s); without it, runs are polled."""
        interval = self.config.poll_interval_s
        if self._notifier is None:
            return interval
        return max(interval, min(30.0, self.tab_idle_s / 4))

    def _follow_loop(self) -> None:
        interval, idle = self.config.poll_interval_s, self._idle_wait_s()
        while not self._stop.is_set():
            # An idle viewer sleeps here until a run changes: a timer that read the database every
            # interval cost each idle tab's server a steady share of a core.
            self._changed.wait(idle)
            self._changed.clear()
            if self._stop.is_set():
                return
            try:
                self._follow_once()
            except Exception:  # a transient DB error must not end following
                log.exception("viewer of project %d could not read its runs", self.backend.project_id)
            # A running run notifies at every progress step: look at most once an interval.
            self._stop.wait(interval)

    def _follow_once(self) -> None:
        if not self.tabs():
            return  # every tab closed: nothing to follow for until the next one opens
        self.looks += 1
        active = self.backend.active_run()
        if active is not None and active.run_id != self._followed:
            # Every tab shows its progress and loads it when it ends (RunWatcher, per tab).
            for session in self.tabs():
                session.runs.watch(active.run_id)
        self._followed = None if active is None else active.run_id
        # A run whose stages were all reused can start and finish between two looks: hand a newly finished
        # run to the tabs that show an older one (their watcher loads it, or keeps it as the newer run).
        done = self.backend.latest_finished_run()
        if done is not None and done.run_id != self._finished:
            self._finished = done.run_id
            for session in self.tabs():
                shown = session.run
                if shown is None or shown.run_id < done.run_id:
                    session.runs.watch(done.run_id)
        now = time.monotonic()
        idle = []
        with self._lock:
            for key, entry in self._tabs.items():
                if entry.session.scene.server.get_clients():
                    entry.seen = now
                elif now - entry.seen > self.tab_idle_s:
                    idle.append(key)
        for key in idle:
            log.info(
                "closing viewer tab %s of project %d: no browser for %.0f s",
                key,
                self.backend.project_id,
                self.tab_idle_s,
            )
            self.close_tab(key)


def _guarded(fn: Callable[[], None]) -> Callable[[], None]:
    def run() -> None:
        try:
            fn()
        except Exception:  # a tab that cannot update must not stop the others
            log.exception("updating a viewer tab failed")

    return run


class ViewerManager:
    """The app's review viewers: per project a :class:`ProjectViewer`, one viser server per browser tab.

    Args:
        settings: app settings.
        jobs: job manager for re-runs (default: the process-wide one).
        config: session tunables.
        tab_idle_s: see :class:`ProjectViewer`.
    """

    def __init__(
        self,
        settings: Settings,
        jobs: JobManager | None = None,
        config: SessionConfig | None = None,
        tab_idle_s: float = 120.0,
    ) -> None:
        self.settings = settings
        self.jobs = jobs
        self.config = config or SessionConfig(
            max_points=settings.viewer_max_points, lod=LodConfig(budget=settings.viewer_max_points)
        )
        self.tab_idle_s = tab_idle_s
        self.tab: str | None = None
        """The tab :meth:`get` looks up by default (None: the tab opened last); see :meth:`for_tab`."""
        self._viewers: dict[int, ProjectViewer] = {}
        self._lock = threading.Lock()

    def for_tab(self, tab: str) -> ViewerManager:
        """This manager (the same viewers, the same lock) with :meth:`get` defaulting to ``tab``: what one
        request of that tab's page sees."""
        bound = copy.copy(self)
        bound.tab = tab
        return bound

    def open(
        self,
        project_id: int,
        run_id: int | None = None,
        sequence: str | None = None,
        reviewer: str | None = None,
    ) -> ViewerInfo:
        """Open a new tab of the project's viewer (starting the viewer if needed), showing ``run_id`` or the
        latest finished run, of the project's sequence ``sequence`` (None: the one shown, else the first),
        for ``reviewer``. Asking for another sequence than the running viewer shows replaces that viewer
        (one sequence per project at a time).

        Raises:
            NotFound: unknown project or run.
            InvalidField: ``sequence`` is not one of the project's.
            Conflict: the run has not finished.
        """
        replaced = None
        with self._lock:
            viewer = self._viewers.get(project_id)
            if viewer is not None and sequence is not None and viewer.sequence != sequence:
                AppBackend(self.settings, project_id, self.jobs, sequence)  # 422 before closing anything
                replaced = self._viewers.pop(project_id)
                viewer = None
            if replaced is not None:
                replaced.close()
            if viewer is None:
                viewer = ProjectViewer(
                    self.settings, project_id, self.jobs, sequence, self.config, self.tab_idle_s
                )
                self._viewers[project_id] = viewer
            if run_id is not None:
                self._check_run(viewer.backend, run_id)
            first = not any(v.tabs() for v in self._viewers.values())
            tab, session = viewer.open_tab(run_id, reviewer, self.settings.viewer_port if first else 0)
            log.info("viewer tab %s for project %d on port %d", tab, project_id, session.port)
        return ViewerInfo(
            project_id,
            None if session.run is None else session.run.run_id,
            session.port,
            viewer.sequence,
            tab,
        )

    @staticmethod
    def _check_run(backend: ProjectBackend, run_id: int) -> RunInfo:
        info = backend.run_info(run_id)
        if info.status != "done":
            raise Conflict(
                f"Run {info.number} (id {run_id}) is {info.status}; only finished runs can be reviewed"
            )
        return info

    def viewer(self, project_id: int) -> ProjectViewer | None:
        with self._lock:
            return self._viewers.get(project_id)

    def get(self, project_id: int, tab: str | None = None) -> ReviewSession | None:
        """The session of ``tab`` (None: :attr:`tab`, else the tab opened last) of the project's viewer."""
        viewer = self.viewer(project_id)
        return None if viewer is None else viewer.tab(self.tab if tab is None else tab)

    def port(self, project_id: int, tab: str | None = None) -> int | None:
        session = self.get(project_id, tab)
        return None if session is None else session.port

    def endpoint(self, project_id: int, tab: str) -> tuple[int, str] | None:
        """(port, websocket secret) of the tab's viser server, for the app's relay; None when not open."""
        session = self.get(project_id, tab)
        return None if session is None else (session.port, session.scene.secret)

    def corrections_changed(self, project_id: int) -> None:
        """Corrections changed outside the viewer (the API): show them in the project's open tabs."""
        viewer = self.viewer(project_id)
        if viewer is not None:
            viewer.push_corrections()

    def close(self, project_id: int) -> bool:
        """Stop the project's viewer (every tab); False when none was running."""
        with self._lock:
            viewer = self._viewers.pop(project_id, None)
        if viewer is None:
            return False
        viewer.close()
        return True

    def close_all(self) -> None:
        with self._lock:
            viewers = list(self._viewers.values())
            self._viewers.clear()
        for viewer in viewers:
            try:
                viewer.close()
            except Exception:  # shutting down: close the others regardless
                log.exception("closing a viewer failed")


__all__ = ["TAB_PATTERN", "AppBackend", "ProjectViewer", "ViewerInfo", "ViewerManager"]
