"""benchmarks/bench_2d.py in its smallest mode: both 2D engines through their labelers with the tiny
random models, a table with the same-process ratio and the result file."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from scripthelpers import ROOT


def test_bench_2d_quick_times_both_engines(tmp_path: Path) -> None:
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "bench_2d.py"),
            "--quick",
            "--frames",
            "1",
            "--batches",
            "1,2",
            # The bare preset's 19 prompts and few regions: the code paths of the 91-prompt default at a
            # fifth of the time (the smoke test times nothing).
            "--schema",
            "semantickitti_bare",
            "--boxes",
            "8",
            "--results-dir",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "ratio = Grounding DINO-T + SAM fp32 batch 1 / row" in proc.stdout
    rows = json.loads((tmp_path / "bench_2d_quick.json").read_text())["rows"]
    assert [(r["engine"], r["batch"]) for r in rows] == [
        ("Grounding DINO-T + SAM", 1),
        ("Grounding DINO-T + SAM", 2),
        ("SAM 3", 1),
        ("SAM 3", 2),
    ]
    sam3 = rows[2]
    assert sam3["passes"]["vision encoder"] == 2 and sam3["passes"]["prompt"] > 0  # warm-up + 1 timed
    assert all(r["s_per_frame"] > 0 and r["sequence_min"] > 0 for r in rows)
