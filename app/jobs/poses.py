"""Estimated poses for a run of a project with "Estimate poses (KISS-ICP)" on (KISS-ICP odometry refined
by a pose graph, :mod:`leap_core.odometry`).

The estimate is made once per dataset into the work folder's cache (``<work_dir>/cache/poses/<key>/``,
``key`` from the dataset's resolved path), reused by every later run while the scans, calibration and
settings are unchanged (:func:`leap_core.odometry.estimate_into`), and linked into ``poses/`` of the
sequence's folder in the run (:attr:`leap_core.run_layout.SequenceLayout.poses`), where the pipeline, the
exports, the corrections job and the viewer read it. The dataset folder is never written.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

from leap_core.datasets.kitti import POSES_NOTE, KittiSequence
from leap_core.io_utils import link_or_copy, remove_tree
from leap_core.paths import real_path_or_none
from leap_core.progress import ProgressFn
from leap_core.run_layout import SequenceLayout

#: Reports the user sees; the worker sends them to the run log and the UI's run warnings.
notice_log = logging.getLogger("leap_core.poses")


def cache_folder(cache_root: Path, dataset: Path) -> Path:
    """The cache folder of one dataset's estimate."""
    real = real_path_or_none(dataset) or Path(dataset).absolute()  # a loop fails the run's own reading
    key = hashlib.sha256(str(real).encode()).hexdigest()[:16]
    return cache_root / "poses" / key


def needs_estimate(dataset: Path) -> bool:
    """Whether a run of a project that estimates poses will estimate them (the dataset has no poses.txt)."""
    return not (Path(dataset) / "poses.txt").is_file()


def prepare_run_poses(
    dataset: Path,
    folder: Path,
    *,
    estimate: bool,
    cache_root: Path | None,
    progress: ProgressFn | None = None,
) -> None:
    """Put the poses a run uses in place before its pipeline starts.

    ``folder`` is the sequence's folder in the run. Without ``estimate`` (or when the dataset has its own
    ``poses.txt``) its ``poses/`` is removed, so poses estimated for an earlier run (carried over with its
    stage outputs) are not used.
    """
    layout = SequenceLayout(folder)
    if not estimate or not needs_estimate(dataset) or cache_root is None:
        remove_tree(layout.poses.parent)
        return
    # KISS-ICP loads in a run that estimates.
    from leap_core.odometry import REFINED_METHOD, estimate_into  # noqa: PLC0415

    seq = KittiSequence(dataset)
    cached = cache_folder(cache_root, dataset) / "poses.txt"
    note, reused = estimate_into(seq, cached, progress=None if progress is None else _per_scan(progress))
    layout.poses.parent.mkdir(parents=True, exist_ok=True)
    link_or_copy(cached.parent / POSES_NOTE, layout.poses.parent / POSES_NOTE)
    link_or_copy(cached, layout.poses)
    how = "reused the estimate cached" if reused else f"estimated them in {note['seconds']:.1f} s, cached"
    refined = " refined by a pose graph" if note.get("method") == REFINED_METHOD else ""
    residual = (note.get("quality") or {}).get("residual_median_m")
    fit = "" if residual is None else f", median residual {100 * residual:.2f} cm between neighbouring scans"
    notice_log.warning(
        "poses: the dataset has no poses.txt; KISS-ICP %s LiDAR odometry%s %s in %s (%d scans%s)",
        note["version"],
        refined,
        how,
        cached.parent,
        note["frames"],
        fit,
    )


def _per_scan(progress: ProgressFn) -> ProgressFn:
    """The estimate reports two passes over the scans (``done`` of ``2 · scans``); the stage counts scans."""

    def scaled(done: int, total: int) -> None:
        progress((done + 1) // 2, total // 2)

    return scaled
