"""Manual corrections applied to points: pure array functions shared by the pipeline's ``label_points``
stage and the app's immediate "apply corrections" job (docs/METHOD.md, "Manual corrections").

Two scopes of correction reach the points:

- **map** scope: ``(keys (K,) int64, class_idx (K,))``, sorted unique voxel keys (``fusion.last_per_key``
  applied) and one class each; every point of every scan whose voxel is listed takes that class.
- **scan** scope: :class:`ScanCorrections`, per frame id the indices of that scan's points and their
  class; only those points change (a moving object smeared over many voxels in the map).

A class index of :data:`ERASE` (``UNLABELED = -1``) erases: the points become unlabeled (export id 0,
confidence 0). A corrected point's confidence is 1. The scan scope is applied after the map scope, so on a
point both touch the scan-scope correction (the more specific one) wins.

:class:`FrameVoxelIndex` answers "which frames have a point in these voxels" for the immediate apply job.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError
from leap_core.io_utils import atomic_save_npz
from leap_core.types import UNLABELED

ERASE = UNLABELED
"""Class index of an erase correction: the points become unlabeled."""


def class_in_keys(
    point_keys: npt.NDArray[np.int64], keys: npt.NDArray[np.int64], class_idx: npt.NDArray[np.integer]
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int16]]:
    """Look points' voxel keys up in a sorted unique key list.

    Args:
        point_keys: (N,) voxel key per point.
        keys: (K,) sorted unique voxel keys.
        class_idx: (K,) class per key.

    Returns:
        ``hit (N,) bool`` (the point's voxel is listed) and ``cls (N,) int16`` (its class where hit, else
        UNLABELED). Example: point_keys [5, 7, 9], keys [5, 9], class_idx [2, -1] → hit [T, F, T],
        cls [2, -1, -1].
    """
    cls = np.full(point_keys.shape, UNLABELED, np.int16)
    if keys.size == 0:
        return np.zeros(point_keys.shape, bool), cls
    pos = np.minimum(np.searchsorted(keys, point_keys), keys.size - 1)
    hit = keys[pos] == point_keys
    cls[hit] = class_idx[pos[hit]]
    return hit, cls


def set_points(
    label: npt.NDArray[np.int16],
    conf: npt.NDArray[np.floating],
    where: npt.NDArray[np.bool_] | npt.NDArray[np.int64],
    cls: npt.ArrayLike,
) -> None:
    """Set the points ``where`` (mask or indices) to class ``cls`` in place: confidence 1, or 0 where the
    class is :data:`ERASE` (label UNLABELED)."""
    c = np.asarray(cls, np.int16)
    label[where] = c
    conf[where] = np.where(c == ERASE, 0.0, 1.0)


def correct_points(
    label: npt.ArrayLike,
    conf: npt.ArrayLike,
    point_keys: npt.ArrayLike,
    map_keys: npt.NDArray[np.int64],
    map_class: npt.NDArray[np.integer],
    *,
    scan_points: npt.NDArray[np.int64] | None = None,
    scan_class: npt.NDArray[np.integer] | None = None,
) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
    """One scan's point labels with the corrections applied (map scope, then this scan's scan scope).

    Args:
        label: (N,) int class per point (UNLABELED = -1), from the final grid.
        conf: (N,) confidence per point.
        point_keys: (N,) voxel key of each point.
        map_keys, map_class: map-scope corrections, (K,) sorted unique keys and their class (ERASE allowed).
        scan_points, scan_class: (P,) point indices of this scan and their class (no repeats), or None.

    Returns:
        New ``label (N,) int16`` and ``conf (N,) float32``. Example: label [0, 1, 1], keys [5, 7, 9],
        map (keys [7], class [2]), scan (points [2], class [-1]) → label [0, 2, -1], conf [c0, 1, 0].

    Raises:
        ValueError: a scan point index outside ``0..N-1``.
    """
    lab = np.array(label, dtype=np.int16, copy=True).reshape(-1)
    cf = np.array(conf, dtype=np.float32, copy=True).reshape(-1)
    pk = np.asarray(point_keys, np.int64).reshape(-1)
    if not lab.shape == cf.shape == pk.shape:
        raise ValueError(f"label {lab.shape}, conf {cf.shape} and point_keys {pk.shape} must match")
    hit, cls = class_in_keys(pk, map_keys, map_class)
    set_points(lab, cf, hit, cls[hit])
    if scan_points is not None and scan_class is not None and scan_points.size:
        if scan_points.min() < 0 or scan_points.max() >= lab.size:
            raise ValueError(f"scan correction point index out of range 0..{lab.size - 1}")
        set_points(lab, cf, scan_points, scan_class)
    return lab, cf


def changed_keys(
    old_keys: npt.NDArray[np.int64],
    old_class: npt.NDArray[np.integer],
    new_keys: npt.NDArray[np.int64],
    new_class: npt.NDArray[np.integer],
) -> npt.NDArray[np.int64]:
    """Voxels whose map-scope correction differs between two sets (added, removed or another class).

    Both sets are sorted unique keys with one class each. Example: old ([1, 2, 3], [0, 0, 1]),
    new ([2, 3, 4], [0, 2, 1]) → [1, 3, 4].

    Returns:
        (D,) sorted unique int64 keys.
    """
    both = np.intersect1d(old_keys, new_keys, assume_unique=True)
    _, o_cls = class_in_keys(both, old_keys, old_class)
    _, n_cls = class_in_keys(both, new_keys, new_class)
    only = np.setxor1d(old_keys, new_keys, assume_unique=True)
    return np.union1d(only, both[o_cls != n_cls]).astype(np.int64)


# ------------------------------------------------------------------------------------------ scan scope
@dataclass(frozen=True)
class ScanCorrections:
    """Scan-scope corrections of a run, per frame (CSR layout).

    Frame ``frame_ids[f]`` owns ``points[ptr[f]:ptr[f+1]]`` (unique point indices, sorted) with classes
    ``class_idx[ptr[f]:ptr[f+1]]`` (ERASE allowed).
    """

    frame_ids: tuple[str, ...]
    """Frame ids (file stems) with at least one corrected point, sorted."""
    ptr: npt.NDArray[np.int64]
    """(F+1,) offsets into ``points`` / ``class_idx``."""
    points: npt.NDArray[np.int64]
    """(P,) point indices."""
    class_idx: npt.NDArray[np.int16]
    """(P,) class per point."""

    @classmethod
    def empty(cls) -> ScanCorrections:
        return cls((), np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int16))

    @classmethod
    def merge(cls, items: Iterable[tuple[str, npt.ArrayLike, int]]) -> ScanCorrections:
        """Flatten ``(frame_id, point indices, class)`` corrections made in this order: on a point listed
        twice the later one wins. Example: [("a", [3, 1], 2), ("a", [1], 0)] → a: points [1, 3], class [0, 2].
        """
        per_frame: dict[str, list[tuple[npt.NDArray[np.int64], npt.NDArray[np.int16]]]] = {}
        for frame_id, pts, c in items:
            p = np.asarray(pts, np.int64).reshape(-1)
            per_frame.setdefault(frame_id, []).append((p, np.full(p.shape, c, np.int16)))
        ids = sorted(f for f, parts in per_frame.items() if sum(p.size for p, _ in parts))
        ptr = [0]
        pts_out: list[npt.NDArray[np.int64]] = []
        cls_out: list[npt.NDArray[np.int16]] = []
        for f in ids:
            p = np.concatenate([a for a, _ in per_frame[f]])
            cl = np.concatenate([b for _, b in per_frame[f]])
            # Last occurrence wins: unique over the reversed list keeps each point's last class.
            uniq, first_rev = np.unique(p[::-1], return_index=True)
            pts_out.append(uniq)
            cls_out.append(cl[::-1][first_rev])
            ptr.append(ptr[-1] + uniq.size)
        return cls(
            tuple(ids),
            np.asarray(ptr, np.int64),
            np.concatenate(pts_out) if pts_out else np.zeros(0, np.int64),
            np.concatenate(cls_out) if cls_out else np.zeros(0, np.int16),
        )

    def of(self, frame_id: str) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int16]]:
        """``(points, class_idx)`` of one frame (empty arrays when it has none)."""
        try:
            f = self.frame_ids.index(frame_id)
        except ValueError:
            return np.zeros(0, np.int64), np.zeros(0, np.int16)
        a, b = int(self.ptr[f]), int(self.ptr[f + 1])
        return self.points[a:b], self.class_idx[a:b]

    def changed_frames(self, other: ScanCorrections) -> list[str]:
        """Frame ids whose scan-scope corrections differ between ``self`` and ``other``, sorted."""
        out = []
        for f in sorted(set(self.frame_ids) | set(other.frame_ids)):
            (p1, c1), (p2, c2) = self.of(f), other.of(f)
            if not (np.array_equal(p1, p2) and np.array_equal(c1, c2)):
                out.append(f)
        return out

    def save(self, path: str | Path) -> None:
        atomic_save_npz(
            path,
            frame_ids=np.asarray(self.frame_ids, dtype=np.str_),
            ptr=self.ptr,
            points=self.points,
            class_idx=self.class_idx,
        )

    @classmethod
    def load(cls, path: str | Path, num_classes: int) -> ScanCorrections:
        """Read :meth:`save`'s file.

        Raises:
            DatasetError: unreadable file, inconsistent offsets, or a class outside ``-1..num_classes-1``.
        """
        try:
            with np.load(path, allow_pickle=False) as z:
                ids = tuple(str(s) for s in np.asarray(z["frame_ids"]).reshape(-1))
                ptr = np.asarray(z["ptr"], np.int64)
                pts = np.asarray(z["points"], np.int64)
                c = np.asarray(z["class_idx"])
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise DatasetError(path, f"unreadable scan corrections ({exc})") from exc
        if ptr.shape != (len(ids) + 1,) or ptr[0] != 0 or ptr[-1] != pts.size or np.any(np.diff(ptr) < 0):
            raise DatasetError(path, "'ptr' must be 0..len(points), non-decreasing, one more than frame_ids")
        if c.shape != pts.shape or not np.issubdtype(c.dtype, np.integer):
            raise DatasetError(path, "'class_idx' must be integers, one per point")
        if c.size and (c.min() < ERASE or c.max() >= num_classes):
            raise DatasetError(path, f"'class_idx' must be in -1..{num_classes - 1}")
        if pts.size and pts.min() < 0:
            raise DatasetError(path, "'points' must be point indices (>= 0)")
        return cls(ids, ptr, pts, c.astype(np.int16))


# -------------------------------------------------------------------------------------- voxel → frames
@dataclass(frozen=True)
class FrameVoxelIndex:
    """Which frames have points in which voxels: every (voxel key, frame) pair, sorted by key.

    Built from each frame's unique point voxel keys; memory is 12 bytes per (frame, voxel) pair.
    """

    keys: npt.NDArray[np.int64]
    """(M,) voxel keys, sorted (a key repeats once per frame that sees it)."""
    frame: npt.NDArray[np.int32]
    """(M,) frame position (index into the frames the index was built over) of each pair."""
    num_frames: int
    """Frames the index was built over."""

    @classmethod
    def build(cls, per_frame: Iterable[npt.ArrayLike]) -> FrameVoxelIndex:
        """From each frame's point voxel keys, in frame order (repeats are dropped)."""
        ks: list[npt.NDArray[np.int64]] = []
        fs: list[npt.NDArray[np.int32]] = []
        n = 0
        for pos, keys in enumerate(per_frame):
            u = np.unique(np.asarray(keys, np.int64))
            ks.append(u)
            fs.append(np.full(u.shape, pos, np.int32))
            n = pos + 1
        if not ks:
            return cls(np.zeros(0, np.int64), np.zeros(0, np.int32), 0)
        k, f = np.concatenate(ks), np.concatenate(fs)
        order = np.argsort(k, kind="stable")
        return cls(k[order], f[order], n)

    def frames_of(self, keys: npt.ArrayLike) -> npt.NDArray[np.int32]:
        """Sorted unique frame positions with a point in any of ``keys``. Example: pairs
        (5: frames 0, 2), (7: frame 1); keys [5, 9] → [0, 2]."""
        q = np.unique(np.asarray(keys, np.int64))
        lo = np.searchsorted(self.keys, q, side="left")
        hi = np.searchsorted(self.keys, q, side="right")
        sel = hi > lo
        if not sel.any():
            return np.zeros(0, np.int32)
        # Mark the [lo, hi) ranges with a difference array, then gather the frames inside them.
        marks = np.zeros(self.keys.size + 1, np.int64)
        np.add.at(marks, lo[sel], 1)
        np.add.at(marks, hi[sel], -1)
        inside = np.cumsum(marks[:-1]) > 0
        return np.unique(self.frame[inside]).astype(np.int32)

    def save(self, path: str | Path) -> None:
        atomic_save_npz(path, keys=self.keys, frame=self.frame, num_frames=np.asarray(self.num_frames))

    @classmethod
    def load(cls, path: str | Path) -> FrameVoxelIndex:
        """Read :meth:`save`'s file. Raises DatasetError when it is unreadable or inconsistent."""
        try:
            with np.load(path, allow_pickle=False) as z:
                out = cls(
                    np.asarray(z["keys"], np.int64), np.asarray(z["frame"], np.int32), int(z["num_frames"])
                )
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise DatasetError(path, f"unreadable frame-voxel index ({exc})") from exc
        if out.keys.shape != out.frame.shape:
            raise DatasetError(path, "'keys' and 'frame' must have the same length")
        return out


__all__ = [
    "ERASE",
    "FrameVoxelIndex",
    "ScanCorrections",
    "changed_keys",
    "class_in_keys",
    "correct_points",
    "set_points",
]
