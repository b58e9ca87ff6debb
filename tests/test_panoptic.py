"""Object metrics on hand-computed cases: panoptic quality (evaluate_panoptic.py's definitions),
moving-object IoU (evaluate_mos.py's) and LSTQ's association score."""

from __future__ import annotations

import math

import numpy as np
import pytest

from leap_core.panoptic import MosCounts, PanopticCounts, association_score, mos_states

GRASS, SKY, PERSON, DOG = 0, 1, 2, 3


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """50 ignored points; grass and sky (stuff) each 40 right and 10 swapped; a dog called person; three
    persons (150, 50, 100 points) predicted as two segments of 200 (the first two merged) and 100."""
    rows: list[tuple[int, int, int, int]] = []  # (gt class, gt id, pred class, pred id) per run of points

    def run(n: int, gc: int, gi: int, pc: int, pi: int) -> None:
        rows.extend([(gc, gi, pc, pi)] * n)

    run(50, -1, 0, -1, 0)
    run(40, GRASS, 0, GRASS, 0)
    run(10, GRASS, 0, SKY, 0)
    run(40, SKY, 0, SKY, 0)
    run(10, SKY, 0, GRASS, 0)
    run(50, DOG, 22, PERSON, 35)
    run(150, PERSON, 33, PERSON, 8)
    run(50, PERSON, 42, PERSON, 8)
    run(100, PERSON, 11, PERSON, 95)
    a = np.array(rows, np.int64)
    return a[:, 0], a[:, 1], a[:, 2], a[:, 3]


def test_panoptic_quality_of_a_hand_computed_scene() -> None:
    counts = PanopticCounts(4, min_points=1)
    counts.add(*_scene())
    pq, sq, rq = counts.per_class()
    # grass / sky: one segment each, IoU 40 / 60; person: 200 vs 150 → 0.75, 100 vs 100 → 1, the
    # 50-point person unmatched (FN) and the dog's "person" segment unmatched (FP); dog: one FN.
    assert sq == pytest.approx([2 / 3, 2 / 3, 1.75 / 2, 0])
    assert rq == pytest.approx([1, 1, 2 / 3, 0])
    assert counts.tp.tolist() == [1, 1, 2, 0]
    assert counts.fp.tolist() == [0, 0, 1, 0] and counts.fn.tolist() == [0, 0, 1, 1]
    scores = counts.scores(np.array([False, False, True, True]))
    assert scores["PQ"] == pytest.approx((2 / 3 + 2 / 3 + 1.75 / 3 + 0) / 4)  # the official example's 0.479
    assert scores["SQ"] == pytest.approx(0.5520833333)
    assert scores["RQ"] == pytest.approx(2 / 3)
    assert scores["PQ_things"] == pytest.approx(1.75 / 3 / 2)
    assert scores["PQ_stuff"] == pytest.approx(2 / 3)
    assert pq[PERSON] == pytest.approx(1.75 / 3)


def test_small_unmatched_segments_are_neither_fp_nor_fn() -> None:
    counts = PanopticCounts(4, min_points=60)
    counts.add(*_scene())
    assert counts.fp.tolist() == [0, 0, 0, 0]  # the 50-point false person
    assert counts.fn.tolist() == [0, 0, 0, 0]  # the 50-point person and dog


def test_counts_add_up_over_scans() -> None:
    one, two = PanopticCounts(4, min_points=1), PanopticCounts(4, min_points=1)
    one.add(*_scene())
    for _ in range(2):
        two.add(*_scene())
    assert two.tp.tolist() == (2 * one.tp).tolist() and two.iou_sum == pytest.approx(2 * one.iou_sum)
    assert two.scores(np.ones(4, bool))["PQ"] == pytest.approx(one.scores(np.ones(4, bool))["PQ"])


def test_mos_iou_counts_unlabeled_moving_points_as_misses() -> None:
    gt = mos_states(np.array([0, 40, 40, 252, 254, 254, 254, 1, 300], np.uint32) | (7 << 16))
    assert gt.tolist() == [0, 1, 1, 2, 2, 2, 2, 0, 0]
    pred = np.array([2, 2, 1, 2, 2, 1, 0, 2, 2])
    counts = MosCounts()
    counts.add(gt, pred)
    # tp: two moving hits; fp: one static called moving (gt 0 ignored); fn: one static, one unlabeled.
    assert (counts.tp, counts.fp, counts.fn) == (2, 1, 2)
    assert counts.iou == pytest.approx(2 / 5)
    assert math.isnan(MosCounts().iou)


def test_association_score_of_a_split_and_a_bloated_track() -> None:
    # gt track 1 (10 points) predicted as tracks 5 (6 points) and 6 (4); gt track 2 (5 points) inside
    # predicted track 7, which also holds 5 stuff points (gt 0).
    gt = np.array([1] * 10 + [2] * 5 + [0] * 5)
    pred = np.array([5] * 6 + [6] * 4 + [7] * 10)
    expected_1 = (6 * 6 / 10 + 4 * 4 / 10) / 10
    expected_2 = (5 * 5 / 10) / 5
    assert association_score(gt, pred) == pytest.approx((expected_1 + expected_2) / 2)
    assert association_score(gt, np.where(gt > 0, gt + 100, 0)) == pytest.approx(1.0)
    assert association_score(gt, pred, min_points=6) == pytest.approx(expected_1)
    assert math.isnan(association_score(np.zeros(3), np.ones(3)))
