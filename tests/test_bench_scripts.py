"""Every benchmark script in benchmarks/ runs in its smallest mode, so none stops working unnoticed (a
baseline commit whose config no longer parses, a renamed function, a changed result layout).

bench_2d.py and bench_poses.py have their own tests (tests/test_bench_2d.py, tests/test_bench_poses.py);
:func:`test_every_benchmark_script_has_a_smoke_run` keeps this list complete. Each run writes its result
file into a temporary folder (``$LEAP_BENCH_RESULTS``), never over a real run's figures, and is checked for
the table or line that shows it measured against its same-process baseline.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from scripthelpers import ROOT

from leap_core.synth import SynthConfig, generate_sequence

BENCH = ROOT / "benchmarks"
OWN_TESTS = {"bench_2d.py", "bench_poses.py"}
"""Scripts whose smallest mode a test file of their own runs."""
BASELINE_COMMIT = "c472ae0"
"""The baseline commit of bench_scan.py and bench_memory.py (checked out from git)."""
BASELINES = {"bench_scan.py": BASELINE_COMMIT, "bench_memory.py": BASELINE_COMMIT, "bench_3dcn.py": "25c0286"}
"""The scripts that import a baseline commit from git, and that commit (their default)."""

SEQ = "{seq}"
"""Stands for the generated 2-frame sequence in a command line."""
SMOKE: dict[str, tuple[list[str], str]] = {
    # script: (smallest command line, text its output must hold)
    "bench_3dcn.py": (["--quick"], "this tree, float32"),
    "bench_app_load.py": (["--quick"], "ratio load / baseline"),
    "bench_check.py": (["--frames", "20", "--repeat", "1"], "check / open"),
    "bench_fusion.py": (["--quick"], "Ratio to the best same-work baseline"),
    # Printed only when every stage and the 3D-CN round's three phases were measured.
    "bench_gpu.py": (["--quick"], "x the target of at most 30 min on one H100"),
    "bench_objects.py": (["--quick"], "tracks stage ms/scan"),
    "bench_lidar_model.py": (["--quick"], "ratio model / baseline time"),
    "bench_memory.py": (["--sequence", SEQ], f"baseline = {BASELINE_COMMIT}"),
    "bench_models.py": (["--quick"], "ratio = total compute"),
    "bench_pipeline.py": (["--sequence", SEQ], "second run, all cached"),
    "bench_ray.py": (["--sequence", SEQ, "--frames", "0:2", "--repeat", "1"], "ray / local"),
    "bench_rig.py": (["--quick"], "cameras / 1 camera"),
    "bench_scale.py": (["--frames", "2", "--seeds", "0", "--repeat", "1", "--no-cached"], "checks"),
    "bench_scan.py": (["--quick"], "outputs identical: yes"),
    "bench_synth.py": (["--quick"], "brute force (baseline)"),
    "bench_viewer_tabs.py": (["--quick"], "each further tab"),
    "bench_viewer.py": (
        [
            "--voxels",
            "20000",
            "--repeats",
            "1",
            "--apply-frames",
            "2",
            "--apply-points",
            "5000",
            "--budget",
            "10000",
        ],
        "worst server time",
    ),
}
SLOW = {"bench_gpu.py"}
"""Scripts whose smallest run takes 10 s or more on 2 cores (``scripts/test.sh --fast`` skips them)."""
NEEDS = {
    "bench_ray.py": "ray",
    "bench_memory.py": "psutil",
    "bench_scale.py": "psutil",
    "bench_app_load.py": "httpx",
}
"""Optional packages (extras) a script needs: without them its run is skipped, as the extras' tests are."""


def _has_commit(commit: str) -> bool:
    probe = ["git", "-C", str(ROOT), "cat-file", "-e", f"{commit}^{{commit}}"]
    return subprocess.run(probe, capture_output=True, check=False).returncode == 0


def test_every_benchmark_script_has_a_smoke_run() -> None:
    scripts = {p.name for p in BENCH.glob("bench_*.py")}
    assert scripts == set(SMOKE) | OWN_TESTS


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("bench_seq")
    return generate_sequence(root, SynthConfig(frames=2)).path


@pytest.mark.parametrize(
    "script", [pytest.param(s, marks=pytest.mark.slow) if s in SLOW else s for s in sorted(SMOKE)]
)
def test_benchmark_smallest_mode_runs(script: str, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    args, expected = SMOKE[script]
    if script in NEEDS and importlib.util.find_spec(NEEDS[script]) is None:
        pytest.skip(f"{NEEDS[script]} not installed (an optional extra)")
    baseline = BASELINES.get(script)
    if baseline is not None and not _has_commit(baseline):
        pytest.skip(f"baseline commit {baseline} of {script} not in this clone's history")
    if SEQ in args:
        seq = request.getfixturevalue("tiny_sequence")
        args = [str(seq) if a == SEQ else a for a in args]
    results = tmp_path / "results"
    proc = subprocess.run(
        [sys.executable, str(BENCH / script), *args],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        cwd=tmp_path,
        env={**os.environ, "LEAP_BENCH_RESULTS": str(results), "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert expected in proc.stdout, proc.stdout[-3000:]
    written = sorted(results.glob("*.json"))
    assert written, f"{script} wrote no result file into $LEAP_BENCH_RESULTS"
    for path in written:
        assert isinstance(json.loads(path.read_text()), dict)
    assert not list(BENCH.glob("results/.*.tmp"))
