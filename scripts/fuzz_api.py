"""Fuzz the live API with schemathesis: no 500s, and no status code the OpenAPI schema does not declare.

Starts a real server (``python -m app.main``, real SQLite, a fresh temporary work folder, 127.0.0.1),
runs ``schemathesis run`` against its ``/api/v1/openapi.json`` with the checks ``not_a_server_error``
and ``status_code_conformance`` (every phase: examples, coverage, fuzzing, stateful), and prints how
many HTTP requests were sent, the status codes they got and the failures found.

Every operation is fuzzed except ``GET /runs/{run_id}/events``: it streams until its run ends, which a
fuzzer cannot wait for (its parameters are the run id, covered by ``tests/app/test_validation.py``).
Before fuzzing, project 1 and its finished run 1 are created on a tiny demo street (2 frames, 16 beams);
runs the fuzzer starts work on the same street, one at a time.

Usage (the acceptance run needs ≥ 2,000 requests; the count varies with the timing of the runs it starts)::

    .venv/bin/python scripts/fuzz_api.py --max-examples 60 --seed 1    # 5,749 requests, 1 min on 2 cores
    .venv/bin/python scripts/fuzz_api.py --max-examples 5 --seed 1     # what the test runs: 3,333, about 30 s

Exit status 0 when no failure was found. The HAR file of every request and schemathesis's JSON report
are kept in ``--report-dir`` (default: a temporary folder, printed).
"""

from __future__ import annotations

import argparse
import collections
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "app"))

from serverproc import Server  # noqa: E402  # the test suite's real-server helper, found via sys.path

CHECKS = "not_a_server_error,status_code_conformance"
EXCLUDED_PATHS = ("/api/v1/runs/{run_id}/events",)
TINY_DEMO = {
    "frames": 2,
    "shadows": False,
    "lidar": {"beams": 16, "azimuth_step_deg": 0.8},
    "camera": {"width": 310, "height": 94, "fx": 180.0, "fy": 180.0, "cx": 155.0, "cy": 47.0},
}


@dataclass
class FuzzResult:
    requests: int
    """HTTP requests schemathesis sent (entries of its HAR report)."""
    statuses: dict[int, int]
    """Response status → count."""
    failures: list[dict[str, object]] = field(default_factory=list)
    """schemathesis's failure summaries (type, code, operations)."""
    errors: list[object] = field(default_factory=list)
    """Errors of the run itself (network failures, schema problems)."""
    exit_code: int = 0
    output: str = ""

    @property
    def server_errors(self) -> int:
        return sum(n for status, n in self.statuses.items() if status >= 500)


def run_schemathesis(base: str, report_dir: Path, *, max_examples: int, seed: int) -> FuzzResult:
    """Fuzz the server at ``base`` (``http://127.0.0.1:PORT``); reports go to ``report_dir``."""
    schemathesis = Path(sys.executable).with_name("schemathesis")
    command = [
        str(schemathesis) if schemathesis.exists() else "schemathesis",
        "run",
        f"{base}/api/v1/openapi.json",
        "--checks",
        CHECKS,
        "--max-examples",
        str(max_examples),
        "--seed",
        str(seed),
        "--workers",
        "1",
        "--request-timeout",
        "30",
        "--report",
        "har,json",
        "--report-har-path",
        str(report_dir / "requests.har"),
        "--report-json-path",
        str(report_dir / "report.json"),
        "--no-color",
    ]
    for path in EXCLUDED_PATHS:
        command += ["--exclude-path", path]
    # In the report folder: schemathesis keeps a crash cache in ./.schemathesis and replays it next time;
    # each run should stand on its own seed.
    proc = subprocess.run(command, capture_output=True, text=True, check=False, cwd=report_dir)
    har = json.loads((report_dir / "requests.har").read_text())
    statuses = collections.Counter(int(e["response"]["status"]) for e in har["log"]["entries"])
    report = json.loads((report_dir / "report.json").read_text())
    return FuzzResult(
        requests=sum(statuses.values()),
        statuses=dict(sorted(statuses.items())),
        failures=list(report.get("failures") or []),
        errors=list(report.get("errors") or []),
        exit_code=proc.returncode,
        output=proc.stdout + proc.stderr,
    )


def seed_project(server: Server, timeout: float = 600.0) -> None:
    """Project 1 (the tiny demo street) with a finished run 1, so that the id 1, which the fuzzer tries
    as the smallest valid id, reaches each operation's real work (exports, metrics, classes, viewer)."""
    with server.client() as client:
        project = client.post("/projects", json={"name": "fuzz", "dataset": {"kind": "demo"}})
        project.raise_for_status()
        run = client.post(f"/projects/{project.json()['id']}/runs")
        run.raise_for_status()
        deadline = time.monotonic() + timeout
        while client.get(f"/runs/{run.json()['id']}").json()["status"] not in ("done", "failed"):
            if time.monotonic() > deadline:
                raise RuntimeError(f"the seed run did not finish within {timeout} s; see {server.log}")
            time.sleep(0.5)


def fuzz_live_server(
    work: Path, *, max_examples: int, seed: int, report_dir: Path | None = None
) -> FuzzResult:
    """Start a server with its data root and work folder under ``work``, fuzz it, stop it."""
    data = work / "data"
    data.mkdir(parents=True, exist_ok=True)
    reports = report_dir or work / "reports"
    reports.mkdir(parents=True, exist_ok=True)
    server = Server(
        data,
        extra_env={
            "LEAP_PREWARM_WORKERS": "false",
            "LEAP_MAX_PARALLEL_RUNS": "1",
            "LEAP_DEMO_SYNTH": json.dumps(TINY_DEMO),
        },
        log=work / "server.log",
    )
    server.start()
    try:
        seed_project(server)
        return run_schemathesis(server.base, reports, max_examples=max_examples, seed=seed)
    finally:
        server.stop()


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--max-examples", type=int, default=60, help="test cases per operation and phase")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--report-dir", type=Path, default=None, help="keep the HAR and JSON reports here")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="leap-fuzz-"))
    reports = args.report_dir or work / "reports"
    try:
        result = fuzz_live_server(work, max_examples=args.max_examples, seed=args.seed, report_dir=reports)
    finally:
        shutil.rmtree(work / "data", ignore_errors=True)
    print(result.output[-3000:])
    print(f"requests sent: {result.requests}")
    print(f"status codes:  {result.statuses}")
    print(f"server errors: {result.server_errors}")
    print(f"failures:      {json.dumps(result.failures) if result.failures else 'none'}")
    print(f"errors:        {len(result.errors)}")
    print(f"reports:       {reports}")
    return 0 if result.exit_code == 0 and not result.failures and not result.server_errors else 1


if __name__ == "__main__":
    sys.exit(main())
