"""``leap poses`` and ``leap run --estimate-poses`` on a generated drive whose poses.txt was removed."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from runhelpers import folder
from typer.testing import CliRunner

from app.cli import cli
from leap_core.datasets.kitti import POSES_NOTE, KittiSequence, read_poses
from leap_core.pipeline.evaluation import read_metrics_json
from leap_core.synth import CameraConfig, LidarConfig, SceneConfig, SynthConfig, generate_sequence

DRIVE = SynthConfig(
    frames=10,
    seed=3,
    lidar=LidarConfig(beams=48, azimuth_step_deg=0.4),
    camera=CameraConfig().scaled(0.25),
    scene=SceneConfig(margin=90.0),
)
"""Ten frames (about 7 m) of a generated street: a LiDAR coarse enough to run fast, fine enough for
KISS-ICP; a small camera for the simulated labeler."""

RUN = ["--labeler", "simulated", "--no-3dcn"]


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The generated sequence, with its true poses (read-only for the tests)."""
    return generate_sequence(tmp_path_factory.mktemp("drive"), DRIVE, workers=1).path


@pytest.fixture
def no_poses(drive: Path, tmp_path: Path) -> Path:
    """A copy of the drive without poses.txt."""
    copy = tmp_path / "sequences" / "00"
    shutil.copytree(drive, copy)
    (copy / "poses.txt").unlink()
    return copy


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_leap_poses_writes_kitti_poses_and_never_replaces_without_force(drive: Path, no_poses: Path) -> None:
    res = CliRunner().invoke(cli, ["poses", str(no_poses)])
    assert res.exit_code == 0, res.output
    # The summary and the residual are the last two lines (after the progress bar's); no true poses here.
    summary, residual = (line.split("\r")[-1] for line in res.output.strip().splitlines()[-2:])
    assert f"wrote {no_poses / 'poses.txt'} and {POSES_NOTE}: 10 poses," in summary, summary
    assert "KISS-ICP + pose graph in" in summary
    assert residual.startswith("registration residual: median ") and "(KISS-ICP alone: " in residual
    note = json.loads((no_poses / POSES_NOTE).read_text())
    assert note["method"] == "kiss-icp+pose-graph" and note["frames"] == 10
    assert "truth" not in note["quality"] and 0 < note["quality"]["residual_median_m"] < 0.05
    est, true = KittiSequence(no_poses), KittiSequence(drive)
    assert est.pose_source == "estimated"
    np.testing.assert_allclose(est.cam_poses[0], np.eye(4), atol=1e-9)
    # Camera frame (z forward, x right): the drive's ≈ 7 m along z within 5 cm, sideways within 5 cm.
    assert true.cam_poses[-1, 2, 3] > 5.0
    assert np.abs(est.cam_poses[:, :3, 3] - true.cam_poses[:, :3, 3]).max() < 0.05

    before = (no_poses / "poses.txt").read_bytes()
    again = CliRunner().invoke(cli, ["poses", str(no_poses)])
    assert again.exit_code == 2
    assert f"{no_poses / 'poses.txt'}: already exists; add --force" in again.output
    assert (no_poses / "poses.txt").read_bytes() == before
    forced = CliRunner().invoke(cli, ["poses", str(no_poses), "--force"])
    assert forced.exit_code == 0, forced.output

    elsewhere = no_poses.parent / "estimates" / "poses.txt"
    res = CliRunner().invoke(cli, ["poses", str(no_poses), "--out", str(elsewhere)])
    assert res.exit_code == 0, res.output
    assert (elsewhere.parent / POSES_NOTE).is_file()
    np.testing.assert_allclose(read_poses(elsewhere), est.cam_poses, atol=1e-9)


def test_leap_poses_measures_the_estimate_against_true_poses(drive: Path, tmp_path: Path) -> None:
    """With --out elsewhere, a sequence's own measured poses.txt is the truth: drift, first step and ATE
    are printed and stored in the note; --truth names another file; a missing one is refused up front."""
    out = tmp_path / "est" / "poses.txt"
    res = CliRunner().invoke(cli, ["poses", str(drive), "--out", str(out)])
    assert res.exit_code == 0, res.output
    against = res.output.strip().splitlines()[-1]
    assert against.startswith(f"against {drive / 'poses.txt'}: translational drift "), against
    assert "(KITTI's definition, segments 1-8 m)" in against and "first step / second step " in against
    truth = json.loads((out.parent / POSES_NOTE).read_text())["quality"]["truth"]
    assert truth["poses"] == str(drive / "poses.txt") and truth["drift_pct"] <= 1.0
    assert abs(truth["first_step_ratio"] - 1.0) <= 0.1 and truth["ate_m"] < 0.02
    assert truth["segment_lengths_m"] == [1.0 * k for k in range(1, 9)]

    copy = tmp_path / "copy" / "00"
    shutil.copytree(drive, copy)
    (copy / "poses.txt").rename(copy / "measured.txt")
    res = CliRunner().invoke(cli, ["poses", str(copy), "--truth", str(copy / "measured.txt"), "--no-refine"])
    assert res.exit_code == 0, res.output
    note = json.loads((copy / POSES_NOTE).read_text())
    assert note["method"] == "kiss-icp" and note["quality"]["truth"]["poses"] == str(copy / "measured.txt")
    assert "KISS-ICP in" in res.output

    # A dataset poses.txt that cannot be read is no truth, and no reason to refuse an estimate elsewhere.
    (copy / "poses.txt").write_text("not a pose\n")
    res = CliRunner().invoke(cli, ["poses", str(copy), "--out", str(tmp_path / "other" / "poses.txt")])
    assert res.exit_code == 0, res.output
    assert res.output.strip().splitlines()[-1].startswith("registration residual: median ")

    missing = tmp_path / "nowhere" / "poses.txt"
    res = CliRunner().invoke(
        cli, ["poses", str(drive), "--out", str(tmp_path / "x.txt"), "--truth", str(missing)]
    )
    assert res.exit_code == 2
    assert f"{missing}: --truth names no poses file" in res.output
    assert not (tmp_path / "x.txt").exists()


def test_leap_run_without_poses_names_both_ways_out(no_poses: Path, tmp_path: Path) -> None:
    res = CliRunner().invoke(cli, ["run", str(no_poses), "--out", str(tmp_path / "run"), *RUN])
    assert res.exit_code == 2
    last = res.output.strip().splitlines()[-1]
    assert last.startswith(f"error: {no_poses / 'poses.txt'}: no poses")  # names the sequence
    assert f"run `leap poses {no_poses}` or pass --estimate-poses" in last
    assert not (tmp_path / "run").exists()


def test_leap_run_estimate_poses_labels_like_true_poses_and_leaves_the_dataset_alone(
    drive: Path, no_poses: Path, tmp_path: Path
) -> None:
    dataset_before = _files(no_poses)
    out = tmp_path / "est"
    res = CliRunner().invoke(cli, ["run", str(no_poses), "--out", str(out), "--estimate-poses", *RUN])
    assert res.exit_code == 0, res.output
    poses = folder(out, no_poses.name) / "poses"  # the sequence's own, in its folder of the run
    assert "poses: estimated in" in res.output and str(poses / "poses.txt") in res.output
    assert _files(no_poses) == dataset_before  # nothing written into the dataset
    assert json.loads((poses / POSES_NOTE).read_text())["method"] == "kiss-icp+pose-graph"

    # A second run in the same folder reuses the estimate (same scans, same settings), and its export
    # says the poses were estimated, how and by whom.
    zip_path = tmp_path / "est.zip"
    again = CliRunner().invoke(
        cli, ["run", str(no_poses), "--out", str(out), "--estimate-poses", "--zip", str(zip_path), *RUN]
    )
    assert again.exit_code == 0 and "poses: reused" in again.output, again.output
    by_run = "the run (into its own folder)"
    assert "poses: estimated (kiss-icp+pose-graph " in again.output and f"by {by_run}" in again.output
    with zipfile.ZipFile(zip_path) as zf:
        (told,) = yaml.safe_load(zf.read("summary.yaml"))["provenance"]["poses"]
    assert told["source"] == "estimated" and told["method"].startswith("kiss-icp+pose-graph ")
    assert told["file"] == str(poses / "poses.txt") and told["estimated_by"] == by_run

    ref = tmp_path / "true"
    res = CliRunner().invoke(cli, ["run", str(drive), "--out", str(ref), *RUN])
    assert res.exit_code == 0, res.output
    est_m, true_m = read_metrics_json(folder(out, no_poses.name)), read_metrics_json(folder(ref, drive.name))
    assert est_m is not None and true_m is not None
    est_miou, true_miou = est_m.miou("camera", "voxel"), true_m.miou("camera", "voxel")
    assert abs(est_miou - true_miou) < 0.02, (est_miou, true_miou)
