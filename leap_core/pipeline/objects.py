"""The ``tracks`` stage: objects through a sequence (docs/METHOD.md B.6).

Per scan, the thing points (a point whose final label or whose own projected label is a thing class) are
clustered into segments and their centroids placed in the world by the scan's pose; segments become
tracks (:mod:`leap_core.tracking`), written to ``tracks.npz`` (:mod:`leap_core.pipeline.tracks_file`).

The export (``stage_export``) gives a tracked point its track id in the upper 16 bits, the track's class
where the track is voted (``tracking.vote``: by default only moving tracks) and, while the track moves,
the class's moving id.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError, LeapError
from leap_core.fusion import voxel_keys
from leap_core.geometry import affine_points
from leap_core.io_utils import read_npz
from leap_core.pipeline.apply import RunCorrections
from leap_core.pipeline.context import Ctx, ordered_map
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.tracking import euclidean_segments, segment_summary, track_ids, track_table

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


def stage_tracks(ctx: Ctx) -> dict[str, Any]:
    """Segments per scan, tracks over the sequence, class vote and motion → ``tracks.npz``. Points a manual
    correction labels are left out (their label is the correction's)."""
    cfg = ctx.cfg.tracking
    things = ctx.schema.things()
    corr = RunCorrections.of_run(ctx.layout, ctx.schema.num_classes)
    vs = ctx.cfg.fusion.voxel_size
    frames = list(ctx.frames)
    total = len(frames)

    def segments(i: int) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int64], Any, Any, Any, Any]:
        fid = ctx.fid(i)
        path = ctx.layout.points(fid)
        try:
            z = read_npz(path, ("label", "point_label"))
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable point labels ({exc})") from exc
        rows, votes = thing_votes(z["label"], z["point_label"], things)
        final_thing = things[np.maximum(z["label"][rows], 0)] & (z["label"][rows] >= 0)
        frame = ctx.seq.frame(i)
        xyz = affine_points(frame.points_at(rows)[:, :3], frame.pose[:3]) if rows.size else np.zeros((0, 3))
        free = ~corrected_rows(corr, fid, rows, voxel_keys(xyz, vs))
        rows, votes, xyz, final_thing = rows[free], votes[free], xyz[free], final_thing[free]
        seg = euclidean_segments(xyz, cfg.cluster_radius, cfg.min_segment_points)
        centroid, hist, box = segment_summary(xyz, seg, votes, things.shape[0])
        keep = seg >= 0
        return rows[keep].astype(np.int32), seg[keep], centroid, hist, box, final_thing[keep]

    per_scan = []
    ctx.tick("tracks", 0, total)
    for done, item in enumerate(ordered_map(segments, frames, ctx.frame_threads), start=1):
        per_scan.append(item)
        ctx.tick("tracks", done, total)
    times = scan_times(ctx)
    ids = track_ids([s[2] for s in per_scan], times, cfg)
    table = track_table(
        ids, [s[2] for s in per_scan], [s[3] for s in per_scan], [s[4] for s in per_scan], times, cfg
    )
    if table.label.size > MAX_TRACKS:
        raise LeapError(
            f"{table.label.size} tracks in sequence {ctx.layout.folder.name}: more than the {MAX_TRACKS} "
            "instance ids a .label holds; raise tracking.min_segment_points or label fewer frames per run"
        )
    # A static track keeps the map's word on its points: those the final grid calls stuff (a mask's bleed
    # onto the road beside a parked car, seen in one scan) stay stuff and get no id; a moving track takes
    # all its points, since the map's label at a mover is its trail.
    kept = []
    for t, s in enumerate(per_scan):
        track_of_row = ids[t][s[1]]
        keep = s[5] | table.moving[track_of_row - 1]
        kept.append((s[0][keep], track_of_row[keep]))
    counts = [r.size for r, _ in kept]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    rows = np.concatenate([r for r, _ in kept]) if kept else np.zeros(0, np.int32)
    track = np.concatenate([k for _, k in kept]).astype(np.int32) if kept else np.zeros(0, np.int32)
    SequenceTracks(tuple(ctx.frame_ids()), offsets, rows.astype(np.int32), track, table).save(
        ctx.layout.tracks
    )
    return {
        "tracks": int(table.label.size),
        "moving_tracks": int(table.moving.sum()),
        "tracked_points": int(rows.size),
    }


__all__ = [
    "SCAN_PERIOD",
    "corrected_rows",
    "scan_times",
    "stage_tracks",
    "thing_votes",
]
