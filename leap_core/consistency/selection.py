"""Reliable label selection for self-training the 3D Consistency Network (METHOD.md stage C.1).

Each scan's points are projected onto the (smoothed) voxel grid and take their voxel's label and
confidence. Per class, only the most confident ``share`` of that class's points become training labels.
Ranking *within* each class, rather than over all points, keeps rare classes represented: a global
confidence threshold would keep mostly road and building.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

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
) -> npt.NDArray[np.bool_]:
    """Per class, mark the ``share`` most confident labeled points.

    For every class ``c`` with ``n_c`` points of label ``c``, keep the ``k_c = ceil(share · n_c)`` points
    with the highest confidence. Points labeled ``UNLABELED`` (-1) are never selected. Ties are broken
    deterministically: by point index (lower first) when ``seed`` is None, else by a random order drawn
    from ``seed``. Fused grids saturate (many voxels reach the same clipped confidence), and an index
    order would then pick points by scan order (e.g. the lowest beams) instead of spreading them out.

    Args:
        labels: (N,) int class index per point in ``[0, num_classes)`` or ``UNLABELED``.
        confidence: (N,) float confidence per point (e.g. its voxel's max class probability).
        num_classes: C, number of classes.
        share: fraction in (0, 1] of each class's points to keep.
        seed: seed of the tie-breaking order; None = point index order.

    Returns:
        (N,) bool mask of selected points; ``mask.sum() == Σ_c k_c``.

    Raises:
        ValueError: on mismatched shapes, a label outside ``[-1, C)`` or ``share`` outside (0, 1].
    """
    labels = np.asarray(labels)
    confidence = np.asarray(confidence)
    if labels.ndim != 1 or confidence.shape != labels.shape:
        raise ValueError(f"labels {labels.shape} and confidence {confidence.shape} must both be (N,)")
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share must be in (0, 1], got {share}")
    selected = np.zeros(labels.shape[0], dtype=bool)
    if labels.size == 0:
        return selected
    lab = labels.astype(np.int64)
    if lab.min() < UNLABELED or lab.max() >= num_classes:
        raise ValueError(f"labels must lie in [-1, {num_classes}), got range [{lab.min()}, {lab.max()}]")
    # One stable sort orders points by (class, confidence descending, tie rank): lexsort's last key is
    # primary and the sort is stable, so with no tie rank equal confidences keep index order.
    conf = np.nan_to_num(confidence.astype(np.float64), nan=-np.inf)
    if seed is None:
        order = np.lexsort((-conf, lab))
    else:
        tie = np.random.default_rng(seed).permutation(lab.shape[0])
        order = np.lexsort((tie, -conf, lab))
    sorted_lab = lab[order]
    counts = np.bincount(lab[lab >= 0], minlength=num_classes)
    starts = np.searchsorted(sorted_lab, np.arange(num_classes), side="left")
    for c in range(num_classes):
        k = per_class_quota(int(counts[c]), share)
        if k:
            selected[order[starts[c] : starts[c] + k]] = True
    return selected


def select_reliable_scans(
    labels: list[npt.NDArray[np.integer]],
    confidence: list[npt.NDArray[np.floating]],
    num_classes: int,
    share: float,
    scope: str = "scan",
    seed: int | None = None,
) -> list[npt.NDArray[np.bool_]]:
    """:func:`select_reliable` over a list of scans, ranking per scan or over the whole sequence.

    ``scope="scan"`` (METHOD.md's reading: project *each scan* onto the grid, then select) keeps the top
    ``share`` of each class within every scan, so every scan contributes training labels.
    ``scope="sequence"`` ranks all points of all scans together, so a class's labels concentrate in the
    scans where its voxels are most confident.

    ``seed`` breaks ties as in :func:`select_reliable` (scan s uses ``seed + s``).

    Returns:
        One (N_s,) bool mask per scan.
    """
    if scope == "scan":
        return [
            select_reliable(lab, conf, num_classes, share, None if seed is None else seed + s)
            for s, (lab, conf) in enumerate(zip(labels, confidence))
        ]
    if scope != "sequence":
        raise ValueError(f"scope must be 'scan' or 'sequence', got {scope!r}")
    sizes = [len(lab) for lab in labels]
    if not sizes:
        return []
    mask = select_reliable(np.concatenate(labels), np.concatenate(confidence), num_classes, share, seed)
    return list(np.split(mask, np.cumsum(sizes)[:-1]))


__all__ = ["per_class_quota", "select_reliable", "select_reliable_scans"]
