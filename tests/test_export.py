"""Export of .label and .conf files."""

from __future__ import annotations

import os

import numpy as np
import pytest

from leap_core.datasets.kitti import read_label
from leap_core.errors import DatasetError
from leap_core.export import export_labels, labels_to_raw, read_confidence

EXPORT_IDS = np.array([10, 40, 48], np.uint32)  # car, road, sidewalk


def test_export_writes_raw_ids_and_confidence(tmp_path) -> None:
    labels = np.array([0, -1, 2, 1, 0], np.int16)
    conf = np.array([0.9, 0.5, 0.7, 0.6, 0.25], np.float32)
    lp, cp = tmp_path / "out" / "000042.label", tmp_path / "out" / "000042.conf"
    export_labels(lp, cp, labels, conf, EXPORT_IDS)
    assert lp.read_bytes() == np.array([10, 0, 48, 40, 10], "<u4").tobytes()  # instance 0 in the high bits
    np.testing.assert_array_equal(read_label(lp, 5), [10, 0, 48, 40, 10])
    np.testing.assert_array_equal(read_confidence(cp, 5), np.array([0.9, 0.0, 0.7, 0.6, 0.25], np.float32))
    assert sorted(os.listdir(tmp_path / "out")) == ["000042.conf", "000042.label"]


def test_labels_to_raw_validates() -> None:
    np.testing.assert_array_equal(labels_to_raw(np.array([-1, 1]), EXPORT_IDS), [0, 40])
    with pytest.raises(ValueError, match="labels must be in"):
        labels_to_raw(np.array([3]), EXPORT_IDS)
    with pytest.raises(ValueError, match="export ids"):
        labels_to_raw(np.array([0]), np.array([70000]))


def test_export_is_atomic(tmp_path, monkeypatch) -> None:
    labels = np.array([0, 1], np.int16)
    conf = np.ones(2, np.float32)
    lp, cp = tmp_path / "000000.label", tmp_path / "000000.conf"
    export_labels(lp, cp, labels, conf, EXPORT_IDS)
    before = (lp.read_bytes(), cp.read_bytes())
    # Bad input fails before anything is written.
    with pytest.raises(ValueError):
        export_labels(lp, cp, np.array([0, 5], np.int16), conf, EXPORT_IDS)
    # A crash at the final rename (fault injected into os.replace) leaves the old files and no temp file.
    from leap_core import io_utils

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(io_utils.os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        export_labels(lp, cp, np.array([2, 2], np.int16), conf, EXPORT_IDS)
    monkeypatch.undo()
    assert (lp.read_bytes(), cp.read_bytes()) == before
    assert sorted(os.listdir(tmp_path)) == ["000000.conf", "000000.label"]


def test_read_confidence_rejects_bad_files(tmp_path) -> None:
    p = tmp_path / "x.conf"
    p.write_bytes(b"abc")
    with pytest.raises(DatasetError, match=r"x\.conf: size 3"):
        read_confidence(p)
    p.write_bytes(np.zeros(3, "<f4").tobytes())
    with pytest.raises(DatasetError, match="count 3 != point count 4"):
        read_confidence(p, 4)
    with pytest.raises(DatasetError, match="cannot read"):
        read_confidence(tmp_path / "missing.conf")
