"""Estimated poses: KISS-ICP and the pose-graph refinement on generated drives, LiDAR ↔ KITTI camera-frame
conversion, the poses file and its note, and the trajectory metrics (hand-computed cases)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from leap_core.datasets.kitti import POSES_NOTE, KittiSequence, lidar_poses, read_poses, write_poses
from leap_core.errors import ConfigError, DatasetError
from leap_core.odometry import (
    METHOD,
    REFINED_METHOD,
    EstimatedPoses,
    OdometryConfig,
    camera_poses,
    estimate_sequence_poses,
    pose_file_rows,
    pose_lines,
    read_note,
    write_estimated_poses,
)
from leap_core.synth import CameraConfig, EgoConfig, LidarConfig, SceneConfig, SynthConfig, generate_sequence
from leap_core.trajectory import (
    align_rigid,
    ate_rmse,
    compare_with_truth,
    fitting_segment_lengths,
    path_distances,
    rotation_angle,
    segment_errors,
)


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _pose(rot: np.ndarray, t: tuple[float, float, float]) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3] = rot
    p[:3, 3] = t
    return p


# KITTI's axes: camera x = −LiDAR y, camera y = −LiDAR z, camera z = LiDAR x; LiDAR 27 cm behind the camera.
TR = _pose(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), (0.0, -0.08, -0.27))


# ------------------------------------------------------------------------------ LiDAR ↔ camera poses
def test_camera_poses_hand_case_and_round_trip_through_kitti_reader() -> None:
    # LiDAR odometry starting away from the origin (as if re-based elsewhere): 2 m forward, then a 90° left
    # turn on the spot.
    l0 = _pose(np.eye(3), (5.0, 1.0, 0.0))
    l1 = l0 @ _pose(np.eye(3), (2.0, 0.0, 0.0))
    l2 = l1 @ _pose(_rz(90.0), (0.0, 0.0, 0.0))
    cam = camera_poses(np.stack([l0, l1, l2]), TR)
    # By hand: first = identity; driving 2 m along LiDAR x is 2 m along camera z; a left turn (LiDAR yaw
    # +90° about z up) is a camera rotation about camera y (down) by −90°.
    np.testing.assert_allclose(cam[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(cam[1], _pose(np.eye(3), (0.0, 0.0, 2.0)), atol=1e-12)
    ry = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # rotation −90° about camera y
    # The camera sits 27 cm ahead of the LiDAR: the turn about the LiDAR swings it 27 cm left (camera −x)
    # and back from 2.27 m to 2 − 0.27 m along camera z.
    np.testing.assert_allclose(cam[2][:3, :3], ry, atol=1e-12)
    np.testing.assert_allclose(cam[2][:3, 3], [-0.27, 0.0, 1.73], atol=1e-12)
    # The reader's conversion gives the odometry back, re-based on the first scan.
    back = lidar_poses(cam, TR)
    np.testing.assert_allclose(back, np.linalg.inv(l0)[None] @ np.stack([l0, l1, l2]), atol=1e-12)


def test_pose_file_rows_follow_frame_numbers() -> None:
    cam = np.stack([_pose(np.eye(3), (0, 0, 1.0)), _pose(np.eye(3), (0, 0, 2.0))])
    assert pose_lines(["000002", "000004"]) == [2, 4]
    assert pose_lines(["a", "b"]) == [0, 1]
    rows = pose_file_rows(["000002", "000004"], cam)
    # Rows without a scan repeat the nearest earlier scan's pose (the first scan's before it).
    assert [r[2, 3] for r in rows] == [1.0, 1.0, 1.0, 1.0, 2.0]
    np.testing.assert_array_equal(pose_file_rows(["x", "y"], cam), cam)


def test_write_estimated_poses_refuses_to_replace_and_notes_what_it_wrote(
    tmp_path: Path, make_tiny_sequence
) -> None:
    tiny = make_tiny_sequence(tmp_path, n_frames=3)
    cam = camera_poses(np.stack([_pose(_rz(5.0 * i), (1.0 * i, 0, 0)) for i in range(3)]), tiny.calib.Tr)
    est = EstimatedPoses(tiny.frame_ids, np.eye(4)[None].repeat(3, 0), cam, 0.5, OdometryConfig())
    measured = tiny.root / "poses.txt"
    before = measured.read_bytes()
    with pytest.raises(DatasetError, match=r"poses\.txt: already exists"):
        write_estimated_poses(measured, est)
    assert measured.read_bytes() == before and not (tiny.root / POSES_NOTE).exists()
    assert KittiSequence(tiny.root).pose_source == "file"

    write_estimated_poses(measured, est, force=True)
    np.testing.assert_allclose(read_poses(measured), cam, atol=1e-9)
    note = json.loads((tiny.root / POSES_NOTE).read_text())
    assert note["method"] == REFINED_METHOD and note["version"] == "1.3.0" and note["frames"] == 3
    assert note["settings"]["voxel_size"] == 0.8 and note["settings"]["deskew"] is False
    assert note["settings"]["refine"]["neighbours"] == 3
    # No residual measured (NaN) is written as null: the note stays strict JSON.
    assert note["quality"] == {"residual_median_m": None, "odometry_residual_median_m": None}
    assert read_note(measured) == note
    seq = KittiSequence(tiny.root)
    assert seq.pose_source == "estimated"
    np.testing.assert_allclose(seq.cam_poses, cam, atol=1e-9)


def test_odometry_config_names_the_bad_field() -> None:
    with pytest.raises(ConfigError, match=r"^max_range: must be a positive number"):
        OdometryConfig(max_range=0.0)
    with pytest.raises(ConfigError, match=r"^min_range: must be in \[0, max_range\)"):
        OdometryConfig(min_range=90.0)
    with pytest.raises(ConfigError, match=r"^voxel_size:"):
        OdometryConfig(voxel_size=float("nan"))
    assert OdometryConfig(max_range=50.0).voxel == 0.5


# ----------------------------------------------------------------------- KISS-ICP and the refinement
def _street(frames: int, **changes: object) -> SynthConfig:
    """A generated street with a coarser LiDAR (32 beams, 0.6° steps) and a tiny, unused camera."""
    base = SynthConfig(
        frames=frames,
        seed=3,
        lidar=LidarConfig(beams=32, azimuth_step_deg=0.6),
        camera=CameraConfig().scaled(0.1),
        scene=SceneConfig(margin=90.0),
        shadows=False,
    )
    return replace(base, **changes)  # type: ignore[arg-type]


SMALL_DRIVE = _street(12)
"""Twelve frames (about 9 m) at the demo's 8 m/s."""

FAST_START = _street(16, ego=EgoConfig(cruise_speed=14.0))
"""Sixteen frames of a car already at 14 m/s (1.4 m per scan) when the recording starts."""

FROM_REST = _street(
    20, ego=EgoConfig(start_speed=0.0), lidar=LidarConfig(beams=32, azimuth_step_deg=0.6, range_noise=0.05)
)
"""Twenty frames of a car pulling away from rest at 1.6 m/s² (2.9 m), with 5 cm range noise."""


def test_refined_estimate_of_a_generated_drive(tmp_path: Path) -> None:
    stats = generate_sequence(tmp_path, SMALL_DRIVE, workers=1)
    seq = KittiSequence(stats.path)
    seen: list[tuple[int, int]] = []
    est = estimate_sequence_poses(seq, progress=lambda d, t: seen.append((d, t)))
    assert seen[0] == (0, 24) and seen[-1] == (24, 24)  # two passes over the 12 scans
    np.testing.assert_allclose(est.lidar[0], np.eye(4), atol=1e-9)
    # Whole-drive error after ≈ 9 m: centimetres, and well under a degree.
    err = np.linalg.inv(est.lidar[-1]) @ seq.poses[-1]
    assert path_distances(seq.poses)[-1] > 5.0
    assert np.linalg.norm(err[:3, 3]) < 0.05
    assert np.degrees(rotation_angle(err)) < 0.5
    np.testing.assert_allclose(lidar_poses(est.cam, seq.calib.Tr), est.lidar, atol=1e-9)
    # Drift (KITTI's definition on segments of a tenth of the drive) within 1 % (KISS-ICP alone: 1.6 %).
    truth = compare_with_truth(seq.poses, est.lidar)
    assert truth.drift_pct <= 1.0, truth
    # The refined poses fit neighbouring scans closer than KISS-ICP's own.
    assert est.odometry is not None and est.residual < est.odometry_residual < 0.05
    note = est.compared_with(seq.poses, "true poses").note()
    assert note["method"] == REFINED_METHOD
    assert note["quality"]["truth"]["drift_pct"] == pytest.approx(truth.drift_pct, abs=1e-6)
    assert note["quality"]["residual_median_m"] == pytest.approx(est.residual, abs=1e-6)


def test_a_recording_that_starts_at_speed_gets_its_first_step_right(tmp_path: Path) -> None:
    """The first scan pair has no motion prior: the estimate's first step must still be within 10 % of its
    second, relative to the truth's (KISS-ICP alone: 20 % long)."""
    seq = KittiSequence(generate_sequence(tmp_path, FAST_START, workers=1).path)
    truth = compare_with_truth(seq.poses, estimate_sequence_poses(seq).lidar)
    assert truth.first_step_ratio is not None
    assert abs(truth.first_step_ratio - 1.0) <= 0.1, truth
    assert truth.drift_pct <= 1.0, truth


def test_a_noisy_recording_from_rest_keeps_up_with_the_car(tmp_path: Path) -> None:
    """A car speeding up outruns a constant-velocity prediction: KISS-ICP alone ends 1.7 m behind after
    2.9 m; registrations that start from the last registered step keep up."""
    seq = KittiSequence(generate_sequence(tmp_path, FROM_REST, workers=1).path)
    est = estimate_sequence_poses(seq)
    end = np.linalg.norm(est.lidar[-1, :3, 3] - seq.poses[-1, :3, 3])
    assert end < 0.1, end
    assert compare_with_truth(seq.poses, est.lidar).ate_m < 0.03


def test_kiss_icp_alone_is_still_available(tmp_path: Path) -> None:
    seq = KittiSequence(generate_sequence(tmp_path, _street(5), workers=1).path)
    est = estimate_sequence_poses(seq, OdometryConfig(refine=None))
    assert est.note()["method"] == METHOD and est.note()["settings"]["refine"] is None
    np.testing.assert_array_equal(est.lidar, est.odometry)
    assert est.residual == est.odometry_residual and 0.0 < est.residual < 0.05


# ------------------------------------------------------------------------------------------- metrics
def _line(n: int, step: float) -> np.ndarray:
    return np.stack([_pose(np.eye(3), (step * k, 0.0, 0.0)) for k in range(n)])


def test_segment_errors_hand_computed_translation() -> None:
    gt = _line(11, 1.0)  # 0..10 m
    est = _line(11, 1.01)  # 1 % too long
    se = segment_errors(gt, est, lengths=(5.0,), step=5)
    # From frame 0 the first frame beyond 5 m is frame 6 (6 m): the estimate says 6.06 m, error 0.06 m
    # over L = 5 m. From frame 5 nothing lies beyond 10 m (strictly), so no second segment.
    assert se.count == 1 and se.first.tolist() == [0]
    assert se.translation_pct == pytest.approx(100 * 0.06 / 5.0)
    assert se.rotation_deg_per_100m == pytest.approx(0.0, abs=1e-9)


def test_segment_errors_hand_computed_rotation() -> None:
    gt = _line(11, 1.0)
    est = gt.copy()
    for k in range(11):
        est[k, :3, :3] = _rz(0.1 * k)  # heading drifts 0.1° per frame, positions exact
    se = segment_errors(gt, est, lengths=(5.0,), step=5)
    # Segment 0 → 6: D = ΔE⁻¹ ΔG = [R₆ᵀ | R₆ᵀ t − R₆ᵀ t] = [R₆ᵀ | 0]:
    # 0.6° over 5 m = 12°/100 m, and no translation error.
    assert se.rotation_deg_per_100m == pytest.approx(12.0)
    assert se.translation_pct == pytest.approx(0.0, abs=1e-9)


def test_segment_errors_without_fitting_segments_is_nan() -> None:
    se = segment_errors(_line(5, 1.0), _line(5, 1.0))  # 4 m path, KITTI's 100 m segments
    assert se.count == 0 and np.isnan(se.translation_pct)


def test_fitting_segment_lengths() -> None:
    assert fitting_segment_lengths(_line(11, 4.0)) == tuple(4.0 * k for k in range(1, 9))  # 40 m path
    assert fitting_segment_lengths(_line(3, 500.0))[0] == 100.0  # 1000 m: KITTI's own


def test_ate_rmse_hand_computed() -> None:
    gt = _line(4, 1.0)
    moved = _pose(_rz(30.0), (3.0, -2.0, 1.0))[None] @ gt  # a rigid move of the whole trajectory: no error
    assert ate_rmse(gt, moved) == pytest.approx(0.0, abs=1e-9)
    # Two frames 2 m apart estimated 4 m apart: the best fit centres the 4 m on the 2 m, 1 m off at each end.
    assert ate_rmse(_line(2, 2.0), _line(2, 4.0)) == pytest.approx(1.0)
    t = align_rigid(moved[:, :3, 3], gt[:, :3, 3])
    np.testing.assert_allclose(t @ moved[2], gt[2], atol=1e-9)


def test_metrics_refuse_mismatched_frames() -> None:
    with pytest.raises(ValueError, match="same frames"):
        segment_errors(_line(3, 1.0), _line(4, 1.0))
    with pytest.raises(ValueError, match=r"\(F, 4, 4\)"):
        ate_rmse(np.eye(4), np.eye(4))


def test_estimated_poses_open_from_another_folder(tmp_path: Path, make_tiny_sequence) -> None:
    """Poses kept outside the dataset (a run's work folder) are read with ``poses_path``."""
    tiny = make_tiny_sequence(tmp_path, n_frames=3)
    (tiny.root / "poses.txt").unlink()
    assert not KittiSequence(tiny.root).has_poses
    elsewhere = tmp_path / "work" / "poses.txt"
    elsewhere.parent.mkdir()
    write_poses(elsewhere, tiny.cam_poses)
    seq = KittiSequence(tiny.root, poses_path=elsewhere)
    assert seq.pose_source == "file"
    np.testing.assert_allclose(seq.cam_poses, tiny.cam_poses)
