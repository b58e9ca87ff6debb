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
from collections.abc import Sequence
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

    def merge(self, other: MosCounts) -> None:
        """Add ``other``'s counts (of other scans) to these."""
        self.tp += other.tp
        self.fp += other.fp
        self.fn += other.fn

    @property
    def iou(self) -> float:
        """Moving IoU, NaN when no point is moving in either."""
        den = self.tp + self.fp + self.fn
        return self.tp / den if den else math.nan


def _dense_codes(ids: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], int]:
    """``(codes, values, bits)``: ``ids`` (N,) (.label values, ``< 2^32``) renumbered densely in their
    order: ``codes`` (N,) below ``2^bits``, ``values[code]`` the id back.

    A .label value's halves (instance ``h``, raw class id ``l``) each take few distinct values in a scan, so
    each is ranked through a 65,536-entry table (no sort): ``code = rank(h) · 2^b + rank(l)`` with ``b`` the
    bits of the number of distinct ``l``, which keeps the ids' order. Where those codes would span far
    more values than there are ids, the ids are ranked by a sort (the same order, denser codes).
    """
    if ids.size == 0:
        return ids, np.zeros(1, np.int64), 1
    ranked = []
    for half in (ids >> 16, ids & 0xFFFF):
        seen = np.bincount(half, minlength=1 << 16) > 0
        ranked.append((np.cumsum(seen)[half] - 1, np.flatnonzero(seen)))
    (r_hi, v_hi), (r_lo, v_lo) = ranked
    b_lo = max(int(v_lo.size - 1).bit_length(), 1)
    if v_hi.size << b_lo > 4 * ids.size:
        # Ids spread over many instances and raw ids at once (a .label file of unusual values): the
        # table of every combination would outgrow the ids, so they are ranked by a sort instead.
        values, codes = np.unique(ids, return_inverse=True)
        return codes.reshape(-1).astype(np.int64), values, max(int(values.size - 1).bit_length(), 1)
    bits = max(int(v_hi.size - 1).bit_length(), 1) + b_lo
    values = np.zeros((v_hi.size, 1 << b_lo), np.int64)
    values[:, : v_lo.size] = (v_hi[:, None] << 16) | v_lo[None, :]
    return (r_hi << b_lo) | r_lo, values.reshape(-1), bits


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
        gc, gs, pc, ps = (
            np.asarray(x, np.int64).reshape(-1) for x in (gt_class, gt_segment, pred_class, pred_segment)
        )
        if not gc.shape == gs.shape == pc.shape == ps.shape:
            raise ValueError("gt and pred classes and segments must have one value per point each")
        keep = gc != UNLABELED
        gc, gs, pc, ps = gc[keep], gs[keep], pc[keep], ps[keep]
        if gs.size and (min(int(gs.min()), int(ps.min())) < 0 or max(int(gs.max()), int(ps.max())) >> 32):
            raise ValueError("segment ids must be .label values, 0 <= id < 2^32")
        # One sort per kind of key instead of several per class: a segment is (class, id) in one int64,
        # a (gt, pred) pair of one class is (class, gt code, pred code), the codes being the ids renumbered
        # densely in their order (:func:`_dense_codes`), so the pairs come out of one 1-D sort in the
        # (gt id, pred id) order of a per-class unique.
        g_keys, g_size = np.unique((gc << 32) | gs, return_counts=True)
        labeled = pc != UNLABELED
        p_keys, p_size = np.unique((pc[labeled] << 32) | ps[labeled], return_counts=True)
        same = gc == pc
        codes, values, bits = _dense_codes(np.concatenate([gs[same], ps[same]]))
        n_same = int(same.sum())
        pair_keys, inter = np.unique(
            (gc[same] << (2 * bits)) | (codes[:n_same] << bits) | codes[n_same:], return_counts=True
        )
        mask = (1 << bits) - 1
        pair_class = pair_keys >> (2 * bits)
        gi = np.searchsorted(g_keys, (pair_class << 32) | values[(pair_keys >> bits) & mask])
        pi = np.searchsorted(p_keys, (pair_class << 32) | values[pair_keys & mask])
        iou = inter / (g_size[gi] + p_size[pi] - inter)
        hit = iou > MATCH_IOU
        g_matched = np.zeros(g_keys.size, bool)
        p_matched = np.zeros(p_keys.size, bool)
        g_matched[gi[hit]] = True
        p_matched[pi[hit]] = True
        c = self.num_classes
        self.tp += np.bincount(pair_class[hit], minlength=c)
        for k in np.unique(pair_class[hit]):
            # One class's matched IoUs summed as numpy sums them (pairwise), in (gt, pred) order.
            self.iou_sum[k] += float(iou[hit & (pair_class == k)].sum())
        self.fn += np.bincount(g_keys[~g_matched & (g_size >= self.min_points)] >> 32, minlength=c)
        self.fp += np.bincount(p_keys[~p_matched & (p_size >= self.min_points)] >> 32, minlength=c)

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


@dataclass
class AssociationCounts:
    """The point counts S_assoc needs (module docstring), summed scan by scan: per ground-truth track its
    size ``|l|``, per predicted track ``|f|``, per pair ``TPA = |f ∩ l|``. Memory grows with the number of
    tracks and pairs, not of points, so a sequence of any length fits.

    Attributes:
        gt: (L,) int64 ground-truth track ids, sorted; ``gt_size`` (L,) their points.
        pred: (F,) int64 predicted track ids, sorted; ``pred_size`` (F,) their points.
        pairs: (P,) int64 ``l · 2^32 + f`` of each pair sharing points, sorted; ``tpa`` (P,) the points.
    """

    gt: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    gt_size: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    pred: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    pred_size: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    pairs: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    tpa: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    @classmethod
    def of(cls, gt_track: npt.ArrayLike, pred_track: npt.ArrayLike) -> AssociationCounts:
        """The counts of some points (one scan, or all of a sequence).

        Args:
            gt_track: (N,) int ground-truth track id per point, 0 = not a thing (stuff, unlabeled); ids
                below 2^31.
            pred_track: (N,) int predicted track id, 0 = none; ids below 2^32.
        """
        g = np.asarray(gt_track).reshape(-1).astype(np.int64)
        p = np.asarray(pred_track).reshape(-1).astype(np.int64)
        if g.shape != p.shape:
            raise ValueError(f"gt has {g.shape[0]} points but pred has {p.shape[0]}")
        if g.size and (int(min(g.min(), p.min())) < 0 or int(g.max()) >> 31 or int(p.max()) >> 32):
            raise ValueError("track ids must be 0 <= gt < 2^31 and 0 <= pred < 2^32")
        both = (g > 0) & (p > 0)
        return cls(
            *np.unique(g[g > 0], return_counts=True),
            *np.unique(p[p > 0], return_counts=True),
            *np.unique((g[both] << 32) | p[both], return_counts=True),
        )

    @classmethod
    def summed(cls, parts: Sequence[AssociationCounts]) -> AssociationCounts:
        """The counts of all ``parts`` (of disjoint points) together."""
        return cls(
            *_summed([(x.gt, x.gt_size) for x in parts]),
            *_summed([(x.pred, x.pred_size) for x in parts]),
            *_summed([(x.pairs, x.tpa) for x in parts]),
        )

    @property
    def entries(self) -> int:
        """Table rows held (the memory these counts take, in units of two int64)."""
        return int(self.gt.size + self.pred.size + self.pairs.size)

    def score(self, min_points: int = 0) -> float:
        """S_assoc in [0, 1] over the ground-truth tracks of at least ``min_points`` points; NaN without
        any."""
        keep = self.gt_size >= min_points
        if not keep.any():
            return math.nan
        gi = np.searchsorted(self.gt, self.pairs >> 32)
        pi = np.searchsorted(self.pred, self.pairs & 0xFFFFFFFF)
        tpa = self.tpa
        # TPA + FPA + FNA = |f| + |l| - TPA.
        iou = tpa / (self.pred_size[pi] + self.gt_size[gi] - tpa)
        per_gt = np.bincount(gi, weights=tpa * iou, minlength=self.gt.size) / self.gt_size
        return float(per_gt[keep].mean())


def _summed(
    tables: Sequence[tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]],
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Sorted key → count tables as one: the union of the keys (sorted), counts of equal keys summed."""
    if not tables:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    keys, at = np.unique(np.concatenate([k for k, _ in tables]), return_inverse=True)
    counts = np.zeros(keys.size, np.int64)
    np.add.at(counts, at, np.concatenate([c for _, c in tables]))
    return keys, counts


def association_score(gt_track: npt.ArrayLike, pred_track: npt.ArrayLike, *, min_points: int = 0) -> float:
    """LSTQ's S_assoc (module docstring) of one sequence's points, all scans concatenated
    (:meth:`AssociationCounts.of`'s arguments); NaN without ground-truth tracks."""
    return AssociationCounts.of(gt_track, pred_track).score(min_points)


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
