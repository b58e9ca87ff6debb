"""Poses for a sequence recorded without them: LiDAR odometry with KISS-ICP (PRBonn's ``kiss-icp``
package), refined by a pose graph over neighbouring-scan registrations (:mod:`leap_core.pose_graph`;
docs/METHOD.md, "Estimated poses").

KISS-ICP registers each scan against a local voxel map and returns LiDAR poses relative to the first
scan; the refinement registers each scan to its next few scans directly and solves the poses that agree
best with all those registrations. A second pass over the scans measures the result: the median
point-to-plane residual between neighbouring scans at the final poses.

KITTI's ``poses.txt`` holds LEFT CAMERA poses, so they are converted with the calibration's ``Tr``
(LiDAR → camera): ``P_cam = Tr · P_lidar · Tr⁻¹``, identity for the first scan as in KITTI, so
:func:`leap_core.datasets.kitti.lidar_poses` (``Tr⁻¹ · P_cam · Tr``) gives the odometry back.

The estimate is written as ``poses.txt`` plus a ``poses_estimated.json`` note beside it
(:data:`leap_core.datasets.kitti.POSES_NOTE`) saying by what and with which settings it was made.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, replace
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from kiss_icp import config as kiss_config  # type: ignore[import-untyped]  # kiss-icp ships no type hints
from kiss_icp.config import config as kiss_sections  # type: ignore[import-untyped]  # (the same)
from kiss_icp.kiss_icp import KissICP  # type: ignore[import-untyped]  # (the same)

from leap_core.datasets.kitti import POSES_NOTE, KittiSequence, write_poses
from leap_core.errors import ConfigError, DatasetError, LeapError
from leap_core.io_utils import atomic_write_bytes
from leap_core.pose_graph import GraphBuilder, RefineConfig, neighbour_residuals, optimise_poses
from leap_core.progress import ProgressFn, report
from leap_core.trajectory import TruthComparison, compare_with_truth

METHOD = "kiss-icp"
"""The ``method`` of the note file for KISS-ICP alone."""
REFINED_METHOD = "kiss-icp+pose-graph"
"""The ``method`` of the note file for KISS-ICP refined by the pose graph (the default)."""

F64 = npt.NDArray[np.float64]
ScanSource = Callable[[], Iterable[npt.NDArray[np.floating[Any]]]]
"""Yields a sequence's scans in recording order, each (N, ≥3) x, y, z, …; called once per pass."""


@dataclass(frozen=True)
class OdometryConfig:
    """KISS-ICP settings for a spinning LiDAR like the demo's 64-beam sensor (KISS-ICP's own defaults
    except the range, which follows the sensor: the demo's returns end at 80 m), and the refinement's."""

    max_range: float = 80.0
    """Points farther than this from the sensor are dropped before registration (m)."""
    min_range: float = 0.0
    """Points nearer than this are dropped (m); raise it to cut returns from the vehicle itself."""
    voxel_size: float | None = None
    """Edge of KISS-ICP's local-map voxels (m); None = ``max_range / 100`` (KISS-ICP's rule, 0.8 m
    here). The scan is subsampled at half and 1.5× this size."""
    max_points_per_voxel: int = 20
    """Points kept per map voxel."""
    initial_threshold: float = 2.0
    """Correspondence distance (m) before the adaptive threshold has seen motion."""
    min_motion_threshold: float = 0.1
    """Frame-to-frame motion (m) below which the adaptive threshold is not updated."""
    max_iterations: int = 500
    """ICP iterations per scan at most."""
    convergence: float = 1e-4
    """ICP stops when the update's norm falls below this."""
    threads: int = 0
    """Threads of the registration (0 = as many as cores)."""
    refine: RefineConfig | None = field(default_factory=RefineConfig)
    """The pose-graph refinement's settings (:mod:`leap_core.pose_graph`); None = KISS-ICP alone."""

    def __post_init__(self) -> None:
        def positive(name: str, value: float) -> None:
            if not (value > 0 and math.isfinite(value)):
                raise ConfigError(f"must be a positive number, got {value}", field=(name,))

        positive("max_range", self.max_range)
        if not (0 <= self.min_range < self.max_range):
            raise ConfigError(f"must be in [0, max_range), got {self.min_range}", field=("min_range",))
        if self.voxel_size is not None:
            positive("voxel_size", self.voxel_size)
        if self.max_points_per_voxel < 1:
            raise ConfigError(
                f"must be >= 1, got {self.max_points_per_voxel}", field=("max_points_per_voxel",)
            )
        positive("initial_threshold", self.initial_threshold)
        if not (self.min_motion_threshold >= 0 and math.isfinite(self.min_motion_threshold)):
            raise ConfigError(
                f"must be >= 0, got {self.min_motion_threshold}", field=("min_motion_threshold",)
            )
        if self.max_iterations < 1:
            raise ConfigError(f"must be >= 1, got {self.max_iterations}", field=("max_iterations",))
        positive("convergence", self.convergence)
        if self.threads < 0:
            raise ConfigError(f"must be >= 0, got {self.threads}", field=("threads",))

    @property
    def voxel(self) -> float:
        """The voxel size in use (``voxel_size`` or ``max_range / 100``)."""
        return self.voxel_size if self.voxel_size is not None else self.max_range / 100.0

    @property
    def method(self) -> str:
        """The note's ``method``: :data:`REFINED_METHOD`, or :data:`METHOD` without refinement."""
        return METHOD if self.refine is None else REFINED_METHOD

    def settings(self) -> dict[str, Any]:
        """The settings as the note file records them (the resolved voxel size included)."""
        return {**asdict(self), "voxel_size": self.voxel, "deskew": False}

    def measure(self) -> RefineConfig:
        """The settings the residual is measured with (the refinement's, or its defaults without one)."""
        return self.refine if self.refine is not None else RefineConfig()


def _kiss(config: OdometryConfig) -> Any:
    """A KISS-ICP odometry object with ``config``'s settings.

    Every section of KISS-ICP's config is passed explicitly: ``KISSConfig`` is a pydantic settings class
    that would otherwise read ``KISS_ICP_*`` environment variables, and leap_core reads no environment.
    Deskewing stays off: a KITTI ``.bin`` scan has no per-point times to deskew with.
    """
    kcfg = kiss_config.KISSConfig(
        out_dir="results",
        data=kiss_sections.DataConfig(max_range=config.max_range, min_range=config.min_range, deskew=False),
        mapping=kiss_sections.MappingConfig(
            voxel_size=config.voxel, max_points_per_voxel=config.max_points_per_voxel
        ),
        registration=kiss_sections.RegistrationConfig(
            max_num_iterations=config.max_iterations,
            convergence_criterion=config.convergence,
            max_num_threads=config.threads,
        ),
        adaptive_threshold=kiss_sections.AdaptiveThresholdConfig(
            initial_threshold=config.initial_threshold, min_motion_th=config.min_motion_threshold
        ),
    )
    return KissICP(kcfg)


def range_cut(points: npt.NDArray[np.floating[Any]], config: OdometryConfig) -> F64:
    """(M, 3) float64 x, y, z of the points (N, ≥3) whose range lies in ``(min_range, max_range)``, the
    points KISS-ICP keeps."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    r = np.linalg.norm(xyz, axis=1)
    return np.ascontiguousarray(xyz[(r > config.min_range) & (r < config.max_range)])


@dataclass(frozen=True)
class LidarOdometry:
    """The result of :func:`estimate_lidar_poses`.

    Attributes:
        poses: (F, 4, 4) LiDAR → world poses, world = the first scan's LiDAR frame (pose 0 = identity).
        odometry: (F, 4, 4) KISS-ICP's poses alone (= ``poses`` without refinement).
        residuals: (F−1,) median |point-to-plane distance| (m) of scan k+1 against scan k at ``poses``
            (:func:`leap_core.pose_graph.pair_residual`).
        odometry_residual: the median of the same residuals at ``odometry``'s poses (m).
    """

    poses: F64
    odometry: F64
    residuals: F64
    odometry_residual: float

    @property
    def residual(self) -> float:
        """Median of :attr:`residuals` (m; NaN for a single scan)."""
        return float(np.median(self.residuals)) if len(self.residuals) else math.nan


def estimate_lidar_poses(
    scans: ScanSource,
    total: int,
    config: OdometryConfig | None = None,
    progress: ProgressFn | None = None,
) -> LidarOdometry:
    """LiDAR odometry of consecutive scans, refined unless ``config.refine`` is None, and measured.

    Two passes over ``scans()``: KISS-ICP and the neighbour registrations, then (after the pose graph) the
    residuals at the final poses.

    Args:
        scans: yields ``total`` scans in recording order, each (N, ≥3): x, y, z in the LiDAR frame
            (further columns such as remission are ignored); called once per pass.
        total: the number of scans.
        config: settings (default :class:`OdometryConfig`).
        progress: ``progress(done, 2 · total)`` after each scan of each pass; may raise ``Cancelled``.
    """
    cfg = config or OdometryConfig()
    odo = _kiss(cfg)
    graph = GraphBuilder.start(cfg.refine) if cfg.refine is not None else None
    kiss: list[F64] = []
    no_times = np.zeros(0, dtype=np.float64)
    report(progress, 0, 2 * total)
    for k, scan in enumerate(scans()):
        xyz = np.ascontiguousarray(np.asarray(scan)[:, :3], dtype=np.float64)
        odo.register_frame(xyz, no_times)
        kiss.append(np.array(odo.last_pose, dtype=np.float64))
        if graph is not None:
            graph.add(k, range_cut(xyz, cfg), kiss[-1])
        report(progress, k + 1, 2 * total)
    if len(kiss) != total:
        raise LeapError(f"expected {total} scans, got {len(kiss)}")
    if total == 0:
        empty = np.zeros((0, 4, 4))
        return LidarOdometry(empty, empty, np.zeros(0), math.nan)
    odometry = np.stack(kiss)
    poses = optimise_poses(odometry, graph.edges) if graph is not None else odometry

    def cut_scans() -> Iterable[F64]:
        for k, scan in enumerate(scans()):
            yield range_cut(scan, cfg)
            report(progress, total + k + 1, 2 * total)

    residuals = neighbour_residuals(cut_scans, poses, cfg.measure())
    if graph is not None:
        odometry_residual = (
            float(np.median(graph.odometry_residuals)) if graph.odometry_residuals else math.nan
        )
    else:
        odometry_residual = float(np.median(residuals)) if len(residuals) else math.nan
    return LidarOdometry(poses, odometry, residuals, odometry_residual)


def camera_poses(lidar: npt.NDArray[np.float64], tr: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """KITTI camera-frame poses (F, 4, 4) from LiDAR poses (F, 4, 4) and ``Tr`` (4, 4, LiDAR → camera):
    ``P_cam_k = Tr · L_0⁻¹ · L_k · Tr⁻¹`` (re-based so the first is the identity, as in KITTI).

    The inverse of :func:`leap_core.datasets.kitti.lidar_poses`.
    """
    lp = np.asarray(lidar, dtype=np.float64)
    if lp.ndim != 3 or lp.shape[1:] != (4, 4) or len(lp) == 0:
        raise ValueError(f"lidar poses must be (F, 4, 4) with F >= 1, got {lp.shape}")
    rel = np.linalg.inv(lp[0])[None] @ lp
    return np.asarray(tr[None] @ rel @ np.linalg.inv(tr)[None], dtype=np.float64)


def pose_lines(frame_ids: list[str]) -> list[int]:
    """The ``poses.txt`` line of each frame: its file number when every frame id is a number (scan
    ``000012.bin`` takes line 12, so a subset of a sequence keeps the original numbering), else its
    position."""
    if all(f.isdigit() for f in frame_ids):
        return [int(f) for f in frame_ids]
    return list(range(len(frame_ids)))


def pose_file_rows(frame_ids: list[str], cam: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The rows of ``poses.txt`` for poses ``cam`` (F, 4, 4) of ``frame_ids``: row :func:`pose_lines`
    ``[k]`` holds ``cam[k]``; rows of numbers without a scan (before the first scan, or gaps) repeat the
    pose of the nearest earlier scan (the first scan's before it), so every row is a valid pose but none
    is invented motion. The note's ``frames`` lists which rows were estimated."""
    lines = pose_lines(frame_ids)
    if len(lines) != len(cam):
        raise ValueError(f"{len(lines)} frame ids but {len(cam)} poses")
    rows = np.empty((max(lines) + 1, 4, 4), dtype=np.float64)
    order = np.argsort(lines, kind="stable")
    sorted_lines = np.asarray(lines)[order]
    # For each row, the last scan whose line is <= the row (or the first scan).
    owner = np.searchsorted(sorted_lines, np.arange(len(rows)), side="right") - 1
    rows[:] = cam[order[np.maximum(owner, 0)]]
    return rows


def _finite(v: float, digits: int = 6) -> float | None:
    """A JSON number (NaN as None)."""
    return None if not math.isfinite(v) else round(float(v), digits)


@dataclass(frozen=True)
class EstimatedPoses:
    """The result of :func:`estimate_sequence_poses`.

    Attributes:
        frame_ids: the scans' file stems, in order.
        lidar: (F, 4, 4) LiDAR poses relative to the first scan.
        cam: (F, 4, 4) KITTI camera-frame poses (first = identity).
        seconds: wall time of the estimate (both passes).
        config: the settings used.
        scans: :func:`scans_signature` of the sequence the estimate was made from.
        residual: median point-to-plane residual (m) between neighbouring scans at ``lidar``.
        odometry_residual: the same at KISS-ICP's poses alone.
        odometry: (F, 4, 4) KISS-ICP's poses alone (None when not kept).
        truth: the estimate against true poses (:meth:`compared_with`), if any.
        truth_source: where the true poses came from.
    """

    frame_ids: list[str]
    lidar: F64
    cam: F64
    seconds: float
    config: OdometryConfig
    scans: str = ""
    residual: float = math.nan
    odometry_residual: float = math.nan
    odometry: F64 | None = None
    truth: TruthComparison | None = None
    truth_source: str = ""

    def compared_with(self, true_lidar: F64, source: str) -> EstimatedPoses:
        """This estimate with its :class:`~leap_core.trajectory.TruthComparison` against ``true_lidar``
        ((F, 4, 4) LiDAR poses of the same frames, any world frame) read from ``source``."""
        return replace(self, truth=compare_with_truth(true_lidar, self.lidar), truth_source=source)

    def quality(self) -> dict[str, Any]:
        """The note's ``quality``: residuals (m) and, with true poses, the comparison."""
        out: dict[str, Any] = {
            "residual_median_m": _finite(self.residual),
            "odometry_residual_median_m": _finite(self.odometry_residual),
        }
        if self.truth is not None:
            out["truth"] = {"poses": self.truth_source, **self.truth.to_dict()}
        return out

    def note(self) -> dict[str, Any]:
        """The ``poses_estimated.json`` content."""
        return {
            "method": self.config.method,
            "version": version("kiss-icp"),
            "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
            "frames": len(self.frame_ids),
            "frame_ids": self.frame_ids,
            "seconds": round(self.seconds, 3),
            "settings": self.config.settings(),
            "scans": self.scans,
            "quality": self.quality(),
        }


def estimate_sequence_poses(
    seq: KittiSequence, config: OdometryConfig | None = None, progress: ProgressFn | None = None
) -> EstimatedPoses:
    """:func:`estimate_lidar_poses` over every scan of ``seq`` (in frame order), as LiDAR and camera
    poses."""
    cfg = config or OdometryConfig()
    t0 = time.perf_counter()
    est = estimate_lidar_poses(lambda: (f.points for f in seq), len(seq), cfg, progress)
    seconds = time.perf_counter() - t0
    return EstimatedPoses(
        list(seq.frame_ids),
        est.poses,
        camera_poses(est.poses, seq.calib.Tr),
        seconds,
        cfg,
        scans_signature(seq),
        residual=est.residual,
        odometry_residual=est.odometry_residual,
        odometry=est.odometry,
    )


def write_estimated_poses(poses_path: str | Path, est: EstimatedPoses, *, force: bool = False) -> Path:
    """Write ``est`` as ``poses_path`` (a ``poses.txt``) and the note beside it, each atomically.

    The note goes first: a crash in between leaves a note without new poses (the sequence then reads as
    it did, or as "missing"), never estimated poses that look measured.

    Raises:
        DatasetError: ``poses_path`` exists and ``force`` is False (measured poses are never replaced
            by accident).
    """
    path = Path(poses_path)
    if path.exists() and not force:
        raise DatasetError(path, "already exists; pass force (CLI: --force) to replace it")
    note = path.parent / POSES_NOTE
    atomic_write_bytes(
        note, (json.dumps(est.note(), indent=2, sort_keys=True, allow_nan=False) + "\n").encode()
    )
    write_poses(path, pose_file_rows(est.frame_ids, est.cam))
    return note


def read_note(poses_path: str | Path) -> dict[str, Any] | None:
    """The note beside ``poses_path`` (None when there is none).

    Raises:
        DatasetError: the note exists but is not a JSON object.
    """
    note = Path(poses_path).parent / POSES_NOTE
    if not note.is_file():
        return None
    try:
        data = json.loads(note.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DatasetError(note, f"unreadable note ({exc})") from exc
    if not isinstance(data, dict):
        raise DatasetError(note, "must be a JSON object")
    return data


def reusable_estimate(seq: KittiSequence, poses_path: str | Path, config: OdometryConfig) -> bool:
    """Whether ``poses_path`` already holds an estimate of exactly these scans (and calibration) made with
    these settings, so estimating again would give the same poses."""
    path = Path(poses_path)
    try:
        note = read_note(path)
    except DatasetError:
        return False
    return (
        path.is_file()
        and note is not None
        and note.get("method") == config.method
        and note.get("scans") == scans_signature(seq)
        and note.get("settings") == config.settings()
    )


def estimate_into(
    seq: KittiSequence,
    poses_path: str | Path,
    config: OdometryConfig | None = None,
    progress: ProgressFn | None = None,
) -> tuple[dict[str, Any], bool]:
    """Estimated poses of ``seq`` at ``poses_path`` (a work folder's own file, replaced when stale):
    reused when :func:`reusable_estimate`, else estimated and written.

    Returns:
        The note of the poses now at ``poses_path``, and whether they were reused.
    """
    cfg = config or OdometryConfig()
    if reusable_estimate(seq, poses_path, cfg):
        report(progress, 2 * len(seq), 2 * len(seq))  # both passes, as an estimate reports them
        note = read_note(poses_path)
        assert note is not None  # reusable_estimate read it
        return note, True
    est = estimate_sequence_poses(seq, cfg, progress)
    write_estimated_poses(poses_path, est, force=True)
    return est.note(), False


def scans_signature(seq: KittiSequence) -> str:
    """What an estimate depends on: the calibration and every scan's name, size and modification time
    (a changed scan or calibration makes a cached estimate stale)."""
    h = hashlib.sha256((seq.root / "calib.txt").read_bytes())
    for i in range(len(seq)):
        st = os.stat(seq.scan_path(i))
        h.update(f"{seq.frame_ids[i]}|{st.st_size}|{st.st_mtime_ns};".encode())
    return h.hexdigest()[:24]


__all__ = [
    "METHOD",
    "REFINED_METHOD",
    "EstimatedPoses",
    "LidarOdometry",
    "OdometryConfig",
    "ScanSource",
    "camera_poses",
    "estimate_into",
    "estimate_lidar_poses",
    "estimate_sequence_poses",
    "pose_file_rows",
    "pose_lines",
    "range_cut",
    "read_note",
    "reusable_estimate",
    "scans_signature",
    "write_estimated_poses",
]
