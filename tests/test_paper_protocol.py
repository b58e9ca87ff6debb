"""The paper's protocol: SemanticKITTI's 19 classes merged into Table 1's 11, camera view, unlabeled
predictions ignored (leap_core.eval_view, leap_core.metrics.merge_confusion, the evaluate stage)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from runhelpers import label

from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import KittiSequence
from leap_core.eval_view import PAPER_VIEW
from leap_core.fusion import voxel_keys, world_points
from leap_core.metrics import confusion_matrix, evaluate, merge_confusion, metrics_from_confusion
from leap_core.pipeline.context import load_observation
from leap_core.pipeline.evaluation import (
    COMMON,
    PAPER,
    PROTOCOLS,
    common_points,
    format_result_tables,
    load_metrics,
    metrics_tables,
    overall_metrics,
    result_tables,
    with_paper_protocol,
)
from leap_core.pipeline.metrics_file import SequenceMetrics
from leap_core.run_layout import SequenceLayout
from leap_core.schema import Schema, builtin_schema
from leap_core.smoothing import SmoothedGrid
from leap_core.types import UNLABELED
from tests.test_pipeline import make_street

# The merge as the paper's Table 1 needs it, written out here independently of leap_core.eval_view.
EXPECTED_MERGE = {
    "car": ["car"],
    "bicycle": ["bicycle", "bicyclist"],
    "motorcycle": ["motorcycle", "motorcyclist"],
    "other-vehicle": ["truck", "other-vehicle"],
    "person": ["person"],
    "road": ["road", "parking"],
    "sidewalk": ["sidewalk"],
    "other-ground": ["other-ground"],
    "manmade": ["building", "fence", "pole", "traffic-sign"],
    "vegetation": ["vegetation", "trunk"],
    "terrain": ["terrain"],
}


# ----------------------------------------------------------------------------------- merge_confusion
def test_merge_confusion_by_hand() -> None:
    # 4 classes a, b, c, d → 2 merged: X = {a, c}, Y = {b, d}; last column = predicted unlabeled.
    conf = np.array([
        # pred a  b  c  d  unl
        [5, 1, 2, 0, 3],   # gt a
        [0, 4, 0, 1, 0],   # gt b
        [1, 0, 6, 2, 1],   # gt c
        [0, 3, 0, 7, 2],   # gt d
    ])  # fmt: skip
    merged = merge_confusion(conf, [0, 1, 0, 1], 2)
    expected = np.array([
        # pred X            Y            unl
        [5 + 2 + 1 + 6,     1 + 0 + 0 + 2, 3 + 1],   # gt X = rows a, c
        [0 + 0 + 0 + 0,     4 + 1 + 3 + 7, 0 + 2],   # gt Y = rows b, d
    ])  # fmt: skip
    assert merged.tolist() == expected.tolist() == [[14, 3, 4], [0, 15, 2]]
    assert merged.dtype == np.int64
    # IoU of the merged matrix, unlabeled ignored: X = 14 / (14 + 0 + 3), Y = 15 / (15 + 3 + 0).
    m = metrics_from_confusion(merged, ["X", "Y"], ["k", "k"], ignore_unlabeled_pred=True)
    assert m.iou.tolist() == pytest.approx([14 / 17, 15 / 18])


def test_merge_confusion_is_the_confusion_of_the_mapped_labels() -> None:
    rng = np.random.default_rng(3)
    c, m = 19, 11
    mapping = PAPER_VIEW.mapping(builtin_schema("semantickitti").names)
    assert mapping is not None
    gt = rng.integers(-1, c, 5000).astype(np.int16)
    pred = rng.integers(-1, c, 5000).astype(np.int16)
    lut = np.append(mapping, UNLABELED)  # index -1 → UNLABELED stays unlabeled
    direct = confusion_matrix(lut[gt], lut[pred], m)
    assert merge_confusion(confusion_matrix(gt, pred, c), mapping, m).tolist() == direct.tolist()


@pytest.mark.parametrize(
    ("conf", "mapping", "m", "message"),
    [
        (np.zeros((3, 4)), [0, 1], 2, r"needs \(2, 3\)"),
        (np.zeros((2, 3)), [0, 2], 2, "must be in 0..1"),
        (np.zeros((2, 3)), [-1, 0], 2, "must be in 0..1"),
    ],
)
def test_merge_confusion_refuses_bad_input(conf, mapping, m, message) -> None:
    with pytest.raises(ValueError, match=message):
        merge_confusion(conf, mapping, m)


# ------------------------------------------------------------------------------------------- the view
def test_paper_view_is_table_1s_merge_of_the_19_classes() -> None:
    assert PAPER_VIEW.to_dict()["merge"] == EXPECTED_MERGE
    sk = builtin_schema("semantickitti").names
    assert sorted(PAPER_VIEW.sources()) == sorted(sk)
    for mc in PAPER_VIEW.classes:
        assert mc.reason.strip()
    for name in ("semantickitti", "semantickitti_bare", "semantickitti_expanded", "demo"):
        assert PAPER_VIEW.problem(builtin_schema(name).names) is None, name
    mapping = PAPER_VIEW.mapping(sk)
    assert mapping is not None
    assert [PAPER_VIEW.names[j] for j in mapping] == [
        next(k for k, v in EXPECTED_MERGE.items() if n in v) for n in sk
    ]


def test_paper_view_does_not_apply_to_other_schemas() -> None:
    assert "lacks" in (PAPER_VIEW.problem(builtin_schema("agri_uav").names) or "")
    assert PAPER_VIEW.mapping(builtin_schema("nuscenes").names) is None
    sk = builtin_schema("semantickitti").names
    assert "lacks trunk" in (PAPER_VIEW.problem([n for n in sk if n != "trunk"]) or "")
    assert "does not know (bus)" in (PAPER_VIEW.problem([*sk, "bus"]) or "")


def _metrics_of(camera_conf: np.ndarray, names: list[str], cats: list[str]) -> dict:
    m = metrics_from_confusion(camera_conf, names, cats, ignore_unlabeled_pred=True).to_dict()
    return {
        "class_names": names,
        "categories": cats,
        "rows": ["point"],
        "protocols": dict(PROTOCOLS),
        "camera": {"point": m},
        "all": {"point": m},
    }


def test_paper_protocol_by_hand_on_the_19_classes() -> None:
    schema = builtin_schema("semantickitti")
    names, c = schema.names, schema.num_classes
    conf = np.zeros((c, c + 1), np.int64)
    ix = schema.index
    conf[ix("truck"), ix("other-vehicle")] = 4  # merged: other-vehicle TP
    conf[ix("other-vehicle"), ix("other-vehicle")] = 1
    conf[ix("parking"), ix("road")] = 3  # road TP
    conf[ix("road"), ix("sidewalk")] = 2  # road FN, sidewalk FP
    conf[ix("road"), c] = 50  # unlabeled prediction: ignored
    conf[ix("building"), ix("pole")] = 6  # manmade TP
    conf[ix("trunk"), ix("terrain")] = 1  # vegetation FN, terrain FP
    conf[ix("vegetation"), ix("trunk")] = 5  # vegetation TP
    conf[ix("bicyclist"), ix("person")] = 2  # bicycle FN, person FP
    conf[ix("bicycle"), ix("bicyclist")] = 2  # bicycle TP
    plain = SequenceMetrics.from_dict(_metrics_of(conf, names, schema.categories()))
    data = with_paper_protocol(plain).to_dict()
    assert PAPER not in plain.tables  # a new object: the one given is not changed
    assert set(data["protocols"]) == {*PROTOCOLS, PAPER} and "protocol_notes" not in data
    assert data["paper_view"]["merge"] == EXPECTED_MERGE
    iou = data[PAPER]["point"]["iou"]
    assert iou["other-vehicle"] == pytest.approx(5 / 5)
    assert iou["road"] == pytest.approx(3 / (3 + 2))
    assert iou["sidewalk"] == pytest.approx(0.0)
    assert iou["manmade"] == pytest.approx(1.0)
    assert iou["vegetation"] == pytest.approx(5 / 6)
    assert iou["terrain"] == pytest.approx(0.0)
    assert iou["bicycle"] == pytest.approx(2 / 4)
    assert iou["person"] == pytest.approx(0.0)
    assert iou["car"] is None and iou["other-ground"] is None
    assert data[PAPER]["point"]["ignore_unlabeled_pred"] is True
    assert data[PAPER]["point"]["labeled_share"] == pytest.approx(26 / (26 + 50))
    # The tables read back and print it.
    tables = load_metrics_from(data)
    assert tables[PAPER]["point"].class_names == tuple(EXPECTED_MERGE)
    assert "manmade" in format_result_tables(SequenceMetrics.from_dict(data))


def load_metrics_from(data: dict) -> dict:
    """The tables of ``data`` written to JSON and read back."""
    return metrics_tables(SequenceMetrics.from_dict(json.loads(json.dumps(data))))


def test_paper_protocol_absent_with_a_note_for_another_schema() -> None:
    schema = builtin_schema("agri_uav")
    c = schema.num_classes
    conf = np.arange(c * (c + 1)).reshape(c, c + 1)
    data = with_paper_protocol(
        SequenceMetrics.from_dict(_metrics_of(conf, schema.names, schema.categories()))
    )
    data = data.to_dict()
    assert PAPER not in data and "paper_view" not in data and set(data["protocols"]) == set(PROTOCOLS)
    assert data["protocol_notes"][PAPER].startswith("not computed: the schema lacks")
    assert set(load_metrics_from(data)) == {"camera", "all"}
    assert "paper protocol not computed" in format_result_tables(SequenceMetrics.from_dict(data))


# ------------------------------------------------------------------------------------------ pipeline
@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_street(tmp_path_factory.mktemp("street") / "sequences" / "00", n_frames=4)


@pytest.fixture(scope="module")
def run(street: Path, tmp_path_factory: pytest.TempPathFactory):
    """(the street's folder in the run, the result)."""
    result = label(street, builtin_schema("semantickitti"), PipelineConfig(), tmp_path_factory.mktemp("runs"))
    return result.folder, result


def test_pipeline_paper_protocol_is_the_merged_camera_protocol(run, street: Path) -> None:
    run_dir, result = run
    m = json.loads(SequenceLayout(run_dir).metrics.read_text())
    assert m == result.metrics.to_dict()
    assert set(m["protocols"]) == {*PROTOCOLS, PAPER} and "protocol_notes" not in m
    assert m["paper_view"]["class_names"] == list(EXPECTED_MERGE)
    schema = builtin_schema("semantickitti")
    mapping = np.array(
        [
            list(EXPECTED_MERGE).index(next(k for k, v in EXPECTED_MERGE.items() if n in v))
            for n in schema.names
        ]
    )
    for row in m["rows"]:
        merged = merge_confusion(np.asarray(m["camera"][row]["confusion"]), mapping, 11)
        assert m[PAPER][row]["confusion"] == merged.tolist()
    # Point by point, independently of the stored matrices: in-view points, both label sets mapped through
    # the merge, unlabeled predictions ignored.
    seq, lay = KittiSequence(street), SequenceLayout(run_dir)
    lut = np.append(mapping, UNLABELED)
    gts, preds = [], []
    for i, fid in enumerate(seq.frame_ids):
        _, _, in_view = load_observation(lay.observation(fid))
        with np.load(lay.points(fid)) as z:
            pred = z["point_label"]
        gts.append(lut[schema.map_gt(seq.frame(i).labels)[in_view]])
        preds.append(lut[pred[in_view]])
    gt, pred = np.concatenate(gts), np.concatenate(preds)
    assert (pred == UNLABELED).any() and (gt != UNLABELED).any()  # the unlabeled rule is exercised
    expected = evaluate(gt, pred, list(EXPECTED_MERGE), PAPER_VIEW.categories, ignore_unlabeled_pred=True)
    assert m[PAPER]["point"] == expected.to_dict()
    # The printed tables show it; the sum over a run's sequences keeps it.
    text = result_tables(run_dir)
    assert text is not None and "the paper's Table 1" in text and "manmade" in text
    tables = load_metrics(run_dir)
    assert tables is not None and tables[PAPER]["voxel"].miou == pytest.approx(m[PAPER]["voxel"]["miou"])
    summed = overall_metrics({"a": result.metrics, "b": result.metrics})
    assert summed is not None
    both = summed.to_dict()
    assert both[PAPER]["voxel"]["confusion"] == (2 * np.asarray(m[PAPER]["voxel"]["confusion"])).tolist()


def test_common_points_by_hand() -> None:
    u = UNLABELED
    in_view = np.array([True, True, True, True, False])
    point = np.array([0, u, 2, 1, 3], np.int16)
    voxel = np.array([1, 1, u, 1, 3], np.int16)
    assert common_points(in_view, [point, voxel]).tolist() == [True, False, False, True, False]
    assert common_points(in_view, []).tolist() == in_view.tolist()
    assert in_view.tolist() == [True, True, True, True, False]  # the input is not written to


def test_common_protocol_scores_every_row_on_the_points_all_rows_label(run, street: Path) -> None:
    run_dir, result = run
    m = json.loads(SequenceLayout(run_dir).metrics.read_text())
    assert m["rows"] == ["point", "voxel", "objects"]
    schema = builtin_schema("semantickitti")
    seq, lay = KittiSequence(street), SequenceLayout(run_dir)
    voxel = SmoothedGrid.load(lay.grid_smooth)
    gts, points, voxels, in_views = [], [], [], []
    for i, fid in enumerate(seq.frame_ids):
        frame = seq.frame(i)
        _, _, in_view = load_observation(lay.observation(fid))
        with np.load(lay.points(fid)) as z:
            points.append(z["point_label"])
        voxels.append(voxel.labels_at(voxel_keys(world_points(frame.points, frame.pose), 0.2))[0])
        gts.append(schema.map_gt(frame.labels))
        in_views.append(in_view)
    gt, point, vox, in_view = map(np.concatenate, (gts, points, voxels, in_views))
    common = in_view & (point != UNLABELED) & (vox != UNLABELED)
    # The rows label different points in view (else the protocol would say nothing camera does not) ...
    assert ((vox != UNLABELED) & in_view).sum() > common.sum() > 0
    for row, pred in (("point", point), ("voxel", vox)):
        expected = evaluate(
            gt[common], pred[common], schema.names, schema.categories(), ignore_unlabeled_pred=True
        )
        assert m[COMMON][row] == expected.to_dict()
    # ... and here each row is scored on the same points.
    assert (
        np.sum(m[COMMON]["point"]["confusion"])
        == np.sum(m[COMMON]["voxel"]["confusion"])
        == ((gt[common] != UNLABELED).sum())
    )
    # A file written before the protocol existed still reads, and a sum with it leaves the protocol out.
    old = {k: v for k, v in m.items() if k != COMMON}
    old["protocols"] = {k: v for k, v in m["protocols"].items() if k != COMMON}
    older = SequenceMetrics.from_dict(old)
    assert COMMON not in metrics_tables(older) and "camera" in metrics_tables(older)
    both = overall_metrics({"a": result.metrics, "b": older})
    assert both is not None and COMMON not in both.tables and COMMON not in both.protocols
    twice = overall_metrics({"a": result.metrics, "b": result.metrics})
    assert twice is not None
    assert (
        twice.table(COMMON)["voxel"].confusion == (2 * np.asarray(m[COMMON]["voxel"]["confusion"])).tolist()
    )


def test_pipeline_without_the_classes_has_no_paper_protocol(street: Path, tmp_path: Path) -> None:
    full = builtin_schema("semantickitti")
    schema = Schema("no-trunk", tuple(c for c in full.classes if c.name != "trunk"))
    result = label(street, schema, PipelineConfig(), tmp_path / "run", until="evaluate")
    assert result.metrics is not None
    m = result.metrics.to_dict()
    assert set(m["protocols"]) == set(PROTOCOLS) and PAPER not in m and "paper_view" not in m
    assert "lacks trunk" in m["protocol_notes"][PAPER]
    assert "paper protocol not computed" in (result_tables(result.folder) or "")


def test_the_merge_is_part_of_the_evaluate_fingerprint(
    street: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from leap_core.pipeline import stage_fingerprints, stages

    schema = builtin_schema("semantickitti")
    before = stage_fingerprints(street, schema, PipelineConfig(), tmp_path)
    other = dataclasses.replace(PAPER_VIEW, name="changed")
    monkeypatch.setattr(stages, "PAPER_VIEW", other)
    after = stage_fingerprints(street, schema, PipelineConfig(), tmp_path)
    assert after["evaluate"] != before["evaluate"]
    assert {s for s in before if before[s] != after[s]} == {"evaluate"}
    # So is the layout of metrics.json: a new one evaluates finished runs again, and only that.
    monkeypatch.setattr(stages, "METRICS_VERSION", stages.METRICS_VERSION + 1)
    again = stage_fingerprints(street, schema, PipelineConfig(), tmp_path)
    assert {s for s in after if after[s] != again[s]} == {"evaluate"}
