"""benchmarks/bench_poses.py in its smallest mode: both estimators on a generated drive, a table and the
result file."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from scripthelpers import ROOT


def test_bench_poses_quick_compares_both_estimators(tmp_path: Path) -> None:
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "bench_poses.py"),
            "--quick",
            "--results-dir",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "KISS-ICP (previous)" in proc.stdout and "+ pose graph (current)" in proc.stdout
    doc = json.loads((tmp_path / "bench_poses_quick.json").read_text())
    (seq,) = doc["sequences"]
    assert seq["sequence"] == "tiny" and seq["frames"] == 12
    previous, current = seq["estimators"]["KISS-ICP (previous)"], seq["estimators"]["+ pose graph (current)"]
    assert previous["method"] == "kiss-icp" and current["method"] == "kiss-icp+pose-graph"
    for e in (previous, current):
        assert e["segment_lengths_m"][0] == 1.0 and e["ms_per_scan"] > 0 and e["residual_median_m"] > 0
    assert current["drift_pct"] <= 1.0 and abs(current["first_step_ratio"] - 1.0) <= 0.1
    assert current["residual_median_m"] < previous["residual_median_m"]
