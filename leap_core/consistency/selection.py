"""Reliable label selection for self-training the 3D Consistency Network (docs/METHOD.md stage C.1).

Each scan's points are projected onto the (smoothed) voxel grid and take their voxel's label and
confidence. Per class, only the most confident ``share`` of that class's points become training labels.
Ranking *within* each class, rather than over all points, keeps rare classes represented: a global
confidence threshold would keep mostly road and building.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import numpy.typing as npt

from leap_core.fusion import rows_in_sorted, union_sorted
from leap_core.types import UNLABELED


def per_class_quota(count: int, share: float) -> int:
    """Number of points kept out of ``count`` labeled points of one class.

    ``k = ceil(share · count)`` so every class with at least one labeled point keeps at least one.
    (``share · count`` is rounded to 9 decimals first, so 0.2 · 10 keeps exactly 2, not 3.)
    """
    if count <= 0:
        return 0
    return min(count, math.ceil(round(share * count, 9)))


def select_reliable(
    labels: npt.NDArray[np.integer],
    confidence: npt.NDArray[np.floating],
    num_classes: int,
    share: float,
    seed: int | None = None,
    support: npt.NDArray[np.floating] | None = None,
) -> npt.NDArray[np.bool_]:
    """Per class, mark the ``share`` most confident labeled points.

    For every class ``c`` with ``n_c`` points of label ``c``, keep the ``k_c = ceil(share · n_c)`` points
    with the highest confidence. Points labeled ``UNLABELED`` (-1) are never selected. Ties are broken
    deterministically: by point index (lower first) when ``seed`` is None, else by a random order drawn
    from ``seed``. Fused grids saturate (many voxels reach the same clipped confidence), and an index
    order would then pick points by scan order (e.g. the lowest beams) instead of spreading them out.

    ``support`` (optional, higher = better) ranks points of equal confidence before the tie order. The
    pipeline passes how many frames observed the point's voxel (:func:`view_counts`): among saturated
    voxels it prefers those many views agreed on over those one image decided, such as the track of a
    moving object seen once per position, whose label a single mistaken mask can flip. (The evidence
    margin does not tell them apart: the many points one mask paints into a voxel count as independent
    observations and saturate it alone.)

    Args:
        labels: (N,) int class index per point in ``[0, num_classes)`` or ``UNLABELED``.
        confidence: (N,) float confidence per point (e.g. its voxel's max class probability).
        num_classes: C, number of classes.
        share: fraction in (0, 1] of each class's points to keep.
        seed: seed of the tie-breaking order; None = point index order.
        support: (N,) secondary key, or None.

    Returns:
        (N,) bool mask of selected points; ``mask.sum() == Σ_c k_c``.

    Raises:
        ValueError: on mismatched shapes, a label outside ``[-1, C)`` or ``share`` outside (0, 1].
    """
    labels = np.asarray(labels)
    confidence = np.asarray(confidence)
    if labels.ndim != 1 or confidence.shape != labels.shape:
        raise ValueError(f"labels {labels.shape} and confidence {confidence.shape} must both be (N,)")
    if support is not None and np.shape(support) != labels.shape:
        raise ValueError(f"support {np.shape(support)} must have the shape of labels {labels.shape}")
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share must be in (0, 1], got {share}")
    selected = np.zeros(labels.shape[0], dtype=bool)
    if labels.size == 0:
        return selected
    lab = labels.astype(np.int64)
    if lab.min() < UNLABELED or lab.max() >= num_classes:
        raise ValueError(f"labels must lie in [-1, {num_classes}), got range [{lab.min()}, {lab.max()}]")
    # One stable sort orders points by (class, confidence descending, support descending, tie rank):
    # lexsort's last key is primary and the sort is stable, so remaining ties keep index order.
    conf = np.nan_to_num(confidence.astype(np.float64), nan=-np.inf)
    keys: list[npt.NDArray[np.generic]] = (
        [] if seed is None else [np.random.default_rng(seed).permutation(lab.shape[0])]
    )
    if support is not None:
        keys.append(-np.nan_to_num(np.asarray(support, np.float64), nan=-np.inf))
    order = np.lexsort((*keys, -conf, lab))
    sorted_lab = lab[order]
    counts = np.bincount(lab[lab >= 0], minlength=num_classes)
    starts = np.searchsorted(sorted_lab, np.arange(num_classes), side="left")
    for c in range(num_classes):
        k = per_class_quota(int(counts[c]), share)
        if k:
            selected[order[starts[c] : starts[c] + k]] = True
    return selected


VIEW_COUNT_BATCH = 1 << 22
""":func:`view_counts` folds frames into its running counts once this many per-frame keys are pending, so
it holds the counts (16 B per voxel) plus one batch, not every frame's keys."""


def view_counts(
    frame_keys: Iterable[npt.NDArray[np.int64]],
    batch: int = VIEW_COUNT_BATCH,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """In how many frames each voxel was observed: ``n_v = |{f : v ∈ K_f}|`` over per-frame key sets K_f.

    Args:
        frame_keys: per frame, the voxel keys of its observed (painted) points, repeats allowed.
        batch: per-frame unique keys gathered before they are folded into the counts (bounds memory; the
            result does not depend on it).

    Returns:
        Sorted unique keys (V,) and their frame counts (V,). Example: frames [5, 5, 7] and [7] give keys
        [5, 7] with counts [1, 2].
    """
    keys = np.zeros(0, np.int64)
    counts = np.zeros(0, np.int64)
    pending: list[npt.NDArray[np.int64]] = []
    n_pending = 0

    def fold() -> None:
        nonlocal keys, counts
        k, c = np.unique(np.concatenate(pending), return_counts=True)
        merged = union_sorted(keys, k)
        out = np.zeros(len(merged), np.int64)
        out[np.searchsorted(merged, keys)] = counts
        out[np.searchsorted(merged, k)] += c
        keys, counts = merged, out

    for fk in frame_keys:
        u = np.unique(np.asarray(fk, np.int64))
        pending.append(u)
        n_pending += len(u)
        if n_pending >= batch:
            fold()
            pending, n_pending = [], 0
    if pending:
        fold()
    return keys, counts


def lookup_counts(
    keys: npt.NDArray[np.int64], count_keys: npt.NDArray[np.int64], counts: npt.NDArray[np.int64]
) -> npt.NDArray[np.int64]:
    """``counts`` of each of ``keys`` (N,) in the sorted ``count_keys``; 0 where absent."""
    rows = rows_in_sorted(count_keys, keys)
    out = np.zeros(rows.shape, np.int64)
    hit = rows >= 0
    out[hit] = np.asarray(counts, np.int64)[rows[hit]]
    return out


def select_reliable_scans(
    labels: list[npt.NDArray[np.integer]],
    confidence: list[npt.NDArray[np.floating]],
    num_classes: int,
    share: float,
    scope: str = "scan",
    *,
    seed: int | None = None,
    support: list[npt.NDArray[np.floating]] | None = None,
    scan_numbers: Sequence[int] | None = None,
) -> list[npt.NDArray[np.bool_]]:
    """:func:`select_reliable` over a list of scans, ranking per scan or over the whole sequence.

    ``scope="scan"`` (docs/METHOD.md's reading: project *each scan* onto the grid, then select) keeps the top
    ``share`` of each class within every scan, so every scan contributes training labels.
    ``scope="sequence"`` ranks all points of all scans together, so a class's labels concentrate in the
    scans where its voxels are most confident.

    ``seed`` and ``support`` break ties as in :func:`select_reliable` (scan s uses ``seed + n_s`` with
    ``n_s = scan_numbers[s]``, its frame number, so a scan's tie order does not depend on which other scans
    the run holds; without ``scan_numbers``, ``n_s = s``).

    Returns:
        One (N_s,) bool mask per scan.
    """
    if scope == "scan":
        return [
            select_reliable(
                lab,
                conf,
                num_classes,
                share,
                None if seed is None else seed + (s if scan_numbers is None else int(scan_numbers[s])),
                None if support is None else support[s],
            )
            for s, (lab, conf) in enumerate(zip(labels, confidence, strict=True))
        ]
    if scope != "sequence":
        raise ValueError(f"scope must be 'scan' or 'sequence', got {scope!r}")
    sizes = [len(lab) for lab in labels]
    if not sizes:
        return []
    mask = select_reliable(
        np.concatenate(labels),
        np.concatenate(confidence),
        num_classes,
        share,
        seed,
        None if support is None else np.concatenate(support),
    )
    return list(np.split(mask, np.cumsum(sizes)[:-1]))


__all__ = [
    "VIEW_COUNT_BATCH",
    "lookup_counts",
    "per_class_quota",
    "select_reliable",
    "select_reliable_scans",
    "view_counts",
]
