"""``tracks.npz``: the ``tracks`` stage's objects (:mod:`leap_core.pipeline.objects`), sparse over the
tracked points only:

- ``frame_ids`` (T,) str and ``offsets`` (T+1,) int64: scan t's entries are ``offsets[t]:offsets[t+1]``;
- ``rows`` (P,) int32 the point's row in its scan, ``track`` (P,) int32 its track id (1..K);
- per track (index = id - 1): ``label`` (K,) int16 voted class, ``velocity`` (K, 3) float32 m/s,
  ``moving`` (K,) bool, ``scans`` (K,) int32, ``sweep`` (K,) float32 m, ``voted`` (K,) bool whether its
  points take ``label`` (``tracking.vote``);
- the class vote's evidence per track (:class:`~leap_core.tracking.VoteEvidence`): ``share`` (K,) float32
  the winner's share of the votes, ``runner_up`` (K,) int16 the runner-up class (-1 none) and
  ``runner_share`` (K,) float32 its share;
- each track's life in the file (:class:`TrackLife`): ``first`` / ``last`` (K,) int32 the first and last
  scan index (position in ``frame_ids``) where it has points, ``gaps`` (K,) int32 the scans between them
  where it has none.

Files written before the evidence and the life were kept still load: the evidence reads as unanimous
(share 1, no runner-up, :meth:`~leap_core.tracking.VoteEvidence.unknown`) and the life is counted from
the file's points (:func:`track_life`), which is what the stored one holds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError, LeapError
from leap_core.io_utils import atomic_save_npz, read_npz
from leap_core.object_review import ObjectQueueConfig, object_queue
from leap_core.tracking import TrackTable, VoteEvidence


@dataclass(frozen=True)
class TrackLife:
    """Where each track (index = id - 1) has points in a ``tracks.npz``.

    Attributes:
        first: (K,) int64 first scan index (position in the file's ``frame_ids``) with a point of it,
            -1 for a track with none.
        last: (K,) int64 last such scan index, -1 for a track with none.
        gaps: (K,) int64 scans in ``first..last`` where it has no point (a broken track: the tracker lost
            it for a while, or the map called all its points stuff there); 0 for a track with none.
        present: (K,) int64 scans where it has points (``last - first + 1 - gaps``; 0 for none).
    """

    first: npt.NDArray[np.int64]
    last: npt.NDArray[np.int64]
    gaps: npt.NDArray[np.int64]
    present: npt.NDArray[np.int64]


_LIFE_BLOCK = 1 << 20
"""Points :func:`track_life` reads at a time."""


def track_life(offsets: npt.ArrayLike, track: npt.ArrayLike, k: int) -> TrackLife:
    """:class:`TrackLife` of tracks 1..``k`` from a file's ``offsets`` (T+1,) and per-point ``track``
    (P,) ids: with ``S_j`` the set of scans t holding a point of track j,
    ``first = min S_j``, ``last = max S_j``, ``present = |S_j|``, ``gaps = last - first + 1 - |S_j|``."""
    off = np.asarray(offsets, np.int64).reshape(-1)
    tid = np.asarray(track).reshape(-1)
    scans = max(off.size - 1, 1)
    # The (track, scan) pairs once each, sorted by track then scan: a track's first pair holds its first
    # scan and its last pair its last (a sort and a diff, no unbuffered ufunc.at over every point). Scans
    # are taken a block of about _LIFE_BLOCK points at a time, so the temporaries stay that size however
    # long the sequence (pairs are far fewer than points).
    parts = [np.zeros(0, np.int64)]
    t0 = 0
    while t0 < off.size - 1:
        t1 = max(int(np.searchsorted(off, off[t0] + _LIFE_BLOCK, side="right")) - 1, t0 + 1)
        scan_of = np.repeat(np.arange(t0, t1, dtype=np.int64), np.diff(off[t0 : t1 + 1]))
        parts.append(np.unique((tid[off[t0] : off[t1]].astype(np.int64) - 1) * scans + scan_of))
        t0 = t1
    pairs = np.sort(np.concatenate(parts))
    row, t = pairs // scans, pairs % scans
    present = np.bincount(row, minlength=k).astype(np.int64)[:k]
    starts = np.flatnonzero(np.r_[True, row[1:] != row[:-1]]) if row.size else np.zeros(0, np.int64)
    ends = np.append(starts[1:], row.size)[: starts.size] - 1
    first = np.full(k, -1, np.int64)
    last = np.full(k, -1, np.int64)
    first[row[starts]] = t[starts]
    last[row[starts]] = t[ends]
    gaps = np.where(present > 0, last - first + 1 - present, 0)
    return TrackLife(first, last, gaps, present)


@dataclass(frozen=True)
class ScanObjects:
    """One scan's tracked points: ``rows`` (P,) int32 point rows and ``track`` (P,) int32 ids (1..K)."""

    rows: npt.NDArray[np.int32]
    track: npt.NDArray[np.int32]


@dataclass(frozen=True)
class SequenceTracks:
    """``tracks.npz`` read back (module docstring)."""

    frame_ids: tuple[str, ...]
    offsets: npt.NDArray[np.int64]
    rows: npt.NDArray[np.int32]
    track: npt.NDArray[np.int32]
    table: TrackTable
    life: TrackLife | None = None
    """As the file stores it; None: counted from the points when asked (:meth:`track_life`)."""

    def track_life(self) -> TrackLife:
        """Where each track has points (:class:`TrackLife`)."""
        if self.life is not None:
            return self.life
        return track_life(self.offsets, self.track, self.table.label.size)

    def entry_scans(self) -> npt.NDArray[np.int64]:
        """(P,) int64 the scan index (position in :attr:`frame_ids`) of each entry of :attr:`rows` (made on
        each call: a long sequence's tracks hold millions of entries)."""
        return np.repeat(np.arange(len(self.frame_ids), dtype=np.int64), np.diff(self.offsets))

    def span(self, frame_id: str) -> tuple[int, int]:
        """``(a, b)``: scan ``frame_id``'s entries are ``rows[a:b]`` (``(0, 0)`` for a scan the file does
        not hold)."""
        try:
            t = self.frame_ids.index(frame_id)
        except ValueError:
            return 0, 0
        return int(self.offsets[t]), int(self.offsets[t + 1])

    def scans_of(self, track: int) -> npt.NDArray[np.int64]:
        """(S,) int64 the scan indices (positions in :attr:`frame_ids`) where track ``track`` has points,
        ascending."""
        return np.unique(self.entry_scans()[self.track == track])

    def review_queue(
        self, things: npt.NDArray[np.bool_], cfg: ObjectQueueConfig
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
        """The tracks to review and why (:func:`leap_core.object_review.object_queue` over this file)."""
        ev, life = self.table.vote_evidence(), self.track_life()
        return object_queue(
            self.table.label,
            things,
            share=ev.share,
            runner_up=ev.runner_up,
            runner_share=ev.runner_share,
            present=life.present,
            gaps=life.gaps,
            cfg=cfg,
        )

    def scan(self, frame_id: str) -> ScanObjects:
        """The tracked points of ``frame_id`` (none for a scan the file does not hold)."""
        a, b = self.span(frame_id)
        return ScanObjects(self.rows[a:b], self.track[a:b])

    def point_objects(
        self,
        frame_id: str,
        labels: npt.NDArray[np.int16],
        keep: npt.NDArray[np.int64] | None = None,
    ) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.uint32], npt.NDArray[np.bool_]]:
        """(label, instance, moving) per point of one scan: ``labels`` with the points of voted tracks
        (``TrackTable.voted``: by default the moving ones) given their track's class, the track id of every
        tracked point (0 elsewhere) and whether the track moves. ``keep``: point rows that keep their label
        and get no object (points corrected by hand after the tracks were made)."""
        obj = self.scan(frame_id)
        if keep is not None and keep.size:
            sel = ~np.isin(obj.rows, keep)
            obj = ScanObjects(obj.rows[sel], obj.track[sel])
        n = labels.shape[0]
        if obj.rows.size and int(obj.rows.max()) >= n:
            raise LeapError(f"tracks.npz: scan {frame_id} has point rows up to {int(obj.rows.max())} of {n}")
        out = labels.astype(np.int16, copy=True)
        instance = np.zeros(n, np.uint32)
        moving = np.zeros(n, bool)
        k = obj.track.astype(np.int64) - 1
        voted = self.table.voted[k]
        out[obj.rows[voted]] = self.table.label[k[voted]]
        instance[obj.rows] = obj.track.astype(np.uint32)
        moving[obj.rows] = self.table.moving[k]
        return out, instance, moving

    def save(self, path: Path) -> None:
        evidence = self.table.vote_evidence()
        life = track_life(self.offsets, self.track, self.table.label.size)
        atomic_save_npz(
            path,
            frame_ids=np.array(self.frame_ids, dtype=np.str_),
            offsets=self.offsets,
            rows=self.rows,
            track=self.track,
            label=self.table.label,
            velocity=self.table.velocity.astype(np.float32),
            moving=self.table.moving,
            scans=self.table.scans.astype(np.int32),
            sweep=self.table.sweep.astype(np.float32),
            voted=self.table.voted,
            share=evidence.share.astype(np.float32),
            runner_up=evidence.runner_up.astype(np.int16),
            runner_share=evidence.runner_share.astype(np.float32),
            first=life.first.astype(np.int32),
            last=life.last.astype(np.int32),
            gaps=life.gaps.astype(np.int32),
        )

    @classmethod
    def load(cls, path: Path) -> SequenceTracks:
        """Raises: DatasetError naming the file when it is unreadable."""
        names = ("frame_ids", "offsets", "rows", "track", "label", "velocity", "moving", "scans", "sweep")
        try:
            z = read_npz(path)
            missing = [n for n in names if n not in z]
            if missing:
                raise KeyError(", ".join(missing))
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable tracks ({exc}); rerun the tracks stage") from exc
        # A file without ``voted`` was written when every track's points took its class.
        voted = z["voted"] if "voted" in z else np.ones(z["label"].shape[0], bool)
        evidence = (
            VoteEvidence(
                z["share"].astype(np.float64),
                z["runner_up"].astype(np.int16),
                z["runner_share"].astype(np.float64),
            )
            if all(n in z for n in ("share", "runner_up", "runner_share"))
            else None
        )
        life = (
            TrackLife(
                z["first"].astype(np.int64),
                z["last"].astype(np.int64),
                z["gaps"].astype(np.int64),
                np.where(z["first"] >= 0, z["last"].astype(np.int64) - z["first"] + 1 - z["gaps"], 0),
            )
            if all(n in z for n in ("first", "last", "gaps"))
            else None
        )
        table = TrackTable(
            label=z["label"].astype(np.int16),
            velocity=z["velocity"].astype(np.float64),
            moving=z["moving"].astype(bool),
            scans=z["scans"].astype(np.int64),
            sweep=z["sweep"].astype(np.float64),
            voted=voted.astype(bool),
            evidence=evidence,
        )
        return cls(
            tuple(str(x) for x in z["frame_ids"]),
            z["offsets"].astype(np.int64),
            z["rows"].astype(np.int32),
            z["track"].astype(np.int32),
            table,
            life,
        )


__all__ = ["ScanObjects", "SequenceTracks", "TrackLife", "track_life"]
