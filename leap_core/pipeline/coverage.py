"""Why points of a finished run stay unlabeled in its export, counted from the run folder and its dataset.

A point is unlabeled exactly when its 0.2 m voxel is not in the final grid (docs/METHOD.md B.5). A voxel
enters the grid only when some frame painted a point in it (B.1-B.3): the point lay in a camera image
and a 2D mask covered it and survived depth clustering. So an unlabeled point has one of two reasons:

- ``outside_view``: no point of its voxel was inside any camera's image in any frame of the run;
- ``no_mask``: its voxel was inside the image in some frame, but no mask kept there covered it (the
  labeler found nothing there, e.g. a detector box below ``box_threshold`` was dropped in 2D, or depth
  clustering removed the point from the mask).

No confidence threshold acts in 3D: every point of a labeled voxel gets the voxel's most likely class, so
there is no "below threshold" count. With the 3D-CN the final grid holds every scanned voxel, so nothing
stays unlabeled.

Counting reads every scan and run file of the run, so the counts are kept in the run folder's
``export-coverage.json`` under a key of the export stage's record (:func:`cached_export_coverage`): a rerun
whose stages are all cached, and the app's export dialog, read them instead of counting again.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError
from leap_core.export import raw_id_counts
from leap_core.fusion import rows_in_sorted, voxel_keys, world_points
from leap_core.io_utils import atomic_write_json
from leap_core.pipeline.context import hash_json, load_view, read_state
from leap_core.run_layout import SequenceLayout
from leap_core.types import UNLABELED


@dataclass(frozen=True)
class ExportCoverage:
    """Point counts of a run's export over its frames.

    Attributes:
        frames: scans in the export.
        points: points in those scans.
        labeled: points with a class.
        outside_view: unlabeled points whose voxel was never inside a camera image (of any camera).
        no_mask: unlabeled points whose voxel was in the image but never covered by a kept mask.
        raw_counts: raw id (0 = unlabeled) → points, as the ``.label`` files hold them.
    """

    frames: int
    points: int
    labeled: int
    outside_view: int
    no_mask: int
    raw_counts: dict[int, int]

    @property
    def unlabeled(self) -> int:
        return self.points - self.labeled

    def to_dict(self) -> dict[str, object]:
        return {**asdict(self), "unlabeled": self.unlabeled}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ExportCoverage:
        """Inverse of :meth:`to_dict` after a JSON round trip (raw ids as strings).

        Raises:
            KeyError, TypeError, ValueError, AttributeError: a field is missing or of the wrong type.
        """
        return cls(
            frames=int(data["frames"]),
            points=int(data["points"]),
            labeled=int(data["labeled"]),
            outside_view=int(data["outside_view"]),
            no_mask=int(data["no_mask"]),
            raw_counts={int(k): int(v) for k, v in data["raw_counts"].items()},
        )


def summed_coverage(parts: Iterable[ExportCoverage]) -> ExportCoverage:
    """The counts of several sequences' exports taken together (a run's export)."""
    parts = list(parts)
    raw: dict[int, int] = {}
    for c in parts:
        for k, v in c.raw_counts.items():
            raw[k] = raw.get(k, 0) + v
    return ExportCoverage(
        frames=sum(c.frames for c in parts),
        points=sum(c.points for c in parts),
        labeled=sum(c.labeled for c in parts),
        outside_view=sum(c.outside_view for c in parts),
        no_mask=sum(c.no_mask for c in parts),
        raw_counts=dict(sorted(raw.items())),
    )


def coverage_counts(cov: ExportCoverage) -> dict[str, object]:
    """The ``counts`` :func:`leap_core.export.summary_yaml` takes."""
    return {
        "scans": cov.frames,
        "points": cov.points,
        "labeled": cov.labeled,
        "unlabeled": cov.unlabeled,
        "unlabeled_by_reason": {"outside_view": cov.outside_view, "no_mask": cov.no_mask},
        "raw_counts": dict(cov.raw_counts),
    }


def unlabeled_reasons(label: npt.ArrayLike, keys: npt.ArrayLike, seen_keys: npt.ArrayLike) -> tuple[int, int]:
    """``(outside_view, no_mask)`` counts of one scan's unlabeled points.

    Args:
        label: (N,) class index per point, ``UNLABELED`` where none.
        keys: (N,) int64 world voxel key per point.
        seen_keys: (S,) sorted unique int64 keys of the voxels some frame saw inside a camera image.
    """
    lab = np.asarray(label).reshape(-1)
    k = np.asarray(keys, dtype=np.int64).reshape(-1)
    if k.shape != lab.shape:
        raise ValueError(f"{k.shape[0]} keys for {lab.shape[0]} labels")
    unl = lab == UNLABELED
    seen = rows_in_sorted(seen_keys, k[unl]) >= 0
    return int((~seen).sum()), int(seen.sum())


def export_coverage(
    folder: Path, dataset: Path, frames: range | None, voxel_size: float, *, merge_at: int = 1 << 19
) -> ExportCoverage:
    """Count a finished run's exported points by label and the unlabeled ones by reason (module docstring).

    Reads the run's ``points/``, ``observations/`` and ``export/`` files and the dataset's scans and poses,
    each once: a point's reason needs the voxels seen in *every* frame, so the unlabeled points are kept as
    (voxel key, point count) pairs, merged over frames (a static world revisits the same voxels, so these
    stay near the number of distinct unlabeled voxels), and split by reason at the end.

    Args:
        folder: the sequence's folder in the run.
        dataset: the run's sequence folder.
        frames: the run's frame numbers (None: all), as given to the run.
        voxel_size: the run's ``fusion.voxel_size``.
        merge_at: pending (key, count) pairs that trigger a merge into the totals (a memory bound, not a
            result switch: tests force small values and require the same counts).

    Raises:
        DatasetError: a missing or unreadable run file, naming it.
    """
    lay = SequenceLayout(folder)
    seq = lay.open_sequence(dataset)
    idx = seq.select(frames)
    seen = _KeyCounts(merge_at)
    unlabeled = _KeyCounts(merge_at)
    points = labeled = 0
    raws: dict[int, int] = {}
    for i in idx:
        fid = seq.frame_ids[i]
        obs_path = lay.observation(fid)
        n, in_view = load_view(obs_path)
        path = lay.points(fid)
        try:
            with np.load(path) as z:
                lab = np.asarray(z["label"])
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable point labels ({exc})") from exc
        frame = seq.frame(i)
        keys = voxel_keys(world_points(frame.points, frame.pose), voxel_size)
        if n != keys.shape[0]:
            raise DatasetError(obs_path, f"observation of {n} points for a scan of {keys.shape[0]}")
        if lab.shape != keys.shape:
            raise DatasetError(path, f"{lab.shape[0]} point labels for a scan of {keys.shape[0]} points")
        seen.add(keys[in_view])
        unl = lab == UNLABELED
        unlabeled.add(keys[unl])
        points += lab.shape[0]
        labeled += int(lab.shape[0] - unl.sum())
        label_path = lay.export_label(fid)
        try:
            raw = np.fromfile(label_path, dtype="<u4")
        except OSError as exc:
            raise DatasetError(label_path, f"cannot read exported labels ({exc.strerror or exc})") from exc
        for rid, c in raw_id_counts([raw]).items():
            raws[rid] = raws.get(rid, 0) + c
    seen_keys, _ = seen.merged()
    unl_keys, unl_counts = unlabeled.merged()
    in_seen = rows_in_sorted(seen_keys, unl_keys) >= 0
    no_mask = int(unl_counts[in_seen].sum())
    outside = int(unl_counts[~in_seen].sum())
    return ExportCoverage(len(idx), points, labeled, outside, no_mask, dict(sorted(raws.items())))


class _KeyCounts:
    """A multiset of int64 voxel keys: ``add`` many, read back sorted unique keys with their counts.

    Per-frame parts wait until ``merge_at`` keys are pending, then are merged into the sorted totals
    (looked up with ``searchsorted``, new keys inserted in order): the temporaries stay at the size of one
    batch and one copy of the totals, not of everything added (a 1,000-frame run adds ~30 M keys for ~1 M
    distinct voxels).
    """

    def __init__(self, merge_at: int) -> None:
        self.merge_at = max(int(merge_at), 1)
        self.keys = np.zeros(0, np.int64)
        self.counts = np.zeros(0, np.int64)
        self.parts: list[tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]] = []
        self.pending = 0

    def add(self, keys: npt.NDArray[np.int64]) -> None:
        k, c = np.unique(keys, return_counts=True)
        self.parts.append((k, c.astype(np.int64)))
        self.pending += k.size
        if self.pending >= self.merge_at:
            self._merge()

    def _merge(self) -> None:
        if not self.parts:
            return
        if len(self.parts) == 1:
            bk, bc = self.parts[0]
        else:
            bk, inverse = np.unique(np.concatenate([k for k, _ in self.parts]), return_inverse=True)
            bc = np.bincount(
                inverse.reshape(-1), weights=np.concatenate([c for _, c in self.parts]), minlength=bk.size
            ).astype(np.int64)
        self.parts, self.pending = [], 0
        pos = np.searchsorted(self.keys, bk)
        hit = np.zeros(bk.size, bool)
        inside = pos < self.keys.size
        hit[inside] = self.keys[pos[inside]] == bk[inside]
        self.counts[pos[hit]] += bc[hit]
        new = ~hit
        # bk is sorted, so the insert positions are too and the totals stay sorted.
        self.keys = np.insert(self.keys, pos[new], bk[new])
        self.counts = np.insert(self.counts, pos[new], bc[new])

    def merged(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """(sorted unique keys (U,), point count per key (U,))."""
        self._merge()
        return self.keys, self.counts


# ------------------------------------------------------------------------------------ the cached counts
COVERAGE_FORMAT = 1
"""Version of the counting rule and of ``export-coverage.json``'s fields (part of :func:`coverage_key`)."""


def coverage_key(folder: Path, dataset: Path, frames: range | None, voxel_size: float) -> str | None:
    """What the counts of a run's current export depend on, hashed; None while its export is not done.

    The export stage's ``stages.json`` record: its fingerprint (which chains every upstream input: the
    dataset's files and poses, the frames, the config, the corrections) and its ``finished`` time (so an
    export stage that ran again, even with the same fingerprint, makes a new key), plus the arguments of
    :func:`export_coverage`. The app's "apply corrections" job rewrites the export without a stage record
    and deletes the counts file instead (``app.exports.invalidate``).
    """
    rec = read_state(SequenceLayout(folder)).get("export")
    if not isinstance(rec, dict) or rec.get("status") != "done" or not rec.get("fingerprint"):
        return None
    span = None if frames is None else [frames.start, frames.stop, frames.step]
    return hash_json(
        {
            "format": COVERAGE_FORMAT,
            "export": rec["fingerprint"],
            "finished": rec.get("finished"),
            "dataset": str(Path(dataset).resolve()),
            "frames": span,
            "voxel_size": float(voxel_size),
        }
    )


def read_coverage_file(path: Path, key: str | None = None) -> ExportCoverage | None:
    """The counts in an ``export-coverage.json``; None when it is missing, unreadable, of an older format
    or (with ``key``) written for another :func:`coverage_key`."""
    try:
        data = json.loads(Path(path).read_text())
        if key is not None and data.get("key") != key:
            return None
        return ExportCoverage.from_dict(data)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def write_coverage_file(path: Path, cov: ExportCoverage, key: str | None) -> None:
    """Write ``export-coverage.json`` atomically: :meth:`ExportCoverage.to_dict` plus ``key``."""
    data = cov.to_dict()
    data["raw_counts"] = {str(k): v for k, v in cov.raw_counts.items()}
    data["key"] = key
    atomic_write_json(path, data)


def cached_export_coverage(
    folder: Path, dataset: Path, frames: range | None, voxel_size: float
) -> ExportCoverage:
    """:func:`export_coverage`, read from the run's ``export-coverage.json`` when it was written for the
    current :func:`coverage_key`, else counted and written there (when the export is done).

    Counting reads every scan and run file of the run again; a rerun whose stages are all cached would pay
    that for the same numbers.
    """
    path = SequenceLayout(folder).export_coverage
    key = coverage_key(folder, dataset, frames, voxel_size)
    if key is not None:
        cached = read_coverage_file(path, key)
        if cached is not None:
            return cached
    cov = export_coverage(folder, dataset, frames, voxel_size)
    if key is not None:
        write_coverage_file(path, cov, key)
    return cov


__all__ = [
    "COVERAGE_FORMAT",
    "ExportCoverage",
    "cached_export_coverage",
    "coverage_counts",
    "coverage_key",
    "export_coverage",
    "read_coverage_file",
    "summed_coverage",
    "unlabeled_reasons",
    "write_coverage_file",
]
