"""Level of detail for voxel maps larger than the browser budget: pure functions on arrays.

A map of V voxels above :attr:`LodConfig.budget` is sent as at most ``budget`` points: every voxel of the
blocks near the *focus* (the shown scan, the focused review region, or the camera's look-at point) at full
resolution, and one point per block elsewhere (the *overview*). The review queue, selections and
corrections keep working on every voxel of the grid; only what is drawn is thinned.

**Index** (:func:`build_index`, once per grid). Voxel indices ``ijk = ⌊centre / s⌋ - min`` (s the voxel edge)
are interleaved bit by bit into a Morton code ``m = Σ_b x_b·2^(3b) + y_b·2^(3b+1) + z_b·2^(3b+2)``, and the
voxels are sorted by it (one argsort). A *block of level n* is the cube of ``2ⁿ`` voxels per edge holding
the voxels with the same ``m >> 3n``; in Morton order every block, at every level, is one contiguous run, so
a block's voxels are ``order[starts[b]:starts[b + 1]]``.

**Overview level** (:func:`choose_level`): the finest ``n ≥ 1`` whose number of non-empty blocks is at
most ``overview_share · budget``. Each overview point sits at the mean centre of its block's voxels and is
drawn with the block's edge; it carries the majority class (class view) or the mean score (confidence and
probability views) of its *visible* voxels, read from per-block, per-class tables (:func:`block_tables`):
``hist[b, c + 1]`` voxels of class c (column 0: unlabeled) passing the threshold, ``ssum[b, c + 1]`` the sum
of their scores. A class toggle then only masks columns: ``count_b = Σ_c hist[b, c]·e_c``,
``majority_b = argmax_c hist[b, c]·e_c``, ``mean_b = Σ_c ssum[b, c]·e_c / count_b``.

**Full resolution** (:func:`full_blocks`): the overview blocks whose cube lies within ``radius`` (horizontal
distance from the focus to the cube's footprint) are replaced by their voxels, nearest block first, while
the total ``Σ_{b∈F} count_b + #{b ∉ F : count_b > 0}`` stays within the budget (adding block b changes it
by ``count_b - 1 ≥ 0``, so a prefix of the nearest blocks is taken). Every visible voxel within
``radius`` of the focus is thus drawn unless the budget ran out first.

**Culling** (:func:`frustum_blocks`, :func:`ray_blocks`): selections and clicks test coarse cubes (edge ≥
:attr:`LodConfig.query_edge`) against the selection's frustum or the click ray first and only then look at
the voxels inside the cubes that pass, with a test that never drops a voxel the full test would keep.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.picking import ray_box_entry
from leap_core.selection import (
    DepthMode,
    PinholeCamera,
    camera_coords,
    pixel_of,
    project_to_screen,
    quat_to_matrix,
    select_points,
)

MAX_AXIS = 1 << 21
"""Voxels per axis a Morton code holds (21 bits each in 63 bits: 419 km at 0.2 m)."""


@dataclass(frozen=True)
class LodConfig:
    """Level of detail of the voxel map (:mod:`app.viewer.lod`)."""

    budget: int = 2_000_000
    """Most points the voxel map sends to a browser (full-resolution voxels + overview blocks). A grid with
    at most this many voxels is drawn exactly as without level of detail."""
    radius: float = 60.0
    """Voxels within this horizontal distance (m) of the focus are drawn at full resolution (nearest first
    while the budget lasts)."""
    overview_share: float = 0.5
    """Share of the budget the overview may take: its level is the finest whose block count fits."""
    query_edge: float = 8.0
    """Smallest edge (m) of the coarse cubes selections and clicks are culled with."""
    refine_distance: float = 15.0
    """The camera's look-at point must move this far (m, horizontally) from the focus before the
    full-resolution area follows it (orbiting or zooming alone moves nothing)."""

    def __post_init__(self) -> None:
        if self.budget < 2:
            raise ValueError(f"lod budget must be >= 2 points, got {self.budget}")
        if not self.radius >= 0:
            raise ValueError(f"lod radius must be >= 0 m, got {self.radius}")
        if not 0.0 < self.overview_share < 1.0:
            raise ValueError(f"lod overview_share must lie in (0, 1), got {self.overview_share}")
        if not self.query_edge > 0 or not self.refine_distance >= 0:
            raise ValueError(
                f"lod query_edge must be > 0 and refine_distance >= 0, got {self.query_edge}, "
                f"{self.refine_distance}"
            )


# ------------------------------------------------------------------------------------------ Morton
_SPREAD_STEPS = (
    (32, 0x1F00000000FFFF),
    (16, 0x1F0000FF0000FF),
    (8, 0x100F00F00F00F00F),
    (4, 0x10C30C30C30C30C3),
    (2, 0x1249249249249249),
)
"""Shift and mask of each step moving bit b of a 21-bit value to bit 3b (halving the gaps each time)."""


def _spread_bits(
    v: npt.NDArray[np.uint64], scratch: npt.NDArray[np.uint64] | None = None
) -> npt.NDArray[np.uint64]:
    """Bit b of each (21-bit) value moved to bit 3b, in place (``scratch``: a buffer of the same shape)."""
    tmp = np.empty_like(v) if scratch is None else scratch
    np.bitwise_and(v, np.uint64(0x1FFFFF), out=v)
    for shift, mask in _SPREAD_STEPS:
        # In place with one scratch buffer: fresh 80 MB temporaries per step cost more than the arithmetic.
        np.left_shift(v, np.uint64(shift), out=tmp)
        np.bitwise_or(v, tmp, out=v)
        np.bitwise_and(v, np.uint64(mask), out=v)
    return v


def morton3(ijk: npt.ArrayLike, origin: npt.ArrayLike | None = None) -> npt.NDArray[np.uint64]:
    """(V,) uint64 Morton codes ``Σ_b x_b·2^(3b) + y_b·2^(3b+1) + z_b·2^(3b+2)`` of (V, 3) integer voxel
    indices minus ``origin`` (default 0), which must lie in ``[0, 2²¹)``.

    Raises:
        ValueError: an index is negative or ≥ 2²¹, or the shape is not (V, 3).
    """
    a = np.asarray(ijk)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"ijk must be (V, 3) voxel indices, got shape {a.shape}")
    o = np.zeros(3, np.int64) if origin is None else np.asarray(origin, dtype=np.int64).reshape(3)
    if a.size:
        lo, hi = int((a.min(axis=0) - o).min()), int((a.max(axis=0) - o).max())
        if lo < 0 or hi >= MAX_AXIS:
            raise ValueError(f"voxel indices must lie in [0, {MAX_AXIS}), got [{lo}, {hi}]")
    n = a.shape[0]
    code = np.zeros(n, np.uint64)
    v, scratch = np.empty(n, np.uint64), np.empty(n, np.uint64)
    for d in range(3):
        np.subtract(a[:, d], o[d], out=v, casting="unsafe")  # checked non-negative above
        _spread_bits(v, scratch)
        if d:
            np.left_shift(v, np.uint64(d), out=v)
        np.bitwise_or(code, v, out=code)
    return code


def block_counts(codes_sorted: npt.NDArray[np.uint64], level: int) -> int:
    """Number of non-empty blocks of ``level`` (distinct ``code >> 3·level``) among sorted codes."""
    if codes_sorted.size == 0:
        return 0
    shift = np.uint64(3 * level)
    return 1 + int(np.count_nonzero((codes_sorted[1:] >> shift) != (codes_sorted[:-1] >> shift)))


def choose_level(codes_sorted: npt.NDArray[np.uint64], cap: int) -> int:
    """The finest level ``n ≥ 1`` with at most ``cap`` non-empty blocks (21 when none fits).

    Neighbours in sorted order lie in different blocks of level n iff their codes differ above bit 3n, i.e.
    ``a XOR b ≥ 2^(3n)``: one XOR pass, then one comparison per level tried.
    """
    if codes_sorted.size == 0:
        return 1
    change = codes_sorted[1:] ^ codes_sorted[:-1]
    for level in range(1, 21):
        if 1 + int(np.count_nonzero(change >= np.uint64(1 << (3 * level)))) <= cap:
            return level
    return 21


def block_starts(codes_sorted: npt.NDArray[np.uint64], level: int) -> npt.NDArray[np.int64]:
    """(B + 1,) start of each block of ``level`` in the sorted order, then V: block b holds sorted positions
    ``starts[b] .. starts[b + 1] - 1``."""
    shift = np.uint64(3 * level)
    coarse = codes_sorted >> shift
    inner = np.flatnonzero(coarse[1:] != coarse[:-1]) + 1
    return np.concatenate([[0], inner, [codes_sorted.shape[0]]]).astype(np.int64)


def segment_rows(
    order: npt.NDArray[np.int64], starts: npt.NDArray[np.int64], blocks: npt.NDArray[np.int64]
) -> npt.NDArray[np.int64]:
    """Rows of the voxels of ``blocks`` (block order, Morton order within a block):
    ``concat(order[starts[b] : starts[b + 1]] for b in blocks)``."""
    b = np.asarray(blocks, dtype=np.int64)
    if b.size == 0:
        return np.zeros(0, np.int64)
    lo, hi = starts[b], starts[b + 1]
    lengths = hi - lo
    total = int(lengths.sum())
    # Position k of block j reads order[lo_j + k]: one arange shifted per block.
    shift = np.repeat(lo - (np.cumsum(lengths) - lengths), lengths)
    return order[np.arange(total, dtype=np.int64) + shift].astype(np.int64, copy=False)


# ------------------------------------------------------------------------------------------- index
class Blocks:
    """The non-empty blocks of one level of a :class:`LodIndex` (per-voxel arrays made on first use: the
    culling cubes need only their runs and corners)."""

    def __init__(self, index: LodIndex, level: int) -> None:
        self.index = index
        self.level = level
        """n: a block is a cube of 2ⁿ voxels per edge."""
        self.edge = (1 << level) * index.voxel_size
        """Block edge in metres (2ⁿ · voxel edge)."""
        self.starts = block_starts(index.codes, level)
        """(B + 1,) start of each block in the index's sorted order (:func:`block_starts`)."""
        first = index.ijk_of(index.order[self.starts[:-1]])
        lower_ijk = ((first - index.origin) >> level << level) + index.origin
        self.lower: npt.NDArray[np.float64] = (lower_ijk * index.voxel_size).astype(np.float64)
        """(B, 3) float64 world corner of each block's cube with the smallest coordinates."""

    @property
    def count(self) -> int:
        """B, the number of non-empty blocks."""
        return int(self.starts.shape[0] - 1)

    @property
    def cube_centres(self) -> npt.NDArray[np.float64]:
        """(B, 3) centre of each block's cube."""
        return self.lower + 0.5 * self.edge

    @functools.cached_property
    def of_sorted(self) -> npt.NDArray[np.int32]:
        """(V,) block of each voxel in the index's sorted order (non-decreasing)."""
        return np.repeat(np.arange(self.count, dtype=np.int32), np.diff(self.starts))

    @functools.cached_property
    def of_row(self) -> npt.NDArray[np.int32]:
        """(V,) block of each grid row."""
        out = np.empty(self.index.num_voxels, np.int32)
        out[self.index.order] = self.of_sorted
        return out

    @functools.cached_property
    def mean(self) -> npt.NDArray[np.float32]:
        """(B, 3) mean centre of each block's voxels (where its overview point is drawn)."""
        counts = np.diff(self.starts).astype(np.float64)
        if self.count == 0:
            return np.zeros((0, 3), np.float32)
        # In sorted order each block is one run: a sum per run, reading the centres front to back (float32
        # sums: a display position may be off by a few millimetres).
        sums = np.add.reduceat(self.index.centres[self.index.order], self.starts[:-1], axis=0)
        return (sums / counts[:, None]).astype(np.float32)


@dataclass(eq=False)
class LodIndex:
    """Spatial index of a grid's voxels (:func:`build_index`); levels are built on first use and kept."""

    voxel_size: float
    """Voxel edge s (m)."""
    origin: npt.NDArray[np.int64]
    """(3,) smallest voxel index; Morton codes encode ``⌊centre / s⌋ - origin``."""
    codes: npt.NDArray[np.uint64]
    """(V,) Morton codes in ascending order."""
    order: npt.NDArray[np.int64]
    """(V,) grid row of each sorted code."""
    centres: npt.NDArray[np.float32]
    """(V, 3) the grid's voxel centres (not copied)."""
    _levels: dict[int, Blocks] = field(default_factory=dict)
    _level_of_cap: dict[int, int] = field(default_factory=dict)
    _in_order: dict[str, tuple[npt.NDArray[Any], npt.NDArray[Any]]] = field(default_factory=dict)

    @property
    def num_voxels(self) -> int:
        return int(self.order.shape[0])

    def ijk_of(self, rows: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        """(M, 3) voxel indices ``⌊centre / s⌋`` of grid rows."""
        return np.floor(self.centres[rows].astype(np.float64) / self.voxel_size).astype(np.int64)

    def blocks(self, level: int) -> Blocks:
        """The non-empty blocks of ``level`` (built once: one pass over the sorted codes)."""
        cached = self._levels.get(level)
        if cached is None:
            cached = self._levels[level] = Blocks(self, level)
        return cached

    def sorted_tables(
        self,
        blocks: Blocks,
        label: npt.NDArray[np.int16],
        num_classes: int,
        *,
        threshold: float = 0.0,
        score: npt.NDArray[np.floating] | None = None,
        chunk_blocks: int = 1 << 16,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32] | None]:
        """:func:`block_tables` of per-row arrays, counted in the index's sorted order, ``chunk_blocks``
        blocks at a time (same result). With ``threshold > 0`` only voxels with ``score ≥ threshold`` are
        counted (``score`` required).

        Why this shape: in sorted order a run of blocks is a run of voxels, so each chunk's counts land in
        a small table (≈ 11 MB at 20 classes) that the allocator reuses, where one count over the whole map
        made two fresh (B, C + 1) int64 / float64 tables (170 MB each at 10 M voxels) and paid their page
        faults on every recount. The sorted copies of ``label`` and ``score`` are kept while the same
        arrays come back (the session hands the same objects until labels or scores change; it never edits
        them in place): at 10 M voxels those two gathers took 240 of a threshold change's 320 ms.
        """
        if threshold > 0 and score is None:
            raise ValueError("a threshold needs the score it applies to")
        if chunk_blocks < 1:
            raise ValueError(f"chunk_blocks must be ≥ 1, got {chunk_blocks}")
        lab = self._sorted("label", label)
        sc = None if score is None else self._sorted("score", score)
        width = num_classes + 1
        hist = np.empty((blocks.count, width), np.float32)
        ssum = None if sc is None else np.empty((blocks.count, width), np.float32)
        thr = np.float32(threshold)
        for b0 in range(0, blocks.count, chunk_blocks):
            b1 = min(blocks.count, b0 + chunk_blocks)
            v0, v1 = int(blocks.starts[b0]), int(blocks.starts[b1])
            part = None if sc is None else sc[v0:v1]
            h, sm = block_tables(
                blocks.of_sorted[v0:v1] - np.int32(b0),
                b1 - b0,
                lab[v0:v1],
                num_classes,
                keep=None if threshold <= 0 or part is None else part >= thr,
                score=part,
            )
            hist[b0:b1] = h
            if ssum is not None and sm is not None:
                ssum[b0:b1] = sm
        return hist, ssum

    def _sorted(self, role: str, values: npt.NDArray[Any]) -> npt.NDArray[Any]:
        """``values[self.order]``, reused while ``values`` is the same array object (held here, so its id
        cannot be reused by another array)."""
        cached = self._in_order.get(role)
        if cached is not None and cached[0] is values:
            return cached[1]
        out = values[self.order]
        self._in_order[role] = (values, out)
        return out

    def overview_level(self, budget: int, share: float) -> int:
        """Level of the overview under ``budget`` points (:func:`choose_level` of ``⌊share · budget⌋``)."""
        cap = max(1, int(share * budget))
        level = self._level_of_cap.get(cap)
        if level is None:
            level = self._level_of_cap[cap] = choose_level(self.codes, cap)
        return level

    def query_level(self, edge: float, at_least: int = 1) -> int:
        """Level of the culling cubes: the smallest ≥ ``at_least`` whose edge is ≥ ``edge`` metres."""
        need = max(0, math.ceil(math.log2(max(edge / self.voxel_size, 1.0))))
        return min(21, max(at_least, need))


def build_index(
    centres: npt.NDArray[np.float32], voxel_size: float, ijk: npt.NDArray[np.int64] | None = None
) -> LodIndex:
    """Sort a grid's voxels by the Morton code of their indices (see the module doc).

    Args:
        centres: (V, 3) voxel centres (m), ``(i + ½)·s`` as :func:`leap_core.fusion.key_centres` makes them.
        voxel_size: s > 0.
        ijk: (V, 3) their integer indices ``⌊centre / s⌋`` when at hand (unpacked from the grid's keys, which
            is cheaper than dividing the centres).

    Raises:
        ValueError: the map spans 2²¹ voxels or more along an axis.
    """
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    c = np.asarray(centres)
    if ijk is None:
        ijk = np.floor(c.astype(np.float64) / voxel_size).astype(np.int64)
    origin = ijk.min(axis=0) if ijk.shape[0] else np.zeros(3, np.int64)
    codes = morton3(ijk, origin)
    del ijk
    order = np.argsort(codes, kind="stable")
    return LodIndex(float(voxel_size), origin, codes[order], order, c)


# ------------------------------------------------------------------------------------ block tables
def block_tables(
    of_row: npt.NDArray[np.int32],
    num_blocks: int,
    label: npt.NDArray[np.int16],
    num_classes: int,
    *,
    keep: npt.NDArray[np.bool_] | None = None,
    score: npt.NDArray[np.floating] | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32] | None]:
    """Per block and class, the count of voxels (and the sum of their scores).

    Args:
        of_row: (V,) block of each voxel.
        num_blocks: B.
        label: (V,) class per voxel, -1 unlabeled.
        num_classes: C.
        keep: (V,) bool, the voxels counted (those passing the threshold); None counts all.
        score: (V,) value to sum per block and class, or None.

    Returns:
        ``(hist (B, C + 1), ssum (B, C + 1) or None)``, float32, column ``c + 1`` for class c and column 0
        for unlabeled. Counts are exact below 2²⁴ voxels per block and class.
    """
    width = num_classes + 1
    rows = np.flatnonzero(keep) if keep is not None else None
    b = of_row if rows is None else of_row[rows]
    lab = label if rows is None else label[rows]
    # key = block · (C + 1) + label + 1, built in one buffer (each fresh 80 MB array costs page faults).
    key = b.astype(np.int64)
    np.multiply(key, width, out=key)
    np.add(key, lab, out=key, casting="unsafe")
    np.add(key, 1, out=key)
    hist = np.bincount(key, minlength=num_blocks * width).astype(np.float32).reshape(num_blocks, width)
    ssum = None
    if score is not None:
        sc = score if rows is None else score[rows]
        ssum = (
            np.bincount(key, weights=sc, minlength=num_blocks * width)
            .astype(np.float32)
            .reshape(num_blocks, width)
        )
    return hist, ssum


def update_tables(
    hist: npt.NDArray[np.float32],
    ssum: npt.NDArray[np.float32],
    block: npt.NDArray[np.int32],
    num_classes: int,
    before: tuple[npt.NDArray[np.int16], npt.NDArray[np.floating], npt.NDArray[np.bool_]],
    after: tuple[npt.NDArray[np.int16], npt.NDArray[np.floating], npt.NDArray[np.bool_]],
) -> None:
    """Move changed voxels in :func:`block_tables`' tables, in place: each voxel's old entry (class, score,
    counted) is taken out of its block's row and its new one put in (a correction changes a few voxels; a
    full recount reads them all).

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
    return np.rint(hist @ columns).astype(np.int64)


def majority_class(
    hist: npt.NDArray[np.float32],
    columns: npt.NDArray[np.float32],
    blocks: npt.NDArray[np.int64] | None = None,
) -> npt.NDArray[np.int16]:
    """(M,) the most frequent visible class of each of ``blocks`` (every block when None; -1 unlabeled).
    Ties go to the lower class index, unlabeled lowest."""
    sub = (hist if blocks is None else hist[blocks]) * columns
    return (np.argmax(sub, axis=1) - 1).astype(np.int16)


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
    return np.divide(s, n, out=np.zeros_like(s), where=n > 0).astype(np.float32)


# ----------------------------------------------------------------------------------- full resolution
def footprint_distance(
    lower: npt.NDArray[np.float64], edge: float, point: npt.ArrayLike
) -> npt.NDArray[np.float64]:
    """(B,) horizontal distance from ``point`` (x, y, …) to each cube's footprint
    ``[lower_x, lower_x + edge] × [lower_y, lower_y + edge]`` (0 inside)."""
    p = np.asarray(point, dtype=np.float64).reshape(-1)[:2]
    d = np.maximum(np.maximum(lower[:, :2] - p, p - (lower[:, :2] + edge)), 0.0)
    return np.sqrt(np.einsum("ij,ij->i", d, d))


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


# -------------------------------------------------------------------------------------------- culling
def frustum_blocks(
    cube_centres: npt.NDArray[np.float64],
    edge: float,
    camera: PinholeCamera,
    rect_min: tuple[float, float],
    rect_max: tuple[float, float],
) -> npt.NDArray[np.bool_]:
    """(B,) bool: cubes that may hold a point in front of ``camera`` projecting into the screen rectangle
    (normalised corners, see :func:`leap_core.selection.project_to_screen`).

    Conservative (never drops such a cube): a cube is kept unless its bounding sphere (radius ``edge·√3/2``)
    lies wholly behind the camera or wholly outside one of the four planes through the camera centre and
    the rectangle's edges. In camera coordinates a point projects into ``u ∈ [u0, u1]`` iff
    ``a0·z ≤ x ≤ a1·z`` with ``a = (2u - 1)·aspect·tan(fov_y / 2)`` (likewise y with v and ``tan(fov_y/2)``).
    """
    rho = edge * math.sqrt(3.0) / 2.0
    rot = quat_to_matrix(camera.wxyz)
    cam = (np.asarray(cube_centres, dtype=np.float64) - np.asarray(camera.position)) @ rot
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    ty = math.tan(camera.fov_y / 2.0)
    tx = camera.aspect * ty
    u0, u1 = sorted((rect_min[0], rect_max[0]))
    v0, v1 = sorted((rect_min[1], rect_max[1]))
    keep = z > -rho
    for a, sign, coord in (
        ((2 * u0 - 1) * tx, 1.0, x),
        ((2 * u1 - 1) * tx, -1.0, x),
        ((2 * v0 - 1) * ty, 1.0, y),
        ((2 * v1 - 1) * ty, -1.0, y),
    ):
        # Inside the half-space: sign·(coord - a·z) ≥ 0; its plane's unit normal has length √(1 + a²).
        keep &= sign * (coord - a * z) >= -rho * math.sqrt(1.0 + a * a)
    return keep


def ray_blocks(
    cube_centres: npt.NDArray[np.float64], edge: float, origin: npt.ArrayLike, direction: npt.ArrayLike
) -> npt.NDArray[np.bool_]:
    """(B,) bool: cubes the ray enters in front of its origin (every voxel it enters lies in one)."""
    if cube_centres.shape[0] == 0:
        return np.zeros(0, bool)
    return np.isfinite(ray_box_entry(origin, direction, cube_centres, edge))


def mask_rect(mask: npt.NDArray[np.bool_]) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """Normalised corners of the bounding rectangle of a screen mask's True pixels (None when empty)."""
    cols = np.flatnonzero(mask.any(axis=0))
    rows = np.flatnonzero(mask.any(axis=1))
    if cols.size == 0:
        return None
    h, w = mask.shape
    return (cols[0] / w, rows[0] / h), ((cols[-1] + 1) / w, (rows[-1] + 1) / h)


def select_culled(  # noqa: PLR0913 (select_points' own keywords, plus the index and its cubes)
    index: LodIndex,
    cubes: Blocks,
    camera: PinholeCamera,
    mask: npt.NDArray[np.bool_],
    *,
    visible: npt.NDArray[np.bool_],
    eligible: npt.NDArray[np.bool_] | None = None,
    depth_mode: DepthMode = "front",
    distance: float = 0.5,
    splat_size: float = 0.2,
) -> npt.NDArray[np.int64]:
    """Rows (ascending) :func:`leap_core.selection.select_points` selects among the ``visible`` voxels, found
    without projecting the voxels of cubes that cannot matter.

    The candidates lie in the mask's bounding rectangle, so the cubes passing :func:`frustum_blocks` for it
    hold them all. In ``front`` mode the z-buffer also reads occluders in the candidates' cell box grown by
    one cell (:func:`leap_core.selection.front_surface`; cell = median on-screen size of the candidates), so
    the cubes of that wider window are added before the exact test runs on the union.

    Args:
        index: the grid's index; ``cubes`` one of its levels (the culling cubes).
        camera, mask: the tool's camera and (H, W) screen mask.
        visible: (V,) bool, the voxels shown (the only ones selectable or occluding).
        eligible: (V,) bool class filter applied after the depth test, or None.
        depth_mode, distance, splat_size: as :func:`~leap_core.selection.select_points`.
    """
    rect = mask_rect(mask)
    if rect is None:
        return np.zeros(0, np.int64)
    centres = index.centres

    def rows_in(lo: tuple[float, float], hi: tuple[float, float]) -> npt.NDArray[np.int64]:
        keep = frustum_blocks(cubes.cube_centres, cubes.edge, camera, lo, hi)
        rows = segment_rows(index.order, cubes.starts, np.flatnonzero(keep))
        return rows[visible[rows]]

    rows = rows_in(*rect)
    if depth_mode == "front" and rows.size:
        w, h = camera.width_px, camera.height_px
        cam = camera_coords(centres[rows], camera.position, camera.wxyz)
        uv, in_front = project_to_screen(
            centres[rows], camera.position, camera.wxyz, camera.fov_y, camera.aspect
        )
        col, row, on = pixel_of(uv, w, h)
        cand = in_front & on & mask[row, col]
        if cand.any():
            splat = splat_size * camera.focal_px / cam[cand, 2]
            cell = max(1.0, float(np.median(splat)))
            ccol, crow = (col[cand] / cell).astype(np.int64), (row[cand] / cell).astype(np.int64)
            # Occluder pixels: columns [(c0 - 1)·cell, (c1 + 2)·cell), one pixel of slack each side.
            u0 = ((ccol.min() - 1) * cell - 1) / w
            u1 = ((ccol.max() + 2) * cell + 1) / w
            v0 = ((crow.min() - 1) * cell - 1) / h
            v1 = ((crow.max() + 2) * cell + 1) / h
            rows = np.union1d(rows, rows_in((u0, v0), (u1, v1)))
    rows = np.sort(rows)
    picked = select_points(
        centres[rows],
        camera,
        mask,
        depth_mode=depth_mode,
        distance=distance,
        splat_size=splat_size,
        eligible=None if eligible is None else eligible[rows],
    )
    return rows[picked]


def ray_rows(
    index: LodIndex, cubes: Blocks, origin: npt.ArrayLike, direction: npt.ArrayLike
) -> npt.NDArray[np.int64]:
    """Rows (ascending) of the voxels in the cubes a click ray enters: every voxel the ray can hit."""
    hit = ray_blocks(cubes.cube_centres, cubes.edge, origin, direction)
    return np.sort(segment_rows(index.order, cubes.starts, np.flatnonzero(hit)))


def thin_rows(
    blocks: Blocks,
    full: npt.NDArray[np.int64],
    centres: npt.NDArray[np.float32],
    rows: npt.NDArray[np.int64],
) -> npt.NDArray[np.float32]:
    """Points marking ``rows``: the centres of those in the ``full`` (ascending) blocks, then the mean centre
    of each other block holding one of them (so a selection over the overview stays within the budget)."""
    b = blocks.of_row[rows].astype(np.int64)
    pos = np.minimum(np.searchsorted(full, b), max(full.shape[0] - 1, 0))
    inside = full[pos] == b if full.size else np.zeros(b.shape[0], bool)
    return np.concatenate([centres[rows[inside]], blocks.mean[np.unique(b[~inside])]]).astype(np.float32)


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
        radius, budget: :class:`LodConfig` values.
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
    "MAX_AXIS",
    "Blocks",
    "LodConfig",
    "LodIndex",
    "LodPlan",
    "block_counts",
    "block_starts",
    "block_tables",
    "build_index",
    "choose_level",
    "enabled_columns",
    "footprint_distance",
    "frustum_blocks",
    "full_blocks",
    "majority_class",
    "mask_rect",
    "mean_score",
    "morton3",
    "plan_view",
    "ray_blocks",
    "ray_rows",
    "segment_rows",
    "select_culled",
    "thin_rows",
    "update_tables",
    "visible_counts",
]
