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
    # The summary is the last line (after the progress bar's).
    last = res.output.strip().splitlines()[-1].split("\r")[-1]
    assert f"wrote {no_poses / 'poses.txt'} and {POSES_NOTE}: 10 poses," in last, last
    note = json.loads((no_poses / POSES_NOTE).read_text())
    assert note["method"] == "kiss-icp" and note["frames"] == 10
    est, true = KittiSequence(no_poses), KittiSequence(drive)
    assert est.pose_source == "estimated"
    np.testing.assert_allclose(est.cam_poses[0], np.eye(4), atol=1e-9)
    # Camera frame (z forward, x right): the drive's ≈ 7 m along z within 0.2 m, sideways within 0.2 m.
    # (KISS-ICP's constant-velocity start lags on the first step; the benchmark measures the drift.)
    assert true.cam_poses[-1, 2, 3] > 5.0
    assert np.abs(est.cam_poses[:, :3, 3] - true.cam_poses[:, :3, 3]).max() < 0.2

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
    assert json.loads((poses / POSES_NOTE).read_text())["method"] == "kiss-icp"

    # A second run in the same folder reuses the estimate (same scans, same settings), and its export
    # says the poses were estimated, how and by whom.
    zip_path = tmp_path / "est.zip"
    again = CliRunner().invoke(
        cli, ["run", str(no_poses), "--out", str(out), "--estimate-poses", "--zip", str(zip_path), *RUN]
    )
    assert again.exit_code == 0 and "poses: reused" in again.output, again.output
    by_run = "the run (into its own folder)"
    assert "poses: estimated (kiss-icp " in again.output and f"by {by_run}" in again.output
    with zipfile.ZipFile(zip_path) as zf:
        (told,) = yaml.safe_load(zf.read("summary.yaml"))["provenance"]["poses"]
    assert told["source"] == "estimated" and told["method"].startswith("kiss-icp ")
    assert told["file"] == str(poses / "poses.txt") and told["estimated_by"] == by_run

    ref = tmp_path / "true"
    res = CliRunner().invoke(cli, ["run", str(drive), "--out", str(ref), *RUN])
    assert res.exit_code == 0, res.output
    est_m, true_m = read_metrics_json(folder(out, no_poses.name)), read_metrics_json(folder(ref, drive.name))
    assert est_m is not None and true_m is not None
    est_miou, true_miou = est_m.miou("camera", "voxel"), true_m.miou("camera", "voxel")
    assert abs(est_miou - true_miou) < 0.02, (est_miou, true_miou)
