"""Object-scope corrections (docs/METHOD.md B.6, "Object corrections"): one action relabels (or erases)
every point of one object, in every scan, and the correction survives re-runs.

An object is a track of the ``tracks`` stage (``tracks.npz``, :class:`SequenceTracks`). Track ids are
numbered afresh by every run, so a correction does not keep the id: it keeps the track's **identity**,
the point rows of the track in each scan (:class:`ObjectIdentity`, the scans' point rows do not change
between runs of the same dataset). A later run's tracks are matched to it by overlap
(:func:`match_track`): the IoU of the identity's (scan, row) pairs and a track's, over the scans both
runs labeled; the track of highest IoU takes the correction when that IoU exceeds :data:`MIN_IOU` (0.5),
else the correction "no longer matches an object" and changes nothing. Tracks are disjoint, so at most one
track can exceed 0.5 (the argument of panoptic quality's matching): the rule never has to choose.

Precedence on a point: scan scope > map scope > object scope > the track's own class vote > the final
grid. The ``tracks`` stage leaves the points a map or scan correction labels out of every track
(:func:`leap_core.pipeline.objects.corrected_rows`), so an object correction reaches exactly the points
the tracks call the object; the immediate apply job does the same with corrections made after the run
(``keep``), so both ways give the same export.

An object correction's points take its class with confidence 1 (erase: unlabeled, confidence 0). A thing
class keeps the track's id (and its moving id while the track moves); a stuff class or an erase drops the
id: instance ids belong to things only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError, LeapError
from leap_core.io_utils import atomic_save_npz, read_npz
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.run_layout import SequenceLayout
from leap_core.schema import Schema
from leap_core.types import UNLABELED

MIN_IOU = 0.5
"""A later run's track takes an object correction only when its IoU with the stored identity exceeds this
(module docstring: above 0.5 the best track is the only candidate)."""

NO_CLASS = -2
"""``track_class`` entry of a track no object correction reaches (-1 is an erase)."""


@dataclass(frozen=True)
class ObjectIdentity:
    """The points of one object: per scan ``frame_ids[f]`` the rows ``rows[ptr[f]:ptr[f+1]]`` (sorted;
    ``frame_ids`` lists every scan the run labeled, those where the object has no point too)."""

    frame_ids: tuple[str, ...]
    ptr: npt.NDArray[np.int64]
    """(F+1,) offsets into ``rows``."""
    rows: npt.NDArray[np.int32]
    """(P,) point rows of the object, scan by scan."""

    @property
    def points(self) -> int:
        return int(self.rows.size)

    @classmethod
    def of_track(cls, tracks: SequenceTracks, track_id: int) -> ObjectIdentity:
        """Track ``track_id``'s points in every scan of ``tracks`` (every scan is listed, with or without
        points: the scans the identity covers, :func:`match_track`).

        Raises:
            LeapError: no track ``track_id`` in ``tracks``.
        """
        k = int(track_id)
        if not 1 <= k <= tracks.table.label.size:
            raise LeapError(f"no track {k}: the run's tracks are 1..{tracks.table.label.size}")
        ids, ptr, parts = [], [0], []
        for t, fid in enumerate(tracks.frame_ids):
            a, b = int(tracks.offsets[t]), int(tracks.offsets[t + 1])
            rows = np.sort(tracks.rows[a:b][tracks.track[a:b] == k])
            ids.append(fid)
            parts.append(rows.astype(np.int32))
            ptr.append(ptr[-1] + rows.size)
        rows_all = np.concatenate(parts) if parts else np.zeros(0, np.int32)
        return cls(tuple(ids), np.asarray(ptr, np.int64), rows_all)

    def of(self, frame_id: str) -> npt.NDArray[np.int32]:
        """The object's rows in scan ``frame_id`` (empty when it has none there)."""
        try:
            f = self.frame_ids.index(frame_id)
        except ValueError:
            return np.zeros(0, np.int32)
        return self.rows[int(self.ptr[f]) : int(self.ptr[f + 1])]

    def save(self, path: str | Path) -> None:
        atomic_save_npz(path, frame_ids=np.asarray(self.frame_ids, np.str_), ptr=self.ptr, rows=self.rows)

    @classmethod
    def load(cls, path: str | Path) -> ObjectIdentity:
        """Raises: DatasetError naming the file when it is unreadable or inconsistent."""
        try:
            z = read_npz(path, ("frame_ids", "ptr", "rows"))
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable object identity ({exc})") from exc
        return _checked(path, tuple(str(s) for s in z["frame_ids"]), z["ptr"], z["rows"])


def _checked(
    path: str | Path, ids: tuple[str, ...], ptr: npt.ArrayLike, rows: npt.ArrayLike
) -> ObjectIdentity:
    p = np.asarray(ptr, np.int64)
    r = np.asarray(rows)
    if p.shape != (len(ids) + 1,) or p[0] != 0 or p[-1] != r.size or np.any(np.diff(p) < 0):
        raise DatasetError(path, "'ptr' must be 0..len(rows), non-decreasing, one more than frame_ids")
    if not np.issubdtype(r.dtype, np.integer) or (r.size and int(r.min()) < 0):
        raise DatasetError(path, "'rows' must be point rows (integers >= 0)")
    return ObjectIdentity(ids, p, r.astype(np.int32))


@dataclass(frozen=True)
class Match:
    """How one object correction meets a run's tracks."""

    track: int
    """The track of highest IoU (0: the run has no track sharing a point with the identity)."""
    iou: float
    """Its IoU with the identity over the scans both cover."""

    @property
    def applied(self) -> bool:
        """Whether the correction reaches the track (IoU above :data:`MIN_IOU`)."""
        return self.track > 0 and self.iou > MIN_IOU


def match_track(identity: ObjectIdentity, tracks: SequenceTracks) -> Match:
    """The track of ``tracks`` that overlaps the stored object most.

    With A the identity's (scan, row) pairs and B_k track k's, both over the scans the two have in common:
    ``IoU_k = |A ∩ B_k| / (|A| + |B_k| - |A ∩ B_k|)``; the result is ``argmax_k IoU_k`` (ties: the lower
    id). Example: A = scan "0": rows [1, 2, 3, 4]; track 1 = rows [1, 2, 3], track 2 = rows [4, 5] →
    track 1, IoU 3 / 4.
    """
    return match_tracks([identity], tracks)[0]


def match_tracks(identities: Sequence[ObjectIdentity], tracks: SequenceTracks) -> list[Match]:
    """:func:`match_track` of each identity, in one pass over the scans: a scan's row → track table is
    filled once (a scatter of its tracked rows) and each identity's rows in it are gathered from it, so
    many corrections cost about one, and scans no identity has points in only count their tracks' sizes
    (one ``bincount`` over every scan, less the scans an identity does not cover)."""
    k = tracks.table.label.size
    m = len(identities)
    inter = np.zeros((m, k + 1), np.int64)
    size_a = np.zeros(m, np.int64)
    track_all = tracks.track
    size_b = np.tile(np.bincount(track_all, minlength=k + 1), (m, 1))
    covered = [{f: i for i, f in enumerate(x.frame_ids)} for x in identities]
    lookup = np.zeros(int(tracks.rows.max(initial=-1)) + 1, np.int32)
    for t, fid in enumerate(tracks.frame_ids):
        lo, hi = int(tracks.offsets[t]), int(tracks.offsets[t + 1])
        rows = tracks.rows[lo:hi]
        filled = False
        for j, (identity, pos) in enumerate(zip(identities, covered, strict=True)):
            f = pos.get(fid)
            if f is None:  # a scan the identity's run never labeled: its tracks do not count
                size_b[j] -= np.bincount(track_all[lo:hi], minlength=k + 1)
                continue
            a_rows = identity.rows[int(identity.ptr[f]) : int(identity.ptr[f + 1])]
            if a_rows.size == 0:
                continue
            if not filled:
                lookup[rows] = track_all[lo:hi]
                filled = True
            size_a[j] += a_rows.size
            inside = a_rows[a_rows < lookup.size]
            inter[j] += np.bincount(lookup[inside], minlength=k + 1)
        if filled:
            lookup[rows] = 0
    out = []
    for j in range(m):
        hits = inter[j, 1:]
        if k == 0 or hits.max(initial=0) == 0:
            out.append(Match(0, 0.0))
            continue
        iou = hits / np.maximum(size_a[j] + size_b[j, 1:] - hits, 1)
        best = int(np.argmax(iou))
        out.append(Match(best + 1, float(iou[best])))
    return out


@dataclass(frozen=True)
class ObjectCorrections:
    """A run's object-scope corrections, in the order they were made (a later one wins on the same
    track): correction ``ids[m]`` gives ``class_idx[m]`` (-1 erases) to the object ``identities[m]``."""

    ids: tuple[int, ...] = ()
    class_idx: npt.NDArray[np.int16] = field(default_factory=lambda: np.zeros(0, np.int16))
    identities: tuple[ObjectIdentity, ...] = ()

    def __len__(self) -> int:
        return len(self.ids)

    def differs(self, other: ObjectCorrections) -> bool:
        """Whether the two sets could label any point differently (other corrections, classes or objects)."""
        if self.ids != other.ids or not np.array_equal(self.class_idx, other.class_idx):
            return True
        return any(
            a.frame_ids != b.frame_ids or not np.array_equal(a.rows, b.rows)
            for a, b in zip(self.identities, other.identities, strict=True)
        )

    def resolve(self, tracks: SequenceTracks) -> tuple[npt.NDArray[np.int16], list[Match]]:
        """``(track_class, matches)``: (K+1,) int16 class per track id (:data:`NO_CLASS` where no correction
        applies; a later correction wins on a track two match) and each correction's :class:`Match`."""
        track_class = np.full(tracks.table.label.size + 1, NO_CLASS, np.int16)
        matches = match_tracks(self.identities, tracks)
        for m, c in zip(matches, self.class_idx, strict=True):
            if m.applied:
                track_class[m.track] = c
        return track_class, matches

    def save(self, path: str | Path) -> None:
        frame_ids = [f for i in self.identities for f in i.frame_ids]
        frame_ptr = np.cumsum([0, *(len(i.frame_ids) for i in self.identities)]).astype(np.int64)
        rows = [i.rows for i in self.identities]
        sizes = [np.diff(i.ptr) for i in self.identities]
        row_ptr = np.cumsum(np.concatenate([[0], *sizes]), dtype=np.int64)
        atomic_save_npz(
            path,
            ids=np.asarray(self.ids, np.int64),
            class_idx=self.class_idx.astype(np.int16),
            frame_ids=np.asarray(frame_ids, np.str_),
            frame_ptr=frame_ptr,
            row_ptr=row_ptr,
            rows=np.concatenate(rows) if rows else np.zeros(0, np.int32),
        )

    @classmethod
    def load(cls, path: str | Path, num_classes: int) -> ObjectCorrections:
        """Read :meth:`save`'s file. Raises DatasetError naming it when it is unreadable or inconsistent."""
        try:
            z = read_npz(path, ("ids", "class_idx", "frame_ids", "frame_ptr", "row_ptr", "rows"))
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable object corrections ({exc})") from exc
        ids, cls_, fptr, rptr = z["ids"], z["class_idx"], z["frame_ptr"].astype(np.int64), z["row_ptr"]
        frame_ids = tuple(str(s) for s in z["frame_ids"])
        if cls_.shape != ids.shape or fptr.shape != (ids.size + 1,) or fptr[-1] != len(frame_ids):
            raise DatasetError(path, "'ids', 'class_idx' and 'frame_ptr' must describe the same corrections")
        if rptr.shape != (len(frame_ids) + 1,):
            raise DatasetError(path, "'row_ptr' must have one more entry than 'frame_ids'")
        if cls_.size and (int(cls_.min()) < UNLABELED or int(cls_.max()) >= num_classes):
            raise DatasetError(path, f"'class_idx' must be in -1..{num_classes - 1}")
        identities = []
        for m in range(ids.size):
            a, b = int(fptr[m]), int(fptr[m + 1])
            ptr = rptr[a : b + 1] - rptr[a]
            identities.append(_checked(path, frame_ids[a:b], ptr, z["rows"][int(rptr[a]) : int(rptr[b])]))
        return cls(tuple(int(i) for i in ids), cls_.astype(np.int16), tuple(identities))

    @classmethod
    def read(cls, path: Path, num_classes: int) -> ObjectCorrections:
        """The file's corrections, or none when it is missing."""
        return cls.load(path, num_classes) if path.is_file() else cls()


def merge_object_corrections(items: Sequence[tuple[int, int, ObjectIdentity]]) -> ObjectCorrections:
    """``(correction id, class index, identity)`` in the order they were made → :class:`ObjectCorrections`."""
    return ObjectCorrections(
        tuple(int(i) for i, _, _ in items),
        np.asarray([c for _, c, _ in items], np.int16),
        tuple(x for _, _, x in items),
    )


@dataclass(frozen=True)
class CorrectedTracks:
    """A run's tracks with its object corrections on top: what the export and the evaluation write."""

    tracks: SequenceTracks
    track_class: npt.NDArray[np.int16]
    """(K+1,) class per track id from the object corrections, :data:`NO_CLASS` where none applies."""
    things: npt.NDArray[np.bool_]
    """(C,) which classes are things (a stuff class or an erase drops the track's id)."""
    matches: tuple[tuple[int, Match], ...] = ()
    """(correction id, match) of each object correction."""

    @classmethod
    def of(
        cls, tracks: SequenceTracks, corrections: ObjectCorrections, things: npt.NDArray[np.bool_]
    ) -> CorrectedTracks:
        track_class, matches = corrections.resolve(tracks)
        return cls(
            tracks, track_class, np.asarray(things, bool), tuple(zip(corrections.ids, matches, strict=True))
        )

    def point_objects(
        self,
        frame_id: str,
        labels: npt.NDArray[np.int16],
        conf: npt.NDArray[np.floating] | None = None,
        keep: npt.NDArray[np.int64] | None = None,
    ) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32], npt.NDArray[np.uint32], npt.NDArray[np.bool_]]:
        """``(label, conf, instance, moving)`` of one scan: :meth:`SequenceTracks.point_objects`, then the
        points of corrected tracks (but ``keep``, the rows a map or scan correction labels) given their
        correction's class, confidence 1 (0 for an erase), and no id or motion unless the class is a thing.
        ``conf`` None: ones (the evaluation reads labels only)."""
        label, instance, moving = self.tracks.point_objects(frame_id, labels, keep)
        out_conf = np.ones(label.shape, np.float32) if conf is None else np.asarray(conf, np.float32).copy()
        obj = self.tracks.scan(frame_id)
        if obj.rows.size == 0 or not np.any(self.track_class != NO_CLASS):
            return label, out_conf, instance, moving
        cls_ = self.track_class[obj.track]
        sel = cls_ != NO_CLASS
        if keep is not None and keep.size:
            sel &= ~np.isin(obj.rows, keep)
        rows, c = obj.rows[sel], cls_[sel]
        label[rows] = c
        out_conf[rows] = np.where(c == UNLABELED, 0.0, 1.0)
        thing = (c >= 0) & self.things[np.maximum(c, 0)]
        instance[rows[~thing]] = 0
        moving[rows[~thing]] = False
        return label, out_conf, instance, moving

    def changed_tracks(self, other: CorrectedTracks) -> npt.NDArray[np.int64]:
        """Track ids whose corrected class differs between ``self`` and ``other`` (same tracks)."""
        return np.flatnonzero(self.track_class != other.track_class).astype(np.int64)

    def frames_of(self, track_ids: npt.NDArray[np.int64]) -> list[str]:
        """Frame ids in which any of ``track_ids`` has points."""
        t = self.tracks
        if track_ids.size == 0:
            return []
        frame_of = np.repeat(np.arange(len(t.frame_ids)), np.diff(t.offsets))
        return [t.frame_ids[f] for f in np.unique(frame_of[np.isin(t.track, track_ids)])]

    def report(self) -> dict[str, Any]:
        """Per correction id (a string: JSON keys) its match: ``{"track", "iou", "applied"}``."""
        out = {}
        for cid, m in self.matches:
            out[str(cid)] = {"track": m.track, "iou": round(m.iou, 4), "applied": m.applied}
        return out


def read_corrected_tracks(layout: SequenceLayout, schema: Schema) -> CorrectedTracks:
    """A sequence folder's ``tracks.npz`` with its ``corrections_object.npz`` (the run's own) on top."""
    objects = ObjectCorrections.read(layout.corrections_object, schema.num_classes)
    return CorrectedTracks.of(SequenceTracks.load(layout.tracks), objects, schema.things())


__all__ = [
    "MIN_IOU",
    "NO_CLASS",
    "CorrectedTracks",
    "Match",
    "ObjectCorrections",
    "ObjectIdentity",
    "match_track",
    "match_tracks",
    "merge_object_corrections",
    "read_corrected_tracks",
]
