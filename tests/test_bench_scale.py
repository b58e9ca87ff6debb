"""benchmarks/bench_scale.py: the fits, the extrapolation and the checks it prints, on made-up figures."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from scripthelpers import load_script

from leap_core.pipeline.stages import STAGES

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    return load_script("benchmarks/bench_scale.py")


def test_fits_recover_exact_laws(bench: ModuleType) -> None:
    x = np.array([60.0, 240.0, 1000.0])
    a, b = bench.power_law_fit(x, 3.0 * x**1.2)
    assert a == pytest.approx(3.0) and b == pytest.approx(1.2)
    a, b = bench.linear_fit(x, 5.0 + 64.0 * x)
    assert a == pytest.approx(5.0) and b == pytest.approx(64.0)
    assert all(math.isnan(v) for v in bench.power_law_fit(x[:1], x[:1]))
    assert bench.memory_target(1e6) == pytest.approx(1.5e9 + 64e6)
    assert bench.memory_target(1e6, cn=True) == pytest.approx(3.0e9 + 64e6)


def _result(frames: int, per_scan: dict[str, float], peak: float, voxels: int) -> dict[str, Any]:
    stages = {s: {"status": "skipped", "wall_s": 0.0, "cpu_s": 0.0, "voxels": None} for s in STAGES}
    for s, t in per_scan.items():
        stages[s] = {"status": "done", "wall_s": t * frames, "cpu_s": t * frames / 2, "voxels": None}
    stages["fuse"]["voxels"] = voxels
    cold = {
        "peak_rss_b": peak,
        "sampled_peak_rss_b": peak,
        "maxrss_b": peak,
        "wall_s": 1.0 * frames,
        "cpu_s": 0.5 * frames,
    }
    return {
        "frames": frames,
        "voxels": voxels,
        "points": 100 * frames,
        "stages": stages,
        "cold": cold,
        "before_stages_s": 1.0,
        "after_stages_s": 1.0,
    }


def test_analyse_checks_and_extrapolation(bench: ModuleType) -> None:
    # fuse: 10 ms per scan at every length; label_points doubles per scan from 60 to 1000 frames.
    lp = {60: 0.01, 240: 0.015, 1000: 0.02}
    results = [
        _result(n, {"labels2d": 0.1, "fuse": 0.01, "label_points": lp[n]}, 2e8 + 500.0 * 1000 * n, 1000 * n)
        for n in (1000, 60, 240)  # any order
    ]
    an = bench.analyse(results)
    assert an["three_d_stages"] == ["fuse", "label_points"]
    fuse = an["stages"]["fuse"]["wall_s"]
    assert fuse["fit_b"] == pytest.approx(1.0) and fuse["growth"] == pytest.approx(1.0)
    assert fuse["extrapolated_per_scan"] == pytest.approx(0.01)
    wall = an["totals"]["wall_s"]
    assert wall["three_d_per_scan"][-1] == pytest.approx(0.03)  # 10 + 20 ms at 1,000 frames
    assert wall["check1_budget_ok"] and not wall["check2_ok"]  # label_points grew 2x per scan
    assert wall["check2_growth"]["label_points"] == pytest.approx(2.0)
    cpu = an["totals"]["cpu_s"]
    assert cpu["three_d_per_scan"][-1] == pytest.approx(0.015)
    x = an["extrapolated"]
    assert x["voxels"] == pytest.approx(1000 * bench.FULL_SEQUENCE)
    assert an["fits"]["peak_rss_vs_voxels_linear"] == pytest.approx([2e8, 500.0])
    # 500 B per voxel against the target's 64: within it up to 1,000 frames, past it at 4,541.
    assert x["peak_rss_b_from_voxels"] == pytest.approx(2e8 + 500.0 * 1000 * bench.FULL_SEQUENCE)
    assert all(m["ok"] for m in an["memory"]) and not x["memory_ok"]
    tables = bench.report_tables({"results": results, "analysis": an})
    assert [t[0] for t in tables][-1] == "checks"
    assert "NO" in {row[-1] for row in tables[-1][2]}


def test_repeated_3d_stages_count_their_least_time(bench: ModuleType, tmp_path: Path) -> None:
    """--repeat: each 3D stage's figure is its least wall and CPU time over the runs; the stages before
    `fuse` ran once, so their figures are the cold run's; invalidate_3d_stages stales exactly the 3D
    stages' fingerprints."""

    def run(wall: float, cpu: float, early_cpu: float) -> dict[str, Any]:
        return {
            s: {
                "status": "done",
                "wall_s": wall if s != "labels2d" else 9.0,
                "cpu_s": cpu if s != "labels2d" else early_cpu,
                "peak_rss_b": 1,
                "voxels": 5,
            }
            for s in STAGES
            if s != "3dcn"
        } | {"3dcn": {"status": "skipped", "wall_s": 0.0, "cpu_s": math.nan, "peak_rss_b": 0, "voxels": None}}

    least = bench.least_of([run(3.0, 2.0, 7.0), run(1.0, 4.0, 0.0), run(2.0, 1.5, 0.0)])
    assert least["fuse"]["wall_s"] == 1.0 and least["fuse"]["cpu_s"] == 1.5
    assert least["export"]["wall_s"] == 1.0 and least["export"]["cpu_s"] == 1.5
    assert least["labels2d"]["cpu_s"] == 7.0 and least["project"]["wall_s"] == 3.0
    assert least["3dcn"]["status"] == "skipped"

    state = {s: {"status": "done", "fingerprint": "f"} for s in STAGES}
    (tmp_path / "stages.json").write_text(json.dumps(state))
    bench.invalidate_3d_stages(tmp_path)
    after = json.loads((tmp_path / "stages.json").read_text())
    first3d = STAGES.index("fuse")
    assert [after[s]["fingerprint"] == "f" for s in STAGES] == [i < first3d for i in range(len(STAGES))]
