"""Object metrics on hand-computed cases: panoptic quality (evaluate_panoptic.py's definitions),
moving-object IoU (evaluate_mos.py's) and LSTQ's association score."""

from __future__ import annotations

import math

import numpy as np
import pytest

from leap_core.panoptic import AssociationCounts, MosCounts, PanopticCounts, association_score, mos_states

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


def _reference_counts(
    gc: np.ndarray, gs: np.ndarray, pc: np.ndarray, ps: np.ndarray, c: int, mp: int
) -> tuple:
    """evaluate_panoptic.py's counting written out segment by segment (dicts, one class at a time)."""
    tp, fp, fn, iou_sum = [0] * c, [0] * c, [0] * c, [0.0] * c
    for k in range(c):
        gt_seg: dict[int, set[int]] = {}
        pred_seg: dict[int, set[int]] = {}
        for i in range(gc.size):
            if gc[i] == -1:
                continue
            if gc[i] == k:
                gt_seg.setdefault(int(gs[i]), set()).add(i)
            if pc[i] == k:
                pred_seg.setdefault(int(ps[i]), set()).add(i)
        matched_g, matched_p = set(), set()
        for g, gp in gt_seg.items():
            for p, pp in pred_seg.items():
                iou = len(gp & pp) / len(gp | pp)
                if iou > 0.5:
                    tp[k] += 1
                    iou_sum[k] += iou
                    matched_g.add(g)
                    matched_p.add(p)
        fn[k] = sum(1 for g, gp in gt_seg.items() if g not in matched_g and len(gp) >= mp)
        fp[k] = sum(1 for p, pp in pred_seg.items() if p not in matched_p and len(pp) >= mp)
    return tp, fp, fn, iou_sum


def test_panoptic_counts_agree_with_a_segment_by_segment_reference() -> None:
    rng = np.random.default_rng(7)
    for _ in range(40):
        n, c = int(rng.integers(0, 400)), int(rng.integers(1, 5))
        gc = rng.integers(-1, c, n)
        # .label-like ids: an instance in the upper half, a raw class id (0, 300 or 600) in the lower
        gs = (rng.integers(0, 6, n) << 16) | rng.integers(0, 3, n) * 300
        pc = np.where(rng.random(n) < 0.8, gc, rng.integers(-1, c, n))
        ps = np.where(rng.random(n) < 0.8, gs, rng.integers(0, 9, n) << 16)
        if rng.random() < 0.2:  # ids anywhere in 32 bits: too spread for the halves' tables
            gs = rng.integers(0, 1 << 32, 40)[rng.integers(0, 40, n)]
            ps = np.where(rng.random(n) < 0.8, gs, rng.integers(0, 1 << 32, n))
        mp = int(rng.choice([1, 5, 30]))
        counts = PanopticCounts(c, min_points=mp)
        counts.add(gc, gs, pc, ps)
        tp, fp, fn, iou_sum = _reference_counts(gc, gs, pc, ps, c, mp)
        assert counts.tp.tolist() == tp and counts.fp.tolist() == fp and counts.fn.tolist() == fn
        assert counts.iou_sum == pytest.approx(iou_sum, abs=1e-12)


def test_association_counts_summed_scan_by_scan_equal_the_whole_sequence() -> None:
    rng = np.random.default_rng(3)
    scans = [(rng.integers(0, 8, 300) * (rng.random(300) < 0.7), rng.integers(0, 12, 300)) for _ in range(9)]
    whole = association_score(np.concatenate([g for g, _ in scans]), np.concatenate([p for _, p in scans]))
    parts = [AssociationCounts.of(g, p) for g, p in scans]
    summed = AssociationCounts.summed([AssociationCounts.summed(parts[:4]), *parts[4:]])
    assert summed.score() == whole
    assert summed.entries < sum(g.size for g, _ in scans)
    with pytest.raises(ValueError, match="track ids"):
        AssociationCounts.of(np.array([1 << 31]), np.array([1]))
