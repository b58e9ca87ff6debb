"""Metrics against a hand-made confusion matrix, both unlabeled protocols, and semantic-kitti-api parity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from leap_core.metrics import confusion_matrix, evaluate, format_table, metrics_from_confusion
from leap_core.presets import load_preset

NAMES = ["car", "road", "sidewalk", "person"]
CATS = ["vehicle", "flat", "flat", "human"]

# (gt, pred, count); -1 = unlabeled. Class 3 (person) appears nowhere.
PAIRS = [
    (0, 0, 2), (0, 1, 1), (0, -1, 1),
    (1, 1, 3), (1, 2, 1), (1, -1, 2),
    (2, 2, 2), (2, 0, 1),
    (-1, 1, 1), (-1, -1, 1),  # unlabeled ground truth: ignored
]  # fmt: skip


def _points():
    gt = np.concatenate([np.full(n, g, np.int16) for g, _, n in PAIRS])
    pred = np.concatenate([np.full(n, p, np.int16) for _, p, n in PAIRS])
    perm = np.random.default_rng(0).permutation(len(gt))
    return gt[perm], pred[perm]


def test_confusion_matrix_by_hand() -> None:
    gt, pred = _points()
    expected = np.array(
        [
            # pred: car road sidewalk person unlabeled
            [2, 1, 0, 0, 1],  # gt car
            [0, 3, 1, 0, 2],  # gt road
            [1, 0, 2, 0, 0],  # gt sidewalk
            [0, 0, 0, 0, 0],  # gt person
        ]
    )
    cm = confusion_matrix(gt, pred, 4)
    np.testing.assert_array_equal(cm, expected)
    assert cm.dtype == np.int64
    with pytest.raises(ValueError, match="pred labels"):
        confusion_matrix(gt, np.full_like(pred, 4), 4)
    with pytest.raises(ValueError, match="gt labels"):
        confusion_matrix(np.full_like(gt, 4), pred, 4)
    # Inputs of any shape are flattened (per-scan label columns, say).
    np.testing.assert_array_equal(confusion_matrix(gt[:, None], pred[:, None], 4), expected)
    with pytest.raises(ValueError, match="points"):
        confusion_matrix(gt, pred[:-1], 4)


def test_ignore_unlabeled_protocol_by_hand() -> None:
    gt, pred = _points()
    m = evaluate(gt, pred, NAMES, CATS, ignore_unlabeled_pred=True)
    # car: tp 2, fp 1 (sidewalk→car), fn 1 (→road) = 2/4; road: 3/(3+1+1); sidewalk: 2/(2+1+1).
    np.testing.assert_allclose(m.iou[:3], [0.5, 0.6, 0.5])
    assert math.isnan(m.iou[3])
    assert m.miou == pytest.approx(1.6 / 3)
    assert m.miou_all_classes == pytest.approx(1.6 / 4)
    # vehicle: tp 2, fp 1, fn 1 = 0.5; flat (road+sidewalk): tp 3+1+2 = 6, fp 1, fn 1 = 0.75.
    assert m.category_iou["vehicle"] == pytest.approx(0.5)
    assert m.category_iou["flat"] == pytest.approx(0.75)
    assert math.isnan(m.category_iou["human"])
    assert m.category_miou == pytest.approx(0.625)
    assert m.n_points == 13 and m.labeled_share == pytest.approx(10 / 13)


def test_all_points_protocol_by_hand() -> None:
    gt, pred = _points()
    m = evaluate(gt, pred, NAMES, CATS, ignore_unlabeled_pred=False)
    # Unlabeled predictions become misses: car fn 1+1, road fn 1+2.
    np.testing.assert_allclose(m.iou[:3], [2 / 5, 3 / 7, 0.5])
    assert m.miou == pytest.approx((0.4 + 3 / 7 + 0.5) / 3)
    assert m.category_iou["vehicle"] == pytest.approx(2 / 5)
    assert m.category_iou["flat"] == pytest.approx(6 / 10)  # fn: 1 (sidewalk→car) + 2 unlabeled
    assert m.category_miou == pytest.approx(0.5)
    assert m.labeled_share == pytest.approx(10 / 13)


def _semantic_kitti_api_iou(gt: np.ndarray, pred: np.ndarray, c: int) -> np.ndarray:
    """The evaluator's per-class IoU, written from its documented rule: indices shifted by one so that
    unlabeled is its ignored class 0; conf[pred, gt]; gt-0 column zeroed; tp = diag, fp = row sum - tp,
    fn = column sum - tp; IoU = tp / (tp + fp + fn + 1e-15)."""
    conf = np.zeros((c + 1, c + 1), np.int64)
    np.add.at(conf, (pred.astype(np.int64) + 1, gt.astype(np.int64) + 1), 1)
    conf[:, 0] = 0
    tp = np.diag(conf)
    fp = conf.sum(axis=1) - tp
    fn = conf.sum(axis=0) - tp
    return (tp / (tp + fp + fn + 1e-15))[1:]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_all_points_protocol_matches_semantic_kitti_api(seed: int) -> None:
    rng = np.random.default_rng(seed)
    c = 6
    gt = rng.integers(-1, c - 1, 5000).astype(np.int16)  # class c-1 never in gt
    pred = np.where(rng.random(5000) < 0.6, gt, rng.integers(-1, c - 2, 5000)).astype(np.int16)
    names = [f"c{i}" for i in range(c)]
    m = evaluate(gt, pred, names, ["x"] * c, ignore_unlabeled_pred=False)
    ref = _semantic_kitti_api_iou(gt, pred, c)
    np.testing.assert_allclose(np.nan_to_num(m.iou, nan=0.0), ref, atol=1e-12)
    assert m.miou_all_classes == pytest.approx(ref.mean(), abs=1e-12)


def test_to_dict_and_format_table() -> None:
    gt, pred = _points()
    ign = evaluate(gt, pred, NAMES, CATS, ignore_unlabeled_pred=True)
    allp = evaluate(gt, pred, NAMES, CATS, ignore_unlabeled_pred=False)
    d = ign.to_dict()
    assert d["iou"]["person"] is None and d["iou"]["road"] == pytest.approx(0.6)
    assert d["category_iou"]["flat"] == pytest.approx(0.75)
    assert d["confusion"][1] == [0, 3, 1, 0, 2]
    table = format_table({"point": allp, "voxel": ign}, NAMES)
    lines = [line.split() for line in table.splitlines() if not line.startswith("-")]
    assert lines[0] == ["%", "point", "voxel"]
    columns = {row[0]: row[1:] for row in lines[1:]}
    assert list(columns) == ["mIoU", "cat-mIoU", "labeled", *NAMES]
    assert [v[0] for v in columns.values()] == ["44.3", "50.0", "76.9", "40.0", "42.9", "50.0", "-"]
    assert [v[1] for v in columns.values()] == ["53.3", "62.5", "76.9", "50.0", "60.0", "50.0", "-"]
    with pytest.raises(ValueError, match="categories"):
        evaluate(gt, pred, NAMES, CATS[:2], ignore_unlabeled_pred=True)


def test_format_table_fits_120_columns_with_the_semantickitti_classes() -> None:
    """19 classes and five result rows (point, voxel, three 3D-CN rounds) fit a 120-column terminal."""
    schema = load_preset("semantickitti").schema
    names = [c.name for c in schema.classes]
    cats = [c.category for c in schema.classes]
    rng = np.random.default_rng(0)
    gt = rng.integers(0, len(names), 5000)
    pred = np.where(rng.random(5000) < 0.7, gt, rng.integers(-1, len(names), 5000))
    m = evaluate(gt, pred, names, cats, ignore_unlabeled_pred=True)
    table = format_table({"point": m, "voxel": m, "+3D-CN x1": m, "+3D-CN x2": m, "+3D-CN x3": m}, names)
    assert max(len(line) for line in table.splitlines()) <= 120, table
    assert len(table.splitlines()) == 2 + 3 + 1 + len(names)


def test_format_table_layout_exactly() -> None:
    """Names left-aligned, figures right-aligned, each column as wide as its longest cell, the header
    included (here the method name is wider than its figures)."""
    gt, pred = _points()
    m = evaluate(gt, pred, NAMES, CATS, ignore_unlabeled_pred=True)
    assert format_table({"voxel-long": m}, NAMES).splitlines() == [
        "%         voxel-long",
        "--------  ----------",
        "mIoU            53.3",
        "cat-mIoU        62.5",
        "labeled         76.9",
        "--------  ----------",
        "car             50.0",
        "road            60.0",
        "sidewalk        50.0",
        "person             -",
    ]


def test_to_dict_keys_and_values() -> None:
    """The metrics file's fields (runs' metrics.json, the API, the app's result table read them by name)."""
    gt, pred = _points()
    d = evaluate(gt, pred, NAMES, CATS, ignore_unlabeled_pred=False).to_dict()
    assert set(d) == {
        "miou",
        "miou_all_classes",
        "category_miou",
        "labeled_share",
        "n_points",
        "ignore_unlabeled_pred",
        "iou",
        "category_iou",
        "confusion",
    }
    assert d["miou"] == pytest.approx((0.4 + 3 / 7 + 0.5) / 3)
    assert d["miou_all_classes"] == pytest.approx((0.4 + 3 / 7 + 0.5) / 4)
    assert d["category_miou"] == pytest.approx(0.5)
    assert d["labeled_share"] == pytest.approx(10 / 13)
    assert d["n_points"] == 13 and type(d["n_points"]) is int
    assert d["ignore_unlabeled_pred"] is False
    assert d["category_iou"] == {"vehicle": pytest.approx(0.4), "flat": pytest.approx(0.6), "human": None}


def test_a_class_with_a_single_point() -> None:
    # One car point predicted car: tp = 1, tp + fp + fn = 1 → IoU 1 (not "absent"); road absent → NaN.
    one = np.array([0])
    m = evaluate(one, one, ["car", "road"], ["vehicle", "flat"], ignore_unlabeled_pred=True)
    assert m.iou[0] == 1.0 and math.isnan(m.iou[1])
    assert m.miou == 1.0 and m.category_iou["vehicle"] == 1.0


def test_metrics_from_a_float_confusion_matrix_store_it_as_int64() -> None:
    cm = np.array([[2, 1, 0, 0, 1], [0, 3, 1, 0, 2], [1, 0, 2, 0, 0], [0, 0, 0, 0, 0]], np.float64)
    m = metrics_from_confusion(cm, NAMES, CATS, ignore_unlabeled_pred=True)
    assert m.confusion.dtype == np.int64
    assert m.to_dict()["confusion"][1] == [0, 3, 1, 0, 2] and type(m.to_dict()["confusion"][1][1]) is int
    np.testing.assert_allclose(m.iou[:3], [0.5, 0.6, 0.5])
    # Either mismatch alone is refused: categories for another class count, a matrix of another shape.
    with pytest.raises(ValueError, match="do not match"):
        metrics_from_confusion(cm, NAMES, CATS[:3], ignore_unlabeled_pred=True)
    with pytest.raises(ValueError, match="do not match"):
        metrics_from_confusion(cm[:, :4], NAMES, CATS, ignore_unlabeled_pred=True)
