"""lab/fit_labeler.py: its in-process point row is the pipeline's, and its fit's pieces."""

from __future__ import annotations

import math
from pathlib import Path

import labfixtures
import numpy as np
import pytest
from runhelpers import label

from lab import fit_labeler
from lab.paper_labeler import SimulatedPaperConfig
from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import KittiSequence
from leap_core.schema import builtin_schema
from tests.test_pipeline import make_street

lab_labeler = labfixtures.lab_labeler  # registers the lab's labeler for each test here


def test_point_confusion_is_the_runs_camera_point_row(tmp_path: Path) -> None:
    # The fit iterates on point_confusion instead of whole runs: it must count what the evaluate stage
    # counts for the "point" row (camera view), here with the paper preset's noise.
    street = make_street(tmp_path / "sequences" / "00", n_frames=3)
    schema = builtin_schema("semantickitti")
    cfg = fit_labeler.with_labeler(PipelineConfig(), SimulatedPaperConfig.from_preset("paper"))
    assert cfg.labeler == "simulated-paper"
    metrics = label(street, schema, cfg, tmp_path / "run", until="evaluate").metrics
    assert metrics is not None
    conf = fit_labeler.point_confusion(KittiSequence(street), schema, cfg)
    assert conf.sum() > 0
    np.testing.assert_array_equal(conf, metrics.table("camera")["point"].confusion_matrix)
    row = fit_labeler.paper_row(conf, schema)
    paper = metrics.table("paper")["point"].iou
    compared = [name for name, v in row.items() if not math.isnan(v)]
    assert compared
    for name in compared:
        assert row[name] == pytest.approx(100.0 * paper[name])


def test_misfit_and_paper_miou_use_only_present_classes() -> None:
    row = dict.fromkeys(fit_labeler.PAPER_POINT, math.nan)
    row.update({"car": 80.2, "road": 87.1})  # car 3 above the paper, road on it
    err, present = fit_labeler.misfit(row)
    assert present == ["car", "road"]
    assert fit_labeler.paper_miou(present) == pytest.approx((77.2 + 87.1) / 2)
    # (3)² for car, 0 for road, and the mIoU is 1.5 above the paper's over these two.
    assert err == pytest.approx(9.0 + 1.5**2)


def test_mean_row_averages_each_class_over_the_sequences_that_contain_it() -> None:
    rows = [
        {"car": 80.0, "bicycle": math.nan, "person": math.nan},
        {"car": 60.0, "bicycle": 20.0, "person": math.nan},
    ]
    got = fit_labeler.mean_row(rows)
    assert got["car"] == pytest.approx(70.0) and got["bicycle"] == pytest.approx(20.0)
    assert math.isnan(got["person"])


def test_paper_config_spreads_a_merged_class_q_over_its_members() -> None:
    cfg = fit_labeler.paper_config({"manmade": 0.4, "car": 0.0}, SimulatedPaperConfig())
    # Person's confusion is fixed (LEAK_FITTED), and with no q for it, none of its masks leak: its 0 and
    # car's stay in the table, or the global box_leak_prob would apply to them instead.
    manmade = {"building": 0.4, "fence": 0.4, "pole": 0.4, "traffic-sign": 0.4}
    assert cfg.class_confusion == {**manmade, "person": 0.1}
    assert cfg.class_box_leak == {"car": 0.0, "person": 0.0}
    assert cfg.confusion_prob == 0.0 and cfg.confusion_targets == fit_labeler.TARGETS


def test_paper_config_fits_the_box_leak_of_leak_fitted_classes() -> None:
    assert fit_labeler.LEAK_FITTED == {"person": 0.1, "car": 0.0}
    cfg = fit_labeler.paper_config(
        {"person": 0.35, "car": 0.05, "other-vehicle": 0.2}, SimulatedPaperConfig()
    )
    # Person's and car's q are their members' box-leak probabilities; their confusions stay at the fixed
    # values (0 leaves car out of the table); other-vehicle's q is its members' confusion.
    assert cfg.class_box_leak == {"person": 0.35, "car": 0.05}
    assert cfg.class_confusion["person"] == 0.1 and "car" not in cfg.class_confusion
    assert cfg.class_confusion["other-vehicle"] == cfg.class_confusion["truck"] == 0.2
    assert "truck" not in cfg.class_box_leak
    # The fixed terms come with it: stratified draws are on.
    assert cfg.stratified_draws
    # A warm start reads the q back from the same places: the committed preset round-trips.
    q = fit_labeler.preset_q()
    paper = SimulatedPaperConfig.from_preset("paper")
    again = fit_labeler.paper_config(q, paper)
    assert (again.class_box_leak, again.class_confusion) == (paper.class_box_leak, paper.class_confusion)


def test_in_band_names_the_classes_and_the_miou_outside_the_bands() -> None:
    row = dict.fromkeys(fit_labeler.PAPER_POINT, math.nan)
    row.update({"car": 82.2, "road": 87.1})  # car 5.0 above the paper's: on the edge, inside
    assert fit_labeler.in_band(row) == []
    row["car"] = 82.3  # 5.1 above, and the mIoU 2.55 above the paper's over car and road: inside
    assert fit_labeler.in_band(row) == ["car"]
    row.update({"car": 81.0, "road": 90.5})  # 3.8 and 3.4 above: each inside, the mIoU 3.6 above: outside
    assert fit_labeler.in_band(row) == ["mIoU"]
    row.update({"bicycle": 10.0})  # 15.5 below; the mIoU over three classes is then within 3
    assert fit_labeler.in_band(row) == ["bicycle"]


def test_best_round_prefers_a_round_within_the_bands_to_a_smaller_misfit() -> None:
    paper = fit_labeler.PAPER_POINT
    rows = [
        {"car": paper["car"] + 5.5, "road": paper["road"]},  # car out by 0.5; misfit 5.5² + 2.75²
        {"car": paper["car"] + 4.9, "road": paper["road"] - 4.9},  # in every band; misfit 2 · 4.9²
        {"car": paper["car"] - 9.0, "road": paper["road"]},
    ]  # out
    assert fit_labeler.misfit(rows[0])[0] < fit_labeler.misfit(rows[1])[0]
    assert fit_labeler.best_round(rows) == 1
    # Among rounds within the bands, the smaller misfit; with none within them, the smallest misfit.
    assert fit_labeler.best_round([*rows, {"car": paper["car"] + 1.0, "road": paper["road"]}]) == 3
    assert fit_labeler.best_round([rows[0], rows[2]]) == 0


def test_spread_counts_each_class_over_the_rows_that_contain_it() -> None:
    paper = fit_labeler.PAPER_POINT
    nan = math.nan
    rows = [
        {"car": paper["car"] + 4.0, "bicycle": nan, "mIoU": (paper["car"] + 4.0)},
        {"car": paper["car"] - 6.0, "bicycle": 20.0, "mIoU": (paper["car"] - 6.0 + 20.0) / 2},
    ]
    got = fit_labeler.spread(rows)
    # car: mean paper − 1, std 5, within ±5 in the first row only; bicycle: one row, 5.5 below: outside.
    assert got["car"] == pytest.approx((paper["car"] - 1.0, 5.0, 1, 2))
    assert got["bicycle"] == pytest.approx((20.0, 0.0, 0, 1))
    # mIoU: row 1 is 4 above the paper's car alone (outside ±3); row 2 is (−6 − 5.5) / 2 = −5.75 below the
    # paper's mean over car and bicycle (outside).
    assert got["mIoU"][2:] == (0, 2)


def test_seed_list_reads_ranges_and_lists() -> None:
    assert fit_labeler._seed_list("0-3") == [0, 1, 2, 3]
    assert fit_labeler._seed_list("2,5") == [2, 5] and fit_labeler._seed_list("4") == [4]


def test_a_missing_sequence_is_named_not_a_traceback(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=f"fit_labeler: {tmp_path / 'nope'}: dataset folder does not exist"):
        fit_labeler.main(["--report", str(tmp_path / "nope")])
    with pytest.raises(SystemExit, match="dataset folder does not exist"):
        fit_labeler.main([str(tmp_path / "nope")])


def test_the_preset_file_the_fit_writes_reads_back_to_its_config(tmp_path: Path) -> None:
    import runpy

    paper = SimulatedPaperConfig.from_preset("paper")
    row = dict.fromkeys(fit_labeler.PAPER_POINT, math.nan)
    row.update({"car": 77.6, "road": 86.6})
    path = tmp_path / "paper_preset.py"
    fit_labeler._write_preset(paper, row, "a test sequence", path)
    assert SimulatedPaperConfig(**runpy.run_path(str(path))["PAPER_PRESET"]) == paper
    text = path.read_text()
    assert "Fitted on a test sequence" in text and "    car             77.2   77.6" in text
    # The committed preset is the writer's text for its own values (the fit's figures above aside).
    body = text[text.index("from typing import Any") :]
    committed = fit_labeler.PRESET_FILE.read_text()
    assert committed[committed.index("from typing import Any") :] == body
