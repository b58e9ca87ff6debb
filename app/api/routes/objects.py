"""A finished run's objects (the ``tracks`` stage's tracks of one sequence): each with its class, life,
motion and vote evidence, and the object review queue (:mod:`leap_core.object_review`) as a filter."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query

from app import crud, models
from app.api.deps import DbDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import RunId, SequenceQuery
from app.core.errors import Conflict, InvalidField, NotFound
from leap_core.object_review import ObjectQueueConfig, reason_codes, reason_text
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.schema import Schema

router = APIRouter(tags=["objects"], responses={**NOT_FOUND, **CONFLICT})

MAX_LIMIT = 1000
"""Most objects one page holds (a long sequence has thousands of tracks)."""

Limit = Annotated[int, Query(ge=1, le=MAX_LIMIT, description=f"objects per page (at most {MAX_LIMIT})")]
Offset = Annotated[int, Query(ge=0, le=2**31, description="objects to skip")]
Queued = Annotated[bool, Query(description="only the object review queue's, in its order")]


@router.get("/runs/{run_id}/objects", response_model=models.ObjectsPublic)
def list_objects(
    run_id: RunId,
    db: DbDep,
    sequence: SequenceQuery = None,
    queued: Queued = False,
    offset: Offset = 0,
    limit: Limit = 100,
) -> models.ObjectsPublic:
    """The run's objects in one sequence (default: its first), by id, or with ``queued`` the review
    queue's in its order (close votes, broken tracks, short tracks; docs/METHOD.md B.6), with the default
    :class:`~leap_core.object_review.ObjectQueueConfig` (the viewer's session may set its own)."""
    run = crud.require_run(db, run_id)
    if run.status != "done":
        raise Conflict(f"Run {run.number} (id {run.id}) is {run.status}; only finished runs have objects")
    names = run.params.names
    name = names[0] if sequence is None else sequence
    if name not in names:
        raise InvalidField(
            ["query", "sequence"], f"run {run.id} has no sequence {sequence!r} (it has {', '.join(names)})"
        )
    path = run.sequence_layout(name).tracks
    if not path.is_file():
        raise NotFound(f"Run {run.id} has no objects in sequence {name!r} (tracking was off): turn it on")
    tracks = SequenceTracks.load(path)
    schema = Schema.from_dict(run.params.schema, source=f"run {run.id} schema")
    classes = [c.name for c in schema.classes]
    ids, reasons = tracks.review_queue(schema.things(), ObjectQueueConfig())
    why = dict(zip(ids.tolist(), reasons.tolist(), strict=True))
    order = ids if queued else np.arange(1, tracks.table.label.size + 1)
    table, ev, life = tracks.table, tracks.table.vote_evidence(), tracks.track_life()

    def frame(t: int) -> str | None:
        return tracks.frame_ids[t] if t >= 0 else None

    def public(track: int) -> models.ObjectPublic:
        k = track - 1
        label, runner = int(table.label[k]), int(ev.runner_up[k])
        mask = why.get(track, 0)
        cls, other = classes[label] if label >= 0 else "", classes[runner] if runner >= 0 else None
        share, second = float(ev.share[k]), float(ev.runner_share[k])
        present, gaps = int(life.present[k]), int(life.gaps[k])
        return models.ObjectPublic(
            id=track,
            class_name=cls,
            scans=present,
            first_frame=frame(int(life.first[k])),
            last_frame=frame(int(life.last[k])),
            gaps=gaps,
            moving=bool(table.moving[k]),
            speed=float(np.linalg.norm(table.velocity[k])),
            vote_share=share,
            runner_up=other,
            runner_up_share=second,
            queued=reason_codes(mask),
            reason=reason_text(
                mask, cls, share=share, runner_name=other, runner_share=second, present=present, gaps=gaps
            ),
        )

    page = order[offset : offset + limit]
    return models.ObjectsPublic(
        run_id=run.id,
        sequence=name,
        data=[public(int(t)) for t in page],
        count=int(order.size),
        offset=offset,
        limit=limit,
    )
