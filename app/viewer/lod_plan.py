"""Level of detail for voxel maps larger than the browser budget: what is drawn (pure functions).

Built on the index of :mod:`app.viewer.lod`. Each overview point sits at the mean centre of its block's
voxels and is drawn with the block's edge; it carries the majority class (class view) or the mean score
(confidence and probability views) of its *visible* voxels, read from the per-block, per-class tables
(:func:`app.viewer.lod.block_tables`): ``hist[b, c + 1]`` voxels of class c (column 0: unlabeled) passing the
threshold, ``ssum[b, c + 1]`` the sum of their scores. A class toggle then only masks columns:
``count_b = Σ_c hist[b, c]·e_c``, ``majority_b = argmax_c hist[b, c]·e_c``,
``mean_b = Σ_c ssum[b, c]·e_c / count_b``.

**Full resolution** (:func:`full_blocks`): the overview blocks whose cube lies within ``radius`` (horizontal
distance from the focus to the cube's footprint) are replaced by their voxels, nearest block first, while
the total ``Σ_{b∈F} count_b + #{b ∉ F : count_b > 0}`` stays within the budget (adding block b changes it
by ``count_b - 1 ≥ 0``, so a prefix of the nearest blocks is taken). Every visible voxel within
``radius`` of the focus is thus drawn unless the budget ran out first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.viewer.lod import Blocks, segment_rows


# ------------------------------------------------------------------------------------ block tables
def update_tables(
    hist: npt.NDArray[np.float32],
    ssum: npt.NDArray[np.float32],
    block: npt.NDArray[np.int32],
    num_classes: int,
    before: tuple[npt.NDArray[np.int16], npt.NDArray[np.floating], npt.NDArray[np.bool_]],
    after: tuple[npt.NDArray[np.int16], npt.NDArray[np.floating], npt.NDArray[np.bool_]],
) -> None:
    """Move changed voxels in :func:`~app.viewer.lod.block_tables`' tables, in place: each voxel's old entry
    (class, score, counted) is taken out of its block's row and its new one put in (a correction changes a
    few voxels; a full recount reads them all).

    Args:
        hist, ssum: (B, C + 1) tables to update.
        block: (K,) block of each changed voxel.
        num_classes: C.
        before, after: ``(label (K,), score (K,), counted (K,) bool)`` of the changed voxels.
    """
    width = num_classes + 1
    flat_h, flat_s = hist.reshape(-1), ssum.reshape(-1)
    for (lab, sc, counted), sign in ((before, -1.0), (after, 1.0)):
        idx = block[counted].astype(np.int64) * width + lab[counted].astype(np.int64) + 1
        np.add.at(flat_h, idx, np.float32(sign))
        np.add.at(flat_s, idx, (sign * np.asarray(sc)[counted]).astype(np.float32))


def enabled_columns(enabled: tuple[bool, ...], num_classes: int) -> npt.NDArray[np.float32]:
    """(C + 1,) 1/0 weight of each table column: unlabeled (column 0) always on, class c per its toggle
    (every class when ``enabled`` is empty, as :func:`app.viewer.view_logic.visible_mask`)."""
    e = np.ones(num_classes + 1, np.float32)
    if len(enabled):
        e[1:] = np.asarray(enabled, bool)[:num_classes]
    return e


def visible_counts(hist: npt.NDArray[np.float32], columns: npt.NDArray[np.float32]) -> npt.NDArray[np.int64]:
    """(B,) visible voxels per block: ``Σ_c hist[b, c] · e_c``."""
    counts: npt.NDArray[np.int64] = np.rint(hist @ columns).astype(np.int64)
    return counts


def majority_class(
    hist: npt.NDArray[np.float32],
    columns: npt.NDArray[np.float32],
    blocks: npt.NDArray[np.int64] | None = None,
) -> npt.NDArray[np.int16]:
    """(M,) the most frequent visible class of each of ``blocks`` (every block when None; -1 unlabeled).
    Ties go to the lower class index, unlabeled lowest."""
    sub = (hist if blocks is None else hist[blocks]) * columns
    majority: npt.NDArray[np.int16] = (np.argmax(sub, axis=1) - 1).astype(np.int16)
    return majority


def mean_score(
    hist: npt.NDArray[np.float32],
    ssum: npt.NDArray[np.float32],
    columns: npt.NDArray[np.float32],
    blocks: npt.NDArray[np.int64] | None = None,
) -> npt.NDArray[np.float32]:
    """(M,) mean score of the visible voxels of each of ``blocks`` (every block when None; 0 for a block with
    none)."""
    n = (hist if blocks is None else hist[blocks]) @ columns
    s = (ssum if blocks is None else ssum[blocks]) @ columns
    mean: npt.NDArray[np.float32] = np.divide(s, n, out=np.zeros_like(s), where=n > 0).astype(np.float32)
    return mean


# ----------------------------------------------------------------------------------- full resolution
def footprint_distance(
    lower: npt.NDArray[np.float64], edge: float, point: npt.ArrayLike
) -> npt.NDArray[np.float64]:
    """(B,) horizontal distance from ``point`` (x, y, …) to each cube's footprint
    ``[lower_x, lower_x + edge] × [lower_y, lower_y + edge]`` (0 inside)."""
    p = np.asarray(point, dtype=np.float64).reshape(-1)[:2]
    d = np.maximum(np.maximum(lower[:, :2] - p, p - (lower[:, :2] + edge)), 0.0)
    dist: npt.NDArray[np.float64] = np.sqrt(np.einsum("ij,ij->i", d, d))
    return dist


def full_blocks(
    distance: npt.NDArray[np.float64], counts: npt.NDArray[np.int64], radius: float, budget: int
) -> npt.NDArray[np.int64]:
    """Blocks drawn at full resolution, ascending: the visible blocks within ``radius``, nearest first
    (ties: lower block), while ``Σ_{b∈F} count_b + #{b ∉ F : count_b > 0} ≤ budget``.

    Args:
        distance: (B,) distance of each block from the focus (:func:`footprint_distance`).
        counts: (B,) visible voxels per block.
        radius: largest distance drawn at full resolution (m).
        budget: most points in all.

    Returns:
        (F,) int64 block ids, ascending (empty when even the overview exceeds the budget).
    """
    shown = int(np.count_nonzero(counts))
    near = np.flatnonzero((distance <= radius) & (counts > 0))
    near = near[np.lexsort((near, distance[near]))]
    grow = np.cumsum(counts[near] - 1)
    take = int(np.searchsorted(grow, budget - shown, side="right"))
    return np.sort(near[:take])


# ---------------------------------------------------------------------------------------------- plan
@dataclass(frozen=True, eq=False)
class LodPlan:
    """What to draw of a big map for one focus and view (:func:`plan_view`)."""

    full: npt.NDArray[np.int64]
    """(F,) the full-resolution blocks, ascending."""
    rows: npt.NDArray[np.int64]
    """Rows of every voxel of the full-resolution blocks (visible or not), block by block."""
    blocks: npt.NDArray[np.int64]
    """(K,) overview blocks drawn: visible and not at full resolution, ascending."""
    level: int
    """Level of the blocks."""


def plan_view(
    blocks: Blocks,
    order: npt.NDArray[np.int64],
    counts: npt.NDArray[np.int64],
    focus: npt.ArrayLike,
    radius: float,
    budget: int,
) -> LodPlan:
    """The full-resolution blocks around ``focus`` (:func:`full_blocks`), the rows of their voxels (the
    caller keeps the visible ones: ``Σ_{b∈F} counts_b`` of them) and the overview blocks.

    Args:
        blocks: the overview level's blocks; ``order`` the index's sorted rows.
        counts: (B,) visible voxels per block (:func:`visible_counts`).
        focus: (3,) world point the full resolution is centred on.
        radius, budget: :class:`~app.viewer.lod.LodConfig` values.
    """
    f = np.asarray(focus, dtype=np.float64).reshape(-1)
    # Only blocks whose footprint meets the square around the disc need their exact distance.
    lo, edge = blocks.lower, blocks.edge
    box = np.flatnonzero(
        (lo[:, 0] <= f[0] + radius)
        & (lo[:, 0] + edge >= f[0] - radius)
        & (lo[:, 1] <= f[1] + radius)
        & (lo[:, 1] + edge >= f[1] - radius)
    )
    dist = np.full(blocks.count, np.inf)
    dist[box] = footprint_distance(lo[box], edge, f)
    full = full_blocks(dist, counts, radius, budget)
    shown = counts > 0
    shown[full] = False
    return LodPlan(full, segment_rows(order, blocks.starts, full), np.flatnonzero(shown), blocks.level)


__all__ = [
    "LodPlan",
    "enabled_columns",
    "footprint_distance",
    "full_blocks",
    "majority_class",
    "mean_score",
    "plan_view",
    "update_tables",
    "visible_counts",
]
