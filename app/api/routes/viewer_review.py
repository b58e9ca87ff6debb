"""The review queue of a project's viewer (web/viewer/review.js: keys a/s/r/n/p and Esc), and review
progress for the web UI's project page.

The viewer routes act on the running :class:`~app.viewer.session.ReviewSession` of the project (404 when no
viewer runs), exactly as the panel's "Review queue" buttons do. Review marks live in SQLite (migration 4),
so the progress route answers without a viewer.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

from fastapi import APIRouter, HTTPException, status
from pydantic import BaseModel, ConfigDict, Field

from app import crud
from app.api.deps import ReadDbDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.routes.viewer import ViewersDep, run_blocking, running_session
from app.api.types import ProjectId, SequenceQuery
from app.viewer.panel_review import progress_text
from app.viewer.records import QueueKind
from app.viewer.session import ReviewSession

router = APIRouter(prefix="/projects/{project_id}", tags=["viewer"], responses={**NOT_FOUND, **CONFLICT})


class QueueBuild(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    kind: QueueKind = Field(
        description="confidence (least confident first) or disagreement (camera vs final)"
    )


class QueueStep(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    step: Literal[-1, 1] = Field(description="1: next region, -1: previous region")
    kind: QueueKind | None = Field(default=None, description="queue to rank first when it is not the current")


class RegionMark(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    state: Literal["accepted", "skipped"] = Field(description="verdict on the highlighted region")


class RegionRelabel(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    class_name: str = Field(
        min_length=1, max_length=64, description="class assigned to the highlighted region's voxels"
    )


class RegionPublic(BaseModel):
    id: str = Field(description="stable region identity (cell of the map), see leap_core.review")
    position: int = Field(description="0-based rank in the queue")
    score: float
    count: int = Field(description="highlighted (candidate) voxels")
    state: str | None = Field(description="accepted / skipped on the region's current content, else null")
    frame_id: str | None = Field(
        description="scan that observed the region most (shown with the region boxed)"
    )


class ReviewStatePublic(BaseModel):
    kind: QueueKind
    building: bool = Field(description="a queue is being ranked")
    total: int
    reviewed: int
    skipped: int
    progress: str = Field(description='e.g. "12 / 100 reviewed"')
    region: RegionPublic | None
    classes: list[str] = Field(description="classes the region can be relabelled to")


class QueueProgress(BaseModel):
    kind: QueueKind
    run_id: int | None
    total: int
    reviewed: int
    skipped: int
    updated_at: str


class ReviewProgressPublic(BaseModel):
    data: list[QueueProgress] = Field(description="one entry per queue ranked so far (latest ranking)")


def _state(session: ReviewSession) -> ReviewStatePublic:
    queue = session.queue
    progress = queue.review_progress()
    region = None
    pos = queue.region_pos
    if queue.focus is not None and 0 <= pos < len(queue.regions):
        r = queue.regions[pos]
        frame_id = None
        if queue.focus_frame is not None and session.outputs is not None:
            frame_id = session.outputs.seq.frame_ids[session.outputs.frame_indices[queue.focus_frame]]
        region = RegionPublic(
            id=r.id,
            position=pos,
            score=r.score,
            count=r.count,
            state=queue.region_state(pos),
            frame_id=frame_id,
        )
    return ReviewStatePublic(
        kind=queue.queue_kind,
        building=queue.queue_building,
        progress=progress_text(progress),
        region=region,
        classes=session.class_names(),
        **progress,
    )


async def _on_region(session: ReviewSession, action: Callable[[str], object], arg: str) -> ReviewStatePublic:
    """Run a region action off the event loop; "no region is shown" (ValueError) answers 409."""
    try:
        await run_blocking(action, arg)
    except ValueError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, detail=str(exc)) from None
    return _state(session)


@router.get("/viewer/review", response_model=ReviewStatePublic)
async def review_state(project_id: ProjectId, viewers: ViewersDep) -> ReviewStatePublic:
    """The viewer's review queue: its kind, progress and the highlighted region."""
    return _state(running_session(viewers, project_id))


@router.post("/viewer/review/queue", response_model=ReviewStatePublic)
async def build_queue(project_id: ProjectId, payload: QueueBuild, viewers: ViewersDep) -> ReviewStatePublic:
    """Rank the regions of a queue (the disagreement queue reads every scan once per run)."""
    session = running_session(viewers, project_id)
    await run_blocking(session.queue.build_queue, payload.kind)
    return _state(session)


@router.post("/viewer/review/step", response_model=ReviewStatePublic)
async def step_region(project_id: ProjectId, payload: QueueStep, viewers: ViewersDep) -> ReviewStatePublic:
    """Highlight the next / previous region (ranking the queue first when there is none yet)."""
    session = running_session(viewers, project_id)
    queue = session.queue
    kind = payload.kind or queue.queue_kind
    if not queue.queue_built or not queue.regions or queue.queue_kind != kind:
        await run_blocking(queue.build_queue, kind)
    await run_blocking(queue.next_region, payload.step)
    return _state(session)


@router.post("/viewer/review/leave", response_model=ReviewStatePublic)
async def leave_review(project_id: ProjectId, viewers: ViewersDep) -> ReviewStatePublic:
    """Leave the review (key Esc, the "Leave review" buttons, and a viewer page that loads): no region
    highlighted, the whole map at full colour and no region box. The queue and its marks stay; the next
    step goes on from the region last shown."""
    session = running_session(viewers, project_id)
    await run_blocking(session.queue.clear_focus)
    return _state(session)


@router.post("/viewer/review/mark", response_model=ReviewStatePublic)
async def mark_region(project_id: ProjectId, payload: RegionMark, viewers: ViewersDep) -> ReviewStatePublic:
    """Accept (reviewed) or skip the highlighted region, stored in the project; then highlight the next
    region without a mark. 409 when no region is highlighted."""
    session = running_session(viewers, project_id)
    return await _on_region(session, session.queue.mark_region, payload.state)


@router.post("/viewer/review/relabel", response_model=ReviewStatePublic)
async def relabel_region(
    project_id: ProjectId, payload: RegionRelabel, viewers: ViewersDep
) -> ReviewStatePublic:
    """Assign a class to the highlighted region's voxels (a correction) and accept the region.
    409 when no region is highlighted; 422 naming ``class_name`` for a class the run does not have."""
    session = running_session(viewers, project_id)
    if payload.class_name not in session.class_names():
        raise HTTPException(
            422,
            detail=[
                {
                    "loc": ["body", "class_name"],
                    "msg": f"unknown class {payload.class_name!r}",
                    "type": "value_error",
                }
            ],
        )
    return await _on_region(session, session.queue.relabel_region, payload.class_name)


@router.get("/review", response_model=ReviewProgressPublic)
def review_progress(
    project_id: ProjectId, db: ReadDbDep, sequence: SequenceQuery = None
) -> ReviewProgressPublic:
    """Review progress of the project's sequence (default: its first) per ranked queue (for the web UI's
    project page; no viewer needed)."""
    crud.require_project(db, project_id)
    name = crud.sequence_name(db, project_id, sequence, loc=("query", "sequence"))
    return ReviewProgressPublic(data=[QueueProgress(**p) for p in crud.review_progress(db, project_id, name)])


__all__ = ["router"]
