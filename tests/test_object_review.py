"""The object review queue (leap_core.object_review) and the vote evidence and track life that
``tracks.npz`` keeps for it (leap_core.tracking.VoteEvidence, leap_core.pipeline.tracks_file.TrackLife),
on a hand-built five-scan sequence: a car whose vote is close to truck, a 2-scan person, and a car with
a gap."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from leap_core.errors import ConfigError
from leap_core.io_utils import atomic_save_npz, read_npz
from leap_core.object_review import (
    BROKEN,
    CLOSE_VOTE,
    SHORT,
    ObjectQueueConfig,
    object_queue,
    reason_codes,
    reason_text,
)
from leap_core.pipeline import tracks_file
from leap_core.pipeline.tracks_file import SequenceTracks, track_life
from leap_core.tracking import TrackingConfig, track_ids, track_table, vote_evidence

CAR, TRUCK, PERSON, ROAD = 0, 1, 2, 3
THINGS = np.array([True, True, True, False])
NAMES = ["car", "truck", "person", "road"]


def _votes(*pairs: tuple[int, float]) -> list[float]:
    v = [0.0] * 4
    for c, n in pairs:
        v[c] += n
    return v


def _sequence() -> SequenceTracks:
    """Five scans 0.1 s apart. Segment A (x=0): car 3 votes / truck 2 per scan, every scan. Segment B
    (x=20): a person in scans 0-1. Segment C (x=40): a car in scans 0, 1, 3, 4 (missed in 2; the tracker
    keeps it over ``max_missed`` 3, so it is one track with a gap). Each segment holds two points."""
    a = ([0.0, 0, 0], _votes((CAR, 3), (TRUCK, 2)))
    b = ([20.0, 0, 0], _votes((PERSON, 2)))
    c = ([40.0, 0, 0], _votes((CAR, 2)))
    scans = [[a, b, c], [a, b, c], [a], [a, c], [a, c]]
    centroids = [np.array([s[0] for s in scan]) for scan in scans]
    votes = [np.array([s[1] for s in scan]) for scan in scans]
    boxes = [np.array([[x[0][0] - 1, -1, x[0][0] + 1, 1] for x in scan]) for scan in scans]
    times = np.arange(5) * 0.1
    cfg = TrackingConfig()
    ids = track_ids(centroids, times, cfg)
    table = track_table(ids, centroids, votes, boxes, times, cfg)
    rows = [np.arange(2 * len(t), dtype=np.int32) for t in ids]
    track = [np.repeat(t, 2).astype(np.int32) for t in ids]
    offsets = np.concatenate([[0], np.cumsum([r.size for r in rows])]).astype(np.int64)
    return SequenceTracks(
        tuple(f"{i:06d}" for i in range(5)), offsets, np.concatenate(rows), np.concatenate(track), table
    )


def test_vote_evidence_keeps_the_winner_and_the_runner_up() -> None:
    ev = vote_evidence([[3, 2, 0], [0, 0, 4], [1, 1, 1], [0, 0, 0]])
    assert ev.share == pytest.approx([0.6, 1.0, 1 / 3, 0.0])
    assert ev.runner_up.tolist() == [1, -1, 1, -1]  # a tie: the lower index after the winner (0)
    assert ev.runner_share == pytest.approx([0.4, 0.0, 1 / 3, 0.0])


def test_tracks_file_keeps_vote_share_runner_up_and_gaps(tmp_path: Path) -> None:
    seq = _sequence()
    assert seq.table.label.tolist() == [CAR, PERSON, CAR]
    seq.save(tmp_path / "tracks.npz")
    back = SequenceTracks.load(tmp_path / "tracks.npz")
    ev, life = back.table.vote_evidence(), back.track_life()
    assert ev.share == pytest.approx([0.6, 1.0, 1.0])
    assert ev.runner_up.tolist() == [TRUCK, -1, -1]
    assert ev.runner_share == pytest.approx([0.4, 0.0, 0.0])
    assert life.first.tolist() == [0, 0, 0]
    assert life.last.tolist() == [4, 1, 4]
    assert life.gaps.tolist() == [0, 0, 1]
    assert life.present.tolist() == [5, 2, 4]


def test_an_older_tracks_file_loads_with_the_documented_defaults(tmp_path: Path) -> None:
    path = tmp_path / "tracks.npz"
    _sequence().save(path)
    old = {
        k: v
        for k, v in read_npz(path).items()
        if k not in ("share", "runner_up", "runner_share", "first", "last", "gaps", "voted")
    }
    atomic_save_npz(path, **old)
    back = SequenceTracks.load(path)
    ev, life = back.table.vote_evidence(), back.track_life()
    assert ev.share.tolist() == [1.0] * 3 and ev.runner_up.tolist() == [-1] * 3
    assert ev.runner_share.tolist() == [0.0] * 3
    assert life.gaps.tolist() == [0, 0, 1] and life.present.tolist() == [5, 2, 4]  # counted from the points


def test_track_life_of_an_empty_track_and_an_empty_file() -> None:
    life = track_life([0, 2, 2, 3], [2, 2, 2], 3)
    assert life.first.tolist() == [-1, 0, -1] and life.last.tolist() == [-1, 2, -1]
    assert life.gaps.tolist() == [0, 1, 0] and life.present.tolist() == [0, 2, 0]
    assert track_life([0], [], 0).gaps.size == 0


def test_track_life_read_a_few_points_at_a_time_is_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(5)
    offsets = np.concatenate([[0], np.cumsum(rng.integers(0, 7, 40))])
    track = rng.integers(1, 9, int(offsets[-1]))
    whole = track_life(offsets, track, 9)
    monkeypatch.setattr(tracks_file, "_LIFE_BLOCK", 5)  # blocks of about one scan, some of several
    blocks = track_life(offsets, track, 9)
    for name in ("first", "last", "gaps", "present"):
        assert getattr(blocks, name).tolist() == getattr(whole, name).tolist(), name


def test_the_queue_orders_close_votes_then_broken_then_short() -> None:
    ids, reasons = _sequence().review_queue(THINGS, ObjectQueueConfig())
    assert ids.tolist() == [1, 3, 2]
    assert reasons.tolist() == [CLOSE_VOTE, BROKEN, SHORT]
    assert [reason_codes(int(r)) for r in reasons] == [["close_vote"], ["broken"], ["short"]]


def test_queue_rule_thresholds_exclusions_and_ties() -> None:
    def queue(**kw: object) -> tuple[list[int], list[int]]:
        arrays = {
            "label": [CAR, CAR, ROAD, CAR, PERSON, TRUCK],
            "share": [0.5, 0.55, 0.5, 0.5, 1.0, 0.52],
            "runner_up": [TRUCK, TRUCK, CAR, TRUCK, -1, CAR],
            "runner_share": [0.45, 0.35, 0.5, 0.5, 0.0, 0.48],
            "present": [9, 9, 9, 0, 9, 1],
            "gaps": [0, 0, 5, 0, 0, 0],
        }
        arrays.update(kw)  # type: ignore[arg-type]
        ids, reasons = object_queue(things=THINGS, cfg=ObjectQueueConfig(), **arrays)  # type: ignore[arg-type]
        return ids.tolist(), reasons.tolist()

    # 3 is stuff (road), 4 has no points, 5 is unanimous: none queued. 6 (margin 0.04, short) comes before
    # 1 (margin 0.05); 2 (margin 0.2) is not close.
    assert queue() == ([6, 1], [CLOSE_VOTE | SHORT, CLOSE_VOTE])
    tied = queue(share=[0.5] * 5 + [0.52], runner_share=[0.5, 0.5, 0.5, 0.5, 0.0, 0.48])
    assert tied[0] == [1, 2, 6]  # equal margins (0): by id
    assert queue(gaps=[0, 2, 0, 0, 3, 0])[0] == [6, 1, 5, 2]  # broken: most gaps first
    with pytest.raises(ValueError, match="one value per track"):
        queue(gaps=[0])


def test_queue_settings_are_bounded() -> None:
    with pytest.raises(ConfigError, match=r"max_margin: must be in \[0, 1\], got 2"):
        ObjectQueueConfig(max_margin=2)
    with pytest.raises(ConfigError, match="min_scans"):
        ObjectQueueConfig(min_scans=0)
    with pytest.raises(ConfigError, match="min_gaps"):
        ObjectQueueConfig(min_gaps=10**6)


def _text(reasons: int, present: int, gaps: int) -> str:
    return reason_text(reasons, "car", share=1, runner_name=None, runner_share=0, present=present, gaps=gaps)


def test_reason_text() -> None:
    assert (
        reason_text(CLOSE_VOTE, "car", share=0.48, runner_name="truck", runner_share=0.41, present=9, gaps=0)
        == "car 48 % vs truck 41 %"
    )
    assert _text(BROKEN | SHORT, present=2, gaps=3) == "3 gaps; seen in 2 scans"
    assert _text(BROKEN | SHORT, present=1, gaps=1) == "1 gap; seen in 1 scan"
