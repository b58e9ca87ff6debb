"""Object metrics: panoptic quality, moving-object IoU and the association score of 4D tracks.

Definitions (docs/METHOD.md D.6), each on points whose ground truth is labeled:

- **Panoptic quality** as PRBonn/semantic-kitti-api ``evaluate_panoptic.py`` computes it. Per scan and per
  class c, a *segment* is the set of points of class c sharing one segment id (the whole ``.label`` value,
  so a stuff class, instance 0, is one segment per scan). A predicted and a ground-truth segment of c match
  when their IoU exceeds 0.5 (so a match is unique). Over all scans, per class:
  ``TP`` = matches, ``Σ IoU`` over them, ``FP`` = unmatched predicted segments of at least ``min_points``
  points, ``FN`` = unmatched ground-truth segments of at least ``min_points``;
  ``SQ = Σ IoU / TP``, ``RQ = TP / (TP + FP/2 + FN/2)``, ``PQ = SQ · RQ`` (0 where the denominators are 0).
  Averages are over every class, absent ones counting 0, as the official script prints them; things and
  stuff average their classes alone. Points predicted unlabeled belong to no predicted segment.
- **Moving-object IoU** as ``evaluate_mos.py``: each point is unlabeled (0), static (1) or moving (2);
  ground-truth-unlabeled points are ignored; ``IoU = TP / (TP + FP + FN)`` of the moving state, where
  a moving point predicted static or unlabeled is a false negative.
- **Association score** S_assoc of LSTQ (Aygün et al., 4D Panoptic LiDAR Segmentation, CVPR 2021): over a
  whole sequence, with ground-truth tracks ``l`` (thing points of one instance id) and predicted tracks
  ``f`` (points of one predicted instance id > 0),
  ``S_assoc = 1/|L| Σ_l 1/|l| Σ_{f: f∩l≠∅} TPA(f,l) · TPA(f,l) / (TPA + FPA + FNA)``, with
  ``TPA = |f ∩ l|``, ``FPA = |f| - TPA``, ``FNA = |l| - TPA``. A track split in two or merged with another
  loses; one id per object over the sequence scores 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.types import UNLABELED

MATCH_IOU = 0.5
"""A predicted and a ground-truth segment match above this IoU (evaluate_panoptic.py)."""

MIN_SEGMENT_POINTS = 50
"""Unmatched segments smaller than this are neither FP nor FN (``evaluate_panoptic.py --min_inst_points``
default)."""

MOS_UNLABELED, MOS_STATIC, MOS_MOVING = 0, 1, 2
"""The three states of ``evaluate_mos.py`` (semantic-kitti-mos.yaml's learning map)."""

SEMANTICKITTI_STATIC_IDS = frozenset(
    (9, 10, 11, 13, 15, 16, 18, 20, 30, 31, 32, 40, 44, 48, 49, 50, 51, 52, 60, 70, 71, 72, 80, 81, 99)
)
"""Raw ids semantic-kitti-mos.yaml maps to static; 251-259 are moving; every other id is unlabeled."""


def mos_states(raw_ids: npt.ArrayLike) -> npt.NDArray[np.int8]:
    """(N,) int8 state of raw SemanticKITTI ids (``.label`` low 16 bits): 2 for 251..259, 1 for
    :data:`SEMANTICKITTI_STATIC_IDS`, else 0, as semantic-kitti-mos.yaml maps them."""
    raw = np.asarray(raw_ids).reshape(-1).astype(np.int64) & 0xFFFF
    lut = np.zeros(0x10000, np.int8)
    lut[list(SEMANTICKITTI_STATIC_IDS)] = MOS_STATIC
    lut[251:260] = MOS_MOVING
    out: npt.NDArray[np.int8] = lut[raw]
    return out


@dataclass
class MosCounts:
    """Moving-object counts summed over scans (``evaluate_mos.py``'s confusion entries)."""

    tp: int = 0
    fp: int = 0
    fn: int = 0

    def add(self, gt_state: npt.ArrayLike, pred_state: npt.ArrayLike) -> None:
        """Count one scan: (N,) states 0/1/2 each. ``fp`` = predicted moving on static ground truth,
        ``fn`` = ground-truth moving predicted static or unlabeled; ground truth 0 is ignored."""
        g = np.asarray(gt_state).reshape(-1)
        p = np.asarray(pred_state).reshape(-1)
        if g.shape != p.shape:
            raise ValueError(f"gt has {g.shape[0]} points but pred has {p.shape[0]}")
        self.tp += int(np.count_nonzero((g == MOS_MOVING) & (p == MOS_MOVING)))
        self.fp += int(np.count_nonzero((g == MOS_STATIC) & (p == MOS_MOVING)))
        self.fn += int(np.count_nonzero((g == MOS_MOVING) & (p != MOS_MOVING)))

    @property
    def iou(self) -> float:
        """Moving IoU, NaN when no point is moving in either."""
        den = self.tp + self.fp + self.fn
        return self.tp / den if den else math.nan


@dataclass
class PanopticCounts:
    """Per-class panoptic counts summed over scans (see the module docstring).

    Attributes:
        tp, fp, fn: (C,) int64 matched, unmatched predicted, unmatched ground-truth segments.
        iou_sum: (C,) float64 sum of the matched segments' IoU.
    """

    num_classes: int
    min_points: int = MIN_SEGMENT_POINTS
    tp: npt.NDArray[np.int64] = field(init=False)
    fp: npt.NDArray[np.int64] = field(init=False)
    fn: npt.NDArray[np.int64] = field(init=False)
    iou_sum: npt.NDArray[np.float64] = field(init=False)

    def __post_init__(self) -> None:
        c = self.num_classes
        self.tp, self.fp, self.fn = (np.zeros(c, np.int64) for _ in range(3))
        self.iou_sum = np.zeros(c, np.float64)

    def add(
        self,
        gt_class: npt.ArrayLike,
        gt_segment: npt.ArrayLike,
        pred_class: npt.ArrayLike,
        pred_segment: npt.ArrayLike,
    ) -> None:
        """Count one scan.

        Args:
            gt_class: (N,) int class index, ``UNLABELED`` (-1) = ignored point.
            gt_segment: (N,) int64 segment id (the raw ``.label`` value: equal ids of one class are one
                segment).
            pred_class: (N,) int class index, ``UNLABELED`` = in no segment.
            pred_segment: (N,) int64 predicted segment id.
        """
        gc = np.asarray(gt_class).reshape(-1).astype(np.int64)
        gs = np.asarray(gt_segment).reshape(-1).astype(np.int64)
        pc = np.asarray(pred_class).reshape(-1).astype(np.int64)
        ps = np.asarray(pred_segment).reshape(-1).astype(np.int64)
        if not gc.shape == gs.shape == pc.shape == ps.shape:
            raise ValueError("gt and pred classes and segments must have one value per point each")
        keep = gc != UNLABELED
        gc, gs, pc, ps = gc[keep], gs[keep], pc[keep], ps[keep]
        for c in np.union1d(gc, pc[pc != UNLABELED]):
            self._add_class(
                int(c), gs[gc == c], ps[pc == c], gs[(gc == c) & (pc == c)], ps[(gc == c) & (pc == c)]
            )

    def _add_class(
        self,
        c: int,
        gt_ids: npt.NDArray[np.int64],
        pred_ids: npt.NDArray[np.int64],
        both_gt: npt.NDArray[np.int64],
        both_pred: npt.NDArray[np.int64],
    ) -> None:
        g_ids, g_size = np.unique(gt_ids, return_counts=True)
        p_ids, p_size = np.unique(pred_ids, return_counts=True)
        pairs, inter = np.unique(np.stack([both_gt, both_pred]), axis=1, return_counts=True)
        gi = np.searchsorted(g_ids, pairs[0])
        pi = np.searchsorted(p_ids, pairs[1])
        iou = inter / (g_size[gi] + p_size[pi] - inter)
        hit = iou > MATCH_IOU
        g_matched = np.zeros(g_ids.size, bool)
        p_matched = np.zeros(p_ids.size, bool)
        g_matched[gi[hit]] = True
        p_matched[pi[hit]] = True
        self.tp[c] += int(hit.sum())
        self.iou_sum[c] += float(iou[hit].sum())
        self.fn[c] += int(np.count_nonzero(~g_matched & (g_size >= self.min_points)))
        self.fp[c] += int(np.count_nonzero(~p_matched & (p_size >= self.min_points)))

    def merge(self, other: PanopticCounts) -> None:
        """Add ``other``'s counts (of other scans) to these."""
        self.tp += other.tp
        self.fp += other.fp
        self.fn += other.fn
        self.iou_sum += other.iou_sum

    def per_class(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(PQ, SQ, RQ), each (C,) float64, 0 where a class has no segment."""
        tp = self.tp.astype(np.float64)
        sq = self.iou_sum / np.maximum(tp, 1e-15)
        rq = tp / np.maximum(tp + 0.5 * self.fp + 0.5 * self.fn, 1e-15)
        return sq * rq, sq, rq

    def scores(self, things: npt.ArrayLike) -> dict[str, float]:
        """``PQ``, ``SQ``, ``RQ`` over all classes and ``PQ_things`` ... ``RQ_stuff`` over each part
        (NaN for a part without classes). ``things``: (C,) bool."""
        th = np.asarray(things, dtype=bool).reshape(-1)
        if th.shape != (self.num_classes,):
            raise ValueError(f"things must have {self.num_classes} entries, got {th.shape[0]}")
        pq, sq, rq = self.per_class()
        out: dict[str, float] = {}
        for part, sel in (("", np.ones_like(th)), ("_things", th), ("_stuff", ~th)):
            for name, v in (("PQ", pq), ("SQ", sq), ("RQ", rq)):
                out[name + part] = float(v[sel].mean()) if sel.any() else math.nan
        return out


def association_score(gt_track: npt.ArrayLike, pred_track: npt.ArrayLike, *, min_points: int = 0) -> float:
    """LSTQ's S_assoc (module docstring) of one sequence's points, all scans concatenated.

    Args:
        gt_track: (N,) int64 ground-truth track id per point, 0 = not a thing (stuff, unlabeled): a
            track is every point with one id, over all scans.
        pred_track: (N,) int64 predicted track id, 0 = none.
        min_points: ground-truth tracks with fewer points are left out.

    Returns:
        S_assoc in [0, 1]; NaN without ground-truth tracks.
    """
    g = np.asarray(gt_track).reshape(-1).astype(np.int64)
    p = np.asarray(pred_track).reshape(-1).astype(np.int64)
    if g.shape != p.shape:
        raise ValueError(f"gt has {g.shape[0]} points but pred has {p.shape[0]}")
    gt_ids, gt_size = np.unique(g[g > 0], return_counts=True)
    pred_ids, pred_size = np.unique(p[p > 0], return_counts=True)
    both = (g > 0) & (p > 0)
    pairs, tpa = np.unique(np.stack([g[both], p[both]]), axis=1, return_counts=True)
    keep = gt_size >= min_points
    if not keep.any():
        return math.nan
    gi = np.searchsorted(gt_ids, pairs[0])
    pi = np.searchsorted(pred_ids, pairs[1])
    # TPA + FPA + FNA = |f| + |l| - TPA.
    iou = tpa / (pred_size[pi] + gt_size[gi] - tpa)
    per_gt = np.bincount(gi, weights=tpa * iou, minlength=gt_ids.size) / gt_size
    return float(per_gt[keep].mean())


def scores_dict(values: dict[str, float]) -> dict[str, Any]:
    """JSON-ready copy: NaN becomes None."""
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in values.items()}


__all__ = [
    "MATCH_IOU",
    "MIN_SEGMENT_POINTS",
    "MOS_MOVING",
    "MOS_STATIC",
    "MOS_UNLABELED",
    "SEMANTICKITTI_STATIC_IDS",
    "MosCounts",
    "PanopticCounts",
    "association_score",
    "mos_states",
    "scores_dict",
]
