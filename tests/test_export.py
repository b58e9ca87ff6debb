"""Export of .label and .conf files, the label-map YAML, and where an export may be written."""

from __future__ import annotations

import os

import numpy as np
import pytest
import yaml

from leap_core.datasets.kitti import read_label
from leap_core.errors import DatasetError
from leap_core.export import (
    ExportConflict,
    export_labels,
    export_target_problem,
    label_map,
    label_map_yaml,
    labels_to_raw,
    load_label_map,
    raw_id_counts,
    read_confidence,
    write_export_folder,
)
from leap_core.pipeline.coverage import unlabeled_reasons
from leap_core.presets import builtin_preset
from leap_core.schema import ClassDef, Schema

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


def test_label_map_yaml_round_trip() -> None:
    schema = builtin_preset("semantickitti").schema
    counts = {0: 5, int(schema.classes[0].export_id): 15}
    text = label_map_yaml(label_map(schema, counts, name="demo run 3"))
    back = load_label_map(text, "label-map.yaml")
    assert back.names == {0: "unlabeled", **{c.export_id: c.name for c in schema.classes}}
    assert back.colors_rgb == {0: (0, 0, 0), **{c.export_id: tuple(c.color) for c in schema.classes}}
    assert back.class_names() == schema.names
    assert back.counts == {raw: counts.get(raw, 0) for raw in back.names}
    for k, c in enumerate(schema.classes, start=1):
        assert back.learning_map_inv[k] == c.export_id and back.learning_map[c.export_id] == k
        assert all(back.learning_map[g] == k for g in c.gt_ids)  # the evaluation mapping the run used
    # On disk: semantic-kitti-api's keys, integer ids, colours as [B, G, R], content as shares of the points.
    raw = yaml.safe_load(text)
    car = next(c for c in schema.classes if c.name == "car")
    assert raw["color_map"][car.export_id] == [car.color[2], car.color[1], car.color[0]]
    assert raw["content"][0] == pytest.approx(0.25) and raw["learning_ignore"][0] is True
    assert list(raw)[:3] == ["name", "labels", "color_map"] and raw["name"] == "demo run 3"
    assert "split" not in raw
    assert label_map(schema, sequence="08")["split"] == {"train": [], "valid": [8], "test": []}


def test_label_map_export_id_wins_over_another_class_gt_id() -> None:
    for a_gt, b_gt in (((7, 8), ()), ((), (7, 8))):  # the clash in either class order
        schema = Schema("s", classes=(ClassDef("a", (1, 2, 3), ("a",), export_id=7, gt_ids=a_gt),
                                      ClassDef("b", (4, 5, 6), ("b",), export_id=8, gt_ids=b_gt)))
        assert label_map(schema)["learning_map"] == {0: 0, 7: 1, 8: 2}


def test_load_label_map_names_the_bad_key() -> None:
    with pytest.raises(DatasetError, match=r"cfg\.yaml: 'labels' must be a mapping"):
        load_label_map("color_map: {}\n", "cfg.yaml")
    with pytest.raises(DatasetError, match=r"color_map\[10\] must be \[B, G, R\]"):
        load_label_map("labels: {10: car}\ncolor_map: {10: [1, 2]}\nlearning_map: {}\nlearning_map_inv: {}\n")


def test_raw_id_counts_ignore_instance_bits() -> None:
    a = np.array([10 | (3 << 16), 10, 0], np.uint32)
    assert raw_id_counts([a, np.array([40], np.uint32)]) == {0: 1, 10: 2, 40: 1}


def test_unlabeled_reasons() -> None:
    label = np.array([0, -1, -1, -1, 2], np.int16)
    keys = np.array([5, 6, 7, 6, 9], np.int64)
    # Voxels 5 and 6 were inside a camera image in some frame; 7 never was.
    assert unlabeled_reasons(label, keys, np.array([5, 6])) == (1, 2)
    with pytest.raises(ValueError):
        unlabeled_reasons(label, keys[:2], np.array([5]))


def make_sequence(root) -> None:
    for sub in ("velodyne", "labels", "image_2"):
        (root / sub).mkdir(parents=True)


def test_export_target_problem(tmp_path) -> None:
    seq = tmp_path / "sequences" / "00"
    make_sequence(seq)
    assert export_target_problem(seq / "predictions") is None
    assert export_target_problem(tmp_path / "elsewhere") is None
    assert "sequence folder" in (export_target_problem(seq) or "")
    for sub in ("labels", "velodyne", "image_2", "labels/deeper"):
        assert "input data or ground truth" in (export_target_problem(seq / sub) or ""), sub
    run = tmp_path / "runs" / "r1"
    run.mkdir(parents=True)
    (run / "stages.json").write_text("{}")
    assert "run folder" in (export_target_problem(run / "export") or "")
    # A folder merely named labels, outside any sequence, is fine.
    assert export_target_problem(tmp_path / "my" / "labels") is None


def test_write_export_folder_needs_overwrite_and_swaps_whole_folders(tmp_path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for name, data in (("000000.label", b"new0"), ("000001.label", b"new1")):
        (src / name).write_bytes(data)
    files = sorted(src.iterdir())
    target = tmp_path / "seq" / "predictions"
    assert write_export_folder(target, files) == 0
    written = {p.name: p.read_bytes() for p in target.iterdir()}
    assert written == {"000000.label": b"new0", "000001.label": b"new1"}

    (target / "000000.label").write_bytes(b"mine")
    (target / "000009.label").write_bytes(b"old9")
    with pytest.raises(ExportConflict, match="already holds 3 files") as err:
        write_export_folder(target, files)
    assert err.value.existing == 3 and (target / "000000.label").read_bytes() == b"mine"
    # overwrite replaces the folder: no stale frame of the previous export survives beside the new ones.
    assert write_export_folder(target, files, overwrite=True) == 3
    assert sorted(p.name for p in target.iterdir()) == ["000000.label", "000001.label"]
    assert sorted(p.name for p in target.parent.iterdir()) == ["predictions"]

    (target / "readme.txt").write_text("keep me")
    with pytest.raises(ExportConflict, match=r"readme\.txt"):
        write_export_folder(target, files, overwrite=True)
    assert (target / "readme.txt").read_text() == "keep me"
    # An empty existing folder takes the export without the flag.
    empty = tmp_path / "empty"
    empty.mkdir()
    assert write_export_folder(empty, files) == 0 and len(list(empty.iterdir())) == 2


def test_write_export_folder_failure_leaves_the_old_folder(tmp_path, monkeypatch) -> None:
    src = tmp_path / "a.label"
    src.write_bytes(b"new")
    target = tmp_path / "predictions"
    target.mkdir()
    (target / "a.label").write_bytes(b"old")
    from leap_core import export as export_mod

    def boom(src_path, dst_path):
        raise OSError("disk full")

    monkeypatch.setattr(export_mod.shutil, "copyfile", boom)
    with pytest.raises(OSError, match="disk full"):
        write_export_folder(target, [src], overwrite=True)
    monkeypatch.undo()
    assert (target / "a.label").read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.label", "predictions"]
