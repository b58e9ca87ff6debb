"""``tracks.npz``: the ``tracks`` stage's objects (:mod:`leap_core.pipeline.objects`), sparse over the
tracked points only:

- ``frame_ids`` (T,) str and ``offsets`` (T+1,) int64: scan t's entries are ``offsets[t]:offsets[t+1]``;
- ``rows`` (P,) int32 the point's row in its scan, ``track`` (P,) int32 its track id (1..K);
- per track (index = id - 1): ``label`` (K,) int16 voted class, ``velocity`` (K, 3) float32 m/s,
  ``moving`` (K,) bool, ``scans`` (K,) int32, ``sweep`` (K,) float32 m, ``voted`` (K,) bool whether its
  points take ``label`` (``tracking.vote``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError, LeapError
from leap_core.io_utils import atomic_save_npz, read_npz
from leap_core.tracking import TrackTable


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

    def scan(self, frame_id: str) -> ScanObjects:
        """The tracked points of ``frame_id`` (none for a scan the file does not hold)."""
        try:
            t = self.frame_ids.index(frame_id)
        except ValueError:
            return ScanObjects(np.zeros(0, np.int32), np.zeros(0, np.int32))
        a, b = int(self.offsets[t]), int(self.offsets[t + 1])
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
        table = TrackTable(
            label=z["label"].astype(np.int16),
            velocity=z["velocity"].astype(np.float64),
            moving=z["moving"].astype(bool),
            scans=z["scans"].astype(np.int64),
            sweep=z["sweep"].astype(np.float64),
            voted=voted.astype(bool),
        )
        return cls(
            tuple(str(x) for x in z["frame_ids"]),
            z["offsets"].astype(np.int64),
            z["rows"].astype(np.int32),
            z["track"].astype(np.int32),
            table,
        )


__all__ = ["ScanObjects", "SequenceTracks"]
