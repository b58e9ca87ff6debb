"""Objects through a sequence: per-scan segments of thing points, tracks, one class per track, motion
(docs/METHOD.md B.6).

Pure functions on arrays; the pipeline stage (:mod:`leap_core.pipeline.stages`, ``tracks``) does the I/O.

1. **Segments.** A scan's thing points (points whose own label or per-scan projected label is a thing
   class) are grouped by Euclidean clustering on a grid (:func:`euclidean_segments`): cubes of side
   ``cluster_radius`` that touch are connected (scipy's ``connected_components``). With ``segments:
   masks`` (:func:`mask_segments`) the points of one 2D instance mask (those the projection kept after
   depth clustering) form one segment whatever their distance, so two people side by side, one mask
   each, are two segments; the points no mask covers join the mask of their nearest covered point in the
   same Euclidean cluster, or form that cluster's own segment where it holds no covered point. Segments
   with fewer than ``min_segment_points`` points are dropped.
2. **Tracks.** Each live track predicts where it is at the scan's time with a constant-velocity model:
   its last centroid (and ground box) move by ``v · (t - t_last)``. ``v`` is the least-squares slope of its
   last ``velocity_scans`` centroids against time (:func:`recent_velocity`; 0 for a track seen once), not
   the step between the last two: the visible part of an object changes from scan to scan (an oncoming
   car shows its front, then its side) and one jump of its centroid would throw the next prediction off.
   The distance of segment s to track k is ``d = ‖ĉ_k - c_s‖`` (``distance: centroid``) or, with
   ``distance: box``, the gap between the ground boxes ``d = ‖(max(0, x0_s - x1_k, x0_k - x1_s), likewise
   y)‖`` (:func:`box_gap`, 0 where they overlap; cost ``d + 0.1 · ‖ĉ_k - c_s‖``, the centroid term
   ordering pairs whose boxes overlap). Pairs with ``d`` above the track's gate are forbidden and scipy's
   ``linear_sum_assignment`` picks the one-to-one assignment of least total cost. The gate grows with what
   the track does not know: ``gate`` for a track with a velocity, ``gate + max_speed · (t - t_last)`` for a
   track seen once, which may be moving at up to ``max_speed`` in any direction. Unassigned segments start
   tracks; a track unseen for more than ``max_missed`` scans ends. Track ids are 1, 2, ... in order of
   birth, unique over the sequence; the ``tracks`` stage keeps only the ids with points in some scan
   (:func:`present_ids`).
3. **Class.** A track's class is the argmax of its segments' summed class votes over all its scans.
   The vote's evidence is kept for review (:class:`VoteEvidence`): the winner's share of the votes and the
   runner-up class with its share.
   Which tracks' points take it is ``vote``: ``"moving"`` (default) only a moving track's, since the map's
   label at a mover is its trail; a static track's points keep their own per-point class (and still get
   the track's id), because a segment from 3D clustering alone can hold a person beside a bicycle or a
   car, and one class would win for both. ``"all"``: every track's points.
4. **Motion.** A track's velocity is the least-squares slope of its centroids against time. Its *sweep*
   is how far its ground footprint reaches beyond one scan's: with each segment's axis-aligned box
   ``[x0, x1] × [y0, y1]`` (world, metres), ``e_x = (max x1 - min x0) - max_t (x1 - x0)`` over its scans,
   likewise ``e_y``, sweep ``= √(e_x² + e_y²)``. A track is moving when it has at least
   ``min_track_scans`` scans, its speed ``‖v‖`` reaches ``moving_speed`` and its sweep reaches
   ``moving_distance``. The sweep, not ``‖v‖ · duration``, because a parked car seen first from afar (a
   few points on its front) and then whole has a centroid that drifts by metres, while its footprint
   never leaves the box of its largest view; a mover's footprint does, by the distance it travelled.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from leap_core.bounds import check_bounds, within
from leap_core.errors import ConfigError

_FORBIDDEN = 1e9
_TIE_BREAK = 0.1
"""Weight of the centroid distance in the association cost: it only orders pairs whose boxes overlap."""
_HALF_NEIGHBOURS = [
    (dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) > (0, 0, 0)
]
"""13 of the 26 neighbour offsets, one of each opposite pair: each adjacency is found once."""


@dataclass(frozen=True)
class TrackingConfig:
    """Segments, association and motion of the ``tracks`` stage."""

    enabled: bool = True
    """Build tracks (instance ids, moving labels); off: exports keep instance 0 and static ids."""
    cluster_radius: float = field(default=0.5, metadata=within(0.05, 10, unit="m"))
    """Euclidean clustering cube side: points in touching cubes are one segment (points closer than this
    always are). 0.5 m joins the returns of one car or person (a few centimetres to 30 cm apart within
    40 m) and keeps apart objects 2 m apart."""
    min_segment_points: int = field(default=5, metadata=within(1, 100_000))
    """Smaller segments are dropped (stray points of a thing class)."""
    gate: float = field(default=2.0, metadata=within(0.1, 100, unit="m"))
    """Largest distance (``distance``) between a track's prediction and a segment for an association, for
    a track whose velocity is known (module docstring, step 2)."""
    max_speed: float = field(default=5.0, metadata=within(0, 100, unit="m/s"))
    """How fast an object seen only once may be moving: such a track has no velocity to predict with, so
    its gate grows by ``max_speed · Δt`` (0.5 m at 10 Hz). Higher lets a new track reach its object after a
    larger first step but also a neighbour's segment (docs/METHOD.md B.6 gives the measured trade)."""
    distance: Literal["centroid", "box"] = "centroid"
    """What the gate and the association cost measure between a track's prediction and a segment:
    ``centroid``, the distance of the centroids; ``box``, the gap between the ground boxes (module
    docstring, step 2; docs/METHOD.md B.6 gives the measured figures behind the default)."""
    velocity_scans: int = field(default=5, metadata=within(2, 100))
    """A track's velocity for its prediction is the least-squares slope over its last this many
    observations, so one jump of a partial view's centroid does not throw it off."""
    max_missed: int = field(default=3, metadata=within(0, 1000))
    """A track not associated for more than this many scans ends."""
    moving_speed: float = field(default=0.5, metadata=within(0, 100, unit="m/s"))
    """Least speed of a moving track (a walking person: 1.3 m/s)."""
    moving_distance: float = field(default=1.0, metadata=within(0, 1000, unit="m"))
    """Least sweep of a moving track: how far its footprint reaches beyond its largest single view."""
    min_track_scans: int = field(default=3, metadata=within(2, 1000))
    """Tracks seen in fewer scans are never moving (their slope is noise)."""
    vote: Literal["moving", "all"] = "moving"
    """Whose points take their track's voted class: ``moving`` tracks' only (a static track's points keep
    their own class and get the id), or ``all`` tracks' (docs/METHOD.md B.6 gives the measured trade)."""
    exclude_moving: bool = False
    """Find moving objects before the fusion, from the per-scan projected labels (the ``motion`` stage),
    and keep their points out of the voxel map, so neither a mover nor what it passes is smeared; their
    labels come from their track. Off (default): every observed point is fused, and the ``tracks`` stage
    finds movers from the final labels too, which on the demo street labels more moving points right
    (docs/METHOD.md B.6 gives the measured trade)."""

    segments: Literal["masks", "euclidean"] = "euclidean"
    """How a scan's thing points form segments: ``euclidean`` (3D clustering only) or ``masks`` (one
    segment per 2D instance mask, Euclidean clustering for the points no mask covers; module docstring,
    step 1; docs/METHOD.md B.6 gives the measured figures behind the default)."""

    def __post_init__(self) -> None:
        check_bounds(self)
        if self.vote not in ("moving", "all"):
            raise ConfigError(f"must be 'moving' or 'all', got {self.vote!r}", field=("vote",))
        if self.distance not in ("centroid", "box"):
            raise ConfigError(f"must be 'centroid' or 'box', got {self.distance!r}", field=("distance",))
        if self.segments not in ("masks", "euclidean"):
            raise ConfigError(f"must be 'masks' or 'euclidean', got {self.segments!r}", field=("segments",))


def euclidean_segments(xyz: npt.ArrayLike, radius: float, min_points: int) -> npt.NDArray[np.int64]:
    """(N,) int64 segment index 0..S-1 per point, -1 for points of segments under ``min_points``.

    Euclidean clustering on a grid: the points fall into cubes of side ``radius``; cubes that share a face,
    edge or corner (26-neighbourhood) are connected, and a segment is a connected set of occupied cubes.
    So points closer than ``radius`` always share a segment, and points more than ``2√3 · radius`` apart
    never do directly. The radius graph of the points themselves (a k-d tree's pairs) is the same idea
    but costs seconds on a scan's near cars (hundreds of neighbours per point); the cubes cost one sort.
    Segments are numbered by their first point, so the result does not depend on any internal order.
    """
    pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = pts.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    cell = np.floor(pts / radius).astype(np.int64)
    cell -= cell.min(axis=0) - 1  # ≥ 1, so a neighbour's coordinate never goes negative
    span = cell.max(axis=0) + 2
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    cells, of_point = np.unique(key, return_inverse=True)
    m = cells.size
    src: list[npt.NDArray[np.int64]] = []
    dst: list[npt.NDArray[np.int64]] = []
    for dx, dy, dz in _HALF_NEIGHBOURS:
        probe = cells + (dx * span[1] + dy) * span[2] + dz
        pos = np.minimum(np.searchsorted(cells, probe), m - 1)
        hit = cells[pos] == probe
        src.append(np.flatnonzero(hit))
        dst.append(pos[hit])
    a, b = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(m, m))
    _, comp_of_cell = connected_components(graph, directed=False)
    return _numbered(comp_of_cell.astype(np.int64)[of_point.reshape(-1)], min_points)


def _numbered(group: npt.NDArray[np.int64], min_points: int) -> npt.NDArray[np.int64]:
    """(N,) the groups 0..G-1 of ``group`` (N,) renumbered 0, 1, ... by their first point, -1 for those
    under ``min_points`` points: a numbering that no internal order of the grouping shows through."""
    n = group.shape[0]
    sizes = np.bincount(group)
    first = np.full(sizes.size, n, np.int64)
    np.minimum.at(first, group, np.arange(n))
    keep = sizes >= min_points
    order = np.argsort(np.where(keep, first, n + 1), kind="stable")
    rank = np.full(sizes.size, -1, np.int64)
    rank[order[: int(keep.sum())]] = np.arange(int(keep.sum()))
    out: npt.NDArray[np.int64] = rank[group]
    return out


def mask_segments(
    xyz: npt.ArrayLike, instance: npt.ArrayLike, radius: float, min_points: int
) -> npt.NDArray[np.int64]:
    """(N,) int64 segment index 0..S-1 per point, -1 for points of segments under ``min_points``: one
    segment per 2D instance, Euclidean clustering for the rest.

    Args:
        xyz: (N, 3) points (world or sensor coordinates; only distances matter).
        instance: (N,) int 2D instance of each point (:func:`leap_core.instances.point_instances`),
            0 = none.
        radius: the Euclidean clustering's cube side (:func:`euclidean_segments`).
        min_points: smallest segment kept.

    Rule: let E be the Euclidean clusters of all N points (:func:`euclidean_segments` with no size
    floor). Points with the same instance k > 0 are one segment, even where E splits them (a mask's
    points after depth clustering belong to one object). A point with instance 0 takes the instance of
    its nearest point with an instance if that point lies in the same cluster of E (a limb outside the
    image, or returns a mask's edge missed, beside the masked rest); the points of a cluster of E that
    holds no instance form one segment, as :func:`euclidean_segments` would make it. Segments are
    numbered by their first point.
    """
    pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    ins = np.asarray(instance, dtype=np.int64).reshape(-1)
    n = pts.shape[0]
    if ins.shape[0] != n:
        raise ValueError(f"{ins.shape[0]} instance ids for {n} points")
    if n == 0:
        return np.zeros(0, np.int64)
    comp = euclidean_segments(pts, radius, 1)
    covered = np.flatnonzero(ins > 0)
    # Segment keys: instance k → k; a cluster c of E with no covered point → max instance + 1 + c.
    key = ins.copy()
    free = np.flatnonzero(ins == 0)
    if free.size and covered.size:
        near = np.asarray(cKDTree(pts[covered]).query(pts[free])[1], np.int64).reshape(-1)
        same = comp[covered[near]] == comp[free]
        key[free[same]] = ins[covered[near[same]]]
        free = free[~same]
    key[free] = int(ins.max(initial=0)) + 1 + comp[free]
    _, seg = np.unique(key, return_inverse=True)
    return _numbered(seg.reshape(-1).astype(np.int64), min_points)


def segment_summary(
    xyz: npt.ArrayLike, segment: npt.ArrayLike, votes: npt.ArrayLike, num_classes: int
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Centroid (S, 3), summed class votes (S, C) and ground box (S, 4) ``[x0, y0, x1, y1]`` of the
    segments 0..S-1.

    Args:
        xyz: (N, 3) world coordinates.
        segment: (N,) segment index, -1 = in none.
        votes: (N, C) class votes of each point (e.g. one-hot labels).
        num_classes: C.
    """
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    s = np.asarray(segment).reshape(-1)
    v = np.asarray(votes, dtype=np.float64).reshape(-1, num_classes)
    n_seg = int(s.max()) + 1 if s.size else 0
    inside = s >= 0
    count = np.bincount(s[inside], minlength=n_seg).astype(np.float64)
    sums = np.stack([np.bincount(s[inside], p[inside, k], n_seg) for k in range(3)], axis=1)
    centroid: npt.NDArray[np.float64] = sums.astype(np.float64) / np.maximum(count, 1)[:, None]
    si, vi = s[inside], v[inside]
    # One weighted bincount per class: a ufunc.at over the (N, C) votes costs five times as much.
    hist = np.zeros((n_seg, num_classes))
    for k in range(num_classes):
        hist[:, k] = np.bincount(si, vi[:, k], n_seg)
    box = np.empty((n_seg, 4))
    box[:, :2] = np.inf
    box[:, 2:] = -np.inf
    for k in range(2):
        np.minimum.at(box[:, k], si, p[inside, k])
        np.maximum.at(box[:, 2 + k], si, p[inside, k])
    return centroid, hist, box


def box_gap(a: npt.ArrayLike, b: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """(K, S) ground distance between the boxes ``a`` (K, 4) and ``b`` (S, 4), each ``[x0, y0, x1, y1]``:
    ``‖(max(0, x0_b - x1_a, x0_a - x1_b), max(0, y0_b - y1_a, y0_a - y1_b))‖``, 0 where they overlap."""
    p = np.asarray(a, dtype=np.float64).reshape(-1, 4)[:, None, :]
    q = np.asarray(b, dtype=np.float64).reshape(-1, 4)[None, :, :]
    dx = np.maximum(0.0, np.maximum(q[..., 0] - p[..., 2], p[..., 0] - q[..., 2]))
    dy = np.maximum(0.0, np.maximum(q[..., 1] - p[..., 3], p[..., 1] - q[..., 3]))
    gap: npt.NDArray[np.float64] = np.hypot(dx, dy)
    return gap


def _point_boxes(centroids: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(S, 4) boxes of zero size at the centroids' ground positions."""
    return np.concatenate([centroids[:, :2], centroids[:, :2]], axis=1)


def associate(
    predicted: npt.ArrayLike,
    centroids: npt.ArrayLike,
    gate: float | npt.ArrayLike,
    predicted_boxes: npt.ArrayLike | None = None,
    boxes: npt.ArrayLike | None = None,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """One-to-one pairs (track rows, segment rows) of least total cost, each pair within its track's gate
    (module docstring, step 2).

    The distance of a pair is ``d = box_gap(B̂_k, B_s)``; a pair with ``d > gate_k`` is forbidden and the
    cost of the others is ``d + 0.1 · ‖ĉ_k - c_s‖``.

    Args:
        predicted: (K, 3) tracks' predicted centroids ``ĉ``.
        centroids: (S, 3) segments' centroids ``c``.
        gate: the gate of every track, or (K,) one per track.
        predicted_boxes: (K, 4) tracks' predicted ground boxes; None: zero-size boxes at ``predicted``.
        boxes: (S, 4) segments' ground boxes; None: zero-size boxes at ``centroids``.
    """
    a = np.asarray(predicted, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(centroids, dtype=np.float64).reshape(-1, 3)
    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    apart = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    if predicted_boxes is None or boxes is None:
        gap, cost = apart, apart
    else:
        gap = box_gap(predicted_boxes, boxes)
        cost = gap + _TIE_BREAK * apart
    limit = np.broadcast_to(np.asarray(gate, dtype=np.float64).reshape(-1), (a.shape[0],))
    cost = np.where(gap <= limit[:, None], cost, _FORBIDDEN)
    rows, cols = linear_sum_assignment(cost)
    ok = cost[rows, cols] < _FORBIDDEN
    return rows[ok].astype(np.int64), cols[ok].astype(np.int64)


def recent_velocity(times: npt.ArrayLike, centroids: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """(K, 3) least-squares slope of each track's recent centroids against time.

    ``v = Σ_i (t_i - t̄)(c_i - c̄) / Σ_i (t_i - t̄)²`` over the track's observations i (0 where there are
    fewer than two at different times).

    Args:
        times: (K, H) seconds of each track's last H observations, NaN where it has fewer.
        centroids: (K, H, 3) their centroids (ignored where the time is NaN).
    """
    t = np.asarray(times, dtype=np.float64)
    c = np.asarray(centroids, dtype=np.float64).reshape(t.shape[0], t.shape[1], 3)
    seen = ~np.isnan(t)
    n = np.maximum(seen.sum(axis=1), 1)
    t0 = np.where(seen, t, 0.0)
    t_mean = t0.sum(axis=1) / n
    dt = np.where(seen, t - t_mean[:, None], 0.0)
    c0 = np.where(seen[..., None], c, 0.0)
    c_mean = c0.sum(axis=1) / n[:, None]
    var = (dt * dt).sum(axis=1)
    cov = (dt[..., None] * (c0 - c_mean[:, None, :]) * seen[..., None]).sum(axis=1)
    v: npt.NDArray[np.float64] = np.where(var[:, None] > 1e-12, cov / np.maximum(var, 1e-12)[:, None], 0.0)
    return v


class _LiveTracks:
    """The state of the live tracks in :func:`track_ids`, one row per track."""

    def __init__(self, history: int) -> None:
        self.box = np.zeros((0, 4))
        """(K, 4) last ground box."""
        self.past_t = np.zeros((0, history))
        """(K, H) times of the last H observations, oldest first, NaN before the first."""
        self.past_c = np.zeros((0, history, 3))
        """(K, H, 3) their centroids."""
        self.last_scan = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)

    @property
    def pos(self) -> npt.NDArray[np.float64]:
        """(K, 3) last centroid."""
        return self.past_c[:, -1]

    @property
    def last_t(self) -> npt.NDArray[np.float64]:
        """(K,) time of the last observation."""
        return self.past_t[:, -1]

    def keep(self, rows: npt.NDArray[np.bool_]) -> None:
        self.box, self.past_t, self.past_c = self.box[rows], self.past_t[rows], self.past_c[rows]
        self.last_scan, self.ids = self.last_scan[rows], self.ids[rows]

    def observe(
        self,
        rows: npt.NDArray[np.int64],
        cen: npt.NDArray[np.float64],
        box: npt.NDArray[np.float64],
        t: float,
        k: int,
    ) -> None:
        """Tracks ``rows`` seen at ``cen`` (R, 3) with ``box`` (R, 4) in scan ``k`` at time ``t``."""
        self.box[rows] = box
        self.past_t[rows] = np.concatenate([self.past_t[rows, 1:], np.full((rows.size, 1), t)], axis=1)
        self.past_c[rows] = np.concatenate([self.past_c[rows, 1:], cen[:, None, :]], axis=1)
        self.last_scan[rows] = k

    def start(
        self,
        ids: npt.NDArray[np.int64],
        cen: npt.NDArray[np.float64],
        box: npt.NDArray[np.float64],
        t: float,
        k: int,
    ) -> None:
        """New tracks ``ids`` (R,) seen at ``cen`` (R, 3) with ``box`` (R, 4) in scan ``k`` at time ``t``."""
        n, h = ids.size, self.past_t.shape[1]
        past_t = np.full((n, h), np.nan)
        past_t[:, -1] = t
        past_c = np.zeros((n, h, 3))
        past_c[:, -1] = cen
        self.box = np.concatenate([self.box, box])
        self.past_t = np.concatenate([self.past_t, past_t])
        self.past_c = np.concatenate([self.past_c, past_c])
        self.last_scan = np.concatenate([self.last_scan, np.full(n, k, np.int64)])
        self.ids = np.concatenate([self.ids, ids])


def track_ids(
    centroids: Sequence[npt.ArrayLike],
    times: npt.ArrayLike,
    cfg: TrackingConfig,
    boxes: Sequence[npt.ArrayLike] | None = None,
) -> list[npt.NDArray[np.int64]]:
    """Track id (1, 2, ...) of every segment of every scan (module docstring, step 2).

    Args:
        centroids: per scan t, (S_t, 3) segment centroids in world coordinates.
        times: (T,) seconds of each scan, increasing.
        cfg: ``gate``, ``max_speed``, ``velocity_scans``, ``distance`` and ``max_missed``.
        boxes: per scan t, (S_t, 4) segment ground boxes ``[x0, y0, x1, y1]``, for ``distance: box``; None:
            zero-size boxes at the centroids.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.shape[0] != len(centroids):
        raise ValueError(f"{t.shape[0]} times for {len(centroids)} scans")
    if boxes is not None and len(boxes) != len(centroids):
        raise ValueError(f"{len(boxes)} scans of boxes for {len(centroids)} scans")
    live = _LiveTracks(cfg.velocity_scans)
    next_id = 1
    out: list[npt.NDArray[np.int64]] = []
    for k, c in enumerate(centroids):
        cen = np.asarray(c, dtype=np.float64).reshape(-1, 3)
        box = _point_boxes(cen) if boxes is None else np.asarray(boxes[k], np.float64).reshape(-1, 4)
        if box.shape[0] != cen.shape[0]:
            raise ValueError(f"scan {k}: {box.shape[0]} boxes for {cen.shape[0]} centroids")
        live.keep(k - live.last_scan <= cfg.max_missed + 1)
        elapsed = t[k] - live.last_t
        shift = recent_velocity(live.past_t, live.past_c) * elapsed[:, None]
        once = np.sum(~np.isnan(live.past_t), axis=1) == 1
        gate = cfg.gate + np.where(once, cfg.max_speed * elapsed, 0.0)
        if cfg.distance == "box":
            rows, cols = associate(live.pos + shift, cen, gate, live.box + shift[:, [0, 1, 0, 1]], box)
        else:
            rows, cols = associate(live.pos + shift, cen, gate)
        seg_ids = np.zeros(cen.shape[0], np.int64)
        seg_ids[cols] = live.ids[rows]
        live.observe(rows, cen[cols], box[cols], float(t[k]), k)
        new = np.setdiff1d(np.arange(cen.shape[0]), cols)
        seg_ids[new] = np.arange(next_id, next_id + new.size)
        next_id += new.size
        live.start(seg_ids[new], cen[new], box[new], float(t[k]), k)
        out.append(seg_ids)
    return out


def present_ids(
    tracks: Sequence[npt.ArrayLike], k: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """Ids without holes for the tracks that have points.

    Args:
        tracks: per scan, (P_t,) the track id 1..K of each point that keeps one.
        k: K, the number of tracks.

    Returns:
        ``new_id`` (K + 1,) int64: the new id of old id j (``new_id[0] = 0``), 1..K' in the old ids' order
        (so still in order of birth) for the tracks with a point, 0 for the others; and ``present`` (K,)
        bool, which old tracks (ids 1..K) have a point, the rows of the table to keep.
    """
    present = np.zeros(k + 1, bool)
    for x in tracks:
        present[np.asarray(x, np.int64).reshape(-1)] = True
    present[0] = False
    new_id = np.where(present, np.cumsum(present), 0).astype(np.int64)
    return new_id, present[1:]


@dataclass(frozen=True)
class VoteEvidence:
    """How clear each track's class vote was (index = id - 1), for the object review queue
    (:mod:`leap_core.object_review`).

    With ``h`` (K, C) the votes summed over a track's scans (:func:`track_table`) and ``n = Σ_c h_c``:
    ``share = h_label / n`` and ``runner_share = h_runner / n``, where ``runner_up`` is the class of the
    second-largest count (ties: the lower index) or -1 when no other class got a vote (then its share is 0).
    A track without votes has ``share`` 0.

    Attributes:
        share: (K,) float64 the winning class's share of the vote, 0..1.
        runner_up: (K,) int16 the runner-up class, -1 = none.
        runner_share: (K,) float64 its share, 0..1.
    """

    share: npt.NDArray[np.float64]
    runner_up: npt.NDArray[np.int16]
    runner_share: npt.NDArray[np.float64]

    @classmethod
    def unknown(cls, k: int) -> VoteEvidence:
        """What a ``tracks.npz`` written before the evidence was kept reads as: every vote unanimous
        (share 1, no runner-up), so no such track is queued for a close vote."""
        return cls(np.ones(k), np.full(k, -1, np.int16), np.zeros(k))

    def take(self, rows: npt.NDArray[np.bool_] | npt.NDArray[np.int64]) -> VoteEvidence:
        """The evidence of the tracks ``rows`` (a mask or indices), in that order."""
        return VoteEvidence(self.share[rows], self.runner_up[rows], self.runner_share[rows])


def vote_evidence(hist: npt.ArrayLike) -> VoteEvidence:
    """:class:`VoteEvidence` of summed class votes ``hist`` (K, C) (the winner is ``argmax``, as
    :func:`track_table` votes)."""
    h = np.asarray(hist, dtype=np.float64)
    k = h.shape[0]
    if k == 0 or h.ndim != 2 or h.shape[1] == 0:
        return VoteEvidence(np.zeros(0), np.zeros(0, np.int16), np.zeros(0))
    total = h.sum(axis=1)
    n = np.maximum(total, 1e-12)
    win = h.argmax(axis=1)
    rest = h.copy()
    rest[np.arange(k), win] = -np.inf
    runner = rest.argmax(axis=1) if h.shape[1] > 1 else np.zeros(k, np.int64)
    runner_votes = rest[np.arange(k), runner] if h.shape[1] > 1 else np.zeros(k)
    has_runner = runner_votes > 0
    return VoteEvidence(
        share=np.where(total > 0, h[np.arange(k), win] / n, 0.0),
        runner_up=np.where(has_runner, runner, -1).astype(np.int16),
        runner_share=np.where(has_runner, runner_votes / n, 0.0),
    )


@dataclass(frozen=True)
class TrackTable:
    """Per track (index = id - 1): class, motion and life.

    Attributes:
        label: (K,) int16 voted class.
        velocity: (K, 3) float64 m/s, the least-squares slope of the centroids.
        moving: (K,) bool.
        scans: (K,) int64 scans the track was seen in.
        sweep: (K,) float64 metres its footprint reaches beyond its largest scan's (module docstring).
        voted: (K,) bool whose points take ``label`` (``TrackingConfig.vote``); the others keep theirs.
        evidence: how clear each class vote was; None where it is not known (a ``tracks.npz`` written
            before it was kept: :meth:`vote_evidence` reads that as unanimous).
    """

    label: npt.NDArray[np.int16]
    velocity: npt.NDArray[np.float64]
    moving: npt.NDArray[np.bool_]
    scans: npt.NDArray[np.int64]
    sweep: npt.NDArray[np.float64]
    voted: npt.NDArray[np.bool_]
    evidence: VoteEvidence | None = None

    def vote_evidence(self) -> VoteEvidence:
        """:attr:`evidence`, or :meth:`VoteEvidence.unknown` where the table has none."""
        return self.evidence if self.evidence is not None else VoteEvidence.unknown(self.label.size)

    def take(self, rows: npt.NDArray[np.bool_] | npt.NDArray[np.int64]) -> TrackTable:
        """The tracks ``rows`` (a mask or indices), in that order."""
        return TrackTable(
            label=self.label[rows],
            velocity=self.velocity.reshape(-1, 3)[rows],
            moving=self.moving[rows],
            scans=self.scans[rows],
            sweep=self.sweep[rows],
            voted=self.voted[rows],
            evidence=None if self.evidence is None else self.evidence.take(rows),
        )


def track_table(
    ids: Sequence[npt.ArrayLike],
    centroids: Sequence[npt.ArrayLike],
    votes: Sequence[npt.ArrayLike],
    boxes: Sequence[npt.ArrayLike],
    times: npt.ArrayLike,
    cfg: TrackingConfig,
) -> TrackTable:
    """Class vote and motion of every track (module docstring, steps 3-4).

    Args:
        ids: per scan, (S_t,) track ids from :func:`track_ids`.
        centroids: per scan, (S_t, 3) centroids.
        votes: per scan, (S_t, C) summed class votes.
        boxes: per scan, (S_t, 4) ground boxes ``[x0, y0, x1, y1]``.
        times: (T,) seconds.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    tid = np.concatenate([np.asarray(x, np.int64).reshape(-1) for x in ids]) if ids else np.zeros(0, np.int64)
    k = int(tid.max()) if tid.size else 0
    c = next((np.asarray(v).shape[1] for v in votes if np.asarray(v).ndim == 2), 1)
    cen = (
        np.concatenate([np.asarray(x, np.float64).reshape(-1, 3) for x in centroids])
        if ids
        else np.zeros((0, 3))
    )
    vot = (
        np.concatenate([np.asarray(x, np.float64).reshape(-1, c) for x in votes]) if ids else np.zeros((0, c))
    )
    when = (
        np.concatenate([np.full(np.asarray(x).reshape(-1).size, t[i]) for i, x in enumerate(ids)])
        if ids
        else np.zeros(0)
    )
    row = tid - 1
    hist = np.zeros((k, c))
    np.add.at(hist, row, vot)
    scans = np.bincount(row, minlength=k).astype(np.int64)
    # Least squares per track: slope = Σ (t - t̄)(x - x̄) / Σ (t - t̄)².
    n = np.maximum(scans, 1).astype(np.float64)
    t_mean = np.bincount(row, when, k) / n
    x_mean = np.stack([np.bincount(row, cen[:, j], k) for j in range(3)], axis=1) / n[:, None]
    dt = when - t_mean[row]
    var = np.bincount(row, dt * dt, k)
    cov = np.stack([np.bincount(row, dt * (cen[:, j] - x_mean[row, j]), k) for j in range(3)], axis=1)
    velocity = np.where(var[:, None] > 0, cov / np.maximum(var, 1e-12)[:, None], 0.0)
    box = np.concatenate([np.asarray(x, np.float64).reshape(-1, 4) for x in boxes or [np.zeros((0, 4))]])
    lo = np.full((k, 2), np.inf)
    hi = np.full((k, 2), -np.inf)
    widest = np.zeros((k, 2))
    for j in range(2):
        np.minimum.at(lo[:, j], row, box[:, j])
        np.maximum.at(hi[:, j], row, box[:, 2 + j])
        np.maximum.at(widest[:, j], row, box[:, 2 + j] - box[:, j])
    sweep = np.linalg.norm(np.maximum(hi - lo - widest, 0), axis=1) if k else np.zeros(0)
    speed = np.linalg.norm(velocity, axis=1)
    moving = (scans >= cfg.min_track_scans) & (speed >= cfg.moving_speed) & (sweep >= cfg.moving_distance)
    return TrackTable(
        label=hist.argmax(axis=1).astype(np.int16) if k else np.zeros(0, np.int16),
        velocity=velocity,
        moving=moving,
        scans=scans,
        sweep=sweep,
        voted=moving.copy() if cfg.vote == "moving" else np.ones(k, bool),
        evidence=vote_evidence(hist),
    )


def stack_tables(first: TrackTable, second: TrackTable) -> TrackTable:
    """The tracks of ``first`` (ids 1..K1) followed by those of ``second`` (ids K1+1..K1+K2)."""
    return TrackTable(
        label=np.concatenate([first.label, second.label]).astype(np.int16),
        velocity=np.concatenate([first.velocity.reshape(-1, 3), second.velocity.reshape(-1, 3)]),
        moving=np.concatenate([first.moving, second.moving]).astype(bool),
        scans=np.concatenate([first.scans, second.scans]).astype(np.int64),
        sweep=np.concatenate([first.sweep, second.sweep]).astype(np.float64),
        voted=np.concatenate([first.voted, second.voted]).astype(bool),
        evidence=_stack_evidence(first.vote_evidence(), second.vote_evidence()),
    )


def _stack_evidence(a: VoteEvidence, b: VoteEvidence) -> VoteEvidence:
    return VoteEvidence(
        np.concatenate([a.share, b.share]).astype(np.float64),
        np.concatenate([a.runner_up, b.runner_up]).astype(np.int16),
        np.concatenate([a.runner_share, b.runner_share]).astype(np.float64),
    )


def moving_only(table: TrackTable) -> tuple[TrackTable, npt.NDArray[np.int64]]:
    """The moving tracks of ``table``, every one voted (its points take its class), and the new id of each
    old track (K,) int64: 1, 2, ... for the moving ones in their order, 0 for the others."""
    new_id = np.where(table.moving, np.cumsum(table.moving), 0).astype(np.int64)
    m = table.moving
    return (
        TrackTable(
            label=table.label[m],
            velocity=table.velocity[m],
            moving=np.ones(int(m.sum()), bool),
            scans=table.scans[m],
            sweep=table.sweep[m],
            voted=np.ones(int(m.sum()), bool),
            evidence=table.vote_evidence().take(m),
        ),
        new_id,
    )


__all__ = [
    "TrackTable",
    "TrackingConfig",
    "VoteEvidence",
    "associate",
    "box_gap",
    "euclidean_segments",
    "mask_segments",
    "moving_only",
    "present_ids",
    "recent_velocity",
    "segment_summary",
    "stack_tables",
    "track_ids",
    "track_table",
    "vote_evidence",
]
