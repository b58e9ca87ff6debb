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


def rank_regions(
    centres: npt.NDArray[np.floating],
    score: npt.NDArray[np.floating],
    candidates: npt.NDArray[np.bool_],
    cell_size: float,
    *,
    min_count: int = 1,
    ascending: bool = True,
    limit: int = 100,
) -> list[Region]:
    """Cluster candidate voxels into coarse cells and order the cells by their mean score
    (:func:`leap_core.review.rank_cells`; ties: more candidates first, then the smaller cell key).

    Args:
        centres: (V, 3) voxel centres.
        score: (V,) per-voxel score.
        candidates: (V,) bool, the voxels to cluster (e.g. the least confident share).
        cell_size: cell edge in metres (> 0).
        min_count: cells with fewer candidates are dropped (isolated voxels are noise, not regions).
        ascending: lowest score first (confidence) or highest first (disagreement).
        limit: return at most this many regions.

    Returns:
        Regions, best first, each with its identity and candidate rows.
    """
    cells = review.rank_cells(
        centres, score, candidates, cell_size, min_count=min_count, ascending=ascending, limit=limit
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
        )
        for c in cells
    ]


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


__all__ = ["REVIEW_BOX_RGB", "Region", "disagreement_rate", "lowest_share", "rank_regions"]
