"""Trajectory error metrics: the KITTI odometry benchmark's relative errors and the absolute trajectory
error (docs/METHOD.md, "Estimated poses").

Poses are (F, 4, 4) float64 rigid transforms sensor → world, one per frame, ground truth and estimate
in the same sensor frame (compare LiDAR with LiDAR poses, or camera with camera poses).

The relative errors follow the KITTI odometry devkit (``evaluate_odometry.cpp``): from every
``step``-th frame ``i`` and for every segment length ``L``, the first frame ``j`` whose ground-truth path
distance from ``i`` exceeds ``L`` closes a segment; with ``ΔG = G_i⁻¹ G_j`` and ``ΔE = E_i⁻¹ E_j`` the
error is ``D = ΔE⁻¹ ΔG``, its translation error ``‖t(D)‖ / L`` and its rotation error ``angle(D) / L``.
Averaging every segment of every length gives the benchmark's two figures, reported here as percent
(translation) and degrees per 100 m (rotation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

KITTI_SEGMENT_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
"""Segment lengths (m) of the KITTI odometry benchmark."""

F64 = npt.NDArray[np.float64]


def _check_poses(name: str, poses: F64) -> F64:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"{name}: poses must be (F, 4, 4), got {arr.shape}")
    return arr


def path_distances(poses: F64) -> F64:
    """(F,) distance travelled along the trajectory up to each frame: ``d_0 = 0``,
    ``d_k = d_{k-1} + ‖t_k − t_{k-1}‖``."""
    p = _check_poses("path_distances", poses)
    steps = np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def rotation_angle(rotation: F64) -> float:
    """Angle (rad) of a 3×3 rotation: ``acos(clip((trace − 1) / 2, −1, 1))``, as the devkit computes it."""
    return float(np.arccos(np.clip((np.trace(rotation[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))


def inverse(t: F64) -> F64:
    """Inverse of rigid transforms (..., 4, 4): ``[Rᵀ | −Rᵀ t]``."""
    out = np.zeros_like(t)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ t[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


@dataclass(frozen=True)
class SegmentErrors:
    """Relative pose errors of every segment (KITTI devkit definition).

    Attributes:
        first: (S,) first frame of each segment.
        length: (S,) the segment's nominal length L (m).
        translation: (S,) ``‖t(D)‖ / L`` (fraction: 0.01 = 1 %).
        rotation: (S,) ``angle(D) / L`` (rad per m).
    """

    first: npt.NDArray[np.int64]
    length: F64
    translation: F64
    rotation: F64

    @property
    def count(self) -> int:
        return int(self.first.shape[0])

    @property
    def translation_pct(self) -> float:
        """Mean translation error in percent (NaN without segments)."""
        return float(100.0 * self.translation.mean()) if self.count else float("nan")

    @property
    def rotation_deg_per_100m(self) -> float:
        """Mean rotation error in degrees per 100 m (NaN without segments)."""
        return float(np.degrees(self.rotation.mean()) * 100.0) if self.count else float("nan")


def segment_errors(
    gt: F64, est: F64, lengths: tuple[float, ...] = KITTI_SEGMENT_LENGTHS, step: int = 10
) -> SegmentErrors:
    """Relative translation and rotation errors over segments, as the KITTI odometry devkit computes them.

    Args:
        gt: (F, 4, 4) ground-truth poses.
        est: (F, 4, 4) estimated poses of the same frames.
        lengths: segment lengths L (m) measured along the ground-truth path.
        step: a segment starts at every ``step``-th frame (the devkit uses 10, i.e. one per second).

    Returns:
        One entry per (first frame, length) whose segment ends inside the trajectory; none when every
        length is longer than the path (then the means are NaN).
    """
    g, e = _check_poses("gt", gt), _check_poses("est", est)
    if g.shape != e.shape:
        raise ValueError(f"gt {g.shape} and est {e.shape} must hold the same frames")
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    dist = path_distances(g)
    firsts: list[int] = []
    lens: list[float] = []
    t_err: list[float] = []
    r_err: list[float] = []
    for i in range(0, len(g), step):
        for length in lengths:
            # The devkit's lastFrameFromSegmentLength: the first frame farther than d_i + L.
            beyond = np.nonzero(dist > dist[i] + length)[0]
            if beyond.size == 0:
                continue
            j = int(beyond[0])
            d = inverse(inverse(e[i]) @ e[j]) @ (inverse(g[i]) @ g[j])
            firsts.append(i)
            lens.append(float(length))
            t_err.append(float(np.linalg.norm(d[:3, 3])) / length)
            r_err.append(rotation_angle(d) / length)
    return SegmentErrors(
        np.asarray(firsts, dtype=np.int64),
        np.asarray(lens, dtype=np.float64),
        np.asarray(t_err, dtype=np.float64),
        np.asarray(r_err, dtype=np.float64),
    )


def fitting_segment_lengths(gt: F64, count: int = 8) -> tuple[float, ...]:
    """KITTI's lengths when the path is at least 800 m long; else ``count`` lengths ``k · s``
    (k = 1..count, ``s`` = a tenth of the path, rounded to the metre, at least 1 m), which keeps the
    devkit's ratio of longest segment to path on sequences too short for 100 m segments."""
    total = float(path_distances(gt)[-1])
    if total >= KITTI_SEGMENT_LENGTHS[-1]:
        return KITTI_SEGMENT_LENGTHS
    s = max(1.0, round(total / 10.0))
    return tuple(float(k * s) for k in range(1, count + 1))


def align_rigid(src: F64, dst: F64) -> F64:
    """The rigid transform T (4, 4) minimising ``Σ ‖T·src_k − dst_k‖²`` over (K, 3) point pairs
    (Kabsch / Umeyama without scale: LiDAR odometry is metric, so no scale is fitted).

    ``R = U · diag(1, 1, det(U Vᵀ)) · Vᵀ`` from the SVD ``U S Vᵀ`` of the cross-covariance
    ``Σ (dst_k − d̄)(src_k − s̄)ᵀ``, ``t = d̄ − R s̄``.
    """
    a = np.asarray(src, dtype=np.float64)
    b = np.asarray(dst, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"align_rigid needs two (K, 3) arrays, got {a.shape} and {b.shape}")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((b - cb).T @ (a - ca))
    fix = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt))) or 1.0])
    r = u @ fix @ vt
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = cb - r @ ca
    return out


def ate_rmse(gt: F64, est: F64) -> float:
    """Absolute trajectory error (m): RMSE of the position differences after aligning the estimated
    positions to the ground truth with :func:`align_rigid`."""
    g, e = _check_poses("gt", gt), _check_poses("est", est)
    if g.shape != e.shape:
        raise ValueError(f"gt {g.shape} and est {e.shape} must hold the same frames")
    t = align_rigid(e[:, :3, 3], g[:, :3, 3])
    moved = e[:, :3, 3] @ t[:3, :3].T + t[:3, 3]
    return float(np.sqrt(np.mean(np.sum((moved - g[:, :3, 3]) ** 2, axis=1))))


def step_lengths(poses: F64) -> F64:
    """(F−1,) distance between consecutive positions ``‖t_k − t_{k−1}‖``."""
    p = _check_poses("step_lengths", poses)
    return np.asarray(np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1), dtype=np.float64)


def first_step_ratio(gt: F64, est: F64, min_step: float = 0.1) -> float | None:
    """How the estimate's first step compares with its second, relative to the truth's:
    ``(‖Δe_1‖ / ‖Δe_2‖) / (‖Δg_1‖ / ‖Δg_2‖)`` with ``Δ_k`` the step from frame k−1 to k. 1 = the first
    step is as right as the second; 0.5 = half as long as it should be next to the second (an odometry
    that starts without a motion prior lags on its first step).

    None when there are fewer than three frames or a true step is shorter than ``min_step`` (m): a vehicle
    at rest has no step to compare.
    """
    g, e = _check_poses("gt", gt), _check_poses("est", est)
    if g.shape != e.shape:
        raise ValueError(f"gt {g.shape} and est {e.shape} must hold the same frames")
    if len(g) < 3:
        return None
    sg, se = step_lengths(g[:3]), step_lengths(e[:3])
    if min(sg) < min_step or se[1] <= 0.0:
        return None
    return float((se[0] / se[1]) / (sg[0] / sg[1]))


@dataclass(frozen=True)
class TruthComparison:
    """An estimated trajectory against the true one (what ``leap poses`` reports when it has both).

    Attributes:
        drift_pct: translational drift (%): the KITTI devkit's mean ``‖t(D)‖ / L`` over the segments of
            :func:`fitting_segment_lengths` (KITTI's 100-800 m on drives of 800 m or more).
        rotation_deg_per_100m: the same segments' rotation error.
        segment_lengths_m: the lengths used.
        first_step_ratio: :func:`first_step_ratio` (None where undefined).
        ate_m: :func:`ate_rmse`.
        path_m: the true path length.
    """

    drift_pct: float
    rotation_deg_per_100m: float
    segment_lengths_m: tuple[float, ...]
    first_step_ratio: float | None
    ate_m: float
    path_m: float

    def to_dict(self) -> dict[str, object]:
        """JSON-ready (NaN, from a drive too short for any segment, as None)."""

        def num(v: float) -> float | None:
            return None if np.isnan(v) else round(float(v), 6)

        ratio = self.first_step_ratio
        return {
            "drift_pct": num(self.drift_pct),
            "rotation_deg_per_100m": num(self.rotation_deg_per_100m),
            "segment_lengths_m": list(self.segment_lengths_m),
            "first_step_ratio": None if ratio is None else round(ratio, 6),
            "ate_m": num(self.ate_m),
            "path_m": num(self.path_m),
        }


def compare_with_truth(gt: F64, est: F64) -> TruthComparison:
    """:class:`TruthComparison` of ``est`` against ``gt`` (both (F, 4, 4), F ≥ 2, the same sensor frame)."""
    g, e = _check_poses("gt", gt), _check_poses("est", est)
    if g.shape != e.shape or len(g) < 2:
        raise ValueError(f"gt {g.shape} and est {e.shape} must hold the same frames, at least two")
    lengths = fitting_segment_lengths(g)
    seg = segment_errors(g, e, lengths)
    return TruthComparison(
        drift_pct=seg.translation_pct,
        rotation_deg_per_100m=seg.rotation_deg_per_100m,
        segment_lengths_m=lengths,
        first_step_ratio=first_step_ratio(g, e),
        ate_m=ate_rmse(g, e),
        path_m=float(path_distances(g)[-1]),
    )


__all__ = [
    "KITTI_SEGMENT_LENGTHS",
    "SegmentErrors",
    "TruthComparison",
    "align_rigid",
    "ate_rmse",
    "compare_with_truth",
    "first_step_ratio",
    "fitting_segment_lengths",
    "inverse",
    "path_distances",
    "rotation_angle",
    "segment_errors",
    "step_lengths",
]
