"""Manual corrections on a run's points and export: the per-frame rule the ``label_points`` stage uses, and
the immediate "apply corrections" update of a finished run (no stage reruns).

**Immediate apply** (:func:`apply_to_run`): a finished run's ``points/<frame>.npz`` and
``export/<frame>.label|.conf`` are rewritten for exactly the frames whose points a changed correction
touches, each frame's labels recomputed from the run's final grid with the new corrections on top
(:func:`leap_core.corrections.correct_points`). "Changed" is the difference between the corrections the
run's files carry now (``applied_corrections*.npz``, else the run's own ``corrections*.npz``) and the new
ones: map-scope voxels whose class differs (:func:`~leap_core.corrections.changed_keys`) → frames through
the run's voxel → frames index (``frame_voxels.npz``, :class:`~leap_core.corrections.FrameVoxelIndex`, built
once per run from the scans: every frame's point voxel keys), plus the frames whose scan-scope corrections
differ. The stage records (``stages.json``) are left as the stages wrote them, so the next run's
fingerprints still see the corrections as new and fuse them (a correction is then evidence for the 3D-CN
and smoothing too); the applied files are only the run's own overlay.

Limit: a correction the run itself already fused is one-hot in its final grid; undoing it here recomputes
those points from that grid, i.e. they keep the corrected class until the next run
(:attr:`ApplyResult.baked_reverts` counts such voxels).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.corrections import ERASE, FrameVoxelIndex, ScanCorrections, changed_keys, correct_points
from leap_core.datasets.kitti import Frame, KittiSequence
from leap_core.errors import DatasetError
from leap_core.export import export_labels
from leap_core.fusion import last_per_key, rows_in_sorted, voxel_keys
from leap_core.geometry import affine_points, row_blocks
from leap_core.io_utils import atomic_save_npz, atomic_write_json
from leap_core.pipeline.object_corrections import CorrectedTracks, ObjectCorrections
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.run_layout import SequenceLayout, load_corrections, save_corrections
from leap_core.smoothing import SmoothedGrid
from leap_core.types import UNLABELED


@dataclass(frozen=True)
class RunCorrections:
    """The corrections a run applies: map scope (sorted unique keys, one class each, -1 = erase), scan
    scope and object scope (:mod:`leap_core.pipeline.object_corrections`)."""

    map_keys: npt.NDArray[np.int64]
    """(K,) sorted unique voxel keys."""
    map_class: npt.NDArray[np.int16]
    """(K,) class per key (-1 erases)."""
    scan: ScanCorrections
    """Scan-scope corrections."""
    objects: ObjectCorrections = field(default_factory=ObjectCorrections)
    """Object-scope corrections (applied to the export over the run's tracks, never fused)."""

    @classmethod
    def empty(cls) -> RunCorrections:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int16), ScanCorrections.empty())

    @classmethod
    def read(
        cls, map_path: Path, scan_path: Path, num_classes: int, object_path: Path | None = None
    ) -> RunCorrections:
        """Read the files of each scope (any may be missing: no corrections of that scope)."""
        keys, cls_ = np.zeros(0, np.int64), np.zeros(0, np.int16)
        if map_path.is_file():
            k, c = last_per_key(*load_corrections(map_path, num_classes))
            keys, cls_ = k, c.astype(np.int16)
        scan = ScanCorrections.empty()
        if scan_path.is_file():
            scan = ScanCorrections.load(scan_path, num_classes)
        objects = ObjectCorrections()
        if object_path is not None:
            objects = ObjectCorrections.read(object_path, num_classes)
        return cls(keys, cls_, scan, objects)

    @classmethod
    def of_run(cls, layout: SequenceLayout, num_classes: int) -> RunCorrections:
        """The corrections the run's stages applied (``corrections.npz``, ``corrections_scan.npz``,
        ``corrections_object.npz``)."""
        return cls.read(layout.corrections, layout.corrections_scan, num_classes, layout.corrections_object)

    @classmethod
    def applied(cls, layout: SequenceLayout, num_classes: int) -> RunCorrections:
        """The corrections the run's points and export carry now (after any immediate apply)."""
        if layout.applied_corrections.is_file():
            return cls.read(
                layout.applied_corrections,
                layout.applied_corrections_scan,
                num_classes,
                layout.applied_corrections_object,
            )
        return cls.of_run(layout, num_classes)

    def erased_keys(self) -> npt.NDArray[np.int64]:
        """(E,) sorted voxel keys of the map-scope erase corrections."""
        erased: npt.NDArray[np.int64] = self.map_keys[self.map_class == ERASE]
        return erased

    def differs(self, other: RunCorrections) -> bool:
        """Whether any point would get another label under ``other`` (a voxel, a scan's points or an object
        correction differ)."""
        return bool(
            changed_keys(self.map_keys, self.map_class, other.map_keys, other.map_class).size
            or self.scan.changed_frames(other.scan)
            or self.objects.differs(other.objects)
        )

    def write(self, map_path: Path, scan_path: Path, object_path: Path | None = None) -> None:
        save_corrections(map_path, self.map_keys, self.map_class)
        self.scan.save(scan_path)
        if object_path is not None:
            self.objects.save(object_path)

    def write_run(self, layout: SequenceLayout) -> None:
        """Write the files a run's stages read (``corrections*.npz`` of the sequence's folder)."""
        self.write(layout.corrections, layout.corrections_scan, layout.corrections_object)


def export_ahead_of_metrics(layout: SequenceLayout, num_classes: int) -> bool:
    """Whether the run's points and export carry corrections its ``metrics.json`` does not (the app's
    apply job changed labels after the run's evaluation: the metrics describe the labels before them)."""
    if not layout.applied_corrections.is_file():
        return False
    return RunCorrections.of_run(layout, num_classes).differs(RunCorrections.applied(layout, num_classes))


def frame_keys(frame: Frame, voxel_size: float) -> npt.NDArray[np.int64]:
    """(N,) world voxel key of every point of a frame: ``voxel_keys(world_points(points, pose))``, computed
    in row blocks (:mod:`leap_core.geometry`: the same bytes without OpenBLAS's threads, and each block's
    float64 temporaries stay in cache)."""
    pts = frame.points
    pose = frame.pose[:3]
    out = np.empty(pts.shape[0], np.int64)
    for start, stop in row_blocks(pts.shape[0]):
        out[start:stop] = voxel_keys(affine_points(pts[start:stop], pose), voxel_size)
    return out


def point_labels(
    final: SmoothedGrid,
    point_keys: npt.NDArray[np.int64],
    frame_id: str,
    corr: RunCorrections,
    subset: npt.NDArray[np.int64] | None = None,
) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
    """One scan's ``(label (N,) int16, conf (N,) float32)``: its voxels' labels in the final grid, then the
    corrections (map scope, then this scan's scan scope).

    ``subset`` (S,) sorted point indices: label only those points (arrays of length S), each exactly as the
    whole scan would label it. Example: scan correction on points [2, 7], subset [1, 7] → position 1 of
    the result carries point 7's scan correction.
    """
    keys = point_keys if subset is None else point_keys[subset]
    lab, conf = grid_labels_at(final, keys)
    pts, cls = corr.scan.of(frame_id)
    if subset is not None and pts.size:
        if subset.size == 0:
            pts, cls = pts[:0], cls[:0]
        else:
            pos = np.minimum(np.searchsorted(subset, pts), subset.size - 1)
            inside = subset[pos] == pts
            pts, cls = pos[inside].astype(np.int64), cls[inside]
    return correct_points(lab, conf, keys, corr.map_keys, corr.map_class, scan_points=pts, scan_class=cls)


def grid_labels_at(
    final: SmoothedGrid, keys: npt.NDArray[np.int64]
) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
    """``final.labels_at(keys)`` (label (N,) int16, conf (N,) float32; UNLABELED and 0 where the voxel is
    not in the grid) in fewer passes over the points: one search, then plain gathers and one ``where``
    each, instead of index masks and masked scatters (≈ 10 % less time on a demo scan; the search itself
    is most of the rest)."""
    labels = final.voxel_labels()
    grid_keys = labels.keys
    q = np.asarray(keys, np.int64)
    if grid_keys.size == 0:
        return np.full(q.shape, UNLABELED, np.int16), np.zeros(q.shape, np.float32)
    pos = np.searchsorted(grid_keys, q)
    np.minimum(pos, grid_keys.size - 1, out=pos)
    hit = grid_keys[pos] == q
    label = np.where(hit, labels.label[pos], np.int16(UNLABELED))
    conf = np.where(hit, labels.conf[pos], np.float32(0.0))
    return label, conf


def check_scan_points(path: Path, frame_id: str, corr: RunCorrections, n_points: int) -> None:
    """Raise DatasetError (naming the corrections file) when a scan correction indexes past the scan."""
    pts, _ = corr.scan.of(frame_id)
    if pts.size and int(pts.max()) >= n_points:
        raise DatasetError(path, f"frame {frame_id}: point index {int(pts.max())}, the scan has {n_points}")


def build_frame_index(seq: KittiSequence, frames: Iterable[int], voxel_size: float) -> FrameVoxelIndex:
    """The voxel → frames index over ``frames`` (positions follow their order)."""
    return FrameVoxelIndex.build(frame_keys(seq.frame(i), voxel_size) for i in frames)


@dataclass
class RunCache:
    """What :func:`apply_to_run` reuses between calls on the same run (kept by the caller)."""

    final: SmoothedGrid
    """The run's final grid."""
    index: FrameVoxelIndex
    """Voxel → frame positions."""


def load_run_cache(layout: SequenceLayout, seq: KittiSequence, frames: range, voxel_size: float) -> RunCache:
    """Load the final grid and the voxel → frames index (built and saved in the run folder when missing
    or built over other frames)."""
    final = SmoothedGrid.load(layout.final_grid_on_disk())
    index: FrameVoxelIndex | None = None
    if layout.frame_voxels.is_file():
        try:
            index = FrameVoxelIndex.load(layout.frame_voxels)
        except DatasetError:
            index = None  # damaged: rebuilt below
        if index is not None and index.num_frames != len(frames):
            index = None
    if index is None:
        index = build_frame_index(seq, frames, voxel_size)
        index.save(layout.frame_voxels)
    return RunCache(final, index)


@dataclass(frozen=True)
class ApplyResult:
    """What one :func:`apply_to_run` changed."""

    frames: tuple[str, ...]
    """Frame ids whose points and export were rewritten."""
    changed_voxels: int
    """Map-scope voxels whose correction changed."""
    baked_reverts: int
    """Undone voxels the run had already fused (they keep their class until the next run)."""
    seconds: float
    """Wall time."""


def _object_changes(
    layout: SequenceLayout, old: ObjectCorrections, new: ObjectCorrections, things: npt.NDArray[np.bool_]
) -> tuple[CorrectedTracks | None, list[str]]:
    """The run's tracks with ``new`` on top (None: the run has none) and the frames where a point's
    corrected object, class or motion differs between ``old`` and ``new``."""
    if not layout.tracks.is_file():
        return None, []
    raw = SequenceTracks.load(layout.tracks)
    tracks = CorrectedTracks.of(raw, new, things)
    return tracks, tracks.changed_frames(CorrectedTracks.of(raw, old, things))


def apply_to_run(  # noqa: PLR0913  the run, its frames and export ids, the corrections, the cache, knobs
    layout: SequenceLayout,
    seq: KittiSequence,
    frames: range,
    voxel_size: float,
    export_ids: npt.NDArray[np.uint32],
    *,
    new: RunCorrections,
    cache: RunCache,
    progress: Callable[[int, int], None] | None = None,
    threads: int = 4,
    moving_export_ids: npt.NDArray[np.uint32] | None = None,
    things_mask: npt.NDArray[np.bool_] | None = None,
) -> ApplyResult:
    """Rewrite the run's points and export of the frames ``new`` changes (module docstring), atomically
    per file, then record ``new`` as applied. ``threads`` frames are rewritten at a time (an error in one
    is raised once the others end; the applied record is then left as it was, so the next call redoes
    them all). A run with objects (``tracks.npz``) keeps them in the export, with ``new``'s object
    corrections on top (the frames where a track's corrected class changed are rewritten too);
    ``moving_export_ids`` are the raw ids of moving points (``Schema.moving_export_ids``; default
    ``export_ids``), ``things_mask`` (C,) which classes are things (``Schema.things``; default none: an
    object correction then drops the track's id).

    Raises:
        DatasetError: a scan correction indexes past its scan, or a points file is unreadable.
    """
    t0 = time.perf_counter()
    num_classes = len(export_ids)
    old = RunCorrections.applied(layout, num_classes)
    diff = changed_keys(old.map_keys, old.map_class, new.map_keys, new.map_class)
    positions = set(cache.index.frames_of(diff).tolist()) if diff.size else set()
    pos_of = {seq.frame_ids[i]: p for p, i in enumerate(frames)}
    positions |= {pos_of[f] for f in new.scan.changed_frames(old.scan) if f in pos_of}
    own = RunCorrections.of_run(layout, num_classes)
    baked = np.setdiff1d(own.map_keys[own.map_class >= 0], new.map_keys, assume_unique=True)
    todo = sorted(positions)
    scan_changed = set(new.scan.changed_frames(old.scan))
    # The run's objects stay: tracked points keep their track's id, moving id and (voted tracks) class,
    # except the points a map or scan correction now labels (such a correction wins over a track's class
    # vote and over an object correction); the object corrections relabel the tracks they match.
    things = np.zeros(num_classes, bool) if things_mask is None else things_mask
    tracks, moved = _object_changes(layout, old.objects, new.objects, things)
    todo = sorted(set(todo) | {pos_of[f] for f in moved if f in pos_of})
    moving_ids = export_ids if moving_export_ids is None else moving_export_ids

    def rewrite(p: int) -> None:
        i = frames[p]
        fid = seq.frame_ids[i]
        frame = seq.frame(i)
        keys = frame_keys(frame, voxel_size)
        check_scan_points(layout.applied_corrections_scan, fid, new, keys.size)
        path = layout.points(fid)
        try:
            with np.load(path) as z:
                point_label = np.asarray(z["point_label"])
                lab = np.array(z["label"], np.int16)
                conf = np.asarray(z["conf"], np.float32)
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable point labels ({exc})") from exc
        if fid in scan_changed or lab.shape != keys.shape or conf.shape != keys.shape:
            lab, conf = point_labels(cache.final, keys, fid, new)
        else:
            # Only points in changed voxels can change (their grid lookup is most of a scan's cost): the
            # others keep the label the file has, which the same rule gave them.
            sel = np.flatnonzero(rows_in_sorted(diff, keys) >= 0).astype(np.int64)
            lab[sel], conf[sel] = point_labels(cache.final, keys, fid, new, subset=sel)
        atomic_save_npz(path, label=lab, conf=conf.astype(np.float16), point_label=point_label)
        if tracks is None:
            export_labels(
                layout.export_label(fid), layout.export_conf(fid), lab, conf.astype(np.float16), export_ids
            )
            return
        scan_points, _ = new.scan.of(fid)
        keep = np.union1d(np.flatnonzero(np.isin(keys, new.map_keys)), scan_points).astype(np.int64)
        lab, out_conf, instance, moving = tracks.point_objects(fid, lab, conf.astype(np.float16), keep)
        export_labels(
            layout.export_label(fid),
            layout.export_conf(fid),
            lab,
            out_conf.astype(np.float16),
            export_ids,
            instance=instance,
            moving=moving,
            moving_ids=moving_ids,
        )

    # Frames are independent files; numpy's lookups and the fsyncs of the atomic writes release the GIL,
    # so a few threads overlap one frame's disk waits with another's arithmetic.
    with ThreadPoolExecutor(max(1, min(threads, len(todo)))) as pool:
        for k, _ in enumerate(pool.map(rewrite, todo)):
            if progress is not None:
                progress(k + 1, len(todo))
    new.write(layout.applied_corrections, layout.applied_corrections_scan, layout.applied_corrections_object)
    if tracks is not None:
        atomic_write_json(layout.object_matches, tracks.report())
    return ApplyResult(
        frames=tuple(seq.frame_ids[frames[p]] for p in todo),
        changed_voxels=int(diff.size),
        baked_reverts=int(np.intersect1d(baked, diff, assume_unique=True).size),
        seconds=time.perf_counter() - t0,
    )


__all__ = [
    "ApplyResult",
    "RunCache",
    "RunCorrections",
    "apply_to_run",
    "build_frame_index",
    "check_scan_points",
    "export_ahead_of_metrics",
    "frame_keys",
    "grid_labels_at",
    "load_run_cache",
    "point_labels",
]
