"""Reviewers of a project: claim a batch of a saved review queue, release it, and progress per reviewer.

Reviewers are names (no accounts, :mod:`app.reviewers`); the web UI keeps the browser's in localStorage.
The viewer tabs of other reviewers skip claimed regions when stepping through the queue.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from app import crud, reviewers
from app.api.deps import DbDep, ReadDbDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import ProjectId, SequenceQuery
from app.models import SEQUENCE_NAME_PATTERN

router = APIRouter(prefix="/projects/{project_id}", tags=["reviewers"], responses={**NOT_FOUND, **CONFLICT})

ReviewerName = Annotated[
    str,
    Field(min_length=1, max_length=reviewers.REVIEWER_MAX, description="the reviewer's name (no account)"),
]


class ClaimBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    reviewer: ReviewerName
    count: int = Field(default=10, ge=1, le=reviewers.MAX_CLAIM, description="regions to hold in all")
    kind: Literal["confidence", "disagreement"] = Field(
        default="confidence", description="which saved review queue"
    )
    sequence: str | None = Field(
        default=None, pattern=SEQUENCE_NAME_PATTERN, description="project sequence (default: the first)"
    )


class ReleaseBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    reviewer: ReviewerName
    sequence: str | None = Field(
        default=None, pattern=SEQUENCE_NAME_PATTERN, description="project sequence (default: the first)"
    )


class ClaimPublic(BaseModel):
    reviewer: str
    regions: list[str] = Field(description="every region the reviewer holds on that queue, in queue order")
    ttl_s: float = Field(description="seconds a claim holds unless claimed again or released")


class ReleasePublic(BaseModel):
    released: int


class ReviewerPublic(BaseModel):
    reviewer: str
    accepted: int = Field(description="regions accepted")
    skipped: int = Field(description="regions skipped")
    corrections: int = Field(description="active corrections made in the viewer")
    claimed: int = Field(description="regions held by an unexpired claim")


class ReviewersPublic(BaseModel):
    data: list[ReviewerPublic]


@router.post("/review/claims", response_model=ClaimPublic)
def claim(project_id: ProjectId, body: ClaimBody, db: DbDep) -> ClaimPublic:
    """Hold the next ``count`` unreviewed regions of the saved queue that no other reviewer holds (409 when
    no queue was ranked yet). Two reviewers claiming at once get disjoint batches."""
    name = crud.sequence_name(db, project_id, body.sequence, loc=("body", "sequence"))
    regions = reviewers.claim_regions(
        db, project_id, reviewer=body.reviewer, kind=body.kind, count=body.count, sequence=name
    )
    return ClaimPublic(reviewer=body.reviewer, regions=regions, ttl_s=reviewers.CLAIM_TTL_S)


@router.post("/review/claims/release", response_model=ReleasePublic)
def release(project_id: ProjectId, body: ReleaseBody, db: DbDep) -> ReleasePublic:
    """Give back every region the reviewer holds on the sequence."""
    name = crud.sequence_name(db, project_id, body.sequence, loc=("body", "sequence"))
    released = reviewers.release_claims(db, project_id, reviewer=body.reviewer, sequence=name)
    return ReleasePublic(released=released)


@router.get("/reviewers", response_model=ReviewersPublic)
async def reviewer_progress(
    project_id: ProjectId,
    db: ReadDbDep,
    sequence: SequenceQuery = None,
) -> ReviewersPublic:
    """What each named reviewer did on the sequence (default: its first): marks, corrections, claims."""
    crud.require_project(db, project_id)
    name = crud.sequence_name(db, project_id, sequence, loc=("query", "sequence"))
    rows = reviewers.reviewer_progress(db, project_id, name)
    return ReviewersPublic(data=[ReviewerPublic(**vars(r)) for r in rows])


__all__ = ["router"]
