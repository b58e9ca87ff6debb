"""Affine maps of point arrays, computed in row blocks (docs/METHOD.md "Performance facts").

``points[:, :3] @ M[:, :3].T + M[:, 3]`` over a whole scan is one (N, 3) × (3, R) BLAS product. OpenBLAS
hands a product above about 2.6 · 10⁵ multiply-adds to its thread pool; for three-term dot products the
hand-off costs far more than the arithmetic (25-35 ms of CPU for a 106 k-point scan on the loaded 2-core
machine, against ≈ 2 ms computed in blocks), and its spinning threads take cores from the other work.
Below the threshold OpenBLAS computes on the calling thread, so each block of :data:`ROW_BLOCK` rows is
one single-threaded product.

Same bytes: every output element is one three-term dot product, and OpenBLAS rounds it the same way
whatever the number of rows (checked on the demo scans for 2 to 320 000 rows and blocks of 7 to 29 000
rows), as long as a block has at least 2 rows: numpy computes a 1-row product by another path, whose
rounding differs, so the remainder rows join the last full block. ``tests/test_scan_speed.py`` compares
the blocked result with the one-call expression for many sizes and block sizes, so a BLAS build that
rounds otherwise fails there. (Not so for longer dot products: a (K, M) × (M, C) float32 product with
M ≈ 100-300 computed in row blocks differs from the one-call product in the last bit once the whole is
large, so painting keeps its one-call product, below the threading threshold on the demo: K·M·C ≤
2.5 · 10⁵.)
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import numpy.typing as npt

ROW_BLOCK = 8192
"""Rows per block: 8192 × 3 × 3 multiply-adds stays below OpenBLAS's threading threshold, and a block's
float64 temporaries (192 KiB) stay in the core's L2 cache."""


def row_blocks(n: int, block: int = ROW_BLOCK) -> Iterator[tuple[int, int]]:
    """``(start, stop)`` covering ``range(n)`` in blocks of ``block`` rows; a remainder shorter than 2 rows
    joins the block before it, so no block but a 1-row whole has a single row.

    Example: n = 10, block = 4 → (0, 4), (4, 8), (8, 10); n = 9 → (0, 4), (4, 9).
    """
    if block < 2:
        raise ValueError(f"block must be >= 2 rows, got {block}")
    start = 0
    while start < n:
        stop = min(start + block, n)
        if 0 < n - stop < 2:
            stop = n
        yield start, stop
        start = stop


def affine_points(
    points: npt.ArrayLike, matrix: npt.ArrayLike, block: int = ROW_BLOCK
) -> npt.NDArray[np.float64]:
    """``points[:, :3] @ matrix[:, :3].T + matrix[:, 3]`` in float64, block by block.

    Byte for byte what the one-call expression ``pts[:, :3].astype(np.float64) @ m[:, :3].T + m[:, 3]``
    gives (module docstring), without OpenBLAS's threads.

    Args:
        points: (N, ≥3) points (extra columns such as remission are ignored), any float type.
        matrix: (R, 4) affine map, e.g. a pose's first 3 rows or a 3 × 4 camera matrix ``P2 · Tr``.
        block: rows per product.

    Returns:
        (N, R) float64.
    """
    pts = np.asarray(points)
    m = np.asarray(matrix, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, 3), got shape {pts.shape}")
    if m.ndim != 2 or m.shape[1] != 4:
        raise ValueError(f"matrix must be (R, 4), got shape {m.shape}")
    rot_t = m[:, :3].T
    shift = m[:, 3]
    out = np.empty((pts.shape[0], m.shape[0]), np.float64)
    for start, stop in row_blocks(pts.shape[0], block):
        part = out[start:stop]
        np.matmul(pts[start:stop, :3].astype(np.float64), rot_t, out=part)
        part += shift
    return out


__all__ = ["ROW_BLOCK", "affine_points", "row_blocks"]
