"""Level of detail for voxel maps larger than the browser budget: the spatial index (pure functions).

A map of V voxels above :attr:`LodConfig.budget` is sent as at most ``budget`` points: every voxel of the
blocks near the *focus* (the shown scan, the focused review region, or the camera's look-at point) at full
resolution, and one point per block elsewhere (the *overview*). The review queue, selections and
corrections keep working on every voxel of the grid; only what is drawn is thinned. This module builds the
index and counts blocks; :mod:`app.viewer.lod_plan` chooses and colours what is drawn from the counts, and
:mod:`app.viewer.lod_cull` culls selections and clicks with the index's coarse cubes.

**Index** (:func:`build_index`, once per grid). Voxel indices ``ijk = ⌊centre / s⌋ - min`` (s the voxel edge)
are interleaved bit by bit into a Morton code ``m = Σ_b x_b·2^(3b) + y_b·2^(3b+1) + z_b·2^(3b+2)``, and the
voxels are sorted by it (one argsort). A *block of level n* is the cube of ``2ⁿ`` voxels per edge holding
the voxels with the same ``m >> 3n``; in Morton order every block, at every level, is one contiguous run, so
a block's voxels are ``order[starts[b]:starts[b + 1]]``.

**Overview level** (:func:`choose_level`): the finest ``n ≥ 1`` whose number of non-empty blocks is at
most ``overview_share · budget``.

**Block tables** (:func:`block_tables`, :meth:`LodIndex.sorted_tables`): ``hist[b, c + 1]`` voxels of class c
(column 0: unlabeled) passing the threshold, ``ssum[b, c + 1]`` the sum of their scores.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

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
    rows: npt.NDArray[np.int64] = order[np.arange(total, dtype=np.int64) + shift].astype(np.int64, copy=False)
    return rows


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


__all__ = [
    "MAX_AXIS",
    "Blocks",
    "LodConfig",
    "LodIndex",
    "block_counts",
    "block_starts",
    "block_tables",
    "build_index",
    "choose_level",
    "morton3",
    "segment_rows",
]
