"""Why points of a finished run stay unlabeled in its export, counted from the run folder and its dataset.

A point is unlabeled exactly when its 0.2 m voxel is not in the final grid (docs/METHOD.md B.5). A voxel
enters the grid only when some frame painted a point in it (B.1-B.3): the point lay in the camera image
and a 2D mask covered it and survived depth clustering. So an unlabeled point has one of two reasons:

- ``outside_view``: no point of its voxel was inside the camera image in any frame of the run;
- ``no_mask``: its voxel was inside the image in some frame, but no mask kept there covered it (the
  labeler found nothing there, e.g. a detector box below ``box_threshold`` was dropped in 2D, or depth
  clustering removed the point from the mask).

No confidence threshold acts in 3D: every point of a labeled voxel gets the voxel's most likely class, so
there is no "below threshold" count. With the 3D-CN the final grid holds every scanned voxel, so nothing
stays unlabeled.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError
from leap_core.export import raw_id_counts
from leap_core.fusion import rows_in_sorted, voxel_keys, world_points
from leap_core.pipeline.context import load_observation
from leap_core.run_layout import RunLayout
from leap_core.types import UNLABELED

_SEEN_BATCH = 1 << 22
"""Per-frame unique keys gathered before :func:`export_coverage` folds them into the seen set."""


@dataclass(frozen=True)
class ExportCoverage:
    """Point counts of a run's export over its frames.

    Attributes:
        frames: scans in the export.
        points: points in those scans.
        labeled: points with a class.
        outside_view: unlabeled points whose voxel was never inside the camera image.
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
        seen_keys: (S,) sorted unique int64 keys of the voxels some frame saw inside the camera image.
    """
    lab = np.asarray(label).reshape(-1)
    k = np.asarray(keys, dtype=np.int64).reshape(-1)
    if k.shape != lab.shape:
        raise ValueError(f"{k.shape[0]} keys for {lab.shape[0]} labels")
    unl = lab == UNLABELED
    seen = rows_in_sorted(seen_keys, k[unl]) >= 0
    return int((~seen).sum()), int(seen.sum())


def export_coverage(run_dir: Path, dataset: Path, frames: range | None, voxel_size: float) -> ExportCoverage:
    """Count a finished run's exported points by label and the unlabeled ones by reason (module docstring).

    Reads the run's ``points/``, ``observations/`` and ``export/`` files and the dataset's scans and poses
    (two passes over the frames: the seen voxels, then the points).

    Args:
        run_dir: the run folder.
        dataset: the run's sequence folder.
        frames: the run's frame numbers (None: all), as given to the run.
        voxel_size: the run's ``fusion.voxel_size``.

    Raises:
        DatasetError: a missing or unreadable run file, naming it.
    """
    lay = RunLayout(run_dir)
    seq = lay.open_sequence(dataset)
    idx = seq.select(frames)

    def keys_of(i: int) -> npt.NDArray[np.int64]:
        frame = seq.frame(i)
        return voxel_keys(world_points(frame.points, frame.pose), voxel_size)

    # Both passes hold one frame at a time: the seen voxels are folded in batches of per-frame unique keys
    # and the exported labels are counted frame by frame, so memory does not grow with the sequence.
    seen = np.zeros(0, np.int64)
    pending: list[npt.NDArray[np.int64]] = []
    n_pending = 0
    for i in idx:
        _, n, in_view = load_observation(lay.observation(seq.frame_ids[i]))
        if n:
            pending.append(np.unique(keys_of(i)[in_view]))
            n_pending += len(pending[-1])
        if n_pending >= _SEEN_BATCH:
            seen = np.union1d(seen, np.concatenate(pending))
            pending, n_pending = [], 0
    if pending:
        seen = np.union1d(seen, np.concatenate(pending))

    points = labeled = outside = no_mask = 0

    def raws() -> Iterator[npt.NDArray[np.uint32]]:
        nonlocal points, labeled, outside, no_mask
        for i in idx:
            fid = seq.frame_ids[i]
            path = lay.points(fid)
            try:
                with np.load(path) as z:
                    lab = np.asarray(z["label"])
            except (OSError, KeyError, ValueError) as exc:
                raise DatasetError(path, f"unreadable point labels ({exc})") from exc
            o, m = unlabeled_reasons(lab, keys_of(i), seen)
            points += lab.shape[0]
            labeled += int((lab != UNLABELED).sum())
            outside += o
            no_mask += m
            label_path = lay.export_label(fid)
            try:
                raw = np.fromfile(label_path, dtype="<u4")
            except OSError as exc:
                why = exc.strerror or exc
                raise DatasetError(label_path, f"cannot read exported labels ({why})") from exc
            yield raw

    counts = raw_id_counts(raws())
    return ExportCoverage(len(idx), points, labeled, outside, no_mask, counts)


__all__ = ["ExportCoverage", "coverage_counts", "export_coverage", "unlabeled_reasons"]
