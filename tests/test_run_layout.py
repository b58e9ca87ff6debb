"""RunLayout and SequenceLayout: a run folder's paths, its sequences, the final-grid rule and the
corrections file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from leap_core.consistency.config import ConsistencyConfig
from leap_core.errors import DatasetError, LeapError
from leap_core.run_layout import (
    RunLayout,
    SequenceLayout,
    load_corrections,
    save_corrections,
    write_run_spec,
)


def test_sequence_paths(tmp_path: Path) -> None:
    lay = SequenceLayout(tmp_path)
    assert lay.labels2d("000007") == tmp_path / "labels2d" / "000007.npz"
    assert lay.observation("000007") == tmp_path / "observations" / "000007.npz"
    assert lay.points("000007") == tmp_path / "points" / "000007.npz"
    assert lay.export_label("000007") == tmp_path / "export" / "000007.label"
    assert lay.export_conf("000007") == tmp_path / "export" / "000007.conf"
    assert lay.frame_folder(SequenceLayout.POINTS) == lay.points_dir == tmp_path / "points"
    assert lay.grid_3dcn(2) == tmp_path / "grid_3dcn2.npz"
    assert lay.grid_smooth_3dcn(2) == tmp_path / "grid_smooth_3dcn2.npz"
    assert lay.joint_3dcn == tmp_path / "3dcn_joint.json"
    assert lay.poses == tmp_path / "poses" / "poses.txt"
    assert SequenceLayout(str(tmp_path)).folder == tmp_path  # type: ignore[arg-type]  # a str path works at run time
    assert {lay.corrections.name, lay.export_coverage.name} <= SequenceLayout.RUN_OWN_FILES


def test_run_paths(tmp_path: Path) -> None:
    lay = RunLayout(tmp_path)
    assert lay.spec == tmp_path / "run.json" and lay.metrics == tmp_path / "metrics.json"
    assert lay.sequence("00") == SequenceLayout(tmp_path / "sequences" / "00")
    assert lay.cn_dir == tmp_path / "3dcn" and lay.joint_state == tmp_path / "3dcn" / "joint.json"
    assert lay.joint_rounds("00") == SequenceLayout(tmp_path / "3dcn" / "rounds" / "00")
    assert (lay.export_zip(), lay.export_zip(with_confidence=True)) == (
        tmp_path / "export.zip",
        tmp_path / "export-conf.zip",
    )
    assert RunLayout(str(tmp_path)).root == tmp_path  # type: ignore[arg-type]  # a str path works at run time
    assert {lay.params.name, lay.log.name, lay.lock.name} <= RunLayout.RUN_OWN_FILES <= RunLayout.RUN_FILES
    # A sequence's name is a folder name under sequences/: nothing that leaves it.
    for bad in ("..", "../x", "a/b", "", ".hidden", "x" * 65):
        with pytest.raises(LeapError, match="sequence name: must be 1-64") as err:
            lay.sequence(bad)
        assert err.value.field == ("name",)
        with pytest.raises(LeapError, match="sequence name"):
            lay.joint_rounds(bad)


def test_a_runs_sequences_are_those_its_record_lists(tmp_path: Path) -> None:
    """``names()``: the sequences ``run.json`` lists, in its order, whose folder exists; without the record,
    every sequence folder by name."""
    lay = RunLayout(tmp_path)
    assert lay.names() == [] and not RunLayout.is_run(tmp_path)
    with pytest.raises(LeapError, match="not a run folder"):
        lay.first()
    for name in ("b", "a", "c", ".tmp-x"):
        (tmp_path / "sequences" / name).mkdir(parents=True)
    (tmp_path / "sequences" / "file").write_text("")
    assert lay.names() == ["a", "b", "c"]
    write_run_spec(
        lay, [("c", tmp_path / "data" / "c", range(2, 5)), ("b", None, None), ("gone", None, None)]
    )
    assert RunLayout.is_run(tmp_path)
    assert lay.names() == ["c", "b"] and lay.first() == lay.sequence("c")
    assert json.loads(lay.spec.read_text()) == {
        "sequences": [
            {"name": "c", "dataset": str((tmp_path / "data" / "c").resolve()), "frames": [2, 5]},
            {"name": "b", "dataset": None, "frames": None},
            {"name": "gone", "dataset": None, "frames": None},
        ]
    }
    lay.spec.write_text("{not json")
    with pytest.raises(DatasetError, match=r"run\.json: unreadable run record"):
        lay.names()


@pytest.mark.parametrize(
    ("enabled", "iterations", "name"),
    [
        (False, 1, "grid_smooth.npz"),
        (False, 2, "grid_smooth.npz"),
        (True, 1, "grid_smooth_3dcn1.npz"),
        (True, 2, "grid_smooth_3dcn2.npz"),
    ],
)
def test_final_grid_follows_the_config(tmp_path: Path, enabled: bool, iterations: int, name: str) -> None:
    cfg = ConsistencyConfig(enabled=enabled, iterations=iterations)
    assert SequenceLayout(tmp_path).final_grid(cfg) == tmp_path / name


def test_final_grid_on_disk_takes_the_last_smoothed_round(tmp_path: Path) -> None:
    lay = SequenceLayout(tmp_path)
    assert lay.final_grid_on_disk() == lay.grid_smooth
    for name in (
        "grid.npz",
        "grid_smooth.npz",
        "grid_smooth_3dcn2.npz",
        "grid_smooth_3dcn10.npz",
        "grid_3dcn11.npz",
        "grid_smooth_3dcnx.npz",
        "old_grid_smooth_3dcn12.npz",
    ):
        (tmp_path / name).write_bytes(b"")
    # 10 > 2 as numbers; a fused-only round (11) and names that are not round files do not count.
    assert lay.final_grid_on_disk() == tmp_path / "grid_smooth_3dcn10.npz"
    assert [p.name for p in lay.cn_grids()] == [
        "grid_3dcn11.npz",
        "grid_smooth_3dcn10.npz",
        "grid_smooth_3dcn2.npz",
    ]
    assert SequenceLayout(tmp_path / "missing").cn_grids() == []


def test_corrections_roundtrip_and_errors(tmp_path: Path) -> None:
    path = SequenceLayout(tmp_path).corrections
    save_corrections(path, np.array([5, 3, 5], np.int64), np.array([1, 0, 2], np.int16))
    keys, cls = load_corrections(path, 3)
    assert keys.tolist() == [5, 3, 5] and cls.tolist() == [1, 0, 2]  # order kept: the last one wins later
    assert keys.dtype == np.int64 and cls.dtype == np.int64
    with pytest.raises(DatasetError, match=r"class_idx' must be in -1\.\.1"):
        load_corrections(path, 2)
    save_corrections(path, np.array([4]), np.array([-1]))  # -1 erases to unlabeled
    assert load_corrections(path, 2)[1].tolist() == [-1]
    save_corrections(path, np.array([4]), np.array([-2]))
    with pytest.raises(DatasetError, match="must be in -1"):
        load_corrections(path, 2)
    save_corrections(path, np.array([1, 2]), np.array([0]))
    with pytest.raises(DatasetError, match="equal-length"):
        load_corrections(path, 3)
    save_corrections(path, np.array([1.5]), np.array([0]))
    with pytest.raises(DatasetError, match="integer"):
        load_corrections(path, 3)
    path.write_bytes(b"junk")
    with pytest.raises(DatasetError, match="unreadable corrections"):
        load_corrections(path, 3)
