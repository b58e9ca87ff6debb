"""Runs of a project: start (with a note), a preview of what the next run recomputes, list, detail, note
edits, cancel, resume, live progress (JSON and server-sent events), metrics, comparison and logs."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

from fastapi import APIRouter, Request, Response, status
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from app import crud, models, services, steering
from app.api.deps import DbDep, JobsDep, ReadDbDep, SettingsDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import ProjectId, RunId, SequenceQuery
from app.core.config import Settings
from app.core.db import open_db
from app.core.errors import NotFound
from app.jobs.manager import JobManager
from app.jobs.progress import TERMINAL_STATUSES
from leap_core.errors import LeapError
from leap_core.pipeline.apply import export_ahead_of_metrics

router = APIRouter(tags=["runs"], responses={**NOT_FOUND, **CONFLICT})

STREAM_MIN_INTERVAL_S = 0.25
"""Shortest time between two events of one stream (changes in between are coalesced)."""
STREAM_HEARTBEAT_S = 15.0
"""Comment lines keep idle streams open through proxies."""
LOG_TAIL_BYTES = 256 * 1024


@router.post(
    "/projects/{project_id}/runs", response_model=models.RunPublic, status_code=status.HTTP_202_ACCEPTED
)
def start_run(
    project_id: ProjectId, jobs: JobsDep, db: DbDep, payload: models.RunCreate | None = None
) -> models.RunPublic:
    frames = (
        None if payload is None or payload.frames is None else (payload.frames.start, payload.frames.stop)
    )
    run = jobs.start_run(project_id, frames=frames)
    if payload is not None and payload.note:
        crud.update_run(db, run.id, note=payload.note)
    return services.run_public(crud.require_run(db, run.id), jobs.progress(run.id))


@router.get("/projects/{project_id}/runs/preview", response_model=models.RunPreview)
def preview_run(project_id: ProjectId, db: DbDep, settings: SettingsDep) -> models.RunPreview:
    """Which stages a new run of all frames would recompute, and what changed since the finished run it
    would start from: the fingerprints it would have against that run's ``stages.json``."""
    return steering.run_preview(db, settings, project_id)


@router.patch("/runs/{run_id}", response_model=models.RunPublic)
def update_run(run_id: RunId, payload: models.RunUpdate, db: DbDep, jobs: JobsDep) -> models.RunPublic:
    """Set or clear the run's note."""
    crud.require_run(db, run_id)
    crud.update_run(db, run_id, note=payload.note or None)
    return services.run_public(crud.require_run(db, run_id), jobs.progress(run_id))


@router.get("/runs/{run_id}/compare/{base_id}", response_model=models.ComparePublic)
def compare_runs(run_id: RunId, base_id: RunId, db: DbDep) -> models.ComparePublic:
    """The run against ``base_id`` (same project): Δ mIoU and Δ IoU per class for every protocol and
    result row both have, and what changed between their inputs (classes, prompts, parameters)."""
    return steering.compare_runs(db, run_id, base_id)


# The two polled read endpoints build their public model once and send its JSON directly (FastAPI would
# otherwise validate the returned model a second time); ``response_model`` still documents them.
@router.get("/projects/{project_id}/runs", response_model=models.RunsPublic)
async def list_runs(project_id: ProjectId, db: ReadDbDep, jobs: JobsDep) -> Response:
    crud.require_project(db, project_id)
    data = [
        services.run_public(jobs.as_stored(r), jobs.progress(r.id)) for r in crud.list_runs(db, project_id)
    ]
    return Response(
        models.RunsPublic(data=data, count=len(data)).model_dump_json(), media_type="application/json"
    )


@router.get("/runs/{run_id}", response_model=models.RunPublic)
async def read_run(run_id: RunId, db: ReadDbDep, jobs: JobsDep) -> Response:
    run = services.run_public(jobs.as_stored(crud.require_run(db, run_id)), jobs.progress(run_id))
    return Response(run.model_dump_json(), media_type="application/json")


@router.post("/runs/{run_id}/cancel", response_model=models.RunPublic)
def cancel_run(run_id: RunId, jobs: JobsDep, db: DbDep) -> models.RunPublic:
    jobs.cancel_run(run_id)
    return services.run_public(crud.require_run(db, run_id), jobs.progress(run_id))


@router.post("/runs/{run_id}/resume", response_model=models.RunPublic, status_code=status.HTTP_202_ACCEPTED)
def resume_run(run_id: RunId, jobs: JobsDep, db: DbDep) -> models.RunPublic:
    """Continue an interrupted, cancelled or failed run in its own folder with the settings it was started
    with: changes to the project since then are not used (a run whose ``fix_setting`` is set failed on a
    setting; start a new run with POST /projects/{id}/runs once it is changed)."""
    jobs.resume_run(run_id)
    return services.run_public(crud.require_run(db, run_id), jobs.progress(run_id))


def _stored_progress(database: Path, run_id: int) -> tuple[int, str, str]:
    with open_db(database) as db:
        run = crud.require_run(db, run_id)
        snap = services.run_progress(run, None)
        return snap.version, snap.status, snap.model_dump_json()


async def _payload(jobs: JobManager, settings: Settings, run_id: int) -> tuple[int, str, str]:
    """(version, status, RunProgress JSON): from memory while the run is recent, else from the database."""
    live = jobs.progress_payload(run_id)
    if live is not None:
        return live
    return await run_in_threadpool(_stored_progress, settings.database, run_id)


@router.get("/runs/{run_id}/progress", response_model=models.RunProgress)
async def read_progress(run_id: RunId, jobs: JobsDep, settings: SettingsDep) -> Response:
    """The run's progress: from memory while it is queued or running (no database access), else stored."""
    _, _, text = await _payload(jobs, settings, run_id)
    return Response(text, media_type="application/json")


@router.get(
    "/runs/{run_id}/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "`progress` events, then `end`"}},
)
async def stream_progress(
    run_id: RunId, request: Request, jobs: JobsDep, settings: SettingsDep
) -> StreamingResponse:
    """Server-sent events: a ``progress`` event (a RunProgress JSON) whenever the run changes, at most four
    times a second, and a final ``end`` event once it is done, failed, cancelled or interrupted."""
    first = await _payload(jobs, settings, run_id)  # 404 before the stream starts

    async def events() -> AsyncIterator[str]:
        version, status, text = first
        yield f"event: progress\ndata: {text}\n\n"
        while status not in TERMINAL_STATUSES:
            waiter = jobs.changes.register(run_id)
            try:
                current = jobs.progress_payload(run_id)
                if current is None or current[0] == version:
                    with contextlib.suppress(asyncio.TimeoutError):
                        await asyncio.wait_for(asyncio.shield(waiter), STREAM_HEARTBEAT_S)
            finally:
                jobs.changes.discard(run_id, waiter)
            if await request.is_disconnected():
                return
            new_version, status, text = await _payload(jobs, settings, run_id)
            if new_version == version and status not in TERMINAL_STATUSES:
                yield ": keep-alive\n\n"
                continue
            version = new_version
            yield f"event: progress\ndata: {text}\n\n"
            # Coalesce bursts: progress bars need no more than four updates a second.
            await asyncio.sleep(STREAM_MIN_INTERVAL_S)
        yield "event: end\ndata: {}\n\n"

    return StreamingResponse(
        events(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )


@router.get("/runs/{run_id}/metrics", response_model=models.MetricsPublic)
def read_metrics(run_id: RunId, db: DbDep, sequence: SequenceQuery = None) -> models.MetricsPublic:
    """The run's result tables; a run of several sequences has them overall (the sequences' confusion
    matrices summed) and, with ``sequence``, per sequence."""
    run = crud.require_run(db, run_id)
    table = services.sequence_metrics(run, sequence)
    if table is None:
        what = f"Sequence {sequence!r} of run {run_id}" if sequence is not None else f"Run {run_id}"
        raise NotFound(f"{what} has no metrics (it is not finished, or its dataset has no ground truth)")
    names = [c["name"] for c in run.params.schema["classes"]]
    chosen = run.params.names if sequence is None else [sequence]
    try:
        stale = any(export_ahead_of_metrics(run.sequence_layout(n), len(names)) for n in chosen)
    except LeapError:
        stale = True  # unreadable applied-corrections files: do not claim the figures are current
    return models.MetricsPublic(
        run_id=run_id,
        class_names=names,
        metrics=table,
        before_corrections=stale,
        sequence=sequence,
        sequences=services.metrics_sequences(run),
    )


@router.get("/runs/{run_id}/logs", response_model=models.LogPublic)
def read_logs(run_id: RunId, db: DbDep) -> models.LogPublic:
    run = crud.require_run(db, run_id)
    path = run.layout.log
    try:
        size = path.stat().st_size
        with path.open("rb") as fh:
            fh.seek(max(0, size - LOG_TAIL_BYTES))
            text = fh.read().decode("utf-8", errors="replace")
    except FileNotFoundError:
        size, text = 0, ""
    return models.LogPublic(run_id=run_id, text=text, truncated=size > LOG_TAIL_BYTES)
