"""leap_core.corrections: per-point application of manual corrections, hand-computed cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from leap_core.corrections import (
    ERASE,
    FrameVoxelIndex,
    ScanCorrections,
    changed_keys,
    class_in_keys,
    correct_points,
)
from leap_core.errors import DatasetError


def test_class_in_keys() -> None:
    hit, cls = class_in_keys(np.array([5, 7, 9]), np.array([5, 9]), np.array([2, -1]))
    assert hit.tolist() == [True, False, True] and cls.tolist() == [2, -1, -1]
    hit, cls = class_in_keys(np.array([5]), np.zeros(0, np.int64), np.zeros(0, np.int16))
    assert hit.tolist() == [False] and cls.tolist() == [-1]


def test_correct_points_map_then_scan_and_erase() -> None:
    label = np.array([0, 1, 1, 3], np.int16)
    conf = np.array([0.5, 0.6, 0.7, 0.8], np.float32)
    keys = np.array([5, 7, 9, 7])
    lab, cf = correct_points(
        label,
        conf,
        keys,
        np.array([7, 9]),
        np.array([2, ERASE]),
        scan_points=np.array([2, 3]),
        scan_class=np.array([0, ERASE]),
    )
    # point 0 untouched; 1: map → 2 (conf 1); 2: map erase, then scan → 0 (conf 1); 3: map → 2, scan erase.
    assert lab.tolist() == [0, 2, 0, -1]
    assert cf.tolist() == [0.5, 1.0, 1.0, 0.0]
    assert label.tolist() == [0, 1, 1, 3]  # inputs not modified
    lab, cf = correct_points(np.array([1]), np.array([0.5]), np.array([9]), np.array([9]), np.array([ERASE]))
    assert lab.tolist() == [-1] and cf.tolist() == [0.0]  # a map-scope erase alone unlabels the point
    with pytest.raises(ValueError, match="out of range"):
        correct_points(
            label,
            conf,
            keys,
            np.zeros(0, np.int64),
            np.zeros(0, np.int16),
            scan_points=np.array([4]),
            scan_class=np.array([0]),
        )


def test_changed_keys() -> None:
    out = changed_keys(np.array([1, 2, 3]), np.array([0, 0, 1]), np.array([2, 3, 4]), np.array([0, 2, 1]))
    assert out.tolist() == [1, 3, 4]
    assert changed_keys(np.array([1]), np.array([0]), np.array([1]), np.array([0])).tolist() == []


def test_scan_corrections_merge_later_wins_and_roundtrip(tmp_path: Path) -> None:
    sc = ScanCorrections.merge([("a", [3, 1], 2), ("b", [0], ERASE), ("a", [1], 0), ("c", [], 1)])
    assert sc.frame_ids == ("a", "b")
    pts, cls = sc.of("a")
    assert pts.tolist() == [1, 3] and cls.tolist() == [0, 2]
    assert sc.of("b")[1].tolist() == [-1] and sc.of("zz")[0].size == 0
    other = ScanCorrections.merge([("a", [3, 1], 2), ("a", [1], 0), ("d", [9], 1)])
    assert sc.changed_frames(other) == ["b", "d"]
    path = tmp_path / "scan.npz"
    sc.save(path)
    back = ScanCorrections.load(path, 3)
    assert back.frame_ids == sc.frame_ids and back.changed_frames(sc) == []
    with pytest.raises(DatasetError, match=r"-1\.\.1"):
        ScanCorrections.load(path, 2)
    path.write_bytes(b"junk")
    with pytest.raises(DatasetError, match="unreadable scan corrections"):
        ScanCorrections.load(path, 3)


def test_frame_voxel_index(tmp_path: Path) -> None:
    idx = FrameVoxelIndex.build([np.array([5, 5, 3]), np.array([7]), np.array([5, 8])])
    assert idx.keys.tolist() == [3, 5, 5, 7, 8] and idx.num_frames == 3
    assert idx.frames_of([5, 9]).tolist() == [0, 2]
    assert idx.frames_of([7, 3]).tolist() == [0, 1]
    assert idx.frames_of([1, 9]).tolist() == []
    idx.save(tmp_path / "fv.npz")
    back = FrameVoxelIndex.load(tmp_path / "fv.npz")
    assert back.frames_of([8]).tolist() == [2] and back.num_frames == 3


def test_point_labels_of_a_subset_equal_the_whole_scans() -> None:
    from leap_core.pipeline.apply import RunCorrections, point_labels
    from leap_core.smoothing import SmoothedGrid

    # Voxels 10 (class 0, p 0.75), 20 (class 1, p 1.0); points 0..5 in voxels 10, 20, 10, 30, 20, 10.
    grid = SmoothedGrid(np.array([10, 20], np.int64), np.array([[0.75, 0.25], [0.0, 1.0]], np.float16), 0.2)
    keys = np.array([10, 20, 10, 30, 20, 10], np.int64)
    scan = ScanCorrections.merge([("f", [2, 4], 1), ("f", [5], ERASE)])
    corr = RunCorrections(np.array([20], np.int64), np.array([0], np.int16), scan)
    lab, conf = point_labels(grid, keys, "f", corr)
    assert lab.tolist() == [0, 0, 1, -1, 1, -1] and conf.tolist() == [0.75, 1, 1, 0, 1, 0]
    subset = np.array([1, 2, 5], np.int64)
    sub_lab, sub_conf = point_labels(grid, keys, "f", corr, subset=subset)
    assert sub_lab.tolist() == lab[subset].tolist() and sub_conf.tolist() == conf[subset].tolist()
    empty = point_labels(grid, keys, "f", corr, subset=np.zeros(0, np.int64))
    assert empty[0].size == 0 and empty[1].size == 0
