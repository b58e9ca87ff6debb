"""Pure maths of the review queue: regions of candidate voxels, candidate shares, camera-vs-final
disagreement.

Like :mod:`app.viewer.view_logic`, everything takes and returns numpy arrays (or small frozen records) and
does no I/O; the review queue (:class:`app.viewer.review_queue.ReviewQueue`) ranks and shows what these
functions find.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from leap_core import review

REVIEW_BOX_RGB = (0, 255, 255)
"""Outline of the focused review region (3D box and image box): cyan, which no SemanticKITTI class uses
(magenta would vanish on the road)."""


@dataclass(frozen=True, eq=False)
class Region:
    """A place worth reviewing: the voxels of the candidate set that fall in one coarse cell."""

    centre: tuple[float, float, float]
    """Mean position of the region's candidate voxels (metres)."""
    extent: float
    """Largest distance of a candidate voxel from the centre (metres), for framing the camera."""
    score: float
    """Mean score of the region's candidate voxels (confidence, or disagreement rate)."""
    count: int
    """Number of candidate voxels in the region."""
    id: str = ""
    """Stable identity across runs (:func:`leap_core.review.region_id`)."""
    rows: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    """(count,) grid rows of the candidate voxels (the ones highlighted)."""
    cell: int = 0
    """Packed cell key (:func:`leap_core.review.rank_cells`)."""
    expected_wrong: float = 0.0
    """How many of its voxels (confidence queue) or camera-labelled points (disagreement queue) are
    expected to be wrong: what ranks it."""


def rank_regions(
    centres: npt.NDArray[np.floating],
    score: npt.NDArray[np.floating],
    candidates: npt.NDArray[np.bool_],
    cell_size: float,
    *,
    wrong: npt.NDArray[np.floating] | None = None,
    min_count: int = 1,
    ascending: bool = True,
    limit: int = 100,
) -> list[Region]:
    """Cluster candidate voxels into coarse cells and order the cells by their expected wrong count, or
    without ``wrong`` by their mean score (:func:`leap_core.review.rank_cells`; ties: more candidates
    first, then the smaller cell key).

    Args:
        centres: (V, 3) voxel centres.
        score: (V,) per-voxel score.
        candidates: (V,) bool, the voxels to cluster (e.g. the least confident share).
        cell_size: cell edge in metres (> 0).
        wrong: (V,) per-voxel expected wrong count (:func:`confidence_wrong`, :func:`disagreement_wrong`).
        min_count: cells with fewer candidates are dropped (isolated voxels are noise, not regions).
        ascending: lowest score first (confidence) or highest first (disagreement).
        limit: return at most this many regions.

    Returns:
        Regions, best first, each with its identity and candidate rows.
    """
    cells = review.rank_cells(
        centres,
        score,
        candidates,
        cell_size,
        wrong=wrong,
        min_count=min_count,
        ascending=ascending,
        limit=limit,
    )
    return [
        Region(
            centre=c.centre,
            extent=c.extent,
            score=c.score,
            count=int(c.rows.shape[0]),
            id=review.region_id(c.cell, cell_size),
            rows=c.rows,
            cell=c.cell,
            expected_wrong=c.expected_wrong,
        )
        for c in cells
    ]


def confidence_wrong(conf: npt.NDArray[np.floating]) -> npt.NDArray[np.float64]:
    """(V,) expected wrong count per voxel from its confidence: ``1 - conf`` (a corrected voxel, conf 1,
    counts 0)."""
    return np.clip(1.0 - np.asarray(conf, dtype=np.float64), 0.0, 1.0)


def disagreement_wrong(
    rate: npt.NDArray[np.floating], observed: npt.NDArray[np.integer]
) -> npt.NDArray[np.float64]:
    """(V,) expected wrong points per voxel from the disagreement: ``rate · observed`` (the camera-labelled
    points of the voxel whose final label differs from the camera's)."""
    return np.asarray(rate, dtype=np.float64) * np.asarray(observed, dtype=np.float64)


def highlight_colors(colors: npt.NDArray[np.uint8], alpha: float = 0.35) -> npt.NDArray[np.uint8]:
    """Colours of a focused region's voxels in the highlight drawn over the map: their own colours
    pulled ``alpha`` toward :data:`REVIEW_BOX_RGB`, ``c' = round((1-α)·c + α·cyan)``, so the class stays
    readable and the region stands out from the dimmed map."""
    c = np.asarray(colors, dtype=np.float64)
    out = (1.0 - alpha) * c + alpha * np.asarray(REVIEW_BOX_RGB, dtype=np.float64)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def lowest_share(score: npt.NDArray[np.floating], share: float) -> npt.NDArray[np.bool_]:
    """(V,) bool: the ``share`` (0..1] of voxels with the lowest score (at least one if V > 0)."""
    if not 0 < share <= 1:
        raise ValueError(f"share must be in (0, 1], got {share}")
    n = score.shape[0]
    if n == 0:
        return np.zeros(0, bool)
    k = max(1, round(share * n))
    if k >= n:
        return np.ones(n, bool)
    cut = np.partition(score, k - 1)[k - 1]
    lowest: npt.NDArray[np.bool_] = score <= cut
    return lowest


def disagreement_rate(
    voxel_rows: npt.NDArray[np.int64],
    camera_label: npt.NDArray[np.int16],
    final_label: npt.NDArray[np.int16],
    num_voxels: int,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """Per voxel, the share of camera-labelled points whose final label differs from the camera label.

    ``rate[n] = #{p in n : cam_p ≥ 0, final_p ≠ cam_p} / #{p in n : cam_p ≥ 0}`` (0 where no camera label).

    Args:
        voxel_rows: (N,) grid row of each point (-1 when its voxel is not in the grid).
        camera_label: (N,) projection-only (camera) label per point, -1 when the camera did not see it.
        final_label: (N,) final label per point (voxel / 3D-CN).
        num_voxels: V.

    Returns:
        ``(rate (V,) float32, observed (V,) int64)``.
    """
    ok = (voxel_rows >= 0) & (camera_label >= 0)
    rows = voxel_rows[ok]
    observed = np.bincount(rows, minlength=num_voxels).astype(np.int64)
    differ = np.bincount(rows, weights=(final_label[ok] != camera_label[ok]), minlength=num_voxels)
    rate = np.divide(differ, observed, out=np.zeros(num_voxels), where=observed > 0).astype(np.float32)
    return rate, observed


__all__ = [
    "REVIEW_BOX_RGB",
    "Region",
    "confidence_wrong",
    "disagreement_rate",
    "disagreement_wrong",
    "highlight_colors",
    "lowest_share",
    "rank_regions",
]
