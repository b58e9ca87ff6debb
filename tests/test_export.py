"""Export of .label and .conf files, the label-map YAML, and where an export may be written."""

from __future__ import annotations

import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from leap_core.datasets.kitti import read_label
from leap_core.errors import DatasetError, LeapError
from leap_core.export import (
    ExportConflict,
    ExportedSequence,
    check_export_targets,
    export_labels,
    export_target_problem,
    export_targets,
    label_map,
    label_map_yaml,
    labels_to_raw,
    load_label_map,
    raw_id_counts,
    read_confidence,
    run_export,
    summary_yaml,
    write_export_folder,
    write_export_zip,
    write_run_export,
    zip_member,
)
from leap_core.pipeline.coverage import unlabeled_reasons
from leap_core.presets import builtin_preset
from leap_core.run_layout import RunLayout, write_run_spec
from leap_core.schema import ClassDef, Schema

EXPORT_IDS = np.array([10, 40, 48], np.uint32)  # car, road, sidewalk


def test_export_writes_raw_ids_and_confidence(tmp_path) -> None:
    labels = np.array([0, -1, 2, 1, 0], np.int16)
    conf = np.array([0.9, 0.5, 0.7, 0.6, 0.25], np.float32)
    lp, cp = tmp_path / "out" / "000042.label", tmp_path / "out" / "000042.conf"
    export_labels(lp, cp, labels, conf, EXPORT_IDS)
    assert lp.read_bytes() == np.array([10, 0, 48, 40, 10], "<u4").tobytes()  # instance 0 in the high bits
    np.testing.assert_array_equal(read_label(lp, 5), [10, 0, 48, 40, 10])
    back = read_confidence(cp, 5)
    np.testing.assert_array_equal(back, np.array([0.9, 0.0, 0.7, 0.6, 0.25], np.float32))
    assert back.dtype == np.float32  # as documented, not float64 (twice the memory per point)
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
    moving = {c.moving_id: c for c in schema.classes if c.moving_id is not None}
    assert moving and back.names == {
        0: "unlabeled",
        **{c.export_id: c.name for c in schema.classes},
        **{raw: f"moving-{c.name}" for raw, c in moving.items()},
    }
    assert back.colors_rgb == {
        0: (0, 0, 0),
        **{c.export_id: tuple(c.color) for c in schema.classes},
        **{raw: tuple(c.color) for raw, c in moving.items()},
    }
    assert back.class_names() == schema.names
    assert back.counts == {raw: counts.get(raw, 0) for raw in back.names}
    for k, c in enumerate(schema.classes, start=1):
        assert back.learning_map_inv[k] == c.export_id and back.learning_map[c.export_id] == k
        assert all(back.learning_map[g] == k for g in c.gt_ids)  # the evaluation mapping the run used
        assert c.moving_id is None or back.learning_map[c.moving_id] == k  # a mover evaluates as its class
    # On disk: semantic-kitti-api's keys, integer ids, colours as [B, G, R], content as shares of the points.
    raw = yaml.safe_load(text)
    car = next(c for c in schema.classes if c.name == "car")
    assert raw["color_map"][car.export_id] == [car.color[2], car.color[1], car.color[0]]
    assert raw["content"][0] == pytest.approx(0.25) and raw["learning_ignore"][0] is True
    assert list(raw)[:3] == ["name", "labels", "color_map"] and raw["name"] == "demo run 3"
    assert "split" not in raw
    assert label_map(schema, sequences=["08"])["split"] == {"train": [], "valid": [8], "test": []}
    # semantic-kitti-api's split lists sequence numbers: names that are not numbers stay out of it.
    assert label_map(schema, sequences=["08", "town", "10"])["split"]["valid"] == [8, 10]
    assert "split" not in label_map(schema, sequences=["town"])


def test_label_map_export_id_wins_over_another_class_gt_id() -> None:
    for a_gt, b_gt in (((7, 8), ()), ((), (7, 8))):  # the clash in either class order
        schema = Schema(
            "s",
            classes=(
                ClassDef("a", (1, 2, 3), ("a",), export_id=7, gt_ids=a_gt),
                ClassDef("b", (4, 5, 6), ("b",), export_id=8, gt_ids=b_gt),
            ),
        )
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
    # A run folder (its run.json) and anything inside it: its own folders, its sequences' folders.
    root = RunLayout(tmp_path / "runs" / "r2")
    root.sequence("00").folder.mkdir(parents=True)
    write_run_spec(root, [("00", seq, None)])
    for inside in (root.root, root.root / "exports", root.cn_dir, root.sequence("00").folder / "export"):
        assert f"inside the pipeline run folder {root.root}" in (export_target_problem(inside) or ""), inside
    assert export_target_problem(tmp_path / "runs" / "elsewhere") is None
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


def test_summary_yaml_holds_every_part_in_order() -> None:
    schema = Schema(
        "mini",
        classes=(
            ClassDef("car", (1, 2, 3), ("car",), export_id=10),
            ClassDef("röad", (4, 5, 6), ("road",), export_id=40),
            ClassDef("pole", (7, 8, 9), ("pole",), export_id=80),
        ),
    )
    counts = {
        "scans": 3,
        "points": 90,
        "labeled": 70,
        "unlabeled": 20,
        "unlabeled_by_reason": {"outside_view": 15, "no_mask": 5},
        "raw_counts": {"0": 20, "10": 30, 40: 40, 99: 7},
    }  # keys as read back from JSON, or ints
    common = {
        "project": {"name": "démo", "id": 1},
        "run": {"id": 7},
        "schema": schema,
        "pipeline": {"voxel_size": 0.1},
        "counts": counts,
        "version": "1.2.3",
        "written_at": "2026-11-27T00:00:00Z",
    }
    sequences = [
        ExportedSequence("08", Path("/runs/r7/sequences/08/export"), Path("/data/seq/08"), range(2, 5)),
        ExportedSequence("town", Path("/runs/r7/sequences/town/export")),
    ]
    text = summary_yaml(sequences=sequences, with_confidence=True, **common)
    assert text.startswith("# LeAP Studio export summary (README, 'Exports').\n")
    assert "démo" in text and "röad" in text  # allow_unicode: names stay readable, not \xe9 escapes
    data = yaml.safe_load(text)
    assert list(data) == [
        "project",
        "run",
        "sequences",
        "files",
        "counts",
        "settings",
        "leap_studio_version",
        "written_at",
    ]  # sort_keys=False: the order written above
    assert data == {
        "project": {"name": "démo", "id": 1},
        "run": {"id": 7},
        "sequences": [
            {"name": "08", "dataset": "/data/seq/08", "frames": [2, 5]},
            {"name": "town", "dataset": None, "frames": "all"},
        ],
        "files": {
            "labels": "sequences/<name>/predictions/<frame>.label (uint32: raw id in the low 16 bits, "
            "a moving thing's moving id; track id in the upper 16, unique over the sequence, "
            "0 = stuff or none)",
            "confidences": "sequences/<name>/confidences/<frame>.conf (float32 per point)",
            "label_map": "label-map.yaml",
        },
        "counts": {
            "scans": 3,
            "points": 90,
            "labeled": 70,
            "unlabeled": 20,
            "unlabeled_by_reason": {"outside_view": 15, "no_mask": 5},
            "per_class": {"car": 30, "röad": 40, "pole": 0},
        },
        "settings": {"schema": "mini", "pipeline": {"voxel_size": 0.1}},
        "leap_studio_version": "1.2.3",
        "written_at": "2026-11-27T00:00:00Z",
    }
    assert list(data["counts"]["per_class"]) == ["car", "röad", "pole"]
    bare = yaml.safe_load(summary_yaml(sequences=sequences[1:], with_confidence=False, **common))
    assert bare["sequences"] == [{"name": "town", "dataset": None, "frames": "all"}]
    assert bare["files"]["confidences"] is None


def test_label_map_defaults_and_the_tables_for_unlabeled() -> None:
    schema = Schema(
        "mini",
        classes=(
            ClassDef("car", (1, 2, 3), ("car",), export_id=10),
            ClassDef("road", (4, 5, 6), ("road",), export_id=40),
        ),
    )
    lm = label_map(schema, {})
    assert lm["name"] == "mini"  # no name given: the schema's
    # "car" with export id 10 is SemanticKITTI's car: a thing whose moving points export 252.
    assert lm["content"] == {0: 0.0, 10: 0.0, 252: 0.0, 40: 0.0} and lm["counts"] == {
        0: 0,
        10: 0,
        252: 0,
        40: 0,
    }
    assert lm["learning_map_inv"] == {0: 0, 1: 10, 2: 40}
    assert lm["learning_ignore"] == {0: True, 1: False, 2: False}
    # Without counts the file has no counts table, and reading it back gives an empty one.
    assert load_label_map(label_map_yaml(label_map(schema))).counts == {}


def test_label_map_yaml_text_is_readable_unicode_with_flow_style_colours() -> None:
    schema = Schema("mini", classes=(ClassDef("véhicule", (255, 0, 10), ("car",), export_id=10),))
    text = label_map_yaml(label_map(schema))
    assert "véhicule" in text and "\\x" not in text and "\\u" not in text
    # One line per id, the colour as a [B, G, R] list on it, as in semantic-kitti-api's own file.
    assert "\n  10: [10, 0, 255]\n" in text and "\n  0: [0, 0, 0]\n" in text
    assert load_label_map(text).names[10] == "véhicule"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "labels: {car: 10}\ncolor_map: {}\nlearning_map: {}\nlearning_map_inv: {}\n",
            r"'labels' has a key that is not an integer id",
        ),
        (
            "labels: {true: car}\ncolor_map: {}\nlearning_map: {}\nlearning_map_inv: {}\n",
            r"'labels' has a key that is not an integer id",
        ),
        (
            "labels: {10: car}\ncolor_map: {10: [0, 0, 256]}\nlearning_map: {}\nlearning_map_inv: {}\n",
            r"color_map\[10\] must be",
        ),
        (
            "labels: {10: car}\ncolor_map: {10: [300, 0, 0]}\nlearning_map: {}\nlearning_map_inv: {}\n",
            r"color_map\[10\] must be",
        ),
        (
            "labels: {10: car}\ncolor_map: {10: [0, -1, 0]}\nlearning_map: {}\nlearning_map_inv: {}\n",
            r"color_map\[10\] must be",
        ),
        (
            "labels: {10: car}\ncolor_map: {10: [0, true, 0]}\nlearning_map: {}\nlearning_map_inv: {}\n",
            r"color_map\[10\] must be",
        ),
    ],
)
def test_load_label_map_refuses_non_integer_ids_and_colours_out_of_range(text: str, match: str) -> None:
    with pytest.raises(DatasetError, match=match):
        load_label_map(text, "cfg.yaml")
    # The highest colour value is fine.
    ok = load_label_map(
        "labels: {10: car}\ncolor_map: {10: [255, 0, 1]}\nlearning_map: {}\nlearning_map_inv: {}\n"
    )
    assert ok.colors_rgb == {10: (1, 0, 255)}


def test_load_label_map_names_a_default_source() -> None:
    with pytest.raises(DatasetError, match=r"^label map: expected a mapping"):
        load_label_map("[1, 2]")


def test_raw_id_counts_add_up_across_scans() -> None:
    scans = [np.array([10, 40], np.uint32), np.array([10 | (1 << 16), 10], np.uint32)]
    assert raw_id_counts(scans) == {10: 3, 40: 1}


def test_zip_member_puts_labels_and_confidences_in_their_folders() -> None:
    assert zip_member("08", "000001", ".label") == "sequences/08/predictions/000001.label"
    assert zip_member("08", "000001", ".conf") == "sequences/08/confidences/000001.conf"


def test_write_export_zip_holds_the_frame_files_and_the_extras(tmp_path) -> None:
    export_dir = tmp_path / "export"
    export_dir.mkdir()
    for name, data in (
        ("000000.label", b"L0" * 400),
        ("000000.conf", b"C0" * 400),
        ("000001.label", b"L1" * 400),
        ("000001.conf", b"C1" * 400),
        ("notes.txt", b"no"),
    ):
        (export_dir / name).write_bytes(data)
    (export_dir / "sub.label").mkdir()  # a folder named like a frame file is not one
    other = tmp_path / "other"
    other.mkdir()
    (other / "000007.label").write_bytes(b"T7" * 10)
    (other / "000007.conf").write_bytes(b"D7" * 10)
    sequences = [ExportedSequence("08", export_dir), ExportedSequence("town", other)]
    extra = {"label-map.yaml": "labels: {}\n", "summary.yaml": "a: 1\n"}
    out = tmp_path / "labels.zip"
    assert write_export_zip(out, sequences, extra, include_confidence=True) == 6
    with zipfile.ZipFile(out) as zf:
        assert sorted(zf.namelist()) == [
            "label-map.yaml",
            "sequences/08/confidences/000000.conf",
            "sequences/08/confidences/000001.conf",
            "sequences/08/predictions/000000.label",
            "sequences/08/predictions/000001.label",
            "sequences/town/confidences/000007.conf",
            "sequences/town/predictions/000007.label",
            "summary.yaml",
        ]
        assert zf.read("sequences/08/predictions/000001.label") == b"L1" * 400
        assert zf.read("sequences/town/confidences/000007.conf") == b"D7" * 10
        assert zf.read("summary.yaml") == b"a: 1\n"
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_DEFLATED}
    before = out.read_bytes()
    with pytest.raises(ExportConflict, match="already exists"):
        write_export_zip(out, sequences, extra, include_confidence=False)
    assert out.read_bytes() == before
    assert write_export_zip(out, sequences[:1], {}, include_confidence=False, overwrite=True) == 2
    with zipfile.ZipFile(out) as zf:
        assert sorted(zf.namelist()) == [
            "sequences/08/predictions/000000.label",
            "sequences/08/predictions/000001.label",
        ]


def test_a_run_export_goes_to_each_sequences_folders_checked_before_any_is_written(tmp_path) -> None:
    """export_targets: ``DIR/sequences/<name>/predictions`` (and ``confidences``); write_run_export copies
    each sequence's files there, after check_export_targets found every folder free: one folder in the way
    and nothing is written, not even the other sequences' folders."""
    runs = tmp_path / "run" / "sequences"
    a = ExportedSequence("00", runs / "00" / "export")
    b = ExportedSequence("01", runs / "01" / "export")
    _frame_files(a.export_dir, **{"000000.label": b"a0", "000000.conf": b"c0", "000001.label": b"a1"})
    _frame_files(b.export_dir, **{"000005.label": b"b5", "000005.conf": b"d5"})
    target = tmp_path / "dataset"
    targets = export_targets(target, ["00", "01"], with_conf=True)
    assert targets == {
        n: [target / "sequences" / n / "predictions", target / "sequences" / n / "confidences"]
        for n in ("00", "01")
    }
    assert export_targets(target, ["01"]) == {"01": [target / "sequences" / "01" / "predictions"]}
    (target / "sequences" / "01" / "confidences").mkdir(parents=True)
    (target / "sequences" / "01" / "confidences" / "000005.conf").write_bytes(b"mine")
    with pytest.raises(ExportConflict, match=r"01/confidences already holds 1 files"):
        write_run_export(targets, [a, b], with_conf=True)
    assert not (target / "sequences" / "00").exists()  # refused before anything was written
    done = write_run_export(targets, [a, b], with_conf=True, overwrite=True)
    assert done.files == {"00": 3, "01": 2} and done.replaced > 0
    assert sorted(p.name for p in (target / "sequences" / "00" / "predictions").iterdir()) == [
        "000000.label",
        "000001.label",
    ]
    assert (target / "sequences" / "01" / "confidences" / "000005.conf").read_bytes() == b"d5"
    # A target inside a dataset's own folders is refused whatever overwrite says.
    (tmp_path / "data" / "sequences" / "00" / "velodyne").mkdir(parents=True)
    bad = export_targets(tmp_path / "data" / "sequences" / "00" / "labels", ["00"])
    with pytest.raises(LeapError, match="input data or ground truth"):
        check_export_targets(bad, overwrite=True)
    with pytest.raises(LeapError, match="input data or ground truth"):
        write_run_export(bad, [a], overwrite=True)
    assert not (tmp_path / "data" / "sequences" / "00" / "labels").exists()


def test_run_export_reads_the_run_record(tmp_path) -> None:
    """run_export: the run's sequences in its record's order (or the names asked for), each with its export
    folder, dataset and frames; a folder that is not a run, or a sequence without .label files, refused."""
    root = RunLayout(tmp_path / "run")
    for name in ("a", "b"):
        _frame_files(root.sequence(name).export_dir, **{"000002.label": b"l", "000002.conf": b"c"})
    write_run_spec(root, [("b", tmp_path / "data" / "b", range(2, 5)), ("a", None, None)])
    got = run_export(root.root)
    assert [(s.name, s.export_dir, s.dataset, s.frames) for s in got] == [
        ("b", root.sequence("b").export_dir, (tmp_path / "data" / "b").resolve(), range(2, 5)),
        ("a", root.sequence("a").export_dir, None, None),
    ]
    assert [s.name for s in run_export(root.root, ["a"])] == ["a"]
    assert [p.name for p in got[0].files(True)] == ["000002.conf", "000002.label"]
    assert [p.name for p in got[0].files(False)] == ["000002.label"]
    with pytest.raises(LeapError, match="not a run folder"):
        run_export(root.sequence("a").folder)
    (root.sequence("a").export_dir / "000002.label").unlink()
    with pytest.raises(LeapError, match=r"sequence a has no exported \.label files"):
        run_export(root.root)
    assert [s.name for s in run_export(root.root, ["b"])] == ["b"]


def _frame_files(folder, **files):
    folder.mkdir(parents=True)
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return sorted(folder.iterdir())


def test_write_export_folder_creates_parents_and_survives_a_failing_fsync(tmp_path, monkeypatch) -> None:
    files = _frame_files(tmp_path / "src", **{"000000.label": b"a"})

    def no_fsync(fd):  # some file systems (network mounts) refuse fsync; the copy itself succeeded
        raise OSError(22, "Invalid argument")

    monkeypatch.setattr(os, "fsync", no_fsync)
    target = tmp_path / "new" / "deep" / "predictions"
    assert write_export_folder(target, files) == 0
    monkeypatch.undo()
    assert (target / "000000.label").read_bytes() == b"a"


def test_write_export_folder_puts_the_old_folder_back_when_the_swap_fails(tmp_path, monkeypatch) -> None:
    files = _frame_files(tmp_path / "src", **{"000000.label": b"new"})
    target = tmp_path / "predictions"
    _frame_files(target, **{"000000.label": b"old", "000005.label": b"old5"})
    real_rename = os.rename

    def fail_second_rename(src, dst):
        if ".leap-new-" in str(src):  # the new folder into place: the old one has been moved aside
            raise OSError(5, "I/O error")
        real_rename(src, dst)

    monkeypatch.setattr(os, "rename", fail_second_rename)
    with pytest.raises(OSError, match="I/O error"):
        write_export_folder(target, files, overwrite=True)
    monkeypatch.undo()
    old = {p.name: p.read_bytes() for p in target.iterdir()}
    assert old == {"000000.label": b"old", "000005.label": b"old5"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["predictions", "src"]


def test_write_export_folder_outlives_an_old_folder_it_cannot_remove(tmp_path, monkeypatch) -> None:
    files = _frame_files(tmp_path / "src", **{"000000.label": b"new"})
    target = tmp_path / "predictions"
    _frame_files(target, **{"000000.label": b"old"})

    def busy(*args, **kwargs):
        raise OSError(16, "Device or resource busy")

    monkeypatch.setattr(os, "unlink", busy)  # the removal of the old folder, after the swap
    assert write_export_folder(target, files, overwrite=True) == 1
    monkeypatch.undo()
    assert (target / "000000.label").read_bytes() == b"new"
    left = [p.name for p in tmp_path.iterdir() if ".leap-old-" in p.name]
    assert len(left) == 1  # best effort: the old copy stays beside it, hidden


def test_write_export_folder_reports_the_failure_not_the_cleanup(tmp_path, monkeypatch) -> None:
    files = _frame_files(tmp_path / "src", **{"000000.label": b"a", "000001.label": b"b"})
    target = tmp_path / "predictions"
    real_copy = shutil.copyfile

    def copy_then_fail(src, dst):
        if src.name == "000001.label":
            raise OSError(28, "No space left on device")
        return real_copy(src, dst)

    def busy(*args, **kwargs):
        raise OSError(16, "Device or resource busy")

    monkeypatch.setattr(shutil, "copyfile", copy_then_fail)
    monkeypatch.setattr(os, "unlink", busy)  # the half-written fresh folder cannot be removed either
    with pytest.raises(OSError, match="No space left"):
        write_export_folder(target, files)
    monkeypatch.undo()
    assert not target.exists()


def test_two_exports_into_one_folder_at_once_do_not_share_a_scratch_folder(tmp_path, monkeypatch) -> None:
    first = _frame_files(tmp_path / "a", **{"000000.label": b"first"})
    second = _frame_files(tmp_path / "b", **{"000000.label": b"second", "000001.label": b"second1"})
    target = tmp_path / "out" / "predictions"
    real_copy = shutil.copyfile
    calls = []

    def copy_while_another_export_runs(src, dst):
        if not calls:  # the first export is half-way when the second one starts and finishes
            calls.append(-1)
            calls[0] = write_export_folder(target, second)
        return real_copy(src, dst)

    monkeypatch.setattr(shutil, "copyfile", copy_while_another_export_runs)
    with pytest.raises(ExportConflict, match="changed while exporting"):
        write_export_folder(target, first)
    monkeypatch.undo()
    assert calls == [0]
    assert {p.name: p.read_bytes() for p in target.iterdir()} == {
        "000000.label": b"second",
        "000001.label": b"second1",
    }
    assert sorted(p.name for p in target.parent.iterdir()) == ["predictions"]


def test_labels_to_raw_bounds_and_dtype() -> None:
    out = labels_to_raw(np.array([0, 1, -1]), np.array([0, 0xFFFF]))  # both ends of the 16-bit range
    np.testing.assert_array_equal(out, [0, 0xFFFF, 0])
    assert out.dtype == np.uint32  # what a .label file holds
    for bad in (-1, 0x10000):
        with pytest.raises(ValueError, match="export ids"):
            labels_to_raw(np.array([0]), np.array([10, bad]))


def test_labels_and_confidences_of_any_shape_are_flattened_in_scan_order(tmp_path) -> None:
    labels = np.array([[0, 2], [-1, 1]], np.int16)
    np.testing.assert_array_equal(labels_to_raw(labels, EXPORT_IDS[:, None]), [10, 48, 0, 40])
    lp, cp = tmp_path / "a.label", tmp_path / "a.conf"
    export_labels(lp, cp, labels, np.array([[0.5, 0.25], [0.75, 1.0]]), EXPORT_IDS)
    np.testing.assert_array_equal(read_label(lp, 4), [10, 48, 0, 40])
    np.testing.assert_array_equal(read_confidence(cp, 4), np.array([0.5, 0.25, 0.0, 1.0], np.float32))


def test_export_writes_instance_ids_and_moving_ids(tmp_path) -> None:
    labels = np.array([0, 0, -1, 1, 0], np.int16)
    conf = np.ones(5, np.float32)
    moving_ids = np.array([252, 40, 48], np.uint32)  # car moves as 252; road and sidewalk have none
    lp, cp = tmp_path / "000000.label", tmp_path / "000000.conf"
    export_labels(
        lp,
        cp,
        labels,
        conf,
        EXPORT_IDS,
        instance=np.array([3, 7, 9, 0, 0]),
        moving=np.array([True, False, True, False, False]),
        moving_ids=moving_ids,
    )
    # A moving car of track 3, a static car of track 7; an unlabeled point carries no instance; stuff 0.
    assert read_label(lp, 5).tolist() == [252 | 3 << 16, 10 | 7 << 16, 0, 40, 10]
    with pytest.raises(ValueError, match="moving_ids"):
        export_labels(lp, cp, labels, conf, EXPORT_IDS, moving=np.ones(5, bool))
