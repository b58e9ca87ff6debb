"""Compiled kernels of a fusion chunk's reduction, merge and finalise, and of the kNN smoothing's weighted
sum (numba, the ``fast`` extra).

Each kernel does the float32 operations of the numpy path in the same order, so a grid fused or smoothed
with them has the same bytes (tests/test_fusion_kernels.py compares the two paths). They are faster because
one pass replaces several numpy passes and their temporaries, and because an LSD radix sort over only the
bits a chunk's packed (voxel, table row) pairs use replaces ``np.sort``'s comparison sort (≈ 45-80 ns per
key here). Importing this module imports numba; :func:`leap_core.fusion.compiled_kernels` imports it lazily
and falls back to numpy when numba is not installed. ``cache=True``: compiled once per machine (≈ 4 s, in
``__pycache__`` or numba's user cache folder), loaded from there afterwards (≈ 0.3 s after ≈ 0.6 s of
importing numba).
"""

from __future__ import annotations

import numba
import numpy as np
import numpy.typing as npt

RADIX_BITS = 11
"""Bits per pass of :func:`radix_sort`: 2048 buckets, whose counters and write positions stay in L1/L2."""


@numba.njit(cache=True, nogil=True)
def axis_bounds(keys: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Per-axis minimum and maximum (3,) of packed voxel keys' offset integer coordinates (x, y, z)."""
    lo = np.full(3, np.iinfo(np.int64).max, np.int64)
    hi = np.full(3, np.iinfo(np.int64).min, np.int64)
    mask = (1 << 21) - 1
    for i in range(keys.shape[0]):
        k = keys[i]
        c0, c1, c2 = k >> 42, (k >> 21) & mask, k & mask
        lo[0], hi[0] = min(lo[0], c0), max(hi[0], c0)
        lo[1], hi[1] = min(lo[1], c1), max(hi[1], c1)
        lo[2], hi[2] = min(lo[2], c2), max(hi[2], c2)
    return lo, hi


@numba.njit(cache=True, nogil=True)
def pack_pairs(
    keys: npt.NDArray[np.int64],
    rows: npt.NDArray[np.int64],
    lo: npt.NDArray[np.int64],
    shifts: npt.NDArray[np.int64],
) -> None:
    """In place: ``keys[p] = (x-lo0) << s0 | (y-lo1) << s1 | (z-lo2) << s2 | rows[p]`` (the numpy path's
    packing of (voxel, table row) into one int64)."""
    mask = (1 << 21) - 1
    for i in range(keys.shape[0]):
        k = keys[i]
        x = ((k >> 42) - lo[0]) << shifts[0]
        y = (((k >> 21) & mask) - lo[1]) << shifts[1]
        z = ((k & mask) - lo[2]) << shifts[2]
        keys[i] = x | y | z | rows[i]


@numba.njit(cache=True, nogil=True)
def radix_sort(a: npt.NDArray[np.int64], bits: int) -> npt.NDArray[np.int64]:
    """``np.sort(a)`` of non-negative int64 values below ``2**bits``: an LSD radix sort in
    ``ceil(bits / RADIX_BITS)`` passes of equal width, all histograms counted in one first pass; a pass
    whose digit is the same for every value is skipped. Returns ``a`` or a new array, sorted."""
    n = a.shape[0]
    passes = max(1, (bits + RADIX_BITS - 1) // RADIX_BITS)
    width = max(1, (bits + passes - 1) // passes)
    buckets = 1 << width
    mask = buckets - 1
    hist = np.zeros((passes, buckets), np.int64)
    for i in range(n):
        v = a[i]
        for p in range(passes):
            hist[p, (v >> (p * width)) & mask] += 1
    src = a
    dst = np.empty_like(a)
    pos = np.empty(buckets, np.int64)
    for p in range(passes):
        h = hist[p]
        if h.max() == n:  # one digit value for all: the pass would copy the array unchanged
            continue
        total = 0
        for b in range(buckets):
            pos[b] = total
            total += h[b]
        shift = p * width
        for i in range(n):
            v = src[i]
            d = (v >> shift) & mask
            dst[pos[d]] = v
            pos[d] += 1
        src, dst = dst, src
    return src


@numba.njit(cache=True, nogil=True)
def count_voxels(pairs: npt.NDArray[np.int64], rbits: int) -> int:
    """How many distinct voxels (``pair >> rbits``) the sorted packed pairs hold."""
    v = 1 if pairs.shape[0] else 0
    for i in range(1, pairs.shape[0]):
        if (pairs[i] >> rbits) != (pairs[i - 1] >> rbits):
            v += 1
    return v


@numba.njit(cache=True, nogil=True)
def reduce_pairs(
    pairs: npt.NDArray[np.int64],
    rbits: int,
    table: npt.NDArray[np.float32],
    weight: np.float32,
    vox: npt.NDArray[np.int64],
    sums: npt.NDArray[np.float32],
) -> None:
    """Sums per voxel of sorted packed pairs into ``vox`` (V,) (the voxel ids) and the zero-filled ``sums``
    (V, C) float32 (V from :func:`count_voxels`): for each run of ``cnt`` equal pairs (voxel, row) in
    ascending order, ``sums[voxel] += (float32(cnt) · weight) · table[row]``, the steps of the numpy path's
    CSR (V × K) @ (K × C) product in its order. The outputs come from the caller so that numpy owns them
    (the accumulator grows in place, :func:`leap_core.fusion._grow`)."""
    n = pairs.shape[0]
    c = table.shape[1]
    row_mask = (1 << rbits) - 1
    vi = -1
    prev = np.int64(-1)
    i = 0
    while i < n:
        p = pairs[i]
        j = i + 1
        while j < n and pairs[j] == p:
            j += 1
        vid = p >> rbits
        if vid != prev:
            vi += 1
            vox[vi] = vid
            prev = vid
        a = np.float32(j - i) * weight
        r = p & row_mask
        for col in range(c):
            sums[vi, col] += a * table[r, col]
        i = j


@numba.njit(cache=True, nogil=True)
def count_new(keys_a: npt.NDArray[np.int64], keys_b: npt.NDArray[np.int64]) -> int:
    """How many of the sorted unique ``keys_b`` are not in the sorted unique ``keys_a``."""
    i, new = 0, 0
    na = keys_a.shape[0]
    for j in range(keys_b.shape[0]):
        k = keys_b[j]
        while i < na and keys_a[i] < k:
            i += 1
        if i == na or keys_a[i] != k:
            new += 1
    return new


@numba.njit(cache=True, nogil=True)
def merge_backward(
    keys: npt.NDArray[np.int64],
    acc: npt.NDArray[np.float32],
    n_old: int,
    keys_b: npt.NDArray[np.int64],
    acc_b: npt.NDArray[np.float32],
) -> None:
    """In place: ``keys`` / ``acc`` hold ``n_old`` sorted rows followed by room for ``keys_b``'s new keys;
    merge ``b`` in from the last row backwards (each old row lands at or after where it was): a key in
    both gets ``a + b``, one only in ``b`` gets ``0 + b`` (float32, as the numpy path's zero fill and add)."""
    c = acc.shape[1]
    i = n_old - 1
    j = keys_b.shape[0] - 1
    w = keys.shape[0] - 1
    while j >= 0:
        kb = keys_b[j]
        if i >= 0 and keys[i] > kb:
            keys[w] = keys[i]
            for col in range(c):
                acc[w, col] = acc[i, col]
            i -= 1
        elif i >= 0 and keys[i] == kb:
            keys[w] = kb
            for col in range(c):
                acc[w, col] = acc[i, col] + acc_b[j, col]
            i -= 1
            j -= 1
        else:
            keys[w] = kb
            for col in range(c):
                acc[w, col] = np.float32(0.0) + acc_b[j, col]
            j -= 1
        w -= 1


@numba.njit(cache=True, nogil=True)
def half_bits(b: int) -> int:
    """IEEE binary16 bits of the float32 whose bits are ``b`` (0 ≤ b < 2³²), rounded to nearest (ties to
    even): ``np.float16(f)``'s bits.

    Overflow gives ±inf; values below half the smallest subnormal (2⁻²⁵) give ±0; a NaN keeps its sign
    and the top 10 bits of its payload (the lowest set when those are all 0, so it stays a NaN), as numpy's
    conversion does (tests/test_fusion_kernels.py compares it with numpy over every exponent).
    """
    sign = (b >> 16) & 0x8000
    a = b & 0x7FFFFFFF
    if 0x38800000 <= a < 0x47800000:  # 2⁻¹⁴ ≤ |f| < 2¹⁶: a normal binary16 (or, rounded up, inf)
        # Adding 0xFFF plus the kept part's lowest bit carries into bit 13 exactly when the dropped 13 bits
        # exceed one half, or equal it with an odd kept part; a carry out of the significand rounds up
        # the exponent. 112 = 127 - 15, the difference of the exponent biases.
        return sign | (((a + 0xFFF + ((a >> 13) & 1)) >> 13) - (112 << 10))
    e = a >> 23
    m = a & 0x7FFFFF
    if e == 0xFF:
        if m == 0:
            return sign | 0x7C00
        q = 0x7C00 + (m >> 13)
        return sign | (q + 1 if q == 0x7C00 else q)
    if e >= 143:  # |f| ≥ 2¹⁶: beyond binary16's largest finite value 65504
        return sign | 0x7C00
    # |f| < 2⁻¹⁴: a binary16 subnormal (units of 2⁻²⁴) or zero
    if e < 102:
        return sign
    full = m | 0x800000
    sh = 126 - e
    q = full >> sh
    r = full & ((1 << sh) - 1)
    half = 1 << (sh - 1)
    if r > half or (r == half and (q & 1) == 1):
        q += 1
    return sign | q


@numba.njit(cache=True, nogil=True)
def to_half(bits: npt.NDArray[np.uint32], out: npt.NDArray[np.uint16]) -> None:
    """``out[i] = half_bits(bits[i])`` over flat arrays (``bits``: float32 values viewed as uint32), in
    index order: ``out`` may be the front of ``bits``' own buffer (element i's two bytes lie in element
    i // 2, already read)."""
    for i in range(bits.shape[0]):
        out[i] = half_bits(np.int64(bits[i]))


@numba.njit(cache=True, nogil=True)
def shift_clip(rows: npt.NDArray[np.float32], top: npt.NDArray[np.float32], clip: np.float32) -> None:
    """In place: ``rows[i] = max(rows[i] - top[i], -clip)``, NaN propagating as in ``np.maximum``.

    ``top`` is numpy's row maximum (:func:`leap_core.fusion.row_max`), not one taken here: numpy's SIMD
    maximum of +0 and -0 returns either depending on where the pair falls in its vector loop, and that
    choice sets the sign of the shifted zeros, so only numpy's own maxima give its bytes."""
    c = rows.shape[1]
    floor = -clip
    for i in range(rows.shape[0]):
        m = top[i]
        for col in range(c):
            x = rows[i, col] - m
            if x < floor:  # noqa: PLR1730  not max(): a NaN must stay NaN, as in np.maximum
                x = floor
            rows[i, col] = x


@numba.njit(cache=True, nogil=True)
def knn_mix(
    w: npt.NDArray[np.float32], idx: npt.NDArray[np.intp], p: npt.NDArray[np.float32]
) -> npt.NDArray[np.float32]:
    """:func:`leap_core.smoothing.knn_mix`: ``out[n] = Σ_{j<k} w[n, j] · p[idx[n, j]]`` accumulated in float32
    from 0, neighbour after neighbour, each product rounded before it is added (its numpy steps, row by
    row instead of neighbour by neighbour over the chunk)."""
    n, k = w.shape
    c = p.shape[1]
    out = np.zeros((n, c), np.float32)
    for i in range(n):
        for j in range(k):
            r = idx[i, j]
            wj = w[i, j]
            for col in range(c):
                out[i, col] += p[r, col] * wj
    return out
