"""Review regions: where to look first, which region is which across runs, and where a region shows.

A review region is one coarse cell (edge ``cell_size`` metres) of the voxel map holding enough *candidate*
voxels (the least confident share, or the voxels where the camera and the final label disagree most).
Regions are ranked by how much a person can fix there: the *expected wrong* count, the sum over the
region's candidates of each one's chance of being wrong (``1 - confidence`` per voxel, or the
disagreeing share of each voxel's camera-labelled points times their number), so a large uncertain area
comes before a speck of a few voxels however uncertain.

Identity and signature (how review marks survive a re-run):

- **identity** ``region_id``: the cell's integer coordinates and edge, ``"<cell>m:<i>,<j>,<k>"`` with
  ``(i, j, k) = floor(xyz / cell_size)``. Cells are fixed in world coordinates, so the same place has the
  same identity in every run of a project, whichever queue (confidence or disagreement) ranks it.
- **signature** ``region_signatures``: a 16-hex-digit BLAKE2b digest of the sorted voxel keys of *every*
  voxel in the cell (not only the candidates) and their (corrected) class indices. It changes exactly when
  a voxel of the cell appears, disappears or changes class; a confidence that merely drifts does not change
  it. A review mark holds the signature it was made on, and counts only while the region's current
  signature is equal.

Everything here is a pure function of numpy arrays (no I/O).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from leap_core.fusion import key_coords, voxel_keys


@dataclass(frozen=True, eq=False)
class RankedCell:
    """One review region as ranked by :func:`rank_cells`."""

    cell: int
    """Packed cell key (:func:`leap_core.fusion.voxel_keys` packing at ``cell_size``)."""
    rows: npt.NDArray[np.int64]
    """(n,) ascending grid rows of the region's candidate voxels."""
    centre: tuple[float, float, float]
    """Mean position of the candidate voxels (metres)."""
    extent: float
    """Largest distance of a candidate voxel from the centre (metres)."""
    score: float
    """Mean score of the candidate voxels."""
    expected_wrong: float = 0.0
    """Sum of the candidates' ``wrong`` values (:func:`rank_cells`): how many the region is expected to
    get wrong."""


def rank_cells(
    centres: npt.NDArray[np.floating],
    score: npt.NDArray[np.floating],
    candidates: npt.NDArray[np.bool_],
    cell_size: float,
    *,
    wrong: npt.NDArray[np.floating] | None = None,
    min_count: int = 1,
    ascending: bool = True,
    limit: int = 100,
) -> list[RankedCell]:
    """Cluster candidate voxels into coarse cells and order the cells by expected wrong count (or score).

    Each candidate voxel goes to cell ``floor(xyz / cell_size)`` (packed into one int64, so grouping is a
    1-D ``unique``, not a row-wise one); a cell with ≥ ``min_count`` candidates is a region with score
    ``mean(score[candidates in cell])`` and expected wrong count ``E = sum(wrong[candidates in cell])``.
    Order: with ``wrong``, the largest E first; without, the score (lowest first when ``ascending``);
    then more candidates first, then the smaller cell key (so equal regions always come in the same order).

    Args:
        centres: (V, 3) voxel centres.
        score: (V,) per-voxel score.
        candidates: (V,) bool.
        cell_size: cell edge in metres (> 0).
        wrong: (V,) per-voxel expected wrong count (≥ 0), e.g. ``1 - confidence``; None ranks by score.
        min_count: cells with fewer candidates are dropped.
        ascending: lowest score first (confidence) or highest first (disagreement), without ``wrong``.
        limit: at most this many regions.

    Returns:
        Regions, best first.
    """
    if not cell_size > 0:
        raise ValueError(f"cell_size must be > 0, got {cell_size}")
    rows = np.flatnonzero(candidates)
    if rows.size == 0:
        return []
    xyz = np.asarray(centres, dtype=np.float64)[rows]
    cells, inverse, counts = np.unique(voxel_keys(xyz, cell_size), return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    k = counts.shape[0]
    s = np.asarray(score, dtype=np.float64)[rows]
    mean_score = np.bincount(inverse, weights=s, minlength=k) / counts
    sum_xyz = np.stack([np.bincount(inverse, weights=xyz[:, d], minlength=k) for d in range(3)], 1)
    mean_xyz = sum_xyz / counts[:, None]
    dist = np.linalg.norm(xyz - mean_xyz[inverse], axis=1)
    extent = np.zeros(k)
    np.maximum.at(extent, inverse, dist)
    keep = np.flatnonzero(counts >= min_count)
    expected: npt.NDArray[np.float64] = np.zeros(k)
    primary: npt.NDArray[np.float64]
    if wrong is not None:
        w = np.asarray(wrong, dtype=np.float64)[rows]
        expected = np.bincount(inverse, weights=w, minlength=k).astype(np.float64)
        primary = -expected[keep]
    else:
        primary = np.asarray(mean_score[keep] if ascending else -mean_score[keep], dtype=np.float64)
    # np.unique sorted the cells, so ``keep`` ascending is the cell-key tie-break (lexsort: last key first).
    order = keep[np.lexsort((keep, -counts[keep], primary))][:limit]
    # Candidate rows grouped by cell: a stable sort of the cell index keeps rows ascending within a cell.
    by_cell = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    return [
        RankedCell(
            cell=int(cells[i]),
            rows=rows[by_cell[starts[i] : starts[i + 1]]],
            centre=(float(mean_xyz[i, 0]), float(mean_xyz[i, 1]), float(mean_xyz[i, 2])),
            extent=float(extent[i]),
            score=float(mean_score[i]),
            expected_wrong=float(expected[i]),
        )
        for i in order
    ]


def region_id(cell: int, cell_size: float) -> str:
    """Stable identity of a region: ``"<cell_size>m:<i>,<j>,<k>"`` from the packed cell key.

    Example: the cell holding (5.0, -1.0, 0.5) at 4 m is (1, -1, 0) → ``"4m:1,-1,0"``.
    """
    i, j, k = (int(v) for v in key_coords(np.asarray([cell], np.int64))[0])
    return f"{cell_size:g}m:{i},{j},{k}"


def region_signatures(
    centres: npt.NDArray[np.floating],
    keys: npt.NDArray[np.int64],
    label: npt.NDArray[np.integer],
    cells: npt.ArrayLike,
    cell_size: float,
) -> list[str]:
    """Content signature of each cell: BLAKE2b-64 of its voxels' sorted keys and class indices.

    ``sig(c) = blake2b(keys[in c] as int64 LE ‖ label[in c] as int16 LE, digest 8 bytes).hex()`` with the
    voxels of cell c in ascending key order (the grid's own order). A cell without voxels hashes the empty
    string. Cost: one packing of the V centres and a binary search of each into the (few) cells.

    Args:
        centres: (V, 3) voxel centres.
        keys: (V,) sorted voxel keys.
        label: (V,) class index per voxel (corrections applied).
        cells: (R,) packed cell keys (:attr:`RankedCell.cell`).
        cell_size: cell edge in metres.

    Returns:
        R hex strings.
    """
    wanted = np.asarray(cells, dtype=np.int64).reshape(-1)
    if wanted.size == 0:
        return []
    order = np.argsort(wanted)
    sorted_cells = wanted[order]
    voxel_cell = voxel_keys(np.asarray(centres), cell_size)
    pos = np.minimum(np.searchsorted(sorted_cells, voxel_cell), sorted_cells.size - 1)
    hit = np.flatnonzero(sorted_cells[pos] == voxel_cell)
    which = pos[hit]
    out = [""] * wanted.size
    k64 = np.asarray(keys, dtype="<i8")
    l16 = np.asarray(label).astype("<i2")
    for slot in range(sorted_cells.size):
        rows = hit[which == slot]
        digest = hashlib.blake2b(k64[rows].tobytes() + l16[rows].tobytes(), digest_size=8).hexdigest()
        out[int(order[slot])] = digest
    return out


def nearest_scans(positions: npt.ArrayLike, centre: npt.ArrayLike, k: int) -> npt.NDArray[np.int64]:
    """Indices of the ``k`` scans whose sensor positions (S, 3) lie nearest ``centre``, nearest first.

    Ties keep the lower index first (stable order).
    """
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    d = np.linalg.norm(p - np.asarray(centre, dtype=np.float64).reshape(1, 3), axis=1)
    return np.argsort(d, kind="stable")[: max(0, k)].astype(np.int64)


def best_observer(in_image: npt.ArrayLike, total: npt.ArrayLike) -> int | None:
    """The scan that observed a region most: most of the region's points seen by its camera, then most
    of its LiDAR points, then the first in the given order (callers list scans nearest the region first,
    :func:`nearest_scans`, so a tie goes to the closer view). None when no scan has a point in the region.

    Args:
        in_image: (S,) per scan, points in the region's voxels that project into its image.
        total: (S,) per scan, points in the region's voxels.
    """
    a = np.asarray(in_image, dtype=np.int64).reshape(-1)
    t = np.asarray(total, dtype=np.int64).reshape(-1)
    if a.shape != t.shape:
        raise ValueError(f"in_image {a.shape} and total {t.shape} must have the same length")
    if t.size == 0 or t.max() <= 0:
        return None
    order = np.lexsort((np.arange(t.size), -t, -a))
    return int(order[0])


def image_box(uv: npt.ArrayLike, width: int, height: int, pad: int = 6) -> tuple[int, int, int, int] | None:
    """Pixel box ``(u0, v0, u1, v1)`` (inclusive) around projected points, padded and clipped to the image.

    ``u0 = max(0, floor(min u) - pad)``, ``u1 = min(width-1, ceil(max u) + pad)``, same for v. None
    without points.
    """
    p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] == 0:
        return None
    u0 = max(0, int(np.floor(p[:, 0].min())) - pad)
    v0 = max(0, int(np.floor(p[:, 1].min())) - pad)
    u1 = min(width - 1, int(np.ceil(p[:, 0].max())) + pad)
    v1 = min(height - 1, int(np.ceil(p[:, 1].max())) + pad)
    if u0 > u1 or v0 > v1:
        return None
    return u0, v0, u1, v1


def draw_box(
    image: npt.NDArray[np.uint8],
    box: tuple[int, int, int, int],
    color: tuple[int, int, int] = (0, 255, 255),
    thickness: int = 2,
) -> npt.NDArray[np.uint8]:
    """A copy of ``image`` (H, W, 3) with the outline of ``box`` (inclusive pixel corners) drawn in ``color``,
    ``thickness`` pixels wide inwards (clipped to the box)."""
    out: npt.NDArray[np.uint8] = image.copy()
    u0, v0, u1, v1 = box
    t = max(1, thickness)
    rgb = np.asarray(color, np.uint8)
    out[v0 : min(v0 + t, v1 + 1), u0 : u1 + 1] = rgb
    out[max(v1 - t + 1, v0) : v1 + 1, u0 : u1 + 1] = rgb
    out[v0 : v1 + 1, u0 : min(u0 + t, u1 + 1)] = rgb
    out[v0 : v1 + 1, max(u1 - t + 1, u0) : u1 + 1] = rgb
    return out


def zoom_box(
    box: tuple[int, int, int, int], width: int, height: int, min_share: float = 0.25
) -> tuple[int, int, int, int]:
    """A crop of the image around ``box`` with the image's aspect ratio: centred on the box, at least
    ``min_share`` of the image's width (so a speck keeps some surroundings), large enough to hold the box,
    shifted inside the image. Inclusive pixel corners, like ``box``.

    ``w = clip(max(min_share·W, (u1-u0+1), (v1-v0+1)·W/H), 1, W)``, ``h = round(w·H/W)`` (≤ H).
    """
    u0, v0, u1, v1 = box
    aspect = height / width
    w = max(min_share * width, u1 - u0 + 1, (v1 - v0 + 1) / aspect)
    w = int(min(width, max(1, round(w))))
    h = int(min(height, max(1, round(w * aspect))))
    cu, cv = (u0 + u1 + 1) / 2, (v0 + v1 + 1) / 2
    left = int(np.clip(round(cu - w / 2), 0, width - w))
    top = int(np.clip(round(cv - h / 2), 0, height - h))
    return left, top, left + w - 1, top + h - 1


def crop_zoom(image: npt.NDArray[np.uint8], crop: tuple[int, int, int, int]) -> npt.NDArray[np.uint8]:
    """The ``crop`` (inclusive corners) of ``image`` (H, W, 3) enlarged to the image's size by nearest
    neighbour (pixels stay sharp, labels stay their colours): output pixel (y, x) takes crop pixel
    ``(floor(y·h/H), floor(x·w/W))``."""
    u0, v0, u1, v1 = crop
    part = image[v0 : v1 + 1, u0 : u1 + 1]
    hh, ww = image.shape[:2]
    ys = (np.arange(hh) * part.shape[0]) // hh
    xs = (np.arange(ww) * part.shape[1]) // ww
    out: npt.NDArray[np.uint8] = part[ys[:, None], xs[None, :]]
    return out


__all__ = [
    "RankedCell",
    "best_observer",
    "crop_zoom",
    "draw_box",
    "image_box",
    "nearest_scans",
    "rank_cells",
    "region_id",
    "region_signatures",
    "zoom_box",
]
