"""Distance-weighted kNN smoothing of the fused voxel grid (docs/METHOD.md stage B.4).

``p̄_i(n) = Σ_{m ∈ N_k(n)} w_nm · p_i(m)`` with ``w_n = softmax(-d_n)`` over the k neighbour distances
(metres). ``N_k(n)`` contains n itself at d = 0. Because voxel neighbours sit 0.2-0.5 m apart, the weights
are fairly flat (e^-0.2 ≈ 0.82 relative to the voxel itself): smoothing is strong, as in the paper.
"""

from __future__ import annotations

import itertools
import math
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from leap_core.bounds import check_bounds, within
from leap_core.errors import DatasetError
from leap_core.fusion import VoxelGrid, VoxelLabels, compiled_kernels, key_centres, keys_sorted_unique
from leap_core.io_utils import atomic_save_npz
from leap_core.npzio import Streamed, has_member, load_npz, release, save_npz


@dataclass(frozen=True)
class SmoothingConfig:
    """Parameters of the kNN smoothing."""

    k: int = field(default=9, metadata=within(1, 64))
    """Neighbours per voxel, the voxel itself included (the paper uses 9). At most 64: each chunk of
    voxels queries and mixes k neighbours apiece, so memory and time grow with k."""
    max_distance: float | None = field(default=0.6, metadata=within(0.01, 100, unit="m"))
    """Neighbours farther than this (metres) get no weight; None = plain kNN as in the paper. 0.6 m is
    three 0.2 m voxels: on surfaces the 9th nearest voxel centre lies 0.28 m away (median; 99th percentile
    0.40 m, max 0.57 m on benchmarks/bench_fusion.py's street surfaces), so the bound only acts on isolated
    voxels (sparse far returns), which would otherwise take labels from other objects metres away."""
    workers: int = field(default=2, metadata=within(1, 256, also=(-1,)))
    """Threads that smooth chunks of voxels at once, each querying the tree and mixing its own chunk
    (-1 = all cores); the result does not depend on it."""

    def __post_init__(self) -> None:
        check_bounds(self)


def knn_weights(dists: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Row-wise ``softmax(-d)``: ``w_j = exp(-d_j) / Σ_l exp(-d_l)``.

    Args:
        dists: (V, k) neighbour distances; ``inf`` marks a missing neighbour.

    Returns:
        (V, k) float32 weights; missing neighbours get 0; a row with no neighbour at all is all 0.
    """
    d = np.asarray(dists, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"dists must be (V, k), got shape {d.shape}")
    if d.size == 0:
        return np.zeros(d.shape, np.float32)
    # Subtracting the row minimum keeps exp() in range; exp(-inf) = 0 drops missing neighbours.
    dmin = d.min(axis=1, keepdims=True)
    dmin[~np.isfinite(dmin)] = 0.0  # rows without any neighbour: all weights 0 below
    e = np.subtract(dmin, d)
    np.exp(e, out=e)
    s = e.sum(axis=1, keepdims=True)
    w: npt.NDArray[np.float32] = np.divide(e, s, out=np.zeros_like(e), where=s > 0)
    return w


SMOOTH_CHUNK = 1 << 14
"""Voxels whose neighbours are queried and mixed at once: bounds the per-chunk temporaries (≈ 1.1 kB per
voxel of a chunk at k = 9, C = 20: ≈ 18 MB; ``workers + 1`` chunks are in flight at once) however large the
grid; the result does not depend on it."""

COMPILED_MIN_VOXELS = 16_000_000
"""Smoothing this many voxels or more loads the compiled :func:`knn_mix` (numba, the ``fast`` extra) when the
process has not already (the fusion of a large sequence loads it): it saves ≈ 0.02-0.1 CPU-seconds per
million voxels (benchmarks/bench_fusion.py) against ≈ 1 s to import numba and load the cached kernels."""

Mix = Callable[
    [npt.NDArray[np.float32], npt.NDArray[np.intp], npt.NDArray[np.float32]], npt.NDArray[np.float32]
]
""":func:`knn_mix` or its compiled twin (same bytes)."""

RowProbs = Callable[[npt.NDArray[np.int64]], npt.NDArray[np.float32]]
"""``row_probs(rows) -> (len(rows), C) float32``: the distributions of the given (sorted unique) rows."""


def knn_mix(
    w: npt.NDArray[np.float32], idx: npt.NDArray[np.intp], p: npt.NDArray[np.float32]
) -> npt.NDArray[np.float32]:
    """Weighted sum of neighbour rows: ``out[n] = Σ_{j<k} w[n, j] · p[idx[n, j]]``.

    Accumulated in float32 from 0, one neighbour after the other (j = 0, 1, …, k − 1), each product
    rounded before it is added: exactly the steps of a CSR (n × R, k entries per row in neighbour order)
    @ dense (R × C) product, so the result is bit for bit that product's, without sorting the indices or
    building the matrix, and with only (n, C) temporaries instead of (n, k, C) ones.

    Args:
        w: (n, k) float32 weights.
        idx: (n, k) rows of ``p`` (each in ``[0, R)``).
        p: (R, C) float32 distributions.

    Returns:
        (n, C) float32.
    """
    n, k = w.shape
    out = np.zeros((n, p.shape[1]), np.float32)
    term = np.empty_like(out)
    # Columns of idx copied contiguous once; mode="clip" lets take() write into ``term`` without the
    # buffer that mode="raise" needs (the indices are in range by construction).
    cols = np.ascontiguousarray(idx.T)
    for j in range(k):
        np.take(p, cols[j], axis=0, out=term, mode="clip")
        np.multiply(term, w[:, j, None], out=term)
        out += term
    return out


def _rows_hit(idx: npt.NDArray[np.intp]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.intp]]:
    """``np.unique(idx, return_inverse=True)`` for non-negative indices, by marking them in a table over
    ``[idx.min(), idx.max()]`` instead of sorting (a chunk's neighbours span a few rows around it): sorted
    unique rows (R,) and idx renumbered into them (same shape as idx)."""
    lo = int(idx.min())
    span = int(idx.max()) - lo + 1
    local = idx - lo
    hit = np.zeros(span, np.bool_)
    hit[local.reshape(-1)] = True
    rows = np.flatnonzero(hit)
    number = np.empty(span, np.intp)
    number[rows] = np.arange(len(rows))
    return (rows + lo).astype(np.int64, copy=False), number[local]


def _smooth_chunk(
    tree: cKDTree,
    s: int,
    e: int,
    source: npt.NDArray[np.float32] | RowProbs,
    k: int,
    bound: float,
    *,
    mix: Mix = knn_mix,
) -> npt.NDArray[np.float32]:
    """Smoothed rows ``[s, e)``: query, weights, mix (:func:`knn_smooth`'s formula)."""
    v = tree.n
    n = e - s
    dists, idx = tree.query(tree.data[s:e], k=k, distance_upper_bound=bound, workers=1)
    w = knn_weights(np.asarray(dists).reshape(n, k))
    idx = np.asarray(idx).reshape(n, k)
    # Missing neighbours come back as index V; they have weight 0, so point them at the voxel itself.
    missing = idx >= v
    if missing.any():
        idx = np.where(missing, np.arange(s, e)[:, None], idx)
    if isinstance(source, np.ndarray):
        return mix(w, idx, source)
    rows, local = _rows_hit(idx)
    return mix(w, local, np.asarray(source(rows), dtype=np.float32))


def _smooth_chunks(
    centres: npt.ArrayLike,
    source: npt.NDArray[np.float32] | RowProbs,
    cfg: SmoothingConfig | None,
    chunk: int,
    compiled: bool | None = None,
) -> Iterator[tuple[int, npt.NDArray[np.float32]]]:
    """:func:`knn_smooth_blocks` with the distributions given whole (an array) or by rows (a callable)."""
    cfg = cfg or SmoothingConfig()
    if chunk < 1:
        raise ValueError(f"chunk must be ≥ 1, got {chunk}")
    pts = np.asarray(centres, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"centres (V, 3) expected, got {pts.shape}")
    v = pts.shape[0]
    if v == 0:
        return
    k = min(cfg.k, v)
    bound = np.inf if cfg.max_distance is None else float(cfg.max_distance)
    kern = compiled_kernels(compiled is not False, load=compiled is True or v >= COMPILED_MIN_VOXELS)
    mix: Mix = knn_mix if kern is None else kern.knn_mix
    # The tree holds its own float64 copy of the centres (the query converts float32 input to exactly
    # these values), so queries read it and the caller's float32 array is not needed past this point.
    tree = cKDTree(pts)
    del pts, centres
    starts = range(0, v, chunk)
    threads = (os.cpu_count() or 1) if cfg.workers == -1 else cfg.workers
    if threads == 1 or len(starts) == 1:
        for s in starts:
            yield s, _smooth_chunk(tree, s, min(v, s + chunk), source, k, bound, mix=mix)
        return
    # Whole chunks (query, weights and mix) run in the threads, not only the query: the numpy steps
    # release the GIL too, and a chunk's rows do not depend on which thread computed them. A few chunks
    # ahead are kept in flight so the threads stay busy while the caller consumes one.
    with ThreadPoolExecutor(threads) as pool:
        pending: deque[Future[npt.NDArray[np.float32]]] = deque()
        todo = iter(starts)
        for s in itertools.islice(todo, threads + 1):
            pending.append(pool.submit(_smooth_chunk, tree, s, min(v, s + chunk), source, k, bound, mix=mix))
        for s in starts:
            block = pending.popleft().result()
            nxt = next(todo, None)
            if nxt is not None:
                pending.append(
                    pool.submit(_smooth_chunk, tree, nxt, min(v, nxt + chunk), source, k, bound, mix=mix)
                )
            yield s, block


def knn_smooth_blocks(
    centres: npt.ArrayLike,
    row_probs: RowProbs,
    cfg: SmoothingConfig | None = None,
    chunk: int = SMOOTH_CHUNK,
) -> Iterator[tuple[int, npt.NDArray[np.float32]]]:
    """:func:`knn_smooth` one chunk of output rows at a time: yields ``(start, out[start:start + n])``.

    One cKDTree is built over all centres; each chunk of ``chunk`` voxels queries it, takes the
    distributions of the rows its neighbours hit (``row_probs``, so the caller never needs all V rows at
    once) and mixes them (:func:`knn_mix`: the entry order and float32 arithmetic of the sparse product
    ``csr(w, idx) @ probs``), so every row is bit for bit what :func:`knn_smooth` gives whatever ``chunk``
    and ``cfg.workers``. Chunks are computed by ``cfg.workers`` threads, a few ahead of the caller; they
    are yielded in order. ``row_probs`` may be called from those threads.

    Args:
        centres: (V, 3) voxel centres in metres (float32 values).
        row_probs: distributions of given rows (:data:`RowProbs`).
        cfg: k, distance bound and threads.
        chunk: voxels per chunk (≥ 1).
    """
    return _smooth_chunks(centres, row_probs, cfg, chunk)


def knn_smooth(
    centres: npt.ArrayLike,
    probs: npt.ArrayLike,
    cfg: SmoothingConfig | None = None,
    chunk: int = SMOOTH_CHUNK,
    *,
    compiled: bool | None = None,
) -> npt.NDArray[np.float32]:
    """Smooth per-voxel distributions over each voxel's k nearest voxels.

    ``out[n] = Σ_{j<k} w_nj · probs[idx_nj]`` with ``(d, idx)`` from a cKDTree query of the centres on
    themselves (``distance_upper_bound = max_distance`` when set) and ``w = knn_weights(d)``. Rows of the
    output sum to 1 when rows of ``probs`` do. Computed in chunks of ``chunk`` voxels
    (:func:`knn_smooth_blocks`; the result does not depend on ``chunk``).

    Args:
        centres: (V, 3) float32 voxel centres in metres.
        probs: (V, C) float32 per-voxel distributions.
        cfg: k, distance bound and threads.
        chunk: voxels per chunk.
        compiled: the weighted sums by the compiled :func:`knn_mix` (True; numpy where numba is missing),
            by numpy (False), or by the compiled one when already loaded or the grid has
            :data:`COMPILED_MIN_VOXELS` (None). The bytes are the same.

    Returns:
        (V, C) float32 smoothed distributions.
    """
    pts = np.asarray(centres, dtype=np.float32)
    p = np.asarray(probs, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or p.ndim != 2 or p.shape[0] != pts.shape[0]:
        raise ValueError(f"centres (V, 3) and probs (V, C) expected, got {pts.shape} and {p.shape}")
    if pts.shape[0] == 0:
        empty: npt.NDArray[np.float32] = p.copy()
        return empty
    out = np.empty(p.shape, np.float32)
    for s, block in _smooth_chunks(pts, p, cfg, chunk, compiled):
        out[s : s + len(block)] = block
    return out


def grid_row_probs(grid: VoxelGrid) -> RowProbs:
    """:data:`RowProbs` of a fused grid: ``softmax(logp[rows])`` per row, the values ``grid.probs()`` has in
    those rows (same float32 steps row by row)."""

    def rows_of(rows: npt.NDArray[np.int64]) -> npt.NDArray[np.float32]:
        block = grid.logp[rows].astype(np.float32)
        block -= block.max(axis=1, keepdims=True)
        np.exp(block, out=block)
        block /= block.sum(axis=1, keepdims=True)
        return block

    return rows_of


def smooth_grid_blocks(
    grid: VoxelGrid, cfg: SmoothingConfig | None = None, chunk: int = SMOOTH_CHUNK
) -> Iterator[tuple[int, npt.NDArray[np.float32]]]:
    """:func:`knn_smooth_blocks` of a fused grid's posteriors: ``(start, rows)`` float32 chunks of
    :func:`smooth_grid`'s output, without ever holding all V rows of probabilities. When the grid is
    memory-mapped (``VoxelGrid.load(mmap=True)``) its pages are dropped after each chunk
    (:func:`leap_core.npzio.release`), so resident memory stays at the tree plus one chunk."""
    blocks = knn_smooth_blocks(grid.centres(), grid_row_probs(grid), cfg, chunk)
    release(grid.keys)
    for s, block in blocks:
        release(grid.logp)
        yield s, block


def smooth_grid(
    grid: VoxelGrid, cfg: SmoothingConfig | None = None, chunk: int = SMOOTH_CHUNK
) -> npt.NDArray[np.float32]:
    """(V, C) float32 :func:`knn_smooth` of ``grid.probs()`` over ``grid.centres()``."""
    out = np.empty(grid.logp.shape, np.float32)
    for s, block in smooth_grid_blocks(grid, cfg, chunk):
        out[s : s + len(block)] = block
    return out


@dataclass(frozen=True, eq=False)
class SmoothedGrid:
    """A grid of per-voxel class distributions (the kNN-smoothed map; ``grid_smooth*.npz`` in a run folder).

    Attributes:
        keys: (V,) int64 sorted unique voxel keys.
        probs: (V, C) float16 class distributions (rows sum to 1 up to float16 rounding).
        voxel_size: voxel edge length in metres.

    Stored as an uncompressed npz with arrays ``keys``, ``probs`` and ``voxel_size`` (float64 scalar).
    """

    keys: npt.NDArray[np.int64]
    probs: npt.NDArray[np.float16]
    voxel_size: float

    def __post_init__(self) -> None:
        k, p = self.keys, self.probs
        if k.dtype != np.int64 or k.ndim != 1:
            raise ValueError(f"smoothed grid 'keys' must be 1-D int64, got {k.dtype} {k.shape}")
        if p.dtype != np.float16 or p.ndim != 2 or p.shape[0] != k.shape[0]:
            raise ValueError(
                f"smoothed grid 'probs' must be ({k.shape[0]}, C) float16, got {p.dtype} {p.shape}"
            )
        if not keys_sorted_unique(k):
            raise ValueError("smoothed grid voxel keys are not sorted and unique")
        if not (self.voxel_size > 0 and math.isfinite(self.voxel_size)):
            raise ValueError(f"smoothed grid 'voxel_size' must be positive, got {self.voxel_size}")

    @property
    def num_voxels(self) -> int:
        return int(self.keys.shape[0])

    @property
    def num_classes(self) -> int:
        return int(self.probs.shape[1])

    def centres(self) -> npt.NDArray[np.float32]:
        """(V, 3) float32 voxel centres in world metres."""
        return key_centres(self.keys, self.voxel_size)

    @cached_property
    def _labels(self) -> VoxelLabels:
        return VoxelLabels.from_probs(self.keys, self.probs)

    def voxel_labels(self) -> VoxelLabels:
        """Argmax class and its (float16) probability per voxel (:meth:`VoxelLabels.from_probs`); computed
        once per grid."""
        return self._labels

    def labels_at(self, query_keys: npt.ArrayLike) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
        """``(label (N,) int16, conf (N,) float32)`` of the voxel of each query key; ``UNLABELED`` and 0 where
        the voxel is not in the grid."""
        return self._labels.at(query_keys)

    def to_voxel_grid(self, logp_clip: float) -> VoxelGrid:
        """A :class:`VoxelGrid` whose ``probs()`` give back these distributions: ``logp = log p - max log p``,
        clipped below at ``-logp_clip`` like any fused grid (float16). Computed over chunks of rows, so only
        the float16 result is held whole."""
        out = np.empty(self.probs.shape, np.float16)
        chunk = 1 << 16
        for s in range(0, self.num_voxels, chunk):
            p = np.asarray(self.probs[s : s + chunk], dtype=np.float32)
            with np.errstate(divide="ignore"):
                lp = np.log(p)
            lp -= lp.max(axis=1, keepdims=True)
            np.maximum(lp, np.float32(-logp_clip), out=lp)
            out[s : s + chunk] = lp
            release(self.probs)
        return VoxelGrid(self.keys, out, float(self.voxel_size))

    @classmethod
    def from_voxel_grid(cls, grid: VoxelGrid) -> SmoothedGrid:
        """The posteriors ``softmax(logp)`` of a fused grid (not smoothed), as float16 distributions."""
        return cls(grid.keys, grid.probs(np.float16), float(grid.voxel_size))

    def save(self, path: str | Path) -> None:
        """Write ``keys``, ``probs`` and ``voxel_size`` as an uncompressed npz, atomically."""
        vs = np.asarray(self.voxel_size, np.float64)
        atomic_save_npz(path, keys=self.keys, probs=self.probs, voxel_size=vs)

    @classmethod
    def save_blocks(
        cls,
        path: str | Path,
        keys: npt.NDArray[np.int64],
        num_classes: int,
        blocks: Iterable[npt.NDArray[np.floating]],
        voxel_size: float,
    ) -> None:
        """Write the file :meth:`save` writes for ``SmoothedGrid(keys, probs, voxel_size)``, with ``probs``
        given as consecutive row blocks (cast to float16 as they come), so the (V, C) array is never whole
        in memory.

        Raises:
            ValueError: the blocks do not add up to ``len(keys)`` rows of ``num_classes`` columns.
        """
        probs = Streamed((len(keys), int(num_classes)), np.dtype(np.float16), blocks)
        save_npz(path, keys=keys, probs=probs, voxel_size=np.asarray(voxel_size, np.float64))

    @classmethod
    def load(cls, path: str | Path, voxel_size: float | None = None, *, mmap: bool = False) -> SmoothedGrid:
        """Read a grid written by :meth:`save` (``probs`` of another float type are cast to float16).

        Args:
            path: the npz file.
            voxel_size: used when the file holds none (files written before it was stored).
            mmap: map ``keys`` and ``probs`` read-only from the file instead of reading them
                (:func:`leap_core.npzio.load_npz`; compressed files are read as usual).

        Raises:
            DatasetError: unreadable or malformed file, naming it.
        """
        try:
            names = ["keys", "probs"] + (["voxel_size"] if has_member(path, "voxel_size") else [])
            z = load_npz(path, names, mmap=mmap)
            keys, probs = z["keys"], z["probs"]
            stored = float(z["voxel_size"]) if "voxel_size" in z else None
        except (OSError, KeyError, ValueError, TypeError, EOFError) as exc:
            raise DatasetError(path, f"unreadable smoothed grid ({exc})") from exc
        vs = stored if stored is not None else voxel_size
        if vs is None:
            raise DatasetError(path, "no voxel_size in the smoothed grid")
        if np.issubdtype(probs.dtype, np.floating):
            probs = probs.astype(np.float16, copy=False)
        try:
            return cls(keys, probs, vs)
        except ValueError as exc:
            raise DatasetError(path, str(exc)) from exc


__all__ = [
    "SMOOTH_CHUNK",
    "RowProbs",
    "SmoothedGrid",
    "SmoothingConfig",
    "grid_row_probs",
    "knn_mix",
    "knn_smooth",
    "knn_smooth_blocks",
    "knn_weights",
    "smooth_grid",
    "smooth_grid_blocks",
]
