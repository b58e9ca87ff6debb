"""Starting and stopping review viewers inside the app process, one per project.

:class:`AppBackend` adapts the app's SQLite store (:mod:`app.crud`, :mod:`app.services`) and job manager
(:mod:`app.jobs.manager`) to the viewer's :class:`~app.viewer.session.ProjectBackend`, so the viewer edits
exactly the data the web UI edits and its re-runs queue like any other run.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app import crud, models, services
from app.core.config import Settings
from app.core.db import open_db
from app.core.errors import Conflict, NotFound
from app.jobs.apply import applier
from app.jobs.manager import JobManager, current_manager
from app.rows import ProjectRow, RunRow, labeled_sequences
from app.viewer.lod import LodConfig
from app.viewer.panel import ReviewPanel
from app.viewer.session import (
    CorrectionRecord,
    ProjectBackend,
    ReviewMarkRecord,
    ReviewSession,
    RunInfo,
    Scope,
    SessionConfig,
)
from leap_core.errors import SchemaError
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
        with open_db(settings.database) as db:
            project = crud.require_project(db, project_id)
            self.sequence = crud.sequence_name(db, project_id, sequence, loc=("body", "sequence"))
            self.several = len(project.sequences) > 1
        # Corrections made in this viewer reach the export at once: load what that needs now.
        applier(settings).warm(project_id)

    def _jobs_manager(self) -> JobManager | None:
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
        manager = self._jobs_manager()
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
        manager = self._jobs_manager()
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
        """Store a correction made in the viewer (author "viewer") and apply it to the latest run's export
        in the background (:mod:`app.jobs.apply`)."""
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
            )
        applier(self.settings).request(self.project_id)
        return cid

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
            )

    def save_review_queue(self, kind: str, run_id: int | None, regions: list[tuple[str, str]]) -> None:
        with open_db(self.settings.database) as db:
            crud.save_review_queue(db, self.project_id, kind, run_id, regions, self.sequence)


@dataclass(frozen=True)
class ViewerInfo:
    """Where a project's viewer listens."""

    project_id: int
    """The project under review."""
    run_id: int | None
    """Run shown (None until the project has a finished run)."""
    port: int
    """Port viser bound on 127.0.0.1."""
    sequence: str | None = None
    """The project sequence shown."""


class ViewerManager:
    """The app's review viewers: at most one per project, each on its own viser port.

    Args:
        settings: app settings.
        jobs: job manager for re-runs (default: the process-wide one).
        config: session tunables.
    """

    def __init__(
        self, settings: Settings, jobs: JobManager | None = None, config: SessionConfig | None = None
    ) -> None:
        self.settings = settings
        self.jobs = jobs
        self.config = config or SessionConfig(
            max_points=settings.viewer_max_points, lod=LodConfig(budget=settings.viewer_max_points)
        )
        self._sessions: dict[int, ReviewSession] = {}
        self._lock = threading.Lock()

    def open(self, project_id: int, run_id: int | None = None, sequence: str | None = None) -> ViewerInfo:
        """Start (or reuse) the project's viewer, showing ``run_id`` or the latest finished run, of the
        project's sequence ``sequence`` (None: the one shown, else the first). Asking for another sequence
        than the running viewer shows replaces that viewer (one per project).

        Raises:
            NotFound: unknown project or run.
            InvalidField: ``sequence`` is not one of the project's.
            Conflict: the run has not finished.
        """
        replaced = None
        with self._lock:
            session = self._sessions.get(project_id)
            if session is not None and sequence is not None and _shown_sequence(session) != sequence:
                AppBackend(self.settings, project_id, self.jobs, sequence)  # 422 before closing anything
                replaced = self._sessions.pop(project_id)
                session = None
            if session is None:
                if replaced is not None:
                    replaced.close()
                backend = AppBackend(self.settings, project_id, self.jobs, sequence)
                if run_id is not None:
                    self._check_run(backend, run_id)
                session = ReviewSession(
                    backend,
                    panel=ReviewPanel,
                    run_id=run_id,
                    host="127.0.0.1",
                    port=self.settings.viewer_port if not self._sessions else 0,
                    config=self.config,
                )
                self._sessions[project_id] = session
                log.info("viewer for project %d on port %d", project_id, session.port)
            elif run_id is not None and (session.run is None or session.run.run_id != run_id):
                session.load_run(self._check_run(session.backend, run_id))
            elif run_id is None and session.run is None:
                latest = session.backend.latest_finished_run()
                if latest is not None:
                    session.load_run(latest)
        return ViewerInfo(
            project_id,
            None if session.run is None else session.run.run_id,
            session.port,
            _shown_sequence(session),
        )

    @staticmethod
    def _check_run(backend: ProjectBackend, run_id: int) -> RunInfo:
        info = backend.run_info(run_id)
        if info.status != "done":
            raise Conflict(
                f"Run {info.number} (id {run_id}) is {info.status}; only finished runs can be reviewed"
            )
        return info

    def get(self, project_id: int) -> ReviewSession | None:
        with self._lock:
            return self._sessions.get(project_id)

    def port(self, project_id: int) -> int | None:
        session = self.get(project_id)
        return None if session is None else session.port

    def endpoint(self, project_id: int) -> tuple[int, str] | None:
        """(port, websocket secret) of the project's viewer, for the app's relay; None when none runs."""
        session = self.get(project_id)
        return None if session is None else (session.port, session.scene.secret)

    def close(self, project_id: int) -> bool:
        """Stop the project's viewer; False when none was running."""
        with self._lock:
            session = self._sessions.pop(project_id, None)
        if session is None:
            return False
        session.close()
        return True

    def close_all(self) -> None:
        with self._lock:
            sessions = list(self._sessions.values())
            self._sessions.clear()
        for session in sessions:
            try:
                session.close()
            except Exception:  # shutting down: close the others regardless
                log.exception("closing a viewer failed")


def _shown_sequence(session: ReviewSession) -> str | None:
    backend = session.backend
    return backend.sequence if isinstance(backend, AppBackend) else None


__all__ = ["AppBackend", "ViewerInfo", "ViewerManager"]
