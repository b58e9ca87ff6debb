"""Point projection, per-mask depth clustering and painting (docs/METHOD.md stage B.1-B.2).

A LiDAR point ``x`` lands on pixel ``(u, v) = round(m₁·x̃ / m₃·x̃, m₂·x̃ / m₃·x̃)`` with ``M = P2 · Tr`` and
``x̃ = [x y z 1]ᵀ`` (PointPainting). It is painted with the confidence-weighted average distribution of the
masks that cover its pixel. Before averaging, each mask keeps only the largest cluster of its points by
camera depth, so the label of a foreground object does not bleed onto the points behind it.

A painted image is stored table-indexed (:class:`Painted`): per point only an int32 row into a table of the
DISTINCT combinations of covering masks, so later stages take logs and move C floats per table row, never
per point (docs/METHOD.md "Performance facts").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.bounds import check_bounds, within
from leap_core.errors import DatasetError
from leap_core.fusion import Observations, log_table
from leap_core.geometry import affine_points
from leap_core.io_utils import atomic_save_npz, read_npz
from leap_core.labelers.base import SoftMasks
from leap_core.types import UNLABELED

POINT_PROB_FLOOR = 1e-3
"""Floor of the class probabilities when a point's observations from several cameras are combined into one
point label (:meth:`Painted.merged`): ``FusionConfig.prob_floor``'s default, so the point label is the
fusion's update on that one point."""


@dataclass(frozen=True)
class ProjectionConfig:
    """Parameters of projection and of the per-mask depth clustering."""

    min_depth: float = field(default=0.5, metadata=within(0, 1000, unit="m"))
    """Points closer than this (metres along the camera's optical axis) are not projected; it also drops
    every point behind the camera."""
    depth_clustering: bool = True
    """Apply the paper's per-mask depth clustering filter (keep only each mask's largest depth cluster)."""
    cluster_gap: float = field(default=1.0, metadata=within(0.01, 1000, unit="m"))
    """Metres: a gap larger than this between consecutive sorted depths of a mask's points splits them
    into clusters. 1 m sits between the depth spread of neighbouring returns on one surface (centimetres
    to a few tens of centimetres, even on oblique surfaces 40 m away) and the usual separation of an object
    from what stands behind it (a person before a wall, a car before a building: metres). Ground masks
    spanning the image do not split either: one LiDAR ring spreads over a wide depth range across the
    image's width, which bridges the gap to the next ring."""
    min_cluster_points: int = field(default=3, metadata=within(0, 1_000_000))
    """Masks covering fewer points are kept whole: with one or two points "largest cluster" carries no
    evidence about which depth the object is at (small far-away objects such as poles often get 1-2
    returns)."""

    def __post_init__(self) -> None:
        check_bounds(self)


@dataclass(frozen=True)
class Projected:
    """Points of one scan that fall inside one image.

    Attributes:
        idx: (P,) int64 indices into the scan of the points inside the image with depth > min_depth.
        u: (P,) int32 pixel column.
        v: (P,) int32 pixel row.
        depth: (P,) float32 camera depth (distance along the optical axis, metres).
    """

    idx: npt.NDArray[np.int64]
    u: npt.NDArray[np.int32]
    v: npt.NDArray[np.int32]
    depth: npt.NDArray[np.float32]

    def __len__(self) -> int:
        return int(self.idx.shape[0])


def project_points(
    xyz: npt.ArrayLike,
    lidar_to_image: npt.ArrayLike,
    height: int,
    width: int,
    min_depth: float = 0.5,
) -> Projected:
    """Project LiDAR points into an image.

    ``[a, b, d]ᵀ = M · [x, y, z, 1]ᵀ``; a point is kept when ``d > min_depth`` and its pixel
    ``(u, v) = (⌊a/d + ½⌋, ⌊b/d + ½⌋)`` lies in ``[0, width) × [0, height)``. Rounding, not flooring: in
    the KITTI convention integer pixel coordinates are pixel centres.

    Args:
        xyz: (N, 3) float32 points in the LiDAR frame ((N, ≥3): extra columns such as remission ignored).
        lidar_to_image: (3, 4) float64 ``M = calib.P2 @ calib.Tr``.
        height, width: image size in pixels.
        min_depth: minimum camera depth in metres.
    """
    pts = np.asarray(xyz)
    m = np.asarray(lidar_to_image, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"xyz must be (N, 3), got shape {pts.shape}")
    if m.shape != (3, 4):
        raise ValueError(f"lidar_to_image must be (3, 4), got shape {m.shape}")
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}×{width}")
    cam = affine_points(pts, m)
    d = cam[:, 2]
    front = np.flatnonzero(d > min_depth)
    cam, d = cam[front], d[front]
    u = np.floor(cam[:, 0] / d + 0.5)
    v = np.floor(cam[:, 1] / d + 0.5)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return Projected(
        idx=front[inside].astype(np.int64),
        u=u[inside].astype(np.int32),
        v=v[inside].astype(np.int32),
        depth=d[inside].astype(np.float32),
    )


# ------------------------------------------------------------------------------------ depth clustering
def depth_cluster_filter(
    member: npt.NDArray[np.bool_],
    depth: npt.ArrayLike,
    gap: float,
    min_points: int = 0,
) -> npt.NDArray[np.bool_]:
    """Keep, per mask, only the points of its largest depth cluster.

    For each mask m, its points' depths are sorted; consecutive depths more than ``gap`` apart start a new
    cluster (1-D single-linkage clustering). The cluster with the most points is kept; ties go to the
    nearest cluster. Masks with fewer than ``min_points`` points are kept whole. All masks are handled in
    one vectorised pass (one sort over the (mask, point) memberships: :func:`cluster_pairs`).

    Args:
        member: (M, P) bool, mask m covers point p.
        depth: (P,) camera depth per point.
        gap: cluster split distance in metres.
        min_points: masks with fewer points are not filtered.

    Returns:
        (M, P) bool, a subset of ``member``.
    """
    member = np.asarray(member, dtype=bool)
    d_all = np.asarray(depth, dtype=np.float64).reshape(-1)
    if member.ndim != 2 or member.shape[1] != d_all.shape[0]:
        raise ValueError(f"member must be (M, {d_all.shape[0]}), got {member.shape}")
    m_idx, p_idx = np.nonzero(member)
    out = np.zeros_like(member)
    ms, ps = cluster_pairs(m_idx, p_idx, d_all, member.shape[0], gap, min_points)
    out[ms, ps] = True
    return out


def cluster_pairs(
    m_idx: npt.NDArray[np.int64],
    p_idx: npt.NDArray[np.int64],
    depth: npt.ArrayLike,
    num_masks: int,
    gap: float,
    min_points: int = 0,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """:func:`depth_cluster_filter` on (mask, point) pairs: the pairs it keeps.

    Args:
        m_idx, p_idx: (K,) int64 pairs "mask m covers point p", in (mask, point) order (``np.nonzero`` of
            the (M, P) membership).
        depth: (P,) camera depth per point.
        num_masks: M.
        gap, min_points: as :func:`depth_cluster_filter`.

    Returns:
        The kept pairs ``(m, p)``, ordered by (mask, depth).
    """
    if len(m_idx) == 0:
        return m_idx, p_idx
    d = np.asarray(depth, dtype=np.float64).reshape(-1)[p_idx]
    # One float argsort of mask·span + depth orders by (mask, depth); ≈ 10× faster than np.lexsort. Stable:
    # the pairs arrive sorted by mask, runs a stable sort exploits. Equal keys are equal depths of one
    # mask, which fall in one cluster whatever their order, so the kept pairs do not depend on the sort.
    span = float(d.max() - d.min()) + 1.0
    order = np.argsort(m_idx * span + (d - d.min()), kind="stable")
    ms, ps, ds = m_idx[order], p_idx[order], d[order]
    start = np.empty(len(ms), bool)
    start[0] = True
    start[1:] = (ms[1:] != ms[:-1]) | (np.diff(ds) > gap)
    cid = np.cumsum(start) - 1
    sizes = np.bincount(cid)
    c_mask = ms[start]
    # Clusters are numbered by (mask, depth), so among equal sizes the lowest id is the nearest.
    c_order = np.lexsort((np.arange(len(sizes)), -sizes, c_mask))
    best_first = np.empty(len(c_order), bool)
    best_first[0] = True
    best_first[1:] = c_mask[c_order][1:] != c_mask[c_order][:-1]
    keep_cluster = np.zeros(len(sizes), bool)
    keep_cluster[c_order[best_first]] = True
    keep = keep_cluster[cid]
    if min_points > 0:
        small = np.bincount(m_idx, minlength=num_masks) < min_points
        keep |= small[ms]
    return ms[keep], ps[keep]


def largest_depth_cluster(depth: npt.ArrayLike, gap: float) -> npt.NDArray[np.bool_]:
    """(P,) bool: the points of the largest 1-D gap cluster of ``depth`` (ties: the nearest cluster)."""
    d = np.asarray(depth).reshape(-1)
    keep: npt.NDArray[np.bool_] = depth_cluster_filter(np.ones((1, d.shape[0]), bool), d, gap)[0]
    return keep


# ------------------------------------------------------------------------------------------- painting
@dataclass(frozen=True)
class Painted:
    """The observation one image gives its scan's points, table-indexed.

    Attributes:
        point_idx: (P',) int64 scan indices of the points covered by at least one (filtered) mask.
        rows: (P',) int32 row of ``table`` for each such point.
        table: (K, C) float32; row k is the confidence-weighted average distribution of one distinct
            combination S_k of covering masks: ``table[k] = Σ_{m∈S_k} w_m p_m / Σ_{m∈S_k} w_m``.
    """

    point_idx: npt.NDArray[np.int64]
    rows: npt.NDArray[np.int32]
    table: npt.NDArray[np.float32]

    @property
    def num_classes(self) -> int:
        return int(self.table.shape[1])

    def __len__(self) -> int:
        return int(self.point_idx.shape[0])

    @classmethod
    def empty(cls, num_classes: int) -> Painted:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros((0, num_classes), np.float32))

    @classmethod
    def joined(cls, parts: Sequence[Painted], num_classes: int) -> Painted:
        """The observations of several images of one scan (a camera rig) as one: the parts' points in
        order, each part's rows shifted past the tables before it. A point two cameras painted appears
        twice, once per observation, so fusion adds both (docs/METHOD.md B.2, "Several cameras"). One
        part is returned as it is."""
        if len(parts) == 1:
            return parts[0]
        if not parts:
            return cls.empty(num_classes)
        offsets = np.cumsum([0, *(p.table.shape[0] for p in parts)])
        return cls(
            np.concatenate([p.point_idx for p in parts]),
            np.concatenate([p.rows + np.int32(o) for p, o in zip(parts, offsets, strict=False)]).astype(
                np.int32
            ),
            np.concatenate([p.table for p in parts]).astype(np.float32),
        )

    def merged(self, prob_floor: float = POINT_PROB_FLOOR) -> Painted:
        """One row per point: a point with several observations (several cameras) gets the posterior of
        their product, ``softmax(Σ_o log max(t_o, floor))`` (the fusion's update on one point); a point
        observed once keeps its row. Returns ``self`` when no point repeats."""
        idx = self.point_idx
        if len(idx) < 2 or bool(np.all(np.diff(idx) > 0)):
            return self
        uniq, inv, counts = np.unique(idx, return_inverse=True, return_counts=True)
        logs = log_table(self.table, prob_floor)[self.rows]  # (P', C) per observation
        summed = np.zeros((len(uniq), self.num_classes), np.float64)
        np.add.at(summed, inv, logs)
        summed -= summed.max(axis=1, keepdims=True)
        post = np.exp(summed)
        post /= post.sum(axis=1, keepdims=True)
        single = counts[inv] == 1
        first_row = np.zeros(len(uniq), np.int64)
        first_row[inv[single]] = self.rows[single]
        once = counts == 1
        table = np.concatenate([self.table, post[~once].astype(np.float32)])
        rows = first_row.copy()
        rows[~once] = self.table.shape[0] + np.arange(int((~once).sum()))
        return Painted(uniq.astype(np.int64), rows.astype(np.int32), table)

    def point_labels(self, num_points: int) -> npt.NDArray[np.int16]:
        """(N,) int16 argmax class per painted point, ``UNLABELED`` elsewhere (the paper's "point" labels;
        a point several cameras painted: of :meth:`merged`)."""
        one = self.merged()
        out = np.full(num_points, UNLABELED, np.int16)
        if len(one):
            out[one.point_idx] = one.table.argmax(axis=1).astype(np.int16)[one.rows]
        return out

    def point_confidence(self, num_points: int) -> npt.NDArray[np.float32]:
        """(N,) float32 max class probability per painted point (of :meth:`merged`), 0 elsewhere."""
        one = self.merged()
        out = np.zeros(num_points, np.float32)
        if len(one):
            out[one.point_idx] = one.table.max(axis=1)[one.rows]
        return out

    def to_observations(self, point_keys: npt.ArrayLike, prob_floor: float) -> Observations:
        """Observations for :func:`leap_core.fusion.fuse`, given the voxel key of every scan point (N,)."""
        keys = np.asarray(point_keys, dtype=np.int64)
        return Observations(keys[self.point_idx], self.rows, log_table(self.table, prob_floor))

    def save(self, path: str | Path) -> None:
        atomic_save_npz(path, point_idx=self.point_idx, rows=self.rows, table=self.table)

    @classmethod
    def load(cls, path: str | Path) -> Painted:
        """Read a file written by :meth:`save`; a malformed file raises :class:`DatasetError`."""
        try:
            arrays = read_npz(path)
        except (OSError, ValueError) as exc:
            raise DatasetError(path, f"unreadable observation file ({exc})") from exc
        return cls.from_arrays(path, arrays)

    @classmethod
    def from_arrays(cls, path: str | Path, arrays: dict[str, npt.NDArray[Any]]) -> Painted:
        """The arrays ``point_idx``, ``rows``, ``table`` of an observation file read by
        :func:`~leap_core.io_utils.read_npz`, checked (``path`` names the file in errors) and copied into
        the documented dtypes."""
        try:
            idx, rows, table = arrays["point_idx"], arrays["rows"], arrays["table"]
        except KeyError as exc:
            raise DatasetError(path, f"unreadable observation file (no array {exc})") from exc
        if idx.ndim != 1 or rows.shape != idx.shape or table.ndim != 2:
            raise DatasetError(
                path, f"inconsistent shapes point_idx {idx.shape}, rows {rows.shape}, table {table.shape}"
            )
        if len(rows) and (rows.min() < 0 or rows.max() >= table.shape[0]):
            raise DatasetError(path, f"rows index outside the {table.shape[0]}-row table")
        return cls(idx.astype(np.int64), rows.astype(np.int32), table.astype(np.float32))


def covering_pairs(
    soft: SoftMasks, u: npt.NDArray[np.integer], v: npt.NDArray[np.integer]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The (mask, point) pairs "mask m covers pixel (u_p, v_p)", in (mask, point) order.

    ``np.nonzero(soft.membership(u, v))``, read straight from the packed bits: one (M, P) byte gather, a
    bit test and a 1-D ``flatnonzero`` of a boolean array (numpy's 2-D ``nonzero`` of a uint8 array is
    ≈ 15× slower).
    """
    flat = v.astype(np.int64) * soft.width + u.astype(np.int64)
    bit = np.right_shift(np.uint8(0x80), (flat & 7).astype(np.uint8))
    hits = soft.bits[:, flat >> 3]
    hits &= bit
    pairs = np.flatnonzero(hits != 0)
    m_idx, p_idx = np.divmod(pairs, np.int64(flat.shape[0]))
    return m_idx, p_idx


def combination_words(
    m_idx: npt.NDArray[np.int64], p_idx: npt.NDArray[np.int64], num_points: int, num_masks: int
) -> npt.NDArray[np.uint64]:
    """(P, ⌈M/64⌉) uint64: point p's set of covering masks as bits.

    The layout is the little-endian uint64 view of ``np.packbits(member, axis=0).T`` padded to whole words
    (mask 8b + r is bit 7 − r of byte b), so rows compare as the packed bit patterns do. A point's masks are
    distinct, so OR-ing their bits is adding them.
    """
    words = -(-num_masks // 64)
    in_word = m_idx % 64
    pos = (in_word // 8) * 8 + 7 - in_word % 8
    out = np.zeros(num_points * words, np.uint64)
    np.add.at(out, p_idx * words + m_idx // 64, np.left_shift(np.uint64(1), pos.astype(np.uint64)))
    return out.reshape(num_points, words)


def unique_word_rows(words: npt.NDArray[np.uint64]) -> tuple[npt.NDArray[np.uint64], npt.NDArray[np.int64]]:
    """Unique rows of a (P, W) uint64 array in lexicographic (numeric) order and the inverse (P,).

    Equal to ``np.unique(words, axis=0, return_inverse=True)`` (for W = 1, to ``np.unique(words[:, 0],
    return_inverse=True)``), through one stable W-key ``np.lexsort``: a point's covering set repeats over
    thousands of points, and numpy's quicksort-based ``unique`` is ≈ 10× slower on such runs of equal
    values (its sort of a structured view for W > 1 another 3× slower).
    """
    p = words.shape[0]
    if p == 0:
        return words[:0], np.zeros(0, np.int64)
    order = np.lexsort(words.T[::-1])  # the last key is the primary one: column 0 first
    ordered = words[order]
    start = np.empty(p, bool)
    start[0] = True
    start[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    inv = np.empty(p, np.int64)
    inv[order] = np.cumsum(start) - 1
    return ordered[start], inv


def paint(soft: SoftMasks, proj: Projected, cfg: ProjectionConfig | None = None) -> Painted:
    """Paint projected points with an image's soft masks.

    1. The pairs (mask m, point p) with m covering p's pixel (:func:`covering_pairs`).
    2. If ``cfg.depth_clustering``: per mask, only its largest depth cluster (:func:`cluster_pairs`).
    3. Points covered by no remaining mask get no observation.
    4. Each distinct covering set S_k (hashed as bits, :func:`combination_words`, :func:`unique_word_rows`)
       becomes a table row ``Σ_{m∈S_k} w_m p_m / Σ_{m∈S_k} w_m`` with ``w = soft.confidence``,
       ``p = soft.probs``; rows are in the order of the sets' packed bit patterns.

    Args:
        soft: the image's masks (M masks, C classes).
        proj: projection of the scan into that image.
        cfg: depth-clustering parameters (``min_depth`` was used by :func:`project_points`).
    """
    cfg = cfg or ProjectionConfig()
    c = soft.num_classes
    if soft.num_masks == 0 or len(proj) == 0:
        return Painted.empty(c)
    if proj.u.max() >= soft.width or proj.v.max() >= soft.height:
        raise ValueError(f"projected pixels exceed the {soft.height}×{soft.width} mask size")
    m_idx, p_idx = covering_pairs(soft, proj.u, proj.v)
    if cfg.depth_clustering:
        m_idx, p_idx = cluster_pairs(
            m_idx, p_idx, proj.depth, soft.num_masks, cfg.cluster_gap, cfg.min_cluster_points
        )
    if len(m_idx) == 0:
        return Painted.empty(c)
    words = combination_words(m_idx, p_idx, len(proj), soft.num_masks)
    covered = np.flatnonzero(np.bincount(p_idx, minlength=len(proj)))
    uniq, inv = unique_word_rows(words[covered])
    uniq_bits = np.ascontiguousarray(uniq).view(np.uint8)[:, : -(-soft.num_masks // 8)]
    combos = np.unpackbits(uniq_bits, axis=1, count=soft.num_masks).astype(np.float32)  # (K, M)
    # A zero confidence would make a single-mask row 0/0; a tiny weight keeps it that mask's distribution.
    w = combos * np.maximum(soft.confidence, np.float32(1e-6))[None, :]
    table = (w @ soft.probs) / w.sum(axis=1, keepdims=True)
    return Painted(proj.idx[covered], inv.astype(np.int32), table.astype(np.float32))


__all__ = [
    "Painted",
    "Projected",
    "ProjectionConfig",
    "cluster_pairs",
    "combination_words",
    "covering_pairs",
    "depth_cluster_filter",
    "largest_depth_cluster",
    "paint",
    "project_points",
    "unique_word_rows",
]
