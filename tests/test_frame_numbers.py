"""A frame is known by its file number everywhere: a copied subset of a sequence (with the sequence's whole
poses.txt and times.txt) labels exactly as the same frames of the whole sequence; runs without poses do
what needs no poses and refuse the rest before any work."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from runhelpers import folder, label
from typer.testing import CliRunner

from app.cli import _frame_range, cli
from leap_core.config import PipelineConfig, config_from_dict
from leap_core.consistency.config import ConsistencyConfig
from leap_core.consistency.stage import reliable_targets
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import PosesMissingError
from leap_core.labelers.simulated import SimulatedLabeler
from leap_core.presets import builtin_preset
from leap_core.smoothing import SmoothedGrid
from leap_core.synth import CameraConfig, LidarConfig, SynthConfig, generate_sequence

SMALL = SynthConfig(
    frames=22,
    seed=0,
    lidar=LidarConfig(beams=16, azimuth_step_deg=1.0),
    camera=CameraConfig().scaled(0.5),
)
"""The default demo street (seed 0) with a coarse LiDAR and a half-size camera: 22 frames, so frames 10-19
have neighbours on both sides."""

SUBSET = range(10, 20)
PER_FRAME = ("velodyne", "image_2", "labels", "gt2d/semantic", "gt2d/instance", "gt2d/name")


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_sequence(tmp_path_factory.mktemp("demo"), SMALL).path


def copy_frames(src: Path, dst: Path, frames: range) -> Path:
    """Copy the files of ``frames`` (scans, images, labels, 2D ground truth) and the whole calib.txt,
    poses.txt and times.txt, as a user copying a part of a sequence does."""
    for name in ("calib.txt", "poses.txt", "times.txt"):
        dst.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src / name, dst / name)
    for sub in PER_FRAME:
        (dst / sub).mkdir(parents=True)
        for path in (src / sub).iterdir():
            if path.stem.isdigit() and int(path.stem) in frames:
                shutil.copy2(path, dst / sub / path.name)
    return dst


@pytest.fixture(scope="module")
def subset(whole: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return copy_frames(whole, tmp_path_factory.mktemp("copy") / "sequences" / "00", SUBSET)


def _exports(out: Path) -> dict[str, bytes]:
    """The export files of the run folder ``out``'s sequence 00."""
    return {p.name: p.read_bytes() for p in sorted((folder(out) / "export").iterdir())}


def test_copy_of_frames_10_19_labels_like_those_frames_of_the_whole_sequence(
    whole: Path, subset: Path, tmp_path: Path
) -> None:
    """The issue's acceptance: `leap run` on the copy = `leap run --frames 10:20` on the whole sequence,
    byte for byte (default labeler and 3D-CN setting)."""
    runner = CliRunner()
    a = runner.invoke(cli, ["run", str(whole), "--out", str(tmp_path / "whole"), "--frames", "10:20"])
    assert a.exit_code == 0, a.output
    b = runner.invoke(cli, ["run", str(subset), "--out", str(tmp_path / "copy")])
    assert b.exit_code == 0, b.output
    exported = _exports(tmp_path / "copy")
    assert sorted(exported) == sorted(f"{i:06d}{s}" for i in SUBSET for s in (".label", ".conf"))
    assert exported == _exports(tmp_path / "whole")
    # The fused grids agree too: same world frame (pose line 0), same voxels.
    assert (folder(tmp_path / "copy") / "grid.npz").read_bytes() == (
        folder(tmp_path / "whole") / "grid.npz"
    ).read_bytes()

    # The 3D-CN's per-scan selection of frame 13 does not depend on where 13 sits in the run's frames.
    seq = KittiSequence(whole)
    smoothed = SmoothedGrid.load(folder(tmp_path / "whole") / "grid_smooth.npz").to_voxel_grid(30.0)
    cfg = ConsistencyConfig(selection_scope="scan", share=0.2)
    c = builtin_preset("semantickitti").schema.num_classes
    late = reliable_targets(seq, smoothed, c, cfg, 0.2, seq.select(range(12, 20)), None)
    early = reliable_targets(seq, smoothed, c, cfg, 0.2, seq.select(range(10, 20)), None)
    np.testing.assert_array_equal(late[1], early[3])


def test_subset_frames_keep_their_poses_seeds_and_2d_labels(whole: Path, subset: Path) -> None:
    """What makes the acceptance hold, frame by frame: the pose (world = pose line 0, not the first scan
    present) and the simulated labeler's draws (seeded by the frame number, not the position)."""
    full, part = KittiSequence(whole), KittiSequence(subset)
    assert part.frame_numbers == tuple(SUBSET)
    np.testing.assert_array_equal(part.poses, full.poses[10:20])
    np.testing.assert_array_equal(part.times, full.times[10:20])
    schema = builtin_preset("semantickitti").schema
    labeler = SimulatedLabeler()
    a, b = labeler.label(part.frame(3), schema), labeler.label(full.frame(13), schema)
    assert part.frame(3).frame_id == "000013"
    np.testing.assert_array_equal(a.bits, b.bits)
    np.testing.assert_array_equal(a.probs, b.probs)


def test_frames_option_takes_frame_numbers_on_a_copy(subset: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(cli, ["run", str(subset), "--out", str(tmp_path / "r"), "--frames", "3:5"])
    assert res.exit_code == 2
    assert "frames 3:5 out of range: the sequence has frames 10..19" in res.output.strip().splitlines()[-1]
    label(
        subset,
        builtin_preset("semantickitti").schema,
        PipelineConfig(),
        tmp_path / "r",
        frames=range(12, 14),
        until="labels2d",
    )
    assert sorted(p.name for p in (folder(tmp_path / "r") / "labels2d").iterdir()) == [
        "000012.npz",
        "000013.npz",
    ]
    assert _frame_range("12:", str(subset)) == range(12, 20)  # "A:" runs to the last scan's number
    assert _frame_range("12", str(subset)) == range(12, 13)


# ---------------------------------------------------------------------------------------- no poses
@pytest.fixture
def no_poses(subset: Path, tmp_path: Path) -> Path:
    root = copy_frames(subset, tmp_path / "np" / "sequences" / "00", SUBSET)
    (root / "poses.txt").unlink()
    return root


def test_stages_without_poses_run_without_them(no_poses: Path, tmp_path: Path) -> None:
    schema = builtin_preset("semantickitti").schema
    result = label(no_poses, schema, PipelineConfig(), tmp_path / "run", until="project")
    assert result.ran == ["labels2d", "project"]
    assert len(list((folder(tmp_path / "run") / "observations").glob("*.npz"))) == len(SUBSET)


def test_a_run_without_poses_stops_before_any_work(no_poses: Path, tmp_path: Path) -> None:
    schema = builtin_preset("semantickitti").schema
    with pytest.raises(
        PosesMissingError,
        match=r"poses\.txt: no poses: the 3D stages \(fuse, label_points, "
        r"tracks, evaluate\) need one pose per scan",
    ) as exc:
        label(no_poses, schema, PipelineConfig(), tmp_path / "run")
    assert exc.value.path == str(no_poses / "poses.txt")
    assert not (tmp_path / "run").exists()  # refused before the run folder, the labeler or any stage
    res = CliRunner().invoke(cli, ["run", str(no_poses), "--out", str(tmp_path / "cli")])
    assert res.exit_code == 2
    last = res.output.strip().splitlines()[-1]
    assert last.startswith("error:") and "poses.txt: no poses" in last
    assert not (tmp_path / "cli").exists()


@pytest.mark.slow
def test_copy_labels_like_the_whole_sequence_with_the_3dcn_on(
    whole: Path, subset: Path, tmp_path: Path
) -> None:
    """The same with a (small, fast) 3D-CN round: its selection, training and fusion see the same frames."""
    cfg = config_from_dict(
        {
            "consistency": {
                "enabled": True,
                "min_steps": 20,
                "points_per_scan": 2048,
                "backbone": {"channels": 16, "layers": 2},
            }
        }
    )
    schema = builtin_preset("semantickitti").schema
    a = label(whole, schema, cfg, tmp_path / "whole", frames=SUBSET)
    b = label(subset, schema, cfg, tmp_path / "copy")
    assert a.stages["3dcn"].status == b.stages["3dcn"].status == "done"
    assert _exports(tmp_path / "copy") == _exports(tmp_path / "whole")
