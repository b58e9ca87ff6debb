"""Pure job bookkeeping: progress/ETA arithmetic and the corrections snapshot a run receives."""

from __future__ import annotations

import numpy as np
import pytest

from app.crud import Correction
from app.jobs.manager import corrections_for_run
from app.jobs.progress import ProgressTracker
from app.jobs.stages import OTHER_UNIT_SECONDS, UNIT_SECONDS
from leap_core.pipeline import STAGES


def test_stage_eta_percent_and_ordering() -> None:
    t = ProgressTracker.create(1, 1, ["a", "b", "c"], expected_seconds={"c": 4.0})
    t.set_status("running", "s0")
    assert t.update("a", 0, 10, now=100.0, stamp="s1")  # stage started
    assert not t.update("a", 4, 10, now=102.0, stamp="s2")
    snap = t.snapshot(now=102.0)
    a = snap["stages"][0]
    # 4 of 10 done in 2 s -> 2 * 6 / 4 = 3 s left, 5 s in all. b, a stage the cost table does not know,
    # is expected to take its 10 frames x OTHER_UNIT_SECONDS; c the 4 s of the previous run.
    b_cost = 10 * OTHER_UNIT_SECONDS
    assert a["eta_s"] == 3.0 and a["percent"] == 40.0 and a["status"] == "running"
    assert a["expected_s"] == 5.0 and snap["stages"][1]["expected_s"] == pytest.approx(b_cost)
    assert snap["percent"] == pytest.approx(100 * 5 * 0.4 / (5 + b_cost + 4), abs=0.05)
    assert snap["stage"] == "a"
    assert snap["eta_s"] == pytest.approx(3 + b_cost + 4, abs=0.05)
    assert t.update("a", 10, 10, now=105.0, stamp="s3")
    assert t.snapshot(now=105.0)["stages"][0]["seconds"] == 5.0
    # c starts without b reporting: b was skipped by the pipeline.
    t.update("c", 1, 2, now=106.0, stamp="s4")
    snap = t.snapshot(now=107.0)
    assert [s["status"] for s in snap["stages"]] == ["done", "skipped", "running"]
    # a took 5 s, b nothing, c 1 of 2 in 1 s (2 s in all): (5 + 0 + 2 * 0.5) / (5 + 0 + 2).
    assert snap["percent"] == pytest.approx(100 * 6 / 7, abs=0.05)
    assert snap["stages"][2]["eta_s"] == 1.0  # 1 of 2 in 1 s
    versions = snap["version"]
    t.set_status("done", "s5")
    assert t.snapshot()["percent"] == 100.0 and t.snapshot()["version"] == versions + 1


def test_sequences_running_at_once_keep_each_others_stages() -> None:
    """A multi-sequence run on Ray interleaves its sequences' reports: a stage of 01 starting closes
    nothing of 00; the joint 3D-CN (``*``) closes every stage before it, and is closed by any after it."""
    names = ["00/labels2d", "00/project", "01/labels2d", "01/project", "*/3dcn", "00/export", "01/export"]
    t = ProgressTracker.create(1, 1, names)
    t.set_status("running", "s0")
    t.update("00/labels2d", 1, 4, now=1.0, stamp="s1")
    t.update("01/labels2d", 1, 3, now=1.5, stamp="s2")
    t.update("00/labels2d", 4, 4, now=2.0, stamp="s3")
    t.update("01/project", 1, 3, now=2.5, stamp="s4")  # 01/labels2d ends unreported, 00/project waits
    status = {s["name"]: s["status"] for s in t.snapshot(now=3.0)["stages"]}
    assert status == {
        "00/labels2d": "done",
        "00/project": "pending",
        "01/labels2d": "done",
        "01/project": "running",
        "*/3dcn": "pending",
        "00/export": "pending",
        "01/export": "pending",
    }
    t.update("00/project", 2, 4, now=3.0, stamp="s5")
    assert t.snapshot(now=3.0)["stages"][1]["status"] == "running"
    t.update("*/3dcn", 0, 10, now=4.0, stamp="s6")
    t.update("01/export", 1, 3, now=5.0, stamp="s7")
    status = {s["name"]: s["status"] for s in t.snapshot(now=5.0)["stages"]}
    assert status["00/project"] == status["01/project"] == status["*/3dcn"] == "done"
    assert status["00/export"] == "pending" and status["01/export"] == "running"


def test_run_eta_adds_expected_seconds_of_pending_stages() -> None:
    t = ProgressTracker.create(1, 1, ["a", "b"], expected_seconds={"b": 7.5})
    t.set_status("running", "s")
    t.update("a", 1, 4, now=0.0, stamp="s")
    t.update("a", 2, 4, now=2.0, stamp="s")  # elapsed 2 s for 2 of 4 -> 2 s left
    assert t.snapshot(now=2.0)["eta_s"] == 9.5


def test_the_run_percent_weights_stages_by_their_cost() -> None:
    """labels2d takes most of a simulated run's time: 93 of its 100 frames done is most of the run, not
    the 12 % that weighing the 8 stages equally gave."""
    names = [f"00/{s}" for s in STAGES]
    t = ProgressTracker.create(1, 1, names, labeler_input="gt2d")
    t.set_status("running", "s")
    t.update("00/labels2d", 0, 100, now=0.0, stamp="s")
    # At the expected rate (UNIT_SECONDS["labels2d"] a frame) the stages to come weigh their table costs.
    now = 93 * UNIT_SECONDS["labels2d"]
    t.update("00/labels2d", 93, 100, now=now, stamp="s")
    snap = t.snapshot(now=now)
    rest = sum(100 * UNIT_SECONDS[s] for s in STAGES if s != "labels2d")
    whole = 100 * UNIT_SECONDS["labels2d"] + rest
    assert snap["percent"] == pytest.approx(100 * now / whole, abs=0.05)
    assert snap["percent"] > 60  # equal weights: 100 * 0.93 / 8 = 11.6
    # A first run (no previous times) has an ETA from the stage's own rate and the costs to come.
    assert snap["eta_s"] == pytest.approx(7 * UNIT_SECONDS["labels2d"] + rest, abs=0.05)


def test_stages_to_come_are_scaled_by_the_measured_speed() -> None:
    """On a machine twice as slow as the cost table, the finished 3D stages say so and the stages to come
    are expected to take twice their cost; labels2d (labeler- and device-bound) does not count."""
    t = ProgressTracker.create(1, 1, ["00/labels2d", "00/project", "00/fuse", "00/export"])
    t.set_status("running", "s")
    t.update("00/labels2d", 0, 10, now=0.0, stamp="s")
    t.update("00/labels2d", 10, 10, now=50.0, stamp="s")  # 5 s a frame: not a measure of the machine
    t.update("00/project", 0, 10, now=50.0, stamp="s")
    project = 2 * 10 * UNIT_SECONDS["project"]
    t.update("00/project", 10, 10, now=50.0 + project, stamp="s")
    t.update("00/fuse", 0, 10, now=50.0 + project, stamp="s")
    assert t.speed() == pytest.approx(2.0)
    snap = t.snapshot(now=50.0 + project)
    assert snap["stages"][3]["expected_s"] == pytest.approx(2 * 10 * UNIT_SECONDS["export"], abs=1e-3)
    # fuse started but has no rate yet: its expected seconds, then export's.
    assert snap["eta_s"] == pytest.approx(2 * 10 * (UNIT_SECONDS["fuse"] + UNIT_SECONDS["export"]), abs=0.05)


def test_no_eta_before_any_stage_has_a_rate() -> None:
    t = ProgressTracker.create(1, 1, ["00/labels2d", "00/project"])
    t.set_status("running", "s")
    t.update("00/labels2d", 0, 10, now=0.0, stamp="s")
    assert t.snapshot(now=1.0)["eta_s"] is None
    t.update("00/labels2d", 1, 10, now=2.0, stamp="s")
    assert t.snapshot(now=2.0)["eta_s"] == pytest.approx(18 + 10 * UNIT_SECONDS["project"], abs=0.06)


def test_record_round_trip_and_interrupted_stage() -> None:
    t = ProgressTracker.create(3, 2, ["a", "b"])
    t.set_status("running", "s")
    t.update("a", 2, 2, now=0.0, stamp="s")
    t.update("b", 1, 5, now=1.0, stamp="s")
    back = ProgressTracker.from_record(3, 2, "interrupted", t.stages_record(), ["a", "b"], error="stopped")
    snap = back.snapshot(now=2.0)
    assert [s["status"] for s in snap["stages"]] == ["done", "cancelled"]
    assert snap["stages"][1]["done"] == 1 and snap["error"] == "stopped" and snap["status"] == "interrupted"


def _corr(i: int, name: str, keys: list[int], size: float = 0.2) -> Correction:
    return Correction(i, 1, "t", name, size, np.array(keys, np.int64), True)


def test_corrections_snapshot_later_wins_and_stale_ones_drop() -> None:
    schema = {"classes": [{"name": "car"}, {"name": "road"}, {"name": "pole"}]}
    pipeline = {"fusion": {"voxel_size": 0.2}}
    corrections = [
        _corr(1, "car", [30, 10, 20]),
        _corr(2, "pole", [20, 40]),  # later: voxel 20 becomes pole
        _corr(3, "gone", [50]),  # class no longer in the schema
        _corr(4, "road", [60], size=0.5),  # made on another voxel size
    ]
    keys, cls = corrections_for_run(corrections, schema, pipeline)
    assert keys.dtype == np.int64 and cls.dtype == np.int16
    assert keys.tolist() == [10, 20, 30, 40] and cls.tolist() == [0, 2, 0, 2]
    empty_keys, empty_cls = corrections_for_run([], schema, pipeline)
    assert empty_keys.shape == (0,) and empty_cls.shape == (0,)
