"""Background runs of the pipeline.

In-process callers (the 3D viewer) use the two functions below; they act on the job manager of the
running server (or on the one given).
"""

from __future__ import annotations

from typing import Any

from app.jobs.manager import JobManager, current_manager


def start_run(project_id: int, *, manager: JobManager | None = None) -> int:
    """Queue a run of the project's current classes, prompts and parameters; returns the run id.

    Raises:
        app.core.errors.NotFound: unknown project.
        app.core.errors.Conflict: the project already has a queued or running run.
    """
    return int((manager or current_manager()).start_run(project_id)["id"])


def run_status(run_id: int, *, manager: JobManager | None = None) -> dict[str, Any]:
    """The run's progress: ``{"status", "stage", "percent", "eta_s", "stages", "error", ...}``.

    An ``app.models.RunProgress`` as a dict.

    Raises:
        app.core.errors.NotFound: unknown run.
    """
    from app import crud, services
    from app.core.db import open_db

    jobs = manager or current_manager()
    live = jobs.progress(run_id)
    if live is not None:
        return live
    with open_db(jobs.settings.database) as db:
        return services.run_progress(crud.require_run(db, run_id), None).model_dump()


__all__ = ["JobManager", "run_status", "start_run"]
