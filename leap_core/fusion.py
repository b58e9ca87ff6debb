"""Sparse voxel grid with Bayesian log-space label fusion (docs/METHOD.md stage B.3).

Per voxel n and class i the paper's update is
``V_n(i) ← V_n(i)·P(i|X_k) / Σ_j V_n(j)·P(j|X_k)``. In log space this is a sum,
``L_n(i) = Σ_k log P(i|X_k)``, normalised only when read: ``V_n = softmax(L_n)``. A sum is
order-independent, so any number of scans can be reduced in one batch, equal (up to float rounding) to
scan-by-scan updates.

Speed (docs/METHOD.md, "Performance facts"): logs are never taken per point. One image's painted points
carry an index ``rows`` into a small per-image table of distinct distributions (one per combination of
covering masks, :mod:`leap_core.projection`); the log is taken per table row (:func:`log_table`).
:func:`fuse` then packs (voxel, table row) into one int64 per point, sorts once, counts equal pairs and
multiplies the (voxel × table-row) count matrix with the stacked log tables as a sparse product, so per point
only 8 bytes are sorted and never C floats moved. With numba installed, large chunks run the same operations
compiled (:mod:`leap_core.fusion_kernels`: a radix sort, one-pass sums, merge and finalise; same bytes).

Voxel keys pack ``floor(xyz / voxel_size)`` in 21 bits per axis (offset by 2²⁰ so negatives work): x in
bits 42-62, y in 21-41, z in 0-20. Sorting keys therefore sorts voxels by (x, y, z).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple, TypeVar

import numpy as np
import numpy.typing as npt
import scipy.sparse

from leap_core.bounds import check_bounds, within
from leap_core.errors import ConfigError, DatasetError
from leap_core.geometry import affine_points
from leap_core.io_utils import atomic_save_npz
from leap_core.npzio import Streamed, load_npz, release, save_npz
from leap_core.types import UNLABELED

AXIS_BITS = 21
"""Bits per axis in a voxel key."""
AXIS_OFFSET = 1 << (AXIS_BITS - 1)
"""Added to each integer voxel coordinate so that coordinates in [-2²⁰, 2²⁰) become non-negative."""
_AXIS_MASK = (1 << AXIS_BITS) - 1


@dataclass(frozen=True)
class FusionConfig:
    """Parameters of the voxel grid and of the Bayesian update."""

    voxel_size: float = field(default=0.2, metadata=within(0.01, 10, unit="m"))
    """Voxel edge length in metres (the paper uses 0.2 m). At least 1 cm, below a LiDAR's precision; a
    voxel key holds ±2²⁰ voxels per axis, ±10 km at that size."""
    prob_floor: float = field(default=1e-3, metadata=within(0, 1, low_open=True, high_open=True))
    """Observation probabilities are clipped to ≥ this before the log (then renormalised), so one confident
    wrong mask adds at most log(1/floor) ≈ 6.9 nats against a class and cannot veto it forever."""
    logp_clip: float = field(default=20.0, metadata=within(0, 100, low_open=True, unit="nats"))
    """Stored log-posteriors are shifted to a row max of 0 and clipped below at ``-logp_clip``: e⁻²⁰ ≈ 2e-9
    is probability zero for labelling, and the bound keeps float16 storage exact to ≈ 0.016 nats (at the
    upper bound of 100, to ≈ 0.06)."""
    chunk_points: int = field(default=2_000_000, metadata=within(1, 20_000_000))
    """:func:`fuse` reduces observations in chunks of about this many points; bounds working memory
    (≈ 36 bytes per point of a chunk, ≈ 720 MB at the upper bound) without changing the result beyond
    float32 rounding. 2 M (≈ 72 MB; ≈ 150 demo frames of painted points): on the 1,000-frame scale sequence
    fuse took 3.8 s with 2 M-point chunks against 4.2-4.8 s with 8 M and 4.2-5.5 s with 1 M (larger chunks
    sort more keys at once, smaller ones fold into the run's key set more often), and its chunk working set
    fell by ≈ 200 MB."""

    def __post_init__(self) -> None:
        check_bounds(self)


@dataclass(frozen=True)
class FusionPaths:
    """Where a fusion chunk's reduction (:func:`fuse`, :func:`fuse_to_file`, :func:`reduce_block`) switches
    between two implementations of the same maths. The result does not depend on them (tests/test_fusion.py
    checks each pair of paths agrees exactly); they exist so tests can reach both sides of each switch on
    small data. Not part of :class:`FusionConfig` (nor of a run's fingerprint): they change speed, never
    output."""

    pack_max_bits: int = 62
    """A fusion chunk packs (voxel, table row) into one int64 per point when its per-axis key ranges plus the
    row bits fit in this many bits; otherwise voxels are first numbered with ``np.unique`` (wide extents,
    e.g. coordinates near ±2²⁰ voxels). 0 = always ``np.unique``."""
    block: int = 1 << 16
    """Elements per block in the in-place key-packing passes (the temporaries stay in L2 cache)."""
    compiled: bool = True
    """Reduce, merge and finalise with the compiled kernels of :mod:`leap_core.fusion_kernels` when numba
    (the ``fast`` extra) is installed; False = the numpy path, which runs without numba."""
    compiled_min_points: int = 2_000_000
    """A chunk of fewer points loads the kernels only if this process already has (merges and finalising
    never load them): importing numba and loading the cached kernels costs ≈ 1 s, which the kernels
    (≈ 75 ns less CPU per point, benchmarks/bench_fusion.py) win back over ≈ 13 M points. A full default
    chunk is the sign of a large fusion (a sequence that fills one mostly fills many; the demo's 60 frames
    fill none), so small fusions (tests, short sequences) stay on numpy. 0 = always load them."""

    def __post_init__(self) -> None:
        if not 0 <= self.pack_max_bits <= 62:
            raise ConfigError(f"must be in 0..62, got {self.pack_max_bits}", field=("pack_max_bits",))
        if self.block < 1:
            raise ConfigError(f"must be ≥ 1, got {self.block}", field=("block",))
        if self.compiled_min_points < 0:
            raise ConfigError(f"must be ≥ 0, got {self.compiled_min_points}", field=("compiled_min_points",))


# ---------------------------------------------------------------------------------------------- keys
def voxel_keys(xyz_world: npt.ArrayLike, voxel_size: float) -> npt.NDArray[np.int64]:
    """Pack the voxel index of each point into one int64.

    Args:
        xyz_world: (N, 3) (or (N, ≥3): extra columns ignored) world coordinates in metres.
        voxel_size: voxel edge length in metres.

    Returns:
        (N,) int64 ``key = (ix+2²⁰) << 42 | (iy+2²⁰) << 21 | (iz+2²⁰)`` with ``i = floor(xyz / voxel_size)``.

    Raises:
        ValueError: a coordinate is non-finite or beyond ±2²⁰ voxels (±209 km at 0.2 m).
    """
    xyz = np.asarray(xyz_world)
    if xyz.ndim != 2 or xyz.shape[1] < 3:
        raise ValueError(f"xyz_world must be (N, 3), got shape {xyz.shape}")
    # float64 division: float32 would misplace points lying within ~1e-7 relative of a voxel face.
    idx = np.floor(xyz[:, :3].astype(np.float64) / float(voxel_size))
    if idx.size and not (np.isfinite(idx).all() and idx.min() >= -AXIS_OFFSET and idx.max() < AXIS_OFFSET):
        raise ValueError(
            f"points must be finite and within ±{AXIS_OFFSET * voxel_size:.0f} m of the origin "
            f"(voxel_size {voxel_size}); re-base world coordinates on the first pose"
        )
    i = idx.astype(np.int64) + AXIS_OFFSET
    return (i[:, 0] << (2 * AXIS_BITS)) | (i[:, 1] << AXIS_BITS) | i[:, 2]


def rows_in_sorted(sorted_keys: npt.ArrayLike, query_keys: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Index of each query key in the sorted unique ``sorted_keys`` (V,), -1 where absent; shape of the query.

    Example: sorted_keys [3, 7, 9], queries [9, 4, 3, 10] → [2, -1, 0, -1].
    """
    keys = np.asarray(sorted_keys, dtype=np.int64)
    q = np.asarray(query_keys, dtype=np.int64)
    if keys.size == 0:
        return np.full(q.shape, -1, np.int64)
    pos = np.minimum(np.searchsorted(keys, q), keys.size - 1)
    return np.where(keys[pos] == q, pos, -1).astype(np.int64)


def key_coords(keys: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """(V, 3) int64 voxel coordinates ``floor(xyz / voxel_size)`` of packed keys (inverse of the packing)."""
    k = np.asarray(keys, dtype=np.int64)
    out = np.empty((k.shape[0], 3), dtype=np.int64)
    out[:, 0] = (k >> (2 * AXIS_BITS)) & _AXIS_MASK
    out[:, 1] = (k >> AXIS_BITS) & _AXIS_MASK
    out[:, 2] = k & _AXIS_MASK
    out -= AXIS_OFFSET
    return out


def key_centres(keys: npt.ArrayLike, voxel_size: float, chunk: int = 1 << 18) -> npt.NDArray[np.float32]:
    """(V, 3) float32 voxel centres ``(i + 0.5) · voxel_size`` of packed keys, computed over chunks of
    ``chunk`` keys so the int64 / float64 temporaries stay small beside the (V, 3) result."""
    k = np.asarray(keys, dtype=np.int64)
    out = np.empty((k.shape[0], 3), np.float32)
    for s in range(0, k.shape[0], chunk):
        out[s : s + chunk] = (key_coords(k[s : s + chunk]) + 0.5) * float(voxel_size)
    return out


def keys_sorted_unique(keys: npt.NDArray[np.int64], chunk: int = 1 << 20) -> bool:
    """Whether ``keys`` (V,) strictly increase, checked over chunks (no (V,) temporaries)."""
    for s in range(0, max(keys.shape[0] - 1, 0), chunk):
        block = keys[s : s + chunk + 1]
        if not (block[1:] > block[:-1]).all():
            return False
    return True


# ---------------------------------------------------------------------------------------------- grid
@dataclass
class VoxelGrid:
    """The fused map: one row of accumulated log-likelihoods per observed voxel.

    Attributes:
        keys: (V,) int64 sorted unique voxel keys (:func:`voxel_keys`).
        logp: (V, C) float16 ``L_n - max_i L_n(i)``, clipped below at ``-FusionConfig.logp_clip``.
        voxel_size: voxel edge length in metres the keys were made with.

    Storage is 8 + 2·C bytes per voxel (48 at C = 20).
    """

    keys: npt.NDArray[np.int64]
    logp: npt.NDArray[np.float16]
    voxel_size: float = field(default=0.2)

    @classmethod
    def empty(cls, num_classes: int, voxel_size: float = 0.2) -> VoxelGrid:
        return cls(np.zeros(0, np.int64), np.zeros((0, num_classes), np.float16), float(voxel_size))

    @property
    def num_classes(self) -> int:
        return int(self.logp.shape[1])

    @property
    def num_voxels(self) -> int:
        return int(self.keys.shape[0])

    def __len__(self) -> int:
        return self.num_voxels

    @property
    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.logp.nbytes)

    def centres(self) -> npt.NDArray[np.float32]:
        """(V, 3) float32 voxel centres in world metres."""
        return key_centres(self.keys, self.voxel_size)

    def probs(self, dtype: npt.DTypeLike = np.float32, chunk: int = 1 << 20) -> npt.NDArray[Any]:
        """(V, C) ``softmax(logp)`` per row (the normalised posterior), computed in float32 over chunks of
        ``chunk`` rows and stored as ``dtype`` (float16 halves a viewer's copy)."""
        out = np.empty(self.logp.shape, dtype)
        for s in range(0, self.num_voxels, chunk):
            block = self.logp[s : s + chunk].astype(np.float32)
            block -= block.max(axis=1, keepdims=True)
            np.exp(block, out=block)
            block /= block.sum(axis=1, keepdims=True)
            out[s : s + chunk] = block
        return out

    def labels_and_confidence(
        self, chunk: int = 1 << 20
    ) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
        """Argmax class (V,) int16 (ties: lowest index) and its posterior probability (V,) float32.

        conf = max_i softmax(logp)_i = 1 / Σ_j exp(logp_j - max logp), computed in chunks to bound memory.
        """
        v = self.num_voxels
        labels = np.empty(v, np.int16)
        conf = np.empty(v, np.float32)
        for s in range(0, v, chunk):
            block = self.logp[s : s + chunk].astype(np.float32)
            labels[s : s + chunk] = block.argmax(axis=1)
            block -= block.max(axis=1, keepdims=True)
            conf[s : s + chunk] = 1.0 / np.exp(block).sum(axis=1)
        return labels, conf

    def voxel_labels(self, chunk: int = 1 << 20) -> VoxelLabels:
        """:meth:`labels_and_confidence` of every voxel, ready for :meth:`VoxelLabels.at` lookups."""
        return VoxelLabels(self.keys, *self.labels_and_confidence(chunk))

    def labels_at(self, query_keys: npt.ArrayLike) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
        """Label and confidence of the voxel of each query key (see :meth:`VoxelLabels.at`).

        Computes every voxel's label first: for many lookups take :meth:`voxel_labels` once.
        """
        return self.voxel_labels().at(query_keys)

    def lookup(self, query_keys: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """(N,) int64 row of each query key in this grid, -1 where the voxel was never observed."""
        return rows_in_sorted(self.keys, query_keys)

    def save(self, path: str | Path) -> None:
        """Write ``keys``, ``logp`` and ``voxel_size`` as an uncompressed npz, atomically."""
        atomic_save_npz(path, keys=self.keys, logp=self.logp, voxel_size=np.float64(self.voxel_size))

    @classmethod
    def load(cls, path: str | Path, *, mmap: bool = False) -> VoxelGrid:
        """Read a grid written by :meth:`save`; a malformed file raises :class:`DatasetError`.

        ``mmap=True`` maps ``keys`` and ``logp`` read-only from the file (:func:`leap_core.npzio.load_npz`;
        a compressed file is read as usual): a whole-grid stage then holds only the pages it touches, and
        :func:`leap_core.npzio.release` drops them after a pass.
        """
        try:
            z = load_npz(path, ["keys", "logp", "voxel_size"], mmap=mmap)
            keys, logp, vs = z["keys"], z["logp"], float(z["voxel_size"])
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise DatasetError(path, f"unreadable voxel grid ({exc})") from exc
        if keys.dtype != np.int64 or keys.ndim != 1:
            raise DatasetError(path, f"voxel grid 'keys' must be 1-D int64, got {keys.dtype} {keys.shape}")
        if logp.dtype != np.float16 or logp.ndim != 2 or logp.shape[0] != keys.shape[0]:
            raise DatasetError(
                path, f"voxel grid 'logp' must be ({keys.shape[0]}, C) float16, got {logp.dtype} {logp.shape}"
            )
        if not keys_sorted_unique(keys):
            raise DatasetError(path, "voxel grid 'keys' are not sorted and unique")
        if not (vs > 0 and math.isfinite(vs)):
            raise DatasetError(path, f"voxel grid 'voxel_size' must be positive, got {vs}")
        return cls(keys, logp, vs)


@dataclass(frozen=True, eq=False)
class VoxelLabels:
    """Per voxel of a grid: its argmax class and that class's probability; looked up per point by key.

    Attributes:
        keys: (V,) int64 sorted unique voxel keys.
        label: (V,) int16 argmax class.
        conf: (V,) float32 probability of that class.
    """

    keys: npt.NDArray[np.int64]
    label: npt.NDArray[np.int16]
    conf: npt.NDArray[np.float32]

    @classmethod
    def from_probs(cls, keys: npt.ArrayLike, probs: npt.ArrayLike, chunk: int = 1 << 20) -> VoxelLabels:
        """``label = argmax_i probs[:, i]`` (ties: lowest index, numpy's rule) and ``conf = probs[v, label]``.

        Args:
            keys: (V,) int64 sorted unique voxel keys.
            probs: (V, C) class probabilities, compared in their own dtype (float16 stays float16, so
                ties are those of the stored values); ``conf`` is that value as float32.
            chunk: rows per step (bounds the temporaries on large grids; the result does not depend on it).
        """
        p = np.asarray(probs)
        k = np.asarray(keys, dtype=np.int64)
        if p.ndim != 2 or k.shape != (p.shape[0],):
            raise ValueError(f"keys (V,) and probs (V, C) expected, got {k.shape} and {p.shape}")
        label = np.empty(p.shape[0], np.int16)
        conf = np.empty(p.shape[0], np.float32)
        for s in range(0, p.shape[0], chunk):
            block = p[s : s + chunk]
            am = block.argmax(axis=1)
            label[s : s + chunk] = am
            conf[s : s + chunk] = np.take_along_axis(block, am[:, None], axis=1)[:, 0]
            release(p)  # a memory-mapped grid: the pass holds one chunk of it, not all of it
        return cls(k, label, conf)

    def at(self, query_keys: npt.ArrayLike) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
        """``(label (N,) int16, conf (N,) float32)`` of the voxel of each query key (N,); ``UNLABELED``
        and 0 where the voxel is not in the grid (never observed)."""
        rows = rows_in_sorted(self.keys, query_keys)
        hit = rows >= 0
        label = np.full(rows.shape, UNLABELED, np.int16)
        conf = np.zeros(rows.shape, np.float32)
        label[hit] = self.label[rows[hit]]
        conf[hit] = self.conf[rows[hit]]
        return label, conf


_V = TypeVar("_V", bound=np.generic)


def last_per_key(
    keys: npt.ArrayLike, values: npt.NDArray[_V]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[_V]]:
    """Deduplicate ``keys`` (N,) keeping, for each distinct key, the value (N,) that comes LAST.

    The rule "a later correction of the same voxel wins" (and "the point painted last wins a pixel"):
    numpy does not promise which write wins when a fancy assignment repeats an index, so callers that
    mean "the latest wins" deduplicate first. Example: keys [4, 1, 4], values [a, b, c] → [1, 4], [b, c].

    Returns:
        ``(unique keys (U,) int64 sorted, their last values (U,))``.
    """
    k = np.asarray(keys, dtype=np.int64).reshape(-1)
    v = np.asarray(values).reshape(-1)
    if v.shape != k.shape:
        raise ValueError(f"keys {k.shape} and values {v.shape} must have the same length")
    uniq, first_in_reversed = np.unique(k[::-1], return_index=True)
    return uniq, v[::-1][first_in_reversed]


def world_points(points: npt.ArrayLike, pose: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """World coordinates of LiDAR-frame points: ``x_w = R · p + t`` with ``pose = [[R, t], [0, 1]]``.

    Args:
        points: (N, ≥3) LiDAR-frame points (extra columns such as remission are ignored).
        pose: (4, 4) LiDAR → world transform.

    Returns:
        (N, 3) float64.
    """
    # Blocked (leap_core.geometry): the same bytes as the one-call product, without OpenBLAS handing an
    # (N, 3) × (3, 3) product to threads that wait on each other on busy cores (fuse, export counts, the
    # viewer's region tools all place whole scans).
    return affine_points(points, np.asarray(pose, dtype=np.float64)[:3])


# ------------------------------------------------------------------------------------- observations
class Observations(NamedTuple):
    """One image's painted points, in voxel keys.

    Attributes:
        keys: (P,) int64 voxel key of each observed point.
        rows: (P,) int32 row of ``log_table`` holding the point's observation.
        log_table: (K, C) float32 normalised log-probabilities (:func:`log_table`).
    """

    keys: npt.NDArray[np.int64]
    rows: npt.NDArray[np.int32]
    log_table: npt.NDArray[np.float32]


def log_table(table: npt.ArrayLike, floor: float) -> npt.NDArray[np.float32]:
    """Floor-clipped, renormalised log of a table of distributions.

    ``out[k, i] = log(max(t[k, i], floor)) - log(Σ_j max(t[k, j], floor))`` for ``table (K, C)``.
    A uniform row maps to a constant row, which changes no posterior.
    """
    t = np.maximum(np.asarray(table, dtype=np.float32), np.float32(floor))
    if t.ndim != 2:
        raise ValueError(f"table must be (K, C), got shape {t.shape}")
    out: npt.NDArray[np.float32] = (np.log(t) - np.log(t.sum(axis=1, keepdims=True))).astype(np.float32)
    return out


# -------------------------------------------------------------------------------------------- fusion
def compiled_kernels(compiled: bool, load: bool = True) -> ModuleType | None:
    """:mod:`leap_core.fusion_kernels` when ``compiled`` and numba is installed, else None (numpy path);
    with ``load`` False only when this process has already imported it. Imported on first use: reading a
    config or a grid never loads numba."""
    if not compiled:
        return None
    if not load:
        loaded: ModuleType | None = sys.modules.get("leap_core.fusion_kernels")
        return loaded
    try:
        from leap_core import fusion_kernels  # noqa: PLC0415  numba is optional and slow to import
    except ImportError as exc:
        if (exc.name or "").partition(".")[0] not in ("numba", "llvmlite"):
            raise
        return None
    return fusion_kernels


def _bits(n: int) -> int:
    """Bits needed to hold integers 0..n (n ≥ 0)."""
    return max(int(n).bit_length(), 0)


def _reduce_chunk(  # noqa: PLR0915  steps 1-3 in one body, each freeing its buffers (del) when done
    obs: list[Observations], weight: float, paths: FusionPaths
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """Σ over a chunk of observations: (sorted unique keys (V,), weight·Σ log-tables (V, C) float32).

    1. Pack (voxel, global table row) into one int64 per point: each key axis is shifted to its range within
       the chunk (a sequence's few-hundred-metre extent needs ≈ 32 bits, leaving ≥ 30 bits for rows).
    2. Sort; equal neighbours are repeated (voxel, row) pairs: their run lengths are the counts.
    3. Σ_pairs count · log_table[row] per voxel as a sparse (V × K) @ (K × C) product.
    The packing runs in place over blocks of ``paths.block`` elements; when the packed pair needs more than
    ``paths.pack_max_bits`` bits, voxels are numbered by ``np.unique`` instead (same sums). The chunk's
    whole working memory, output included, measured ≈ 36 bytes per point at 5M points
    (benchmarks/bench_fusion.py).
    """
    n = sum(len(o.keys) for o in obs)
    offsets = np.cumsum([0] + [o.log_table.shape[0] for o in obs])
    k_total = int(offsets[-1])
    rbits = _bits(k_total - 1)
    comp = np.empty(n, np.int64)
    rows = np.empty(n, np.int32 if k_total < 2**31 else np.int64)
    s = 0
    for o, off in zip(obs, offsets[:-1], strict=True):
        e = s + len(o.keys)
        comp[s:e] = o.keys
        np.add(o.rows, off, out=rows[s:e], casting="unsafe")
        s = e
    table = np.concatenate([o.log_table for o in obs], axis=0).astype(np.float32, copy=False)
    kern = compiled_kernels(paths.compiled, load=n >= paths.compiled_min_points)

    block = paths.block
    if kern is not None:
        lo, hi = kern.axis_bounds(comp)
    else:
        lo = np.full(3, np.iinfo(np.int64).max)
        hi = np.full(3, np.iinfo(np.int64).min)
        for b in range(0, n, block):
            blk = comp[b : b + block]
            for a, c in enumerate(_axes(blk)):
                lo[a] = min(lo[a], int(c.min()))
                hi[a] = max(hi[a], int(c.max()))
    cbits = [_bits(int(h - m)) for h, m in zip(hi, lo, strict=True)]
    uniq_keys = None
    if sum(cbits) + rbits <= paths.pack_max_bits:
        shifts = (cbits[1] + cbits[2] + rbits, cbits[2] + rbits, rbits)
        pair_bits = sum(cbits) + rbits
        if kern is not None:
            kern.pack_pairs(comp, rows, lo, np.array(shifts, np.int64))
        else:
            for b in range(0, n, block):
                blk = comp[b : b + block]
                x, y, z = _axes(blk)
                x -= lo[0]
                x <<= shifts[0]
                y -= lo[1]
                y <<= shifts[1]
                z -= lo[2]
                z <<= shifts[2]
                x |= y
                x |= z
                np.bitwise_or(x, rows[b : b + block], out=blk)
    else:
        uniq_keys, vox = np.unique(comp, return_inverse=True)
        if _bits(len(uniq_keys)) + rbits > 62:
            raise ValueError(f"too many table rows ({k_total}) in one fusion chunk; lower chunk_points")
        comp = (vox.astype(np.int64) << rbits) | rows
        pair_bits = _bits(len(uniq_keys) - 1) + rbits
    del rows

    if kern is not None:
        comp = kern.radix_sort(comp, pair_bits)
        n_vox = int(kern.count_voxels(comp, rbits))
        vox_ids = np.empty(n_vox, np.int64)
        # With spare rows: the first chunk's sums become fuse's accumulator, which then grows in place.
        sums = np.zeros((n_vox + int(n_vox * SPARE_ROWS), table.shape[1]), np.float32)[:n_vox]
        kern.reduce_pairs(comp, rbits, table, np.float32(weight), vox_ids, sums)
        del comp
        return _pair_keys(vox_ids, uniq_keys, lo, cbits), sums
    comp.sort()
    first = np.empty(n, bool)
    first[0] = True
    np.not_equal(comp[1:], comp[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    del first
    pairs = comp[starts]
    del comp
    counts = np.diff(np.append(starts, n)).astype(np.float32)
    pair_rows = pairs & ((1 << rbits) - 1)
    pair_vox = pairs >> rbits
    vfirst = np.empty(len(pairs), bool)
    vfirst[0] = True
    np.not_equal(pair_vox[1:], pair_vox[:-1], out=vfirst[1:])
    vstarts = np.flatnonzero(vfirst)
    vox_ids = pair_vox[vstarts]
    indptr = np.append(vstarts, len(pairs)).astype(np.int64)
    counts *= np.float32(weight)
    mat = scipy.sparse.csr_matrix((counts, pair_rows, indptr), shape=(len(vstarts), k_total))
    sums = np.asarray(mat @ table, dtype=np.float32)
    return _pair_keys(vox_ids, uniq_keys, lo, cbits), sums


def _pair_keys(
    vox_ids: npt.NDArray[np.int64],
    uniq_keys: npt.NDArray[np.int64] | None,
    lo: npt.NDArray[np.int64],
    cbits: list[int],
) -> npt.NDArray[np.int64]:
    """Voxel keys of a chunk's voxel ids: ``uniq_keys[ids]`` when voxels were numbered by ``np.unique``,
    else the packed axis fields (``cbits`` wide, offset by ``lo``) turned back into keys."""
    if uniq_keys is not None:
        out: npt.NDArray[np.int64] = uniq_keys[vox_ids]
        return out
    bz, by = cbits[2], cbits[1]
    x = (vox_ids >> (by + bz)) + lo[0]
    y = ((vox_ids >> bz) & ((1 << by) - 1)) + lo[1]
    z = (vox_ids & ((1 << bz) - 1)) + lo[2]
    keys: npt.NDArray[np.int64] = (x << (2 * AXIS_BITS)) | (y << AXIS_BITS) | z
    return keys


def union_sorted(a: npt.NDArray[np.int64], b: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """``np.union1d(a, b)`` for sorted, duplicate-free int64 ``a`` (N,) and ``b`` (M,), in O(N + M log N).

    ``np.union1d`` concatenates and re-sorts (numpy ≥ 2.3: hashes) both arrays; a run that folds chunk
    after chunk into a growing key set paid that for the whole set each time, so its cost per chunk grew
    with the sequence. Here only ``b``'s keys missing from ``a`` are located (binary search) and inserted.
    Example: a = [1, 4, 9], b = [0, 4, 10] → [0, 1, 4, 9, 10].
    """
    if len(a) == 0:
        return np.array(b, np.int64)
    pos = np.searchsorted(a, b)
    present = np.zeros(len(b), bool)
    inside = pos < len(a)
    present[inside] = a[pos[inside]] == b[inside]
    return np.insert(a, pos[~present], b[~present])


def _axes(keys: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int64], ...]:
    """Integer axis fields (x, y, z) of packed keys, offset (non-negative) form."""
    return keys >> (2 * AXIS_BITS), (keys >> AXIS_BITS) & _AXIS_MASK, keys & _AXIS_MASK


_MOVE_BLOCK = 1 << 16
"""Rows per block when :func:`_merge` shifts the accumulator's rows in place, and per block of
:func:`_finalise` (times C elements at most 1 << 22): the temporaries of both stay a few MB."""


def _grow(arr: npt.NDArray[Any], rows: int) -> npt.NDArray[Any]:
    """``arr`` with ``rows`` rows, the first ``len(arr)`` kept: resized in place when it owns its memory
    (``realloc``, which for large blocks remaps pages instead of copying them, so the accumulator never
    exists twice), else copied into a new array. Callers hold no view of ``arr``."""
    if arr.flags.owndata and arr.flags.c_contiguous and arr.base is None:
        try:
            arr.resize((rows, *arr.shape[1:]), refcheck=False)
            return arr
        except ValueError:
            pass
    out = np.zeros((rows, *arr.shape[1:]), arr.dtype)
    out[: len(arr)] = arr
    return out


def _owner(arr: npt.NDArray[Any], views: bool) -> npt.NDArray[Any] | None:
    """The array owning ``arr``'s memory when ``arr`` is it or, with ``views`` (``arr`` is this module's
    accumulator, never a caller's array), a leading slice of it (both C-contiguous, same row shape); else
    None. The buffer an accumulator with spare rows (:func:`_grow_spare`) lives in."""
    if arr.flags.owndata and arr.base is None and arr.flags.c_contiguous:
        return arr
    b = arr.base
    if (
        views
        and isinstance(b, np.ndarray)
        and b.base is None
        and b.flags.owndata
        and b.flags.c_contiguous
        and arr.flags.c_contiguous
        and b.dtype == arr.dtype
        and b.shape[1:] == arr.shape[1:]
        and arr.ctypes.data == b.ctypes.data
    ):
        return b
    return None


SPARE_ROWS = 2.0
"""Spare rows (a share of the rows needed) that :func:`_grow_spare` and the compiled chunk sums reserve.
Never-touched rows cost address space, not memory; they spare the ``realloc`` of a large accumulator,
which here copies it into fresh pages (numpy asks for transparent huge pages on large arrays, and moving
those cost ≈ 40 ms per 44 MB on idle cores, 135 ms on busy ones). Twice: a street drive's second chunk
nearly doubles the first one's voxels (298 k → 548 k → 674 k in benchmarks/bench_fusion.py); with half
as many spare rows the first merge still reallocated, and fuse took 18 % more CPU time."""


def _grow_spare(arr: npt.NDArray[Any], rows: int) -> npt.NDArray[Any]:
    """``arr`` (an accumulator of this module) with ``rows`` rows, the first ``len(arr)`` kept and the rest
    undefined: a longer slice of its buffer when that has the rows (:func:`_owner`), else the buffer
    resized in place with :data:`SPARE_ROWS` more (:func:`_grow` when no buffer is owned). Callers hold no
    other view of it."""
    owner = _owner(arr, views=True)
    if owner is None:
        return _grow(arr, rows)
    if owner.shape[0] < rows:
        owner.resize((rows + int(rows * SPARE_ROWS), *owner.shape[1:]), refcheck=False)
    return owner[:rows]


def merge_sparse(
    keys_a: npt.NDArray[np.int64],
    accs_a: list[npt.NDArray[Any]],
    keys_b: npt.NDArray[np.int64],
    accs_b: list[npt.NDArray[Any]],
) -> tuple[npt.NDArray[np.int64], list[npt.NDArray[Any]]]:
    """Sum two sparse accumulators with sorted unique keys, growing ``keys_a`` / ``accs_a`` in place.

    ``accs_a[j]`` and ``accs_b[j]`` hold one row per key (any trailing shape, same dtype). A key only in b
    gets ``0 + b``, one in both ``a + b``; with a empty, b is returned as it is. The old rows move to their
    merged positions from the last block backwards (each lands at or after where it was, so no row is
    overwritten before it moved): the accumulators are resized in place (:func:`_grow`), never copied
    whole, so merging needs the merged size plus b, not twice the merged size. The caller must hold no
    view of ``keys_a`` / ``accs_a``. Example: keys [2, 5] rows [1, 1] + keys [3, 5] rows [4, 4] → keys
    [2, 3, 5] rows [1, 4, 5].
    """
    if len(keys_a) == 0:
        return keys_b, accs_b
    pos = np.minimum(np.searchsorted(keys_a, keys_b), len(keys_a) - 1)
    found = keys_a[pos] == keys_b
    if found.all():
        for acc_a, acc_b in zip(accs_a, accs_b, strict=True):
            acc_a[pos] += acc_b
        return keys_a, accs_a
    new = keys_b[~found]
    del pos, found
    n, m = len(keys_a), len(new)
    # Merged position of each new key: its rank among the new keys plus the old keys below it.
    dest_new = np.arange(m) + np.searchsorted(keys_a, new)
    keys_a = _grow(keys_a, n + m)
    accs_a = [_grow(acc, n + m) for acc in accs_a]
    for s in range(((n - 1) // _MOVE_BLOCK) * _MOVE_BLOCK, -1, -_MOVE_BLOCK):
        e = min(n, s + _MOVE_BLOCK)
        k_blk = keys_a[s:e].copy()
        dest = np.arange(s, e) + np.searchsorted(new, k_blk)
        for acc in accs_a:
            acc[dest] = acc[s:e].copy()
        keys_a[dest] = k_blk
    keys_a[dest_new] = new
    rows_b = np.searchsorted(keys_a, keys_b)
    for acc_a, acc_b in zip(accs_a, accs_b, strict=True):
        acc_a[dest_new] = 0
        acc_a[rows_b] += acc_b
    return keys_a, accs_a


def _merge(
    keys_a: npt.NDArray[np.int64],
    acc_a: npt.NDArray[np.float32],
    keys_b: npt.NDArray[np.int64],
    acc_b: npt.NDArray[np.float32],
    compiled: bool = True,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """:func:`merge_sparse` of one (V, C) float32 accumulator; with ``compiled`` and numba, the same sums
    by one backward pass over the grown arrays (:func:`leap_core.fusion_kernels.merge_backward`)."""
    kern = compiled_kernels(compiled, load=False)
    if kern is None or len(keys_a) == 0 or acc_a.dtype != np.float32 or acc_b.dtype != np.float32:
        keys, (acc,) = merge_sparse(keys_a, [acc_a], keys_b, [acc_b])
        return keys, acc
    n = len(keys_a)
    m = int(kern.count_new(keys_a, keys_b))
    keys_a, acc_a = _grow_spare(keys_a, n + m), _grow_spare(acc_a, n + m)
    kern.merge_backward(keys_a, acc_a, n, keys_b, acc_b)
    return keys_a, acc_a


def row_max(rows: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """``max_i rows[:, i]`` (B,) of ``rows`` (B, C), C > 0, taken one column at a time.

    The same values as ``rows.max(axis=1)`` (a maximum rounds nothing; NaN propagates in both), ≈ 2.4× faster
    on (65536, 20) float32 blocks: numpy's reduction along a short last axis runs its inner loop once per
    row, while C element-wise maxima over whole columns stay vectorised.
    """
    out: npt.NDArray[np.float32] = rows[:, 0].copy()
    for j in range(1, rows.shape[1]):
        np.maximum(out, rows[:, j], out=out)
    return out


def _finalise(
    keys: npt.NDArray[np.int64],
    acc: npt.NDArray[np.float32],
    cfg: FusionConfig,
    compiled: bool = True,
    *,
    ours: bool = True,
) -> VoxelGrid:
    """Shift each row to max 0, clip at -logp_clip, store float16.

    Works over blocks of rows and, when ``acc`` owns its memory or (``ours``: an accumulator of this module,
    not a caller's array) is a leading slice of an array that does (:func:`_owner`), writes the float16
    rows into the front of that buffer (block [s, e)'s float16 bytes
    lie inside float32 rows [s/2, e/2), already done) and shrinks it, so the float32 and float16 grids never
    both exist whole.

    numpy only: torch's row max and float16 cast are ≈ 3.6× faster on one thread (25 against 91 ms for
    687k voxels × 20 classes), but importing torch costs ≈ 1.7 s, which a run without the 3D-CN never pays
    otherwise (the break-even is ≈ 18 M voxels, 7× a whole SemanticKITTI sequence), and with two threads
    on busy cores it was 4× slower than numpy (433 against 94 ms). With ``compiled`` and numba, the shift and
    clip are one pass per block from numpy's row maxima (:func:`leap_core.fusion_kernels.shift_clip`) and the
    float16 bits one pass over all (:func:`leap_core.fusion_kernels.to_half`): the same bytes.
    """
    kern = compiled_kernels(compiled, load=False)
    v, c = acc.shape
    owner = _owner(acc, views=ours) if v > 0 else None
    out16 = None if owner is not None else np.empty((v, c), np.float16)
    flat16 = acc.reshape(-1).view(np.float16) if owner is not None else None
    block = max(1, min(_MOVE_BLOCK, (1 << 22) // max(c, 1)))
    if kern is not None and v > 0:
        for s in range(0, v, block):
            rows = acc[s : s + block]
            kern.shift_clip(rows, row_max(rows), np.float32(cfg.logp_clip))
        # The float16 bits in one pass, in index order, so into the front of acc's own buffer too.
        dest = flat16 if flat16 is not None else out16
        assert dest is not None
        kern.to_half(acc.reshape(-1).view(np.uint32), dest.reshape(-1).view(np.uint16))
        del dest, rows
    for s in range(0, v if kern is None else 0, block):
        rows = acc[s : s + block]
        rows -= row_max(rows)[:, None]
        np.maximum(rows, np.float32(-cfg.logp_clip), out=rows)
        half = rows.astype(np.float16)
        if flat16 is not None:
            flat16[s * c : s * c + half.size] = half.reshape(-1)
        else:
            assert out16 is not None
            out16[s : s + block] = half
        del rows, half  # views of acc's buffer, which the resize below may move
    if out16 is not None:
        return VoxelGrid(keys, out16, cfg.voxel_size)
    del flat16, acc
    # The float16 rows fill the first v·c/2 float32 elements: shrink the buffer to them, in place.
    assert owner is not None
    owner.resize(((v * c + 1) // 2,), refcheck=False)
    logp = owner.view(np.float16)[: v * c].reshape(v, c)
    return VoxelGrid(keys, logp, cfg.voxel_size)


def _start(
    grid: VoxelGrid | None, num_classes: int, cfg: FusionConfig, weight: float
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    if not (weight >= 0 and math.isfinite(weight)):
        raise ValueError(f"fusion weight must be a finite number ≥ 0, got {weight}")
    if grid is None:
        return np.zeros(0, np.int64), np.zeros((0, num_classes), np.float32)
    if grid.num_classes != num_classes:
        raise ValueError(f"grid has {grid.num_classes} classes, observations have {num_classes}")
    if not math.isclose(grid.voxel_size, cfg.voxel_size, rel_tol=1e-9):
        raise ValueError(f"grid voxel_size {grid.voxel_size} != FusionConfig.voxel_size {cfg.voxel_size}")
    keys, acc = grid.keys.copy(), grid.logp.astype(np.float32)
    # A memory-mapped prior grid: its pages are not needed once copied.
    release(grid.keys)
    release(grid.logp)
    return keys, acc


def _check_obs(o: Observations, num_classes: int, i: int) -> None:
    keys, rows, lt = o
    if keys.ndim != 1 or rows.shape != keys.shape:
        raise ValueError(f"observation batch {i}: keys {keys.shape} and rows {rows.shape} must be equal 1-D")
    if lt.ndim != 2 or lt.shape[1] != num_classes:
        raise ValueError(f"observation batch {i}: log_table must be (K, {num_classes}), got {lt.shape}")
    if len(rows) and (int(rows.min()) < 0 or int(rows.max()) >= lt.shape[0]):
        raise ValueError(f"observation batch {i}: rows must index 0..{lt.shape[0] - 1} of log_table")


_T = TypeVar("_T")


def _chunked(items: Iterable[tuple[int, _T]], chunk_points: int) -> Iterator[list[_T]]:
    """``(points, item)`` pairs grouped in order into the chunks fusion reduces: a chunk closes as soon as
    its points reach ``chunk_points``; items of 0 points belong to none. The one chunking rule of
    :func:`fuse`, :func:`fuse_to_file` and :func:`fusion_blocks`, whose equality of bytes rests on it."""
    pending: list[_T] = []
    n_pending = 0
    for n, item in items:
        if n == 0:
            continue
        pending.append(item)
        n_pending += n
        if n_pending >= chunk_points:
            yield pending
            pending, n_pending = [], 0
    if pending:
        yield pending


def _checked(batches: Iterable[Observations], num_classes: int) -> Iterator[tuple[int, Observations]]:
    """Each batch as arrays of the fused dtypes, checked (:func:`_check_obs`), with its point count."""
    for i, batch in enumerate(batches):
        o = Observations(
            np.asarray(batch[0], dtype=np.int64), np.asarray(batch[1]), np.asarray(batch[2], dtype=np.float32)
        )
        _check_obs(o, num_classes, i)
        yield len(o.keys), o


def fuse(
    batches: Iterable[Observations],
    num_classes: int,
    cfg: FusionConfig | None = None,
    grid: VoxelGrid | None = None,
    weight: float = 1.0,
    *,
    paths: FusionPaths | None = None,
) -> VoxelGrid:
    """Bayesian fusion of painted observations into a voxel grid.

    ``L_n(i) = L⁰_n(i) + weight · Σ_{points p in voxel n} log_table_p[rows_p, i]`` where ``L⁰`` is ``grid``'s
    stored logp (0 without a grid), then stored as ``max(L - max_i L, -logp_clip)`` in float16.

    The sum is accumulated in float32 per chunk of ``cfg.chunk_points`` points, so the result does not
    depend on how observations are split into batches or ordered (up to float32 rounding). Fusing in two
    calls instead of one differs only where the intermediate float16 storage clipped a row.

    Args:
        batches: per-image :class:`Observations` (keys, rows into log_table, log_table (K, C)).
        num_classes: C.
        cfg: grid and clipping parameters.
        grid: prior grid to update (not modified); None starts from an empty grid.
        weight: multiplies every log-likelihood (1 = plain Bayes; < 1 trusts these observations less).
        paths: implementation switches (:class:`FusionPaths`); the result does not depend on them.

    Returns:
        A new :class:`VoxelGrid`.
    """
    cfg = cfg or FusionConfig()
    paths = paths or FusionPaths()
    acc_keys, acc = _start(grid, num_classes, cfg, weight)
    for chunk in _chunked(_checked(batches, num_classes), cfg.chunk_points):
        acc_keys, acc = _merge(acc_keys, acc, *_reduce_chunk(chunk, weight, paths), paths.compiled)
    return _finalise(acc_keys, acc, cfg, paths.compiled)


def fuse_dense(
    grid: VoxelGrid | None,
    keys: npt.ArrayLike,
    logp: npt.ArrayLike,
    num_classes: int,
    cfg: FusionConfig | None = None,
    weight: float = 1.0,
) -> VoxelGrid:
    """Fuse per-point log-probabilities (e.g. 3D-CN predictions fused back with temperature T, weight = 1/T).

    ``L_n(i) = L⁰_n(i) + weight · Σ_{p in n} max(logp_p(i), log prob_floor)``; stored as in :func:`fuse`.
    Rows of ``logp`` should be normalised log-probabilities (log-softmax); they are clipped, not renormalised.

    Args:
        grid: prior grid (not modified) or None.
        keys: (N,) int64 voxel key per point.
        logp: (N, C) float32 log-probabilities per point.
        num_classes: C.
        cfg: grid and clipping parameters.
        weight: multiplies every log-probability.
    """
    import torch  # noqa: PLC0415  imported where tensors are made: reading a FusionConfig must not load it

    cfg = cfg or FusionConfig()
    acc_keys, acc = _start(grid, num_classes, cfg, weight)
    k = np.asarray(keys, dtype=np.int64)
    lp = torch.as_tensor(np.asarray(logp, dtype=np.float32))
    if k.ndim != 1 or lp.ndim != 2 or lp.shape[0] != k.shape[0] or lp.shape[1] != num_classes:
        raise ValueError(
            f"keys (N,) and logp (N, {num_classes}) expected, got {k.shape} and {tuple(lp.shape)}"
        )
    if len(k):
        # argsort + scatter of group ids gives the inverse faster than np.unique(return_inverse=True).
        order = np.argsort(k)
        sk = k[order]
        first = np.empty(len(sk), bool)
        first[0] = True
        np.not_equal(sk[1:], sk[:-1], out=first[1:])
        inv = np.empty(len(k), np.int64)
        inv[order] = np.cumsum(first) - 1
        lp = torch.clamp_min(lp, math.log(cfg.prob_floor))
        if weight != 1.0:
            lp.mul_(weight)
        sums = torch.zeros((int(first.sum()), num_classes), dtype=torch.float32)
        sums.index_add_(0, torch.from_numpy(inv), lp)
        acc_keys, acc = _merge(acc_keys, acc, sk[first], sums.numpy())
    return _finalise(acc_keys, acc, cfg)


def fuse_unique(
    grid: VoxelGrid | None,
    keys: npt.NDArray[np.int64],
    logp: npt.NDArray[np.float32],
    num_classes: int,
    cfg: FusionConfig | None = None,
    weight: float = 1.0,
) -> VoxelGrid:
    """:func:`fuse_dense` for one row per voxel (``keys`` sorted and unique), working in ``logp`` itself.

    Same values as ``fuse_dense(grid, keys, logp, ...)`` (the floor, the float32 product with the weight
    and the sums are the same operations; tests/test_memory.py compares them), without its per-row copies:
    the 3D-CN's per-voxel means are fused this way, so no second and third (V, C) float32 array exists.
    ``logp`` (V, C) float32, C-contiguous, is overwritten.
    """
    cfg = cfg or FusionConfig()
    if keys.ndim != 1 or logp.shape != (len(keys), num_classes) or logp.dtype != np.float32:
        raise ValueError(
            f"keys (V,), logp (V, {num_classes}) float32 expected: {keys.shape}, {logp.shape} {logp.dtype}"
        )
    if len(keys) > 1 and not keys_sorted_unique(keys):
        raise ValueError("fuse_unique needs sorted unique keys")
    acc_keys, acc = _start(grid, num_classes, cfg, weight)
    if len(keys):
        np.maximum(logp, np.float32(math.log(cfg.prob_floor)), out=logp)
        if weight != 1.0:
            logp *= np.float32(weight)
        acc_keys, acc = _merge(acc_keys, acc, keys, logp)
    # Without a prior grid the accumulator is the caller's logp itself: finalised in its buffer only when
    # that is logp's own (as always), never in an array logp is a slice of.
    return _finalise(acc_keys, acc, cfg, ours=grid is not None)


FILE_BLOCK_VOXELS = 1 << 20
""":func:`fuse_to_file` sums and finalises the grid over blocks of this many voxels (≈ (8 + 6C) bytes each
while a block is built); the result does not depend on it."""


def _override_obs(
    keys: npt.ArrayLike, class_idx: npt.ArrayLike, num_classes: int, strength: float
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """:func:`apply_overrides`' observation per corrected voxel: sorted unique keys (U,) and (U, C) rows of
    ``-strength`` per correction of another class."""
    k = np.asarray(keys, dtype=np.int64).reshape(-1)
    c = np.asarray(class_idx, dtype=np.int64).reshape(-1)
    if k.shape != c.shape:
        raise ValueError(f"keys {k.shape} and class_idx {c.shape} must have the same length")
    if len(c) and (c.min() < 0 or c.max() >= num_classes):
        raise ValueError(f"class_idx must be in 0..{num_classes - 1}")
    if not strength > 0:
        raise ValueError(f"override strength must be > 0, got {strength}")
    uk, inv = np.unique(k, return_inverse=True)
    obs = np.full((len(uk), num_classes), 0.0, np.float32)
    hits = np.zeros((len(uk), num_classes), np.float32)
    np.add.at(hits, (inv, c), 1.0)
    # Each correction: -strength on every class except its own.
    obs -= strength * (hits.sum(axis=1, keepdims=True) - hits)
    return uk, obs


def fuse_to_file(  # noqa: PLR0915  fuse's inputs, the override and the files; one pass per step
    batches: Iterable[Observations],
    num_classes: int,
    path: str | Path,
    spill_dir: str | Path,
    cfg: FusionConfig | None = None,
    *,
    overrides: tuple[npt.ArrayLike, npt.ArrayLike, float] | None = None,
    paths: FusionPaths | None = None,
    block_voxels: int = FILE_BLOCK_VOXELS,
) -> int:
    """``apply_overrides(fuse(batches, num_classes, cfg), *overrides)`` written to ``path`` as
    :meth:`VoxelGrid.save` writes it, the same bytes, without the grid ever being in memory whole.

    1. The observations are reduced in the chunks :func:`fuse` uses (``cfg.chunk_points``); each chunk's
       sorted keys and float32 sums go to ``spill_dir`` (``8 + 4C`` bytes per voxel of a chunk, on disk)
       and its keys are merged into the sorted set of all keys (8 bytes per voxel, the only per-voxel
       array held).
    2. Per block of ``block_voxels`` keys, each chunk's rows of the block are read back (memory-mapped) and
       summed in chunk order as :func:`fuse`'s merge sums them (the first chunk's rows as they are, later
       ones added to a zero-filled row when new), finalised (:func:`_finalise`), the overrides applied as
       :func:`apply_overrides` applies them, and the float16 rows written to the file as they come.

    Args:
        batches: per-image :class:`Observations`.
        num_classes: C.
        path: the grid file to write (atomically).
        spill_dir: a folder for the chunk files (created; its chunk files are deleted at the end).
        cfg: grid, clipping and chunk size.
        overrides: ``(keys, class_idx, strength)`` of :func:`apply_overrides`, or None.
        paths: implementation switches (:class:`FusionPaths`); the result does not depend on them.
        block_voxels: voxels per block of step 2 (≥ 1; the result does not depend on it).

    Returns:
        The number of voxels written.
    """
    cfg = cfg or FusionConfig()
    paths = paths or FusionPaths()
    if block_voxels < 1:
        raise ValueError(f"block_voxels must be ≥ 1, got {block_voxels}")
    spill = Path(spill_dir)
    spill.mkdir(parents=True, exist_ok=True)
    chunk_files: list[tuple[Path, Path]] = []
    all_keys = np.zeros(0, np.int64)
    try:
        for chunk in _chunked(_checked(batches, num_classes), cfg.chunk_points):
            k, sums = _reduce_chunk(chunk, 1.0, paths)
            chunk.clear()  # the chunk's observations go now, not when the next one starts
            kp, sp = spill / f"chunk{len(chunk_files)}.keys.npy", spill / f"chunk{len(chunk_files)}.sums.npy"
            chunk_files.append((kp, sp))  # listed before writing, so a failed write's half still goes
            np.save(kp, k)
            np.save(sp, sums)
            all_keys = union_sorted(all_keys, k)

        o_keys = np.zeros(0, np.int64)
        o_obs = np.zeros((0, num_classes), np.float32)
        if overrides is not None:
            o_keys, o_obs = _override_obs(overrides[0], overrides[1], num_classes, overrides[2])
        out_keys = union_sorted(all_keys, o_keys) if len(o_keys) else all_keys

        spilled = [(np.load(kp, mmap_mode="r"), np.load(sp, mmap_mode="r")) for kp, sp in chunk_files]

        def blocks() -> Iterator[npt.NDArray[np.float16]]:
            for b0 in range(0, len(out_keys), block_voxels):
                bk = out_keys[b0 : b0 + block_voxels]
                first, last = bk[0], bk[-1]
                f0, f1 = np.searchsorted(all_keys, first), np.searchsorted(all_keys, last, side="right")
                fk = all_keys[f0:f1]
                acc = np.zeros((len(fk), num_classes), np.float32)
                for c, (ck, cs) in enumerate(spilled if len(fk) else []):
                    lo, hi = int(np.searchsorted(ck, fk[0])), int(np.searchsorted(ck, fk[-1], side="right"))
                    if hi > lo:
                        pos = np.searchsorted(fk, ck[lo:hi])
                        if c == 0:
                            acc[pos] = cs[lo:hi]  # fuse's first chunk starts the accumulator as it is
                        else:
                            acc[pos] += cs[lo:hi]
                        release(ck)
                        release(cs)
                grid = _finalise(fk, acc, cfg, paths.compiled)
                if len(o_keys):
                    lo_o, hi_o = np.searchsorted(o_keys, first), np.searchsorted(o_keys, last, side="right")
                    if hi_o > lo_o:
                        ka, acc_a = fk.copy(), np.asarray(grid.logp, dtype=np.float32)
                        ka, acc_a = _merge(
                            ka, acc_a, o_keys[lo_o:hi_o].copy(), o_obs[lo_o:hi_o].copy(), paths.compiled
                        )
                        grid = _finalise(ka, acc_a, cfg, paths.compiled)
                yield np.asarray(grid.logp, np.float16)

        save_npz(
            path,
            keys=out_keys,
            logp=Streamed((len(out_keys), num_classes), np.dtype(np.float16), blocks()),
            voxel_size=np.float64(cfg.voxel_size),
        )
        spilled.clear()  # unmaps the chunk files before they are deleted
        return len(out_keys)
    finally:
        for kp, sp in chunk_files:
            kp.unlink(missing_ok=True)
            sp.unlink(missing_ok=True)


def apply_overrides(
    grid: VoxelGrid,
    keys: npt.ArrayLike,
    class_idx: npt.ArrayLike,
    strength: float = 50.0,
    cfg: FusionConfig | None = None,
) -> VoxelGrid:
    """Apply manual corrections as overriding observations.

    Each (key, class c) adds ``-strength`` to every class but c, i.e. an observation with
    ``P(c) / P(j) = e^strength``. With the stored clip at ``-logp_clip`` the corrected class ends at logp 0
    and the others at ``-logp_clip`` whenever ``strength ≥ 2·logp_clip`` (so ≥ 3 later contrary
    observations at the default floor are needed to flip it back). Unobserved voxels are added.

    Args:
        grid: the grid to correct (not modified).
        keys: (N,) int64 voxel keys.
        class_idx: (N,) class index per key.
        strength: log-odds of each correction.
        cfg: clipping parameters (``voxel_size`` must match the grid's); default FusionConfig().
    """
    cfg = cfg or FusionConfig(voxel_size=grid.voxel_size)
    uk, obs = _override_obs(keys, class_idx, grid.num_classes, strength)  # checks the arguments first
    acc_keys, acc = _start(grid, grid.num_classes, cfg, 1.0)
    acc_keys, acc = _merge(acc_keys, acc, uk, obs)
    return _finalise(acc_keys, acc, cfg)


# ------------------------------------------------------------------------- fusion in blocks (distributed)
def fusion_blocks(point_counts: Iterable[int], chunk_points: int) -> list[list[int]]:
    """The chunks :func:`fuse` reduces, for batches of these point counts, in its order.

    Args:
        point_counts: (B,) points per batch (``len(Observations.keys)``), in fusion order.
        chunk_points: :attr:`FusionConfig.chunk_points`.

    Returns:
        Lists of batch positions: a chunk closes as soon as its points reach ``chunk_points``; empty
        batches belong to none. Example: counts [5, 0, 4, 3], chunk_points 8 → [[0, 2], [3]].

    With :func:`reduce_block` per chunk (anywhere, in any order) and :func:`fold_blocks` of the partials
    in this order, the grid is :func:`fuse`'s, byte for byte: the same float32 additions in the same order.
    """
    return list(_chunked(((int(n), b) for b, n in enumerate(point_counts)), chunk_points))


Partial = tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]
"""A block's partial sum: sorted unique voxel keys (V,) and ``weight · Σ log-likelihoods`` (V, C) float32."""


def reduce_block(
    batches: Iterable[Observations],
    num_classes: int,
    weight: float = 1.0,
    *,
    paths: FusionPaths | None = None,
) -> Partial:
    """The partial sum of one :func:`fusion_blocks` chunk: the batches of its positions, in order (empty
    ones may be included; they add nothing). Checks each batch as :func:`fuse` does."""
    obs = [o for n, o in _checked(batches, num_classes) if n]
    if not obs:
        return np.zeros(0, np.int64), np.zeros((0, num_classes), np.float32)
    return _reduce_chunk(obs, weight, paths or FusionPaths())


def fold_blocks(
    partials: Iterable[Partial],
    num_classes: int,
    cfg: FusionConfig | None = None,
    grid: VoxelGrid | None = None,
    weight: float = 1.0,
) -> VoxelGrid:
    """``grid`` plus the :func:`reduce_block` partials, added in the order given, stored as :func:`fuse`
    stores (row max 0, clip, float16). float32 sums are not associative: fold in :func:`fusion_blocks`
    order to get :func:`fuse`'s bytes. Partials may be read-only (a Ray object store's zero-copy arrays):
    they are copied before being added to."""
    cfg = cfg or FusionConfig()
    acc_keys, acc = _start(grid, num_classes, cfg, weight)
    for keys, sums in partials:
        k = np.asarray(keys, dtype=np.int64)
        s = np.asarray(sums, dtype=np.float32)
        if k.ndim != 1 or s.shape != (k.shape[0], num_classes):
            raise ValueError(
                f"partial keys (V,) and sums (V, {num_classes}) expected, got {k.shape} and {s.shape}"
            )
        if len(k) == 0:
            continue
        if len(acc_keys) == 0:
            # _merge hands the first partial back as the accumulator, which later merges write into.
            k, s = k.copy(), s.copy()
        acc_keys, acc = _merge(acc_keys, acc, k, s)
    return _finalise(acc_keys, acc, cfg)


__all__ = [
    "AXIS_BITS",
    "AXIS_OFFSET",
    "FusionConfig",
    "FusionPaths",
    "Observations",
    "Partial",
    "VoxelGrid",
    "VoxelLabels",
    "apply_overrides",
    "compiled_kernels",
    "fold_blocks",
    "fuse",
    "fuse_dense",
    "fuse_to_file",
    "fuse_unique",
    "fusion_blocks",
    "key_centres",
    "key_coords",
    "keys_sorted_unique",
    "last_per_key",
    "log_table",
    "merge_sparse",
    "reduce_block",
    "rows_in_sorted",
    "voxel_keys",
    "world_points",
]
