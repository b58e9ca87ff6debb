"""Several reviewers on one project: claims that split a saved review queue, and progress per reviewer.

A reviewer is a name (no account): the browser asks for it once and keeps it (web/reviewer.js), the viewer
tab records it with every correction and review mark (``corrections.reviewer``, ``review_marks.reviewer``,
migration 9). A *claim* reserves regions of a sequence's saved review queue
(:func:`app.crud.save_review_queue`) for one reviewer until it expires or is released; the other reviewers'
viewers skip claimed regions.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

import sqlite_utils

from app import crud
from app.core.db import transaction
from app.core.errors import Conflict

REVIEWER_MAX = 64
"""Longest reviewer name."""
CLAIM_TTL_S = 3600.0
"""How long a claim holds when it is not released (an hour: a batch is a sitting's work)."""
MAX_CLAIM = 500
"""Most regions one claim takes (bounds the request)."""


@dataclass(frozen=True)
class Claim:
    """One claimed region."""

    region: str
    """Region identity (:func:`leap_core.review.region_id`)."""
    reviewer: str
    """Who claimed it."""
    expires_at: str
    """ISO UTC time the claim lapses."""


@dataclass(frozen=True)
class ReviewerProgress:
    """What one reviewer did on one sequence of a project."""

    reviewer: str
    accepted: int
    """Regions accepted (marks by this reviewer)."""
    skipped: int
    """Regions skipped."""
    corrections: int
    """Active corrections made."""
    claimed: int
    """Regions claimed now (unexpired)."""


def _now() -> datetime:
    return datetime.now(timezone.utc)


def _iso(t: datetime) -> str:
    return t.isoformat(timespec="seconds")


def active_claims(
    db: sqlite_utils.Database, project_id: int, sequence: str | None = None, *, now: datetime | None = None
) -> dict[str, Claim]:
    """Unexpired claims on the sequence (None: the first) by region identity."""
    seq = crud.sequence_name(db, project_id, sequence)
    rows = db.execute(
        "SELECT region, reviewer, expires_at FROM review_claims "
        "WHERE project_id = ? AND sequence = ? AND expires_at > ?",
        [project_id, seq, _iso(now or _now())],
    ).fetchall()
    return {r[0]: Claim(r[0], r[1], r[2]) for r in rows}


def claim_regions(
    db: sqlite_utils.Database,
    project_id: int,
    *,
    reviewer: str,
    kind: str,
    count: int,
    sequence: str | None = None,
    ttl_s: float = CLAIM_TTL_S,
    now: datetime | None = None,
) -> list[str]:
    """Claim for ``reviewer`` the first ``count`` regions of the saved ``kind`` queue that have no mark on
    their current content and no unexpired claim of another reviewer; returns every region the reviewer
    holds on that queue afterwards, in queue order (earlier claims are renewed).

    One write transaction: two reviewers claiming at once get disjoint batches.

    Raises:
        Conflict: no queue of that kind was ranked yet for the sequence.
    """
    if not 1 <= count <= MAX_CLAIM:
        raise ValueError(f"count must lie in [1, {MAX_CLAIM}], got {count}")
    t = now or _now()
    expires = _iso(t + timedelta(seconds=ttl_s))
    with transaction(db):
        seq = crud.sequence_name(db, project_id, sequence)
        row = db.execute(
            "SELECT regions_json FROM review_queues WHERE project_id = ? AND sequence = ? AND kind = ?",
            [project_id, seq, kind],
        ).fetchone()
        if row is None:
            raise Conflict(
                f"No {kind} review queue is ranked yet for sequence {seq!r}: open the 3D viewer and press "
                "Next region (N) once"
            )
        queue = [(str(r), str(s)) for r, s in json.loads(row[0])]
        marks = crud.list_review_marks(db, project_id, seq)
        claims = active_claims(db, project_id, seq, now=t)
        mine = [r for r, _ in queue if (c := claims.get(r)) is not None and c.reviewer == reviewer]
        free = [
            r for r, sig in queue if r not in claims and ((m := marks.get(r)) is None or m.signature != sig)
        ]
        taken = mine + free[: max(0, count - len(mine))]
        db.execute(
            "DELETE FROM review_claims WHERE project_id = ? AND sequence = ? AND expires_at <= ?",
            [project_id, seq, _iso(t)],
        )
        for region in taken:
            db.execute(
                "INSERT INTO review_claims (project_id, sequence, region, reviewer, claimed_at, expires_at) "
                "VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT(project_id, sequence, region) DO UPDATE SET "
                "expires_at = excluded.expires_at",
                [project_id, seq, region, reviewer, _iso(t), expires],
            )
    order = {r: i for i, (r, _) in enumerate(queue)}
    return sorted(taken, key=order.__getitem__)


def release_claims(
    db: sqlite_utils.Database, project_id: int, *, reviewer: str, sequence: str | None = None
) -> int:
    """Release every claim of ``reviewer`` on the sequence (None: the first); returns how many."""
    seq = crud.sequence_name(db, project_id, sequence)
    with transaction(db):
        cursor = db.execute(
            "DELETE FROM review_claims WHERE project_id = ? AND sequence = ? AND reviewer = ?",
            [project_id, seq, reviewer],
        )
    return int(cursor.rowcount)


def reviewer_progress(
    db: sqlite_utils.Database, project_id: int, sequence: str | None = None
) -> list[ReviewerProgress]:
    """Per named reviewer of the sequence (None: the first): marks, active corrections and current claims,
    by name."""
    seq = crud.sequence_name(db, project_id, sequence)
    prefix = crud.review_key(db, project_id, seq, "")
    counts: dict[str, dict[str, int]] = {}

    def add(name: str, field: str, n: int) -> None:
        counts.setdefault(name, {"accepted": 0, "skipped": 0, "corrections": 0, "claimed": 0})[field] += n

    for name, state, n in db.execute(
        "SELECT reviewer, state, COUNT(*) FROM review_marks WHERE project_id = ? AND reviewer IS NOT NULL "
        "AND substr(region, 1, ?) = ? GROUP BY reviewer, state",
        [project_id, len(prefix), prefix],
    ).fetchall():
        add(name, str(state), int(n))
    for name, n in db.execute(
        "SELECT reviewer, COUNT(*) FROM corrections WHERE project_id = ? AND sequence = ? AND active = 1 "
        "AND reviewer IS NOT NULL GROUP BY reviewer",
        [project_id, seq],
    ).fetchall():
        add(name, "corrections", int(n))
    for claim in active_claims(db, project_id, seq).values():
        add(claim.reviewer, "claimed", 1)
    return [ReviewerProgress(name, **c) for name, c in sorted(counts.items())]


__all__ = [
    "CLAIM_TTL_S",
    "MAX_CLAIM",
    "REVIEWER_MAX",
    "Claim",
    "ReviewerProgress",
    "active_claims",
    "claim_regions",
    "release_claims",
    "reviewer_progress",
]
