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

Besides relabelling (``relabel``), a correction may **merge** two objects (``merge``: two identities; the
second object's points take the first's id, one class, moving when either part moves) or **split** one at
a scan (``split``: an identity and a frame id; its points from that scan on take a new id beyond the run's
track ids). Corrections apply in the order they were made, each matched (by the IoU rule above) to the
objects the ones before it left, so a relabel made on a merged object reaches both parts and one made on a
split-off part reaches that part only (:class:`ObjectEdit`, :func:`_objects_after`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

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

MAX_OBJECT_ID = 0xFFFF
"""Largest object id: the export keeps it in a label's upper 16 bits."""


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
        return cls.of_ids(tracks, tracks.track, k)

    @classmethod
    def of_ids(cls, tracks: SequenceTracks, ids: npt.NDArray[np.int32], object_id: int) -> ObjectIdentity:
        """The points whose entry in ``ids`` (P,) (aligned with ``tracks.rows``: the run's track ids, or
        its objects after merges and splits) is ``object_id``, in every scan of ``tracks``."""
        ptr, parts = [0], []
        for t in range(len(tracks.frame_ids)):
            a, b = int(tracks.offsets[t]), int(tracks.offsets[t + 1])
            rows = np.sort(tracks.rows[a:b][ids[a:b] == object_id]).astype(np.int32)
            parts.append(rows)
            ptr.append(ptr[-1] + rows.size)
        rows_all = np.concatenate(parts) if parts else np.zeros(0, np.int32)
        return cls(tracks.frame_ids, np.asarray(ptr, np.int64), rows_all)

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
    """:func:`match_track` of each identity, in one pass over the scans (:func:`_match`)."""
    return _match(identities, tracks, tracks.track, tracks.table.label.size)


def _match(
    identities: Sequence[ObjectIdentity], tracks: SequenceTracks, track_all: npt.NDArray[np.int32], k: int
) -> list[Match]:
    """:func:`match_track` of each identity against the objects ``track_all`` (P,) (ids 1..k, aligned with
    ``tracks.rows``: the run's tracks, or its objects after earlier merges and splits). One pass over the
    scans: a scan's row → object table is filled once (a scatter of its tracked rows) and each identity's
    rows in it are gathered from it, so many corrections cost about one, and scans no identity has points in
    only count their objects' sizes (one ``bincount`` over every scan, less the scans an identity does not
    cover)."""
    m = len(identities)
    inter = np.zeros((m, k + 1), np.int64)
    size_a = np.zeros(m, np.int64)
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


Action = Literal["relabel", "merge", "split"]
ACTIONS: tuple[Action, ...] = ("relabel", "merge", "split")
"""What an object correction does; its index is the ``action`` code of ``corrections_object.npz``."""


@dataclass(frozen=True)
class ObjectEdit:
    """One object correction as made: ``relabel`` gives ``class_idx`` (-1 erases) to the object
    ``identity``; ``merge`` joins the object ``other`` into ``identity``'s; ``split`` gives the points of
    ``identity``'s object from scan ``frame_id`` on a new id."""

    id: int
    action: Action
    identity: ObjectIdentity
    class_idx: int = NO_CLASS
    """Relabel only (:data:`NO_CLASS` for the others)."""
    other: ObjectIdentity | None = None
    """Merge only: the object merged into ``identity``'s."""
    frame_id: str | None = None
    """Split only: the first scan of the new object."""

    def __post_init__(self) -> None:
        if (self.action == "relabel") != (self.class_idx != NO_CLASS):
            raise LeapError(f"object correction {self.id}: a class is for relabels only")
        if (self.action == "merge") != (self.other is not None):
            raise LeapError(f"object correction {self.id}: a second object is for merges only")
        if (self.action == "split") != (self.frame_id is not None):
            raise LeapError(f"object correction {self.id}: a scan is for splits only")


@dataclass(frozen=True)
class ObjectCorrections:
    """A run's object-scope corrections (:class:`ObjectEdit`), in the order they were made: each is
    matched to the objects the ones before it left (module docstring)."""

    edits: tuple[ObjectEdit, ...] = ()

    def __len__(self) -> int:
        return len(self.edits)

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(e.id for e in self.edits)

    @property
    def class_idx(self) -> npt.NDArray[np.int16]:
        """(M,) each correction's class (-1 erases; :data:`NO_CLASS` for merges and splits)."""
        return np.asarray([e.class_idx for e in self.edits], np.int16)

    @property
    def identities(self) -> tuple[ObjectIdentity, ...]:
        return tuple(e.identity for e in self.edits)

    def differs(self, other: ObjectCorrections) -> bool:
        """Whether the two sets could label any point differently (other corrections, classes or objects)."""
        if len(self.edits) != len(other.edits):
            return True

        def same(a: ObjectIdentity | None, b: ObjectIdentity | None) -> bool:
            if a is None or b is None:
                return a is b
            return (
                a.frame_ids == b.frame_ids and np.array_equal(a.ptr, b.ptr) and np.array_equal(a.rows, b.rows)
            )

        return not all(
            (a.id, a.action, a.class_idx, a.frame_id) == (b.id, b.action, b.class_idx, b.frame_id)
            and same(a.identity, b.identity)
            and same(a.other, b.other)
            for a, b in zip(self.edits, other.edits, strict=True)
        )

    def save(self, path: str | Path) -> None:
        """One npz: per correction ``ids``, ``class_idx``, ``action`` (index into :data:`ACTIONS`),
        ``split_frame`` ("" but for splits); the identities packed as ``frame_ids`` / ``frame_ptr`` /
        ``row_ptr`` / ``rows``, each correction's own first, then the merges' second ones in order."""
        every = [*self.identities, *(e.other for e in self.edits if e.other is not None)]
        frame_ids = [f for i in every for f in i.frame_ids]
        frame_ptr = np.cumsum([0, *(len(i.frame_ids) for i in every)]).astype(np.int64)
        sizes = [np.diff(i.ptr) for i in every]
        row_ptr = np.cumsum(np.concatenate([[0], *sizes]), dtype=np.int64)
        atomic_save_npz(
            path,
            ids=np.asarray(self.ids, np.int64),
            class_idx=self.class_idx,
            action=np.asarray([ACTIONS.index(e.action) for e in self.edits], np.int8),
            split_frame=np.asarray([e.frame_id or "" for e in self.edits], np.str_),
            frame_ids=np.asarray(frame_ids, np.str_),
            frame_ptr=frame_ptr,
            row_ptr=row_ptr,
            rows=np.concatenate([i.rows for i in every]) if every else np.zeros(0, np.int32),
        )

    @classmethod
    def load(cls, path: str | Path, num_classes: int) -> ObjectCorrections:
        """Read :meth:`save`'s file (one without ``action`` holds relabels only). Raises DatasetError naming
        it when it is unreadable or inconsistent."""
        try:
            z = read_npz(path)
            ids, cls_, fptr, rptr = z["ids"], z["class_idx"], z["frame_ptr"].astype(np.int64), z["row_ptr"]
            rows = z["rows"]
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable object corrections ({exc})") from exc
        m = ids.size
        action = z["action"].astype(np.int64) if "action" in z else np.zeros(m, np.int64)
        split = [str(s) for s in z["split_frame"]] if "split_frame" in z else [""] * m
        frame_ids = tuple(str(s) for s in z["frame_ids"])
        if action.shape != ids.shape or len(split) != m or (m and not 0 <= int(action.min()) <= 2):
            raise DatasetError(path, "'action' and 'split_frame' must hold one valid entry per correction")
        acts = [ACTIONS[int(a)] for a in action]
        n_ident = m + acts.count("merge")
        if cls_.shape != ids.shape or fptr.shape != (n_ident + 1,) or fptr[-1] != len(frame_ids):
            raise DatasetError(path, "'ids', 'class_idx' and 'frame_ptr' must describe the same corrections")
        if rptr.shape != (len(frame_ids) + 1,):
            raise DatasetError(path, "'row_ptr' must have one more entry than 'frame_ids'")
        relabel = np.asarray([a == "relabel" for a in acts], bool)
        if relabel.any() and (
            int(cls_[relabel].min()) < UNLABELED or int(cls_[relabel].max()) >= num_classes
        ):
            raise DatasetError(path, f"'class_idx' must be in -1..{num_classes - 1}")

        def identity(j: int) -> ObjectIdentity:
            a, b = int(fptr[j]), int(fptr[j + 1])
            return _checked(
                path, frame_ids[a:b], rptr[a : b + 1] - rptr[a], rows[int(rptr[a]) : int(rptr[b])]
            )

        edits, second = [], m
        try:
            for j in range(m):
                other = None
                if acts[j] == "merge":
                    other, second = identity(second), second + 1
                edits.append(
                    ObjectEdit(
                        int(ids[j]),
                        acts[j],
                        identity(j),
                        class_idx=int(cls_[j]) if acts[j] == "relabel" else NO_CLASS,
                        other=other,
                        frame_id=split[j] if acts[j] == "split" else None,
                    )
                )
        except LeapError as exc:
            raise DatasetError(path, str(exc)) from exc
        return cls(tuple(edits))

    @classmethod
    def read(cls, path: Path, num_classes: int) -> ObjectCorrections:
        """The file's corrections, or none when it is missing."""
        return cls.load(path, num_classes) if path.is_file() else cls()


def merge_object_corrections(
    items: Sequence[tuple[int, int, ObjectIdentity] | ObjectEdit],
) -> ObjectCorrections:
    """The corrections in the order they were made → :class:`ObjectCorrections`; a ``(correction id, class
    index, identity)`` triple is a relabel."""
    return ObjectCorrections(
        tuple(
            x if isinstance(x, ObjectEdit) else ObjectEdit(int(x[0]), "relabel", x[2], int(x[1]))
            for x in items
        )
    )


@dataclass(frozen=True)
class EditResult:
    """How one object correction met a run's objects."""

    action: Action
    match: Match
    """Its object (the one merged into, for a merge)."""
    other: Match | None = None
    """Merge: the object merged into it."""
    applied: bool = False
    """Whether it changed the objects: its object(s) matched (two different ones for a merge; a split's
    scan is one of the run's and the new id fits the export's 16 bits)."""
    new_track: int = 0
    """Split: the new object's id (0 when it did not apply)."""


def _objects_after(
    tracks: SequenceTracks, edits: Sequence[ObjectEdit]
) -> tuple[npt.NDArray[np.int32], dict[str, npt.NDArray[Any]], list[EditResult]]:
    """Apply ``edits`` in order to the run's tracks: ``(instance, table, results)`` with ``instance`` (P,)
    the object id of each tracked entry (aligned with ``tracks.rows``) and ``table`` the per-object arrays
    ``label``, ``voted``, ``moving``, ``velocity``, ``cls`` (index = object id; 0 unused). Each correction
    is matched to the objects the ones before it left; consecutive corrections up to the next merge or
    split are matched in one pass (:func:`_match`)."""
    t = tracks.table
    k = int(t.label.size)
    cap = k + 1 + sum(e.action == "split" for e in edits)
    table: dict[str, npt.NDArray[Any]] = {
        "label": np.concatenate([[UNLABELED], t.label]).astype(np.int16),
        "voted": np.concatenate([[False], t.voted]).astype(bool),
        "moving": np.concatenate([[False], t.moving]).astype(bool),
        "velocity": np.concatenate([np.zeros((1, 3)), t.velocity]).astype(np.float64),
        "cls": np.full(k + 1, NO_CLASS, np.int16),
    }
    for name, arr in table.items():
        grown = np.zeros((cap, *arr.shape[1:]), arr.dtype)
        grown[: k + 1] = arr
        table[name] = grown
    table["cls"][k + 1 :] = NO_CLASS
    instance = tracks.track.astype(np.int32, copy=True)
    scan_of = tracks.entry_scans()
    results: list[EditResult] = []
    count = k
    start = 0
    while start < len(edits):
        stop = start
        while stop < len(edits) and edits[stop].action == "relabel":
            stop += 1
        stop = min(stop + 1, len(edits))  # the merge or split ending the batch is matched with it
        batch = edits[start:stop]
        wanted = [e.identity for e in batch] + [e.other for e in batch if e.other is not None]
        found = _match(wanted, tracks, instance, count)
        seconds = iter(found[len(batch) :])
        for e, m in zip(batch, found, strict=False):
            if e.action == "relabel":
                if m.applied:
                    table["cls"][m.track] = e.class_idx
                results.append(EditResult("relabel", m, applied=m.applied))
            elif e.action == "merge":
                o = next(seconds)
                ok = m.applied and o.applied and m.track != o.track
                if ok:
                    a, b = m.track, o.track
                    instance[instance == b] = a
                    if table["moving"][b] and not table["moving"][a]:
                        table["velocity"][a] = table["velocity"][b]
                    table["moving"][a] |= table["moving"][b]
                    # One object, one class: the merged object's points all take it.
                    table["voted"][a] = True
                results.append(EditResult("merge", m, o, applied=bool(ok)))
            else:
                pos = tracks.frame_ids.index(e.frame_id) if e.frame_id in tracks.frame_ids else -1
                ok = m.applied and pos >= 0 and count + 1 <= MAX_OBJECT_ID
                new = 0
                if ok:
                    count += 1
                    new = count
                    for arr in table.values():
                        arr[new] = arr[m.track]
                    instance[(instance == m.track) & (scan_of >= pos)] = new
                results.append(EditResult("split", m, applied=bool(ok), new_track=new))
        start = stop
    return instance, {n: a[: count + 1] for n, a in table.items()}, results


@dataclass(frozen=True)
class CorrectedTracks:
    """A run's tracks with its object corrections on top: what the export, the evaluation and the viewer
    show. Objects are the run's tracks (ids 1..K) as the corrections leave them: merged ones under the id
    of the object merged into, split-off parts under new ids K+1, K+2, … in the order the splits were
    made."""

    tracks: SequenceTracks
    instance: npt.NDArray[np.int32]
    """(P,) object id of each tracked entry (aligned with ``tracks.rows``)."""
    label: npt.NDArray[np.int16]
    """(N+1,) each object's voted class (index = id; a merged object keeps the one of the object merged
    into, a split-off part its object's)."""
    voted: npt.NDArray[np.bool_]
    """(N+1,) whether its points take ``label`` (``TrackTable.voted``; true for a merged object)."""
    moving: npt.NDArray[np.bool_]
    """(N+1,) whether it moves (a merged object: when either part does)."""
    velocity: npt.NDArray[np.float64]
    """(N+1, 3) m/s (a merged object: the moving part's, the one merged into's when both or neither
    move)."""
    track_class: npt.NDArray[np.int16]
    """(N+1,) class per object id from the relabels, :data:`NO_CLASS` where none applies."""
    things: npt.NDArray[np.bool_]
    """(C,) which classes are things (a stuff class or an erase drops the object's id)."""
    results: tuple[tuple[int, EditResult], ...] = ()
    """(correction id, result) of each object correction."""

    @classmethod
    def of(
        cls, tracks: SequenceTracks, corrections: ObjectCorrections, things: npt.NDArray[np.bool_]
    ) -> CorrectedTracks:
        instance, table, results = _objects_after(tracks, corrections.edits)
        return cls(
            tracks,
            instance,
            table["label"],
            table["voted"],
            table["moving"],
            table["velocity"],
            table["cls"],
            np.asarray(things, bool),
            tuple(zip(corrections.ids, results, strict=True)),
        )

    def scan_rows(self, frame_id: str) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int32]]:
        """(rows, object ids) of one scan's tracked points (none for a scan the tracks do not hold)."""
        a, b = self.tracks.span(frame_id)
        return self.tracks.rows[a:b], self.instance[a:b]

    def point_objects(
        self,
        frame_id: str,
        labels: npt.NDArray[np.int16],
        conf: npt.NDArray[np.floating] | None = None,
        keep: npt.NDArray[np.int64] | None = None,
    ) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32], npt.NDArray[np.uint32], npt.NDArray[np.bool_]]:
        """``(label, conf, instance, moving)`` of one scan, as :meth:`SequenceTracks.point_objects` gives
        them but over the corrected objects: each tracked point (but ``keep``, the rows a map or scan
        correction labels) gets its object's id and motion, a voted object's points its class; then the
        relabelled objects' points their correction's class, confidence 1 (0 for an erase), and no id or
        motion unless the class is a thing. ``conf`` None: ones (the evaluation reads labels only)."""
        rows, obj = self.scan_rows(frame_id)
        if keep is not None and keep.size:
            sel = ~np.isin(rows, keep)
            rows, obj = rows[sel], obj[sel]
        n = labels.shape[0]
        if rows.size and int(rows.max()) >= n:
            raise LeapError(f"tracks.npz: scan {frame_id} has point rows up to {int(rows.max())} of {n}")
        label = labels.astype(np.int16, copy=True)
        out_conf = np.ones(n, np.float32) if conf is None else np.asarray(conf, np.float32).copy()
        instance = np.zeros(n, np.uint32)
        moving = np.zeros(n, bool)
        voted = self.voted[obj]
        label[rows[voted]] = self.label[obj[voted]]
        instance[rows] = obj.astype(np.uint32)
        moving[rows] = self.moving[obj]
        cls_ = self.track_class[obj]
        sel = cls_ != NO_CLASS
        rows, c = rows[sel], cls_[sel]
        label[rows] = c
        out_conf[rows] = np.where(c == UNLABELED, 0.0, 1.0)
        thing = (c >= 0) & self.things[np.maximum(c, 0)]
        instance[rows[~thing]] = 0
        moving[rows[~thing]] = False
        return label, out_conf, instance, moving

    def _entry_state(self) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int16], npt.NDArray[np.bool_]]:
        """(object id, class its point takes (-3: its own), moving) of every tracked entry."""
        obj = self.instance
        own = np.where(self.voted[obj], self.label[obj], np.int16(-3)).astype(np.int16)
        cls_ = np.where(self.track_class[obj] != NO_CLASS, self.track_class[obj], own).astype(np.int16)
        return obj, cls_, self.moving[obj]

    def changed_frames(self, other: CorrectedTracks) -> list[str]:
        """Frame ids in which a point's object, class or motion differs between ``self`` and ``other``
        (the same tracks with other corrections)."""
        a, b = self._entry_state(), other._entry_state()
        diff = np.zeros(self.instance.shape, bool)
        for x, y in zip(a, b, strict=True):
            diff |= x != y
        t = self.tracks
        return [t.frame_ids[f] for f in np.unique(t.entry_scans()[diff])]

    def object_scans(self, object_id: int) -> list[str]:
        """Frame ids of the scans in which object ``object_id`` has points, in order."""
        t = self.tracks
        return [t.frame_ids[f] for f in np.unique(t.entry_scans()[self.instance == object_id])]

    def identity(self, object_id: int) -> ObjectIdentity:
        """Object ``object_id``'s points in every scan of the tracks (:meth:`ObjectIdentity.of_track` of a
        corrected object: what a correction made on it keeps)."""
        return ObjectIdentity.of_ids(self.tracks, self.instance, object_id)

    @property
    def count(self) -> int:
        """Largest object id (the run's tracks and the parts splits cut off)."""
        return int(self.label.size) - 1

    def report(self) -> dict[str, Any]:
        """Per correction id (a string: JSON keys) how it met the objects: ``{"track", "iou", "applied"}``
        (a relabel); a merge adds ``"action": "merge"``, ``"other_track"``, ``"other_iou"``, a split
        ``"action": "split"``, ``"new_track"``."""
        out: dict[str, Any] = {}
        for cid, r in self.results:
            entry: dict[str, Any] = {
                "track": r.match.track,
                "iou": round(r.match.iou, 4),
                "applied": r.applied,
            }
            if r.action == "merge" and r.other is not None:
                entry.update(action="merge", other_track=r.other.track, other_iou=round(r.other.iou, 4))
            elif r.action == "split":
                entry.update(action="split", new_track=r.new_track)
            out[str(cid)] = entry
        return out


def read_corrected_tracks(layout: SequenceLayout, schema: Schema) -> CorrectedTracks:
    """A sequence folder's ``tracks.npz`` with its ``corrections_object.npz`` (the run's own) on top."""
    objects = ObjectCorrections.read(layout.corrections_object, schema.num_classes)
    return CorrectedTracks.of(SequenceTracks.load(layout.tracks), objects, schema.things())


__all__ = [
    "ACTIONS",
    "MAX_OBJECT_ID",
    "MIN_IOU",
    "NO_CLASS",
    "Action",
    "CorrectedTracks",
    "EditResult",
    "Match",
    "ObjectCorrections",
    "ObjectEdit",
    "ObjectIdentity",
    "match_track",
    "match_tracks",
    "merge_object_corrections",
    "read_corrected_tracks",
]
