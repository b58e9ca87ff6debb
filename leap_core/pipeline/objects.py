"""The ``motion`` and ``tracks`` stages: objects through a sequence (docs/METHOD.md B.6).

``motion`` (after ``project``, before ``fuse``; when ``tracking.exclude_moving``): per scan, the points whose
own projected label is a thing class are clustered into segments, placed in the world by the scan's pose
and tracked through the sequence (:mod:`leap_core.tracking`); the moving tracks' points go to
``motion.npz`` (the ``tracks.npz`` format, moving tracks only), which the fusion reads to leave them out.

``tracks`` (after ``label_points``): the same on the remaining thing points (a point whose final label or
whose own projected label is a thing class), numbered after the motion stage's movers, both written to
``tracks.npz`` (:mod:`leap_core.pipeline.tracks_file`).

The export (``stage_export``) gives a tracked point its track id in the upper 16 bits, the track's class
where the track is voted (``tracking.vote``: by default only moving tracks) and, while the track moves,
the class's moving id.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError, LeapError
from leap_core.fusion import voxel_keys
from leap_core.geometry import affine_points
from leap_core.instances import CameraInstances, point_instances
from leap_core.io_utils import read_npz
from leap_core.labelers.base import Instances
from leap_core.pipeline.apply import RunCorrections
from leap_core.pipeline.context import Ctx, load_observation, ordered_map
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.projection import project_points
from leap_core.tracking import (
    TrackingConfig,
    TrackTable,
    euclidean_segments,
    mask_segments,
    moving_only,
    present_ids,
    segment_summary,
    stack_tables,
    track_ids,
    track_table,
)
from leap_core.types import UNLABELED

SCAN_PERIOD = 0.1
"""Seconds between scans when a sequence has no ``times.txt`` (KITTI's 10 Hz): frame number × this."""

MAX_TRACKS = 0xFFFF
"""Track ids go into the upper 16 bits of a ``.label`` value."""


def scan_times(ctx: Ctx) -> npt.NDArray[np.float64]:
    """(T,) seconds of the run's frames: ``times.txt`` where the sequence has it, else frame number ×
    :data:`SCAN_PERIOD`."""
    idx = np.asarray(list(ctx.frames), dtype=np.int64)
    if ctx.seq.times is not None:
        return np.asarray(ctx.seq.times, dtype=np.float64)[idx]
    numbers = np.asarray(ctx.seq.frame_numbers, dtype=np.float64)[idx]
    return numbers * SCAN_PERIOD


def thing_votes(
    label: npt.NDArray[np.int16], point_label: npt.NDArray[np.int16], things: npt.NDArray[np.bool_]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Thing points of one scan and their class votes.

    Returns:
        rows (P,) int64 of points whose ``label`` (final) or ``point_label`` (this scan's projection) is a
        thing class; votes (P, C) float64: 1 for each of the two that is a thing (a mover's final label is
        often the map's smeared guess, its projected label this scan's own view).
    """
    c = things.shape[0]
    lut = np.concatenate([things, [False]])  # index -1 (UNLABELED) → False
    is_final = lut[label]
    is_point = lut[point_label]
    rows = np.flatnonzero(is_final | is_point)
    votes = np.zeros((rows.size, c))
    sel = is_final[rows]
    votes[np.flatnonzero(sel), label[rows][sel]] += 1
    sel = is_point[rows]
    votes[np.flatnonzero(sel), point_label[rows][sel]] += 1
    return rows, votes


def corrected_rows(
    corr: RunCorrections, frame_id: str, rows: npt.NDArray[np.int64], keys: npt.NDArray[np.int64]
) -> npt.NDArray[np.bool_]:
    """(P,) bool: which of a scan's points ``rows`` (with their voxel ``keys``) a manual correction labels
    (map scope: its voxel; scan scope: the point): a correction wins over a track's class vote."""
    scan_points, _ = corr.scan.of(frame_id)
    return np.isin(keys, corr.map_keys) | np.isin(rows, scan_points)


_INSTANCE_MEMBERS = ("size", "instance_ids", "instance_label", "instance_score")


def scan_instances(ctx: Ctx, i: int) -> npt.NDArray[np.int32]:
    """(N,) int32 the 2D instance each point of frame ``i``'s scan falls in (0 = none), numbered across
    the frame's cameras (:func:`~leap_core.instances.point_instances`).

    Nothing is stored for it: the scan is projected into each camera again (as the ``project`` stage did,
    ``projection.min_depth``), the instance ids come from the 2D label files, and the points the
    depth clustering kept in a camera are those its observation painted (``observations/``, per camera
    by its ``camera`` member). A 2D label file without instances (written before they existed) adds none.
    """
    fid = ctx.fid(i)
    obs = ctx.layout.observation(fid)
    rig = ctx.seq.cameras
    try:
        z = read_npz(obs, ("point_idx", "n_points", *(("camera",) if len(rig) > 1 else ())))
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(obs, f"unreadable observation file ({exc})") from exc
    n = int(z["n_points"])
    painted = np.asarray(z["point_idx"], np.int64)
    camera = np.asarray(z["camera"], np.int64) if "camera" in z else np.zeros(painted.size, np.int64)
    pts: npt.NDArray[np.float32] | None = None
    views: list[CameraInstances] = []
    for k, cam in enumerate(rig):
        path = ctx.layout.labels2d(fid, cam.name if k else None)
        if k and not path.is_file():
            continue
        try:
            arrays = read_npz(path, _INSTANCE_MEMBERS)
        except KeyError:
            continue
        except (OSError, ValueError) as exc:
            raise DatasetError(path, f"unreadable 2D label file ({exc})") from exc
        h, w = (int(x) for x in arrays["size"])
        try:
            ins = Instances(
                np.asarray(arrays["instance_ids"], np.int32),
                np.asarray(arrays["instance_label"], np.int16),
                np.asarray(arrays["instance_score"], np.float32),
            )
        except ValueError as exc:
            raise DatasetError(path, f"unreadable 2D label file ({exc})") from exc
        if ins.num_instances == 0:
            continue
        if pts is None:
            pts = ctx.seq.frame(i).points
        proj = project_points(pts, ctx.seq.lidar_to_image(i, k), h, w, ctx.cfg.projection.min_depth)
        kept = np.isin(proj.idx, painted[camera == k])
        views.append(CameraInstances(proj.idx, proj.u, proj.v, kept, ins))
    return point_instances(n, views).point


def segment_points(
    ctx: Ctx, i: int, rows: npt.NDArray[np.int64], xyz: npt.NDArray[np.float64]
) -> npt.NDArray[np.int64]:
    """Segments of frame ``i``'s thing points ``rows`` (P,) at world ``xyz`` (P, 3) by the run's
    ``tracking.segments`` (:func:`~leap_core.tracking.euclidean_segments` or
    :func:`~leap_core.tracking.mask_segments`): (P,) segment index, -1 = dropped."""
    cfg = ctx.cfg.tracking
    if cfg.segments == "euclidean" or not rows.size:
        return euclidean_segments(xyz, cfg.cluster_radius, cfg.min_segment_points)
    return mask_segments(xyz, scan_instances(ctx, i)[rows], cfg.cluster_radius, cfg.min_segment_points)


Segments = tuple[
    npt.NDArray[np.int32],
    npt.NDArray[np.int32],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.bool_],
]
"""One scan's segmented points: rows (P,) int32, segment (P,) int32, per segment centroid (S, 3), votes
(S, C) and ground box (S, 4), and per point a stage's own flag (P,) bool."""


_NO_SEGMENTS: Segments = (
    np.zeros(0, np.int32),
    np.zeros(0, np.int32),
    np.zeros((0, 3)),
    np.zeros((0, 0)),
    np.zeros((0, 4)),
    np.zeros(0, bool),
)
"""A scan's segments once they are used (:func:`_tracked_points`)."""


def _track_scans(
    ctx: Ctx, stage: str, segments: Callable[[int], Segments]
) -> tuple[list[Segments], list[npt.NDArray[np.int64]], TrackTable]:
    """``segments`` of every frame (frame threads at a time, in order), their track ids and the track
    table (:mod:`leap_core.tracking`, steps 2-5)."""
    cfg = ctx.cfg.tracking
    frames = list(ctx.frames)
    total = len(frames)
    per_scan: list[Segments] = []
    ctx.tick(stage, 0, total)
    for done, item in enumerate(ordered_map(segments, frames, ctx.frame_threads), start=1):
        per_scan.append(item)
        ctx.tick(stage, done, total)
    times = scan_times(ctx)
    ids = track_ids([s[2] for s in per_scan], times, cfg, [s[4] for s in per_scan])
    table = track_table(
        ids, [s[2] for s in per_scan], [s[3] for s in per_scan], [s[4] for s in per_scan], times, cfg
    )
    return per_scan, ids, table


def _check_count(ctx: Ctx, tracks: int) -> None:
    if tracks > MAX_TRACKS:
        raise LeapError(
            f"{tracks} tracks in sequence {ctx.layout.folder.name}: more than the {MAX_TRACKS} instance ids "
            "a .label holds; raise tracking.min_segment_points or label fewer frames per run"
        )


def _save(
    ctx: Ctx, path: Path, kept: list[tuple[npt.NDArray[np.int32], npt.NDArray[np.int32]]], table: TrackTable
) -> int:
    """Writes per-scan (rows, track ids) and the table as ``tracks.npz``'s format; returns the point count.
    Empties ``kept`` once its arrays are joined, so that the per-scan copies are gone while the file is
    written."""
    offsets = np.concatenate([[0], np.cumsum([r.size for r, _ in kept])]).astype(np.int64)
    rows = np.concatenate([r for r, _ in kept], dtype=np.int32) if kept else np.zeros(0, np.int32)
    track = np.concatenate([k for _, k in kept], dtype=np.int32) if kept else np.zeros(0, np.int32)
    kept.clear()
    SequenceTracks(tuple(ctx.frame_ids()), offsets, rows, track, table).save(path)
    return int(rows.size)


# -------------------------------------------------------------------------------------------- motion
def motion_enabled(cfg: TrackingConfig) -> bool:
    """Whether the ``motion`` stage runs and the fusion leaves its movers out."""
    return cfg.enabled and cfg.exclude_moving


def motion_inputs(ctx: Ctx) -> dict[str, Any]:
    """The ``motion`` stage's fingerprint parts: the tracking settings it uses (not ``vote``, which only
    the export reads, so that trying the other vote does not fuse again) and which classes are things."""
    cfg = ctx.cfg.tracking
    used = (
        "cluster_radius",
        "min_segment_points",
        "gate",
        "max_missed",
        "moving_speed",
        "moving_distance",
        "min_track_scans",
        "max_speed",
        "velocity_scans",
        "distance",
        "segments",
    )
    return {
        "tracking": {k: getattr(cfg, k) for k in used},
        "things": [[c.name, bool(c.thing)] for c in ctx.schema.classes],
    }


def stage_motion(ctx: Ctx) -> dict[str, Any]:
    """Moving objects from the per-scan projected labels, before the fusion → ``motion.npz``.

    A scan's thing points are those whose own projected label (B.2, this scan's view) is a thing class,
    one vote each; segments, tracks and motion as the ``tracks`` stage makes them. Only the moving tracks
    are kept, numbered 1..M in order of birth; each takes the class its points' projected labels vote for
    over all its scans. Manual corrections play no part here (the ``tracks`` stage leaves corrected points
    out of objects), so a scan-scope correction does not fuse again.
    """
    things = ctx.schema.things()

    def segments(i: int) -> Segments:
        path = ctx.layout.observation(ctx.fid(i))
        painted, n, _ = load_observation(path)
        point_label = painted.point_labels(n)
        rows, votes = thing_votes(np.full(n, UNLABELED, np.int16), point_label, things)
        frame = ctx.seq.frame(i)
        xyz = affine_points(frame.points_at(rows)[:, :3], frame.pose[:3]) if rows.size else np.zeros((0, 3))
        seg = segment_points(ctx, i, rows, xyz)
        centroid, hist, box = segment_summary(xyz, seg, votes, things.shape[0])
        keep = seg >= 0
        return (
            rows[keep].astype(np.int32),
            seg[keep].astype(np.int32),
            centroid,
            hist,
            box,
            np.ones(int(keep.sum()), bool),
        )

    per_scan, ids, table = _track_scans(ctx, "motion", segments)
    movers, new_id = moving_only(table)
    _check_count(ctx, movers.label.size)
    kept = []
    for t, s in enumerate(per_scan):
        track_of_row = new_id[ids[t][s[1]] - 1].astype(np.int32)
        keep = track_of_row > 0
        kept.append((s[0][keep], track_of_row[keep]))
    del per_scan
    points = _save(ctx, ctx.layout.motion, kept, movers)
    return {"tracks": int(table.label.size), "moving_tracks": int(movers.label.size), "moving_points": points}


def read_motion(ctx: Ctx) -> SequenceTracks | None:
    """The ``motion`` stage's movers, or None when it does not run (tracking or ``exclude_moving`` off)."""
    if not motion_enabled(ctx.cfg.tracking):
        return None
    return SequenceTracks.load(ctx.layout.motion)


def _tracked_points(
    frames: Sequence[int],
    per_scan: list[Segments],
    ids: list[npt.NDArray[np.int64]],
    first: int,
    moving: npt.NDArray[np.bool_],
    mover_rows: dict[int, tuple[npt.NDArray[np.int32], npt.NDArray[np.int64]]],
) -> list[tuple[npt.NDArray[np.int32], npt.NDArray[np.int32]]]:
    """Per scan, the (rows, track ids) that keep their track: the ``motion`` stage's movers (``mover_rows``
    by frame), then the segments' points, their ids offset by ``first`` (the movers' count).

    A static track keeps the map's word on its points: those the final grid calls stuff (a mask's bleed
    onto the road beside a parked car, seen in one scan) stay stuff and get no id; a moving track takes
    all its points, since the map's label at a mover is its trail. Empties ``per_scan`` as it goes, so
    one copy of the sequence's tracked points is held at a time.
    """
    kept = []
    for t, i in enumerate(frames):
        s = per_scan[t]
        track_of_row = (ids[t][s[1]] + first).astype(np.int32)
        keep = s[5] | moving[track_of_row - 1]
        own = (s[0][keep], track_of_row[keep])
        if i in mover_rows:
            m_rows, m_track = mover_rows[i]
            own = (
                np.concatenate([m_rows, own[0]]).astype(np.int32),
                np.concatenate([m_track, own[1]]).astype(np.int32),
            )
        kept.append(own)
        per_scan[t] = _NO_SEGMENTS
    return kept


# -------------------------------------------------------------------------------------------- tracks
def stage_tracks(ctx: Ctx) -> dict[str, Any]:
    """Segments per scan, tracks over the sequence, class vote and motion → ``tracks.npz``, after the
    ``motion`` stage's movers (ids 1..M, kept as that stage found them: their points were left out of the
    map, so their final labels hold no word of theirs). Points a manual correction labels are left out
    (their label is the correction's)."""
    things = ctx.schema.things()
    corr = RunCorrections.of_run(ctx.layout, ctx.schema.num_classes)
    movers = read_motion(ctx)
    vs = ctx.cfg.fusion.voxel_size
    mover_rows: dict[int, tuple[npt.NDArray[np.int32], npt.NDArray[np.int64]]] = {}

    def segments(i: int) -> Segments:
        fid = ctx.fid(i)
        path = ctx.layout.points(fid)
        try:
            z = read_npz(path, ("label", "point_label"))
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable point labels ({exc})") from exc
        rows, votes = thing_votes(z["label"], z["point_label"], things)
        final_thing = things[np.maximum(z["label"][rows], 0)] & (z["label"][rows] >= 0)
        frame = ctx.seq.frame(i)
        if movers is not None:
            obj = movers.scan(fid)
            mxyz = (
                affine_points(frame.points_at(obj.rows)[:, :3], frame.pose[:3])
                if obj.rows.size
                else np.zeros((0, 3))
            )
            free = ~corrected_rows(corr, fid, obj.rows.astype(np.int64), voxel_keys(mxyz, vs))
            mover_rows[i] = (obj.rows[free], obj.track[free].astype(np.int64))
            mine = ~np.isin(rows, obj.rows)
            rows, votes, final_thing = rows[mine], votes[mine], final_thing[mine]
        xyz = affine_points(frame.points_at(rows)[:, :3], frame.pose[:3]) if rows.size else np.zeros((0, 3))
        free = ~corrected_rows(corr, fid, rows, voxel_keys(xyz, vs))
        rows, votes, xyz, final_thing = rows[free], votes[free], xyz[free], final_thing[free]
        seg = segment_points(ctx, i, rows, xyz)
        centroid, hist, box = segment_summary(xyz, seg, votes, things.shape[0])
        keep = seg >= 0
        return rows[keep].astype(np.int32), seg[keep].astype(np.int32), centroid, hist, box, final_thing[keep]

    per_scan, ids, table = _track_scans(ctx, "tracks", segments)
    first = movers.table.label.size if movers is not None else 0
    if movers is not None:
        table = stack_tables(movers.table, table)
    _check_count(ctx, table.label.size)
    kept = _tracked_points(ctx.frames, per_scan, ids, first, table.moving, mover_rows)
    # An id only for a track with points: a static track whose points the map all calls stuff, or a track
    # whose points are all corrected, goes, and the others close up (still in order of birth).
    new_id, present = present_ids([k for _, k in kept], table.label.size)
    new_id32 = new_id.astype(np.int32)
    for t, (r, k) in enumerate(kept):
        kept[t] = (r, new_id32[k])
    table = table.take(present)
    points = _save(ctx, ctx.layout.tracks, kept, table)
    return {
        "tracks": int(table.label.size),
        "moving_tracks": int(table.moving.sum()),
        "moving_before_fusion": int(present[:first].sum()),
        "tracked_points": points,
    }


__all__ = [
    "SCAN_PERIOD",
    "corrected_rows",
    "motion_enabled",
    "motion_inputs",
    "read_motion",
    "scan_instances",
    "scan_times",
    "segment_points",
    "stage_motion",
    "stage_tracks",
    "thing_votes",
]
