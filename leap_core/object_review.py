"""The object review queue: which tracks of a run a person should look at first (docs/METHOD.md B.6,
"Object review queue").

Pure functions on a run's per-track arrays (``tracks.npz``, :mod:`leap_core.pipeline.tracks_file`); the
viewer (:mod:`app.viewer.object_queue`) and the API (``GET /runs/{id}/objects``) read the file and call
:func:`object_queue`.

A track is queued for up to three reasons, each a bit of its reason mask:

- :data:`CLOSE_VOTE`: its class vote was close, ``share - runner_share < max_margin`` with a runner-up
  class (:class:`~leap_core.tracking.VoteEvidence`): the class may be the wrong one of two;
- :data:`BROKEN`: the scans between its first and last have ``gaps ≥ min_gaps`` scans without its points
  (:class:`~leap_core.pipeline.tracks_file.TrackLife`): it may be two objects, or one that lost its id;
- :data:`SHORT`: it has points in fewer than ``min_scans`` scans: a stray segment, or an object whose id
  was broken into pieces.

Tracks with no points in the file and tracks whose class is not a thing class are never queued.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from leap_core.bounds import check_bounds, within

CLOSE_VOTE = 1
"""Reason bit: the class vote's margin lies under ``max_margin``."""
BROKEN = 2
"""Reason bit: the track has ``min_gaps`` or more gaps."""
SHORT = 4
"""Reason bit: the track has points in fewer than ``min_scans`` scans."""
ReasonCode = Literal["close_vote", "broken", "short"]
REASON_CODES: dict[int, ReasonCode] = {CLOSE_VOTE: "close_vote", BROKEN: "broken", SHORT: "short"}
"""Each reason bit's name in the API, in priority order."""


@dataclass(frozen=True)
class ObjectQueueConfig:
    """Which tracks the object review queue holds (module docstring)."""

    max_margin: float = field(default=0.2, metadata=within(0, 1))
    """A vote whose winner leads the runner-up by less than this share of the votes is close (0.2: car
    55 % vs truck 40 % is queued, car 70 % vs truck 25 % is not)."""
    min_scans: int = field(default=3, metadata=within(1, 1000))
    """A track with points in fewer scans is short (the tracker's ``min_track_scans`` default: what it
    needs to call a track moving at all)."""
    min_gaps: int = field(default=1, metadata=within(1, 1000))
    """A track with at least this many scans without its points between its first and last is broken."""

    def __post_init__(self) -> None:
        check_bounds(self)


def object_queue(
    label: npt.ArrayLike,
    things: npt.ArrayLike,
    *,
    share: npt.ArrayLike,
    runner_up: npt.ArrayLike,
    runner_share: npt.ArrayLike,
    present: npt.ArrayLike,
    gaps: npt.ArrayLike,
    cfg: ObjectQueueConfig,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
    """The tracks to review in order, and why.

    Args:
        label: (K,) int the class of track id k + 1 (-1: none).
        things: (C,) bool which classes are things.
        share, runner_up, runner_share: (K,) the class vote's evidence (:class:`~leap_core.tracking.
            VoteEvidence`; ``runner_up`` -1 = none).
        present: (K,) int scans in which the track has points.
        gaps: (K,) int scans without its points between its first and last.
        cfg: the thresholds.

    Returns:
        ids (Q,) int64 track ids (1-based) and reasons (Q,) uint8 masks of :data:`CLOSE_VOTE`,
        :data:`BROKEN`, :data:`SHORT`.

    Rule: a track with ``present > 0`` whose class is a thing is queued when any reason holds (module
    docstring). Order: by the highest-priority reason it has (close vote, then broken, then short), then
    within it the most doubtful first (the smallest margin ``share - runner_share``; the most gaps; the
    fewest scans), then by id.
    """
    lab = np.asarray(label, np.int64).reshape(-1)
    thing = np.asarray(things, bool).reshape(-1)
    win = np.asarray(share, np.float64).reshape(-1)
    runner = np.asarray(runner_up, np.int64).reshape(-1)
    second = np.asarray(runner_share, np.float64).reshape(-1)
    seen = np.asarray(present, np.int64).reshape(-1)
    holes = np.asarray(gaps, np.int64).reshape(-1)
    k = lab.size
    if not all(a.size == k for a in (win, runner, second, seen, holes)):
        raise ValueError("object_queue: every per-track array needs one value per track")
    is_thing = np.zeros(k, bool)
    known = (lab >= 0) & (lab < thing.size)
    is_thing[known] = thing[lab[known]]
    eligible = is_thing & (seen > 0)
    margin = win - second
    close = eligible & (runner >= 0) & (margin < cfg.max_margin)
    broken = eligible & (holes >= cfg.min_gaps)
    short = eligible & (seen < cfg.min_scans)
    reasons = (close * CLOSE_VOTE + broken * BROKEN + short * SHORT).astype(np.uint8)
    rows = np.flatnonzero(reasons)
    tier = np.where(close, 0, np.where(broken, 1, 2))[rows]
    doubt = np.where(close, margin, np.where(broken, -holes, seen)).astype(np.float64)[rows]
    order = np.lexsort((rows, doubt, tier))
    return (rows[order] + 1).astype(np.int64), reasons[rows[order]]


def reason_codes(reasons: int) -> list[ReasonCode]:
    """The names of a reason mask's bits, in priority order (``["close_vote", "short"]``)."""
    return [name for bit, name in REASON_CODES.items() if reasons & bit]


def reason_text(
    reasons: int,
    class_name: str,
    *,
    share: float,
    runner_name: str | None,
    runner_share: float,
    present: int,
    gaps: int,
) -> str:
    """Why a track is queued, for a person: ``"car 48 % vs truck 41 %; seen in 2 scans; 3 gaps"``."""
    parts = []
    if reasons & CLOSE_VOTE:
        parts.append(f"{class_name} {share:.0%} vs {runner_name} {runner_share:.0%}".replace("%", " %"))
    if reasons & BROKEN:
        parts.append(f"{gaps} gap" + ("s" if gaps != 1 else ""))
    if reasons & SHORT:
        parts.append(f"seen in {present} scan" + ("s" if present != 1 else ""))
    return "; ".join(parts)


__all__ = [
    "BROKEN",
    "CLOSE_VOTE",
    "REASON_CODES",
    "SHORT",
    "ObjectQueueConfig",
    "ReasonCode",
    "object_queue",
    "reason_codes",
    "reason_text",
]
