"""benchmarks/fit_labeler.py: its in-process point row is the pipeline's, and its fit's pieces."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import KittiSequence
from leap_core.labelers.simulated import SimulatedLabelerConfig
from leap_core.pipeline import run_pipeline
from leap_core.schema import builtin_schema
from tests.test_pipeline import make_street

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import fit_labeler


def test_point_confusion_is_the_runs_camera_point_row(tmp_path: Path) -> None:
    # The fit iterates on point_confusion instead of whole runs: it must count what the evaluate stage
    # counts for the "point" row (camera view), here with the paper preset's noise.
    street = make_street(tmp_path / "sequences" / "00", n_frames=3)
    schema = builtin_schema("semantickitti")
    cfg = dataclasses.replace(PipelineConfig(), simulated=SimulatedLabelerConfig.from_preset("paper"))
    metrics = run_pipeline(street, schema, cfg, tmp_path / "run", until="evaluate").metrics
    assert metrics is not None
    conf = fit_labeler.point_confusion(KittiSequence(street), schema, cfg)
    assert conf.sum() > 0
    np.testing.assert_array_equal(conf, np.asarray(metrics["camera"]["point"]["confusion"]))
    row = fit_labeler.paper_row(conf, schema)
    paper = metrics["paper"]["point"]["iou"]
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
    rows = [{"car": 80.0, "bicycle": math.nan, "person": math.nan},
            {"car": 60.0, "bicycle": 20.0, "person": math.nan}]
    got = fit_labeler.mean_row(rows)
    assert got["car"] == pytest.approx(70.0) and got["bicycle"] == pytest.approx(20.0)
    assert math.isnan(got["person"])


def test_paper_config_spreads_a_merged_class_q_over_its_members() -> None:
    cfg = fit_labeler.paper_config({"manmade": 0.4, "car": 0.0}, SimulatedLabelerConfig())
    # Person's confusion is fixed (LEAK_FITTED), and with no q for it, none of its masks leak: its 0 and
    # car's stay in the table, or the global box_leak_prob would apply to them instead.
    manmade = {"building": 0.4, "fence": 0.4, "pole": 0.4, "traffic-sign": 0.4}
    assert cfg.class_confusion == {**manmade, "person": 0.1}
    assert cfg.class_box_leak == {"car": 0.0, "person": 0.0}
    assert cfg.confusion_prob == 0.0 and cfg.confusion_targets == fit_labeler.TARGETS


def test_paper_config_fits_the_box_leak_of_leak_fitted_classes() -> None:
    assert fit_labeler.LEAK_FITTED == {"person": 0.1, "car": 0.0}
    cfg = fit_labeler.paper_config({"person": 0.35, "car": 0.05, "other-vehicle": 0.2},
                                   SimulatedLabelerConfig())
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
    paper = SimulatedLabelerConfig.from_preset("paper")
    again = fit_labeler.paper_config(q, paper)
    assert (again.class_box_leak, again.class_confusion) == (paper.class_box_leak, paper.class_confusion)
