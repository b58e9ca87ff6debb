"""The evaluate stage's bookkeeping on hand-made metrics files (leap_core.pipeline.evaluation): the sum over
several sequences, the all-points labeled share, the printed tables. The protocols themselves are checked
against real runs in tests/test_paper_protocol.py and tests/test_runs.py."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from leap_core.errors import DatasetError, LeapError
from leap_core.metrics import metrics_from_confusion
from leap_core.pipeline.evaluation import (
    COMMON,
    PAPER,
    PROTOCOLS,
    format_result_tables,
    load_metrics,
    metrics_tables,
    overall_metrics,
    result_tables,
)
from leap_core.pipeline.metrics_file import SequenceMetrics
from leap_core.run_layout import SequenceLayout

NAMES = ["a", "b"]
CATS = ["x", "y"]
ROWS = ["point", "voxel"]


def _sequence(scale: int, *, common: bool = True, frames: list[int] | None = None) -> dict[str, Any]:
    """A two-class metrics.json: every protocol's confusion is ``scale`` times a fixed (2, 3) matrix (rows:
    ground truth a, b; columns: predicted a, b, unlabeled), plus 1 on the diagonal for the voxel row."""
    base = np.array([[3, 1, 2], [0, 4, 1]], np.int64)
    out: dict[str, Any] = {
        "class_names": NAMES,
        "categories": CATS,
        "rows": ROWS,
        "labeler": f"simulated x{scale}",
        "protocols": {p: d for p, d in PROTOCOLS.items() if common or p != COMMON},
        "frames": frames or [scale, scale + 1],
        "n_points": 10 * scale,
        "n_points_in_view": 8 * scale,
        "labeled_points": {"point": 4 * scale, "voxel": 6 * scale},
        "coverage_ratio": {"point": 1.0, "voxel": 1.5},
    }
    for p in out["protocols"]:
        out[p] = {}
        for r, extra in zip(ROWS, (0, 1), strict=True):
            conf = scale * base + extra * np.eye(2, 3, dtype=np.int64)
            out[p][r] = metrics_from_confusion(conf, NAMES, CATS, ignore_unlabeled_pred=p != "all").to_dict()
    return out


def _metrics(data: dict[str, Any]) -> SequenceMetrics:
    back = SequenceMetrics.from_dict(data)
    assert back.to_dict() == data  # the file round-trips
    return back


def test_overall_metrics_by_hand() -> None:
    one, two = _metrics(_sequence(1)), _metrics(_sequence(2, frames=[7, 9]))
    summed = overall_metrics({"s1": one, "none": None, "s2": two})
    assert summed is not None and summed.sequences == ["s1", "s2"]
    out = summed.to_dict()
    assert out["sequences"] == ["s1", "s2"]
    assert out["frames"] == {"s1": [1, 2], "s2": [7, 9]}
    assert out["labeler"] == "simulated x1"  # the first sequence's
    assert (out["class_names"], out["categories"], out["rows"]) == (NAMES, CATS, ROWS)
    assert out["n_points"] == 30 and out["n_points_in_view"] == 24
    assert out["labeled_points"] == {"point": 12, "voxel": 18}
    assert out["labeled_share_all_points"] == {
        "point": pytest.approx(12 / 30),
        "voxel": pytest.approx(18 / 30),
    }
    assert out["coverage_ratio"] == {"point": 1.0, "voxel": pytest.approx(18 / 12)}
    assert out["protocols"] == PROTOCOLS
    # Voxel row, summed: 3·base + 2 on the diagonal = [[11, 3, 6], [0, 14, 3]].
    for p in PROTOCOLS:
        assert out[p]["voxel"]["confusion"] == [[11, 3, 6], [0, 14, 3]]
        assert out[p]["point"]["confusion"] == [[9, 3, 6], [0, 12, 3]]
    # camera / common ignore the unlabeled column: IoU_a = 11 / (11 + 3 + 0), IoU_b = 14 / (14 + 0 + 3).
    for p in ("camera", COMMON):
        assert out[p]["voxel"]["ignore_unlabeled_pred"] is True
        assert out[p]["voxel"]["iou"] == {"a": pytest.approx(11 / 14), "b": pytest.approx(14 / 17)}
    # all counts it as a miss: IoU_a = 11 / (11 + 0 + 3 + 6), IoU_b = 14 / (14 + 3 + 0 + 3).
    assert out["all"]["voxel"]["ignore_unlabeled_pred"] is False
    assert out["all"]["voxel"]["iou"] == {"a": pytest.approx(11 / 20), "b": pytest.approx(14 / 20)}
    assert out["all"]["voxel"]["miou"] == pytest.approx((11 / 20 + 14 / 20) / 2)
    # Two classes are not SemanticKITTI's: the paper's protocol is noted, not computed.
    assert PAPER not in out and "not computed" in out["protocol_notes"][PAPER]
    # The tables read back as the sums.
    assert metrics_tables(summed)["all"]["voxel"].miou == pytest.approx((11 / 20 + 14 / 20) / 2)
    assert summed.miou("all", "voxel") == pytest.approx((11 / 20 + 14 / 20) / 2)


def test_overall_metrics_without_points() -> None:
    empty = _sequence(1)
    empty.update(n_points=0, labeled_points={"point": 0, "voxel": 0})
    summed = overall_metrics({"s": _metrics(empty)})
    assert summed is not None
    out = summed.to_dict()
    assert out["labeled_share_all_points"] == {"point": None, "voxel": None}
    assert out["coverage_ratio"] == {"point": None, "voxel": None}


def test_overall_metrics_refuse_other_classes_or_rows_and_leave_out_a_missing_protocol() -> None:
    one, two = _metrics(_sequence(1)), _metrics(_sequence(2))
    with pytest.raises(LeapError, match="sequence s2: metrics class_names"):
        overall_metrics({"s1": one, "s2": dataclasses.replace(two, class_names=["a", "c"])})
    with pytest.raises(LeapError, match="sequence s2: metrics rows"):
        overall_metrics({"s1": one, "s2": dataclasses.replace(two, rows=["point"])})
    # A file without its rows or classes is not read at all: the error names the file and the key.
    for key in ("rows", "class_names"):
        with pytest.raises(DatasetError, match=rf"^s2\.json: unreadable metrics \(KeyError: '{key}'\)"):
            SequenceMetrics.from_dict({k: v for k, v in _sequence(2).items() if k != key}, "s2.json")
    # A sequence evaluated before `common` existed: the sum leaves that protocol out, keeps the others.
    summed = overall_metrics({"s1": one, "s2": _metrics(_sequence(2, common=False))})
    assert summed is not None
    out = summed.to_dict()
    assert COMMON not in out and COMMON not in out["protocols"]
    assert out["all"]["voxel"]["confusion"] == [[11, 3, 6], [0, 14, 3]]
    assert list(out["protocols"]) == ["camera", "all"]


def test_overall_metrics_count_what_older_files_lack_as_zero() -> None:
    """Files written before the in-view and labeled counts existed add nothing to those sums."""
    one = _sequence(1)
    two = {k: v for k, v in _sequence(2).items() if k not in ("n_points_in_view", "labeled_points")}
    three = {**_sequence(3), "labeled_points": {"point": 5}}
    summed = overall_metrics(
        {n: SequenceMetrics.from_dict(m) for n, m in (("s1", one), ("s2", two), ("s3", three))}
    )
    assert summed is not None
    out = summed.to_dict()
    assert (out["n_points"], out["n_points_in_view"]) == (60, 8 + 24)
    assert out["labeled_points"] == {"point": 4 + 5, "voxel": 6}


def test_all_points_labeled_share() -> None:
    def share(**fields: Any) -> dict[str, float | None]:
        data = {k: v for k, v in _sequence(1).items() if k not in ("n_points", "labeled_points")}
        return SequenceMetrics.from_dict({**data, **fields}).all_points_labeled_share()

    assert share(labeled_share_all_points={"voxel": 0.5, "point": None}, n_points=2) == {
        "voxel": 0.5,
        "point": None,
    }
    # Older files: computed from the counts.
    assert share(labeled_points={"voxel": 3, "point": 1}, n_points=4) == {"voxel": 0.75, "point": 0.25}
    assert share(labeled_points={"voxel": 1}, n_points=1) == {"voxel": 1.0}
    assert share(labeled_points={"voxel": 3}, n_points=0) == {"voxel": None}
    assert share(labeled_points={"voxel": 3}) == {"voxel": None}
    assert share() == {}


def test_format_result_tables_by_hand() -> None:
    data = _sequence(1)
    data["protocol_notes"] = {PAPER: "not computed: other classes"}
    data["coverage_ratio"] = {"point": 1.0, "voxel": 1.5}
    text = format_result_tables(_metrics(data))
    blocks = text.split("\n\n")
    assert len(blocks) == len(PROTOCOLS) + 2
    for block, desc in zip(blocks, PROTOCOLS.values(), strict=False):
        assert block.startswith(f"{desc}; 2D labels: simulated x1\n")
        assert "point" in block and "voxel" in block
    assert blocks[-2] == "paper protocol not computed: other classes"
    assert blocks[-1] == "voxel labels cover 1.50x as many points as projection alone"
    # A file's own description of a protocol wins; no coverage line without a ratio.
    data["protocols"] = {**data["protocols"], "all": "every point"}
    data.pop("coverage_ratio")
    data.pop("protocol_notes")
    text = format_result_tables(SequenceMetrics.from_dict(data))
    assert "\n\nevery point; 2D labels: simulated x1\n" in text and "cover" not in text
    data.pop("labeler")
    assert format_result_tables(SequenceMetrics.from_dict(data)).startswith(
        f"{PROTOCOLS['camera']}; 2D labels: ?\n"
    )


def test_unreadable_metrics_name_their_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"^metrics: unreadable metrics"):
        SequenceMetrics.from_dict({"rows": ROWS})
    with pytest.raises(DatasetError, match=r"^m\.json: unreadable metrics"):
        SequenceMetrics.from_dict({"rows": ROWS}, "m.json")
    path = SequenceLayout(tmp_path).metrics
    assert load_metrics(tmp_path) is None and result_tables(tmp_path) is None
    path.write_text(json.dumps({"rows": ROWS}))
    for read_run in (load_metrics, result_tables):
        with pytest.raises(DatasetError) as err:
            read_run(tmp_path)
        assert err.value.path == str(path)
    path.write_text(json.dumps(_sequence(1)))
    tables = load_metrics(tmp_path)
    assert tables is not None and list(tables) == list(PROTOCOLS)
    assert tables["camera"]["voxel"].confusion.tolist() == [[4, 1, 2], [0, 5, 1]]
    assert result_tables(tmp_path) == format_result_tables(_metrics(_sequence(1)))
    path.write_text("{not json")
    with pytest.raises(DatasetError) as err:
        result_tables(tmp_path)
    assert err.value.path == str(path)


def test_object_scores_round_trip_and_print() -> None:
    data = _sequence(1)
    data["objects"] = {
        "camera": {"PQ": 0.5, "PQ_things": 0.25, "PQ_stuff": 0.75, "SQ": 0.8, "RQ": 0.625},
        "all": {"PQ": 0.3, "PQ_things": None, "PQ_stuff": 0.3, "SQ": 0.6, "RQ": 0.5},
        "motion": {"mos_iou": 0.4, "s_assoc": 0.9, "moving_points": 12.0},
        "moving_right_class": {"a": 0.5},
    }
    m = _metrics(data)
    assert m.objects is not None and m.objects["motion"]["s_assoc"] == 0.9
    text = format_result_tables(m)
    assert "PQ_things              25.0           -" in text and "S_assoc" in text and "a 50.0" in text
    # A run's overall holds no object scores (they are per sequence).
    summed = overall_metrics({"s1": m})
    assert summed is not None and summed.objects is None
