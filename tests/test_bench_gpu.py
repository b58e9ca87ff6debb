"""benchmarks/bench_gpu.py's figures on made-up spans: the stage windows its progress callback opens, the
3D-CN round's phases from the round's own reports, the extrapolation to 4,541 frames and the GPU busy
share (its smallest run is in tests/test_bench_scripts.py)."""

from __future__ import annotations

import sys
from types import ModuleType
from typing import Any

import pytest
from scripthelpers import ROOT, load_script

from leap_core.config import PipelineConfig
from leap_core.pipeline.run import JOINT
from leap_core.pipeline.stages import STAGES


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    return load_script("benchmarks/bench_gpu.py")


def round_meter(bench: ModuleType, n: int, steps: int, stop_at: int | None = None) -> Any:
    """A meter holding a round of ``n`` scans and ``steps`` steps as the pipeline reports it: unit u done at
    100 + u/10 s, in thousandths of the round; a finished round's last report comes after its smoothing,
    5 s after its last unit. ``stop_at``: the round stopped after that many units."""
    total = 2 * n + steps
    last = total if stop_at is None else stop_at
    meter = bench.Meter(cuda=False)
    meter.marks = [(100 + u / 10, u * 1000 // total) for u in range(1, last + 1)]
    end = 100 + last / 10
    if stop_at is None:
        end += 5
        meter.marks.append((end, 1000))
    meter.windows = [bench.Window("3dcn round", 99.0, end)]
    return meter


def test_round_phases_split_selection_training_and_inference(bench: ModuleType) -> None:
    phases = bench.round_phases(round_meter(bench, 300, 500), 300, 500)
    got = [(w.t0, w.t1, units, done) for w, units, done in phases]
    assert got == [(99.0, 130.0, 300, True), (130.0, 180.0, 500, True), (180.0, 215.0, 300, True)]


def test_a_round_stopped_in_training_keeps_its_seconds_per_step(bench: ModuleType) -> None:
    phases = bench.round_phases(round_meter(bench, 300, 500, stop_at=600), 300, 500)
    assert [done for _, _, done in phases] == [True, False]
    training, steps, _ = phases[1]
    assert (training.t0, training.t1) == (130.0, 160.0)
    assert abs(steps - 300) <= 1  # thousandths of 1,100 units: within one unit


def test_rows_extrapolate_per_frame_and_training_by_its_step_rule(bench: ModuleType) -> None:
    meter = round_meter(bench, 300, 500)
    meter.windows += [bench.Window("2D baseline", 0.0, 8.0), bench.Window("2D batched", 8.0, 68.0)]
    records = {s: {"status": "done", "seconds": 3.0} for s in STAGES}
    records["motion"] = {"status": "skipped", "seconds": 0.0}
    rows = {
        r.name: r
        for r in bench.table_rows(meter, records, 300, PipelineConfig(), {"baseline": 16, "batched": 300})
    }
    assert rows["2D baseline"].per_unit == 0.5 and not rows["2D baseline"].in_whole
    assert rows["2D batched"].minutes_at_length == pytest.approx(0.2 * 4541 / 60)
    assert rows["fuse"].minutes_at_length == pytest.approx(3.0 / 300 * 4541 / 60)
    assert "motion" not in rows
    # 500 steps at 300 scans (min_steps), one per scan at 4,541: the training grows 9.1x, not 15.1x
    assert rows["3D-CN training (500 steps)"].minutes_at_length == pytest.approx(0.1 * 4541 / 60)
    assert rows["3D-CN selection (300 scans)"].minutes_at_length == pytest.approx(31 / 300 * 4541 / 60)
    assert bench.not_reached(records, list(rows.values())) == []
    del records["export"]
    assert bench.not_reached(records, list(rows.values())) == ["export"]


def test_windows_tile_the_run_and_only_the_round_marks_its_phases(bench: ModuleType) -> None:
    meter = bench.Meter(cuda=False)
    reports = [("00", "labels2d", 0, 2), ("00", "labels2d", 2, 2), ("00", "smooth", 1, 1)]
    reports += [(JOINT, "3dcn", 500, 1000), (JOINT, "3dcn", 1000, 1000), ("00", "labels2d", 2, 2)]
    times = []
    for report in reports:
        meter.report(*report)
        times.append(meter.last_report)
    meter.close()
    assert [w.name for w in meter.windows] == ["labels2d", "smooth", "3dcn round", "labels2d"]
    # A stage's window opens at the previous stage's last report: the work before its own first report
    # (the round's first one comes after its first scan's selection) is its own.
    assert [w.t0 for w in meter.windows[1:]] == [times[1], times[2], times[4]]
    assert all(a.t1 == b.t0 for a, b in zip(meter.windows, meter.windows[1:], strict=False))
    assert [th for _, th in meter.marks] == [500, 1000]
    assert all(w.peak_rss_gib and w.peak_gpu_gib is None for w in meter.windows)


def test_busy_share_averages_the_samples_inside_the_windows(bench: ModuleType) -> None:
    windows = [bench.Window("fuse", 10.0, 20.0), bench.Window("fuse", 30.0, 31.0)]
    assert bench.busy_share(windows, None) == "no GPU"
    sampler = bench.GpuSampler(0.25)
    sampler.source = "nvidia-smi"
    sampler.samples = [
        (5.0, 90.0, 1.0),
        (12.0, 40.0, 1.0),
        (19.0, 20.0, 1.0),
        (30.5, 60.0, 1.0),
        (40.0, 99.0, 1.0),
    ]
    assert bench.busy_share(windows, sampler) == pytest.approx(40.0)
    assert bench.busy_share([bench.Window("smooth", 21.0, 22.0)], sampler) == "-"
    sampler.source = ""
    assert bench.busy_share(windows, sampler) == "not sampled"
