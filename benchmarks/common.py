"""Shared helpers for the benchmark scripts: timing, peak memory, a printed table and JSON results.

Benchmarks report figures, they never assert speed. Each script prints a table (with a ratio against a
baseline measured in the same process on the same data) and writes ``benchmarks/results/<name>.json``
(:data:`RESULTS_DIR`).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import importlib
import io
import json
import os
import platform
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tarfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

REPO = Path(__file__).resolve().parents[1]
"""The repository root (its git history holds the baseline commits some benchmarks import)."""
RESULTS_DIR = Path(os.environ.get("LEAP_BENCH_RESULTS") or Path(__file__).resolve().parent / "results")
"""Where result files go: ``benchmarks/results``, or the folder ``$LEAP_BENCH_RESULTS`` names (the tests'
smoke runs write there, so they never replace a real run's figures)."""


@dataclass
class Timing:
    """Wall-clock seconds of repeated runs of one function."""

    runs: list[float]
    cold: float | None = None
    """The first (warm-up) call, which pays page faults and lazy initialisation."""
    cpu: list[float] = field(default_factory=list)
    """Process CPU seconds of each timed run (all threads). On a machine shared with other work the wall
    time stretches while the CPU time stays close to what the run costs on an idle machine."""

    @property
    def best(self) -> float:
        return min(self.runs)

    @property
    def median(self) -> float:
        return statistics.median(self.runs)

    @property
    def cpu_median(self) -> float:
        return statistics.median(self.cpu) if self.cpu else float("nan")

    def to_dict(self) -> dict[str, Any]:
        return {
            "best_s": self.best,
            "median_s": self.median,
            "runs_s": self.runs,
            "cold_s": self.cold,
            "cpu_median_s": self.cpu_median,
            "cpu_runs_s": self.cpu,
        }


def time_it(fn: Callable[[], Any], repeat: int = 5, warmup: int = 1) -> Timing:
    """Run ``fn`` ``warmup`` times (the first one is reported as ``cold``), then time ``repeat`` runs."""
    cold = None
    for i in range(warmup):
        t = time.perf_counter()
        fn()
        if i == 0:
            cold = time.perf_counter() - t
    runs, cpu = [], []
    for _ in range(repeat):
        c = time.process_time()
        t = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return Timing(runs, cold, cpu)


def _status_kb(field_name: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field_name + ":"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


@dataclass
class PeakMemory:
    """Peak resident memory added while the ``with`` block ran, in bytes (``.added``).

    On Linux the process's high-water mark (VmHWM) is reset through ``/proc/self/clear_refs`` on entry,
    so ``added = VmHWM(exit) - VmRSS(entry)`` counts every allocator (numpy, torch, scipy). Elsewhere it
    falls back to ``ru_maxrss``, which only grows: then ``added`` is a lower bound (``exact`` False).
    """

    added: int = 0
    exact: bool = False
    peak: int = 0
    """The process's peak resident size while measured, in bytes (with ``exact`` False: since it began)."""
    _start: int = field(default=0, repr=False)

    def start(self) -> None:
        """Begin measuring (what ``measure`` does on entry; for spans that are not one ``with`` block)."""
        try:
            Path("/proc/self/clear_refs").write_text("5")
            self.exact = _status_kb("VmHWM") is not None
        except OSError:
            self.exact = False
        if self.exact:
            self._start = (_status_kb("VmRSS") or 0) * 1024
        else:
            self._start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    def stop(self) -> None:
        """End measuring: sets ``peak`` and ``added``."""
        if self.exact:
            self.peak = (_status_kb("VmHWM") or 0) * 1024
        else:
            self.peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        self.added = max(self.peak - self._start, 0)

    @contextlib.contextmanager
    def measure(self) -> Iterator[PeakMemory]:
        self.start()
        yield self
        self.stop()


def peak_memory(fn: Callable[[], Any]) -> tuple[Any, PeakMemory]:
    """Run ``fn`` once and return (its result, the :class:`PeakMemory` it added)."""
    pm = PeakMemory()
    with pm.measure():
        out = fn()
    return out, pm


def machine_info() -> dict[str, Any]:
    info: dict[str, Any] = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "affinity_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "load_average_1_5_15_min": os.getloadavg() if hasattr(os, "getloadavg") else None,
    }
    for mod in ("numpy", "scipy", "torch"):
        if mod in sys.modules:
            info[mod] = getattr(sys.modules[mod], "__version__", None)
    if "torch" in sys.modules:
        info["torch_threads"] = sys.modules["torch"].get_num_threads()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu"] = line.split(":", 1)[1].strip()
                break
    return info


def format_table(title: str, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """Plain text table: first column left-aligned, the others right-aligned."""

    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:,.3g}" if abs(v) < 1000 else f"{v:,.0f}"
        return str(v)

    body = [[cell(v) for v in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in body)) if body else len(h) for i, h in enumerate(header)]

    def line(vals: Sequence[str]) -> str:
        cells = enumerate(zip(vals, widths, strict=True))
        return "  ".join(v.ljust(w) if i == 0 else v.rjust(w) for i, (v, w) in cells)

    out = [title, line(list(header)), "  ".join("-" * w for w in widths)]
    out += [line(r) for r in body]
    return "\n".join(out)


def print_table(title: str, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    sys.stdout.write(format_table(title, header, rows) + "\n\n")
    sys.stdout.flush()


def write_results(name: str, payload: dict[str, Any], results_dir: Path = RESULTS_DIR) -> Path:
    """Write ``<results_dir>/<name>.json`` atomically with a timestamp and machine info added."""
    results_dir.mkdir(parents=True, exist_ok=True)
    doc = {
        "benchmark": name,
        "timestamp": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine_info(),
        **payload,
    }
    path = results_dir / f"{name}.json"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=2, sort_keys=False, default=float) + "\n")
    os.replace(tmp, path)
    return path


def import_commit(commit: str, into: Path, modules: Sequence[str]) -> dict[str, ModuleType]:
    """``leap_core`` and ``projects/`` as of git ``commit``, imported beside today's as the package
    ``leap_base_<commit>``, so a benchmark runs both versions in one process on the same data.

    Args:
        commit: a commit of this repository's history.
        into: a folder for the extracted tree (its ``baseline/`` is replaced).
        modules: dotted module names under ``leap_core`` to import, e.g. ``"pipeline.runner"``.

    Returns:
        Each of ``modules`` to its imported baseline module.
    """
    name = f"leap_base_{re.sub(r'[^0-9A-Za-z]', '_', commit)}"
    tar = subprocess.run(
        ["git", "-C", str(REPO), "archive", commit, "leap_core", "projects"], check=True, capture_output=True
    ).stdout
    root = into / "baseline"
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    with tarfile.open(fileobj=io.BytesIO(tar)) as tf:
        tf.extractall(root, filter="data")
    (root / "leap_core").rename(root / name)
    for py in (root / name).rglob("*.py"):
        py.write_text(re.sub(r"\bleap_core\b", name, py.read_text()))
    sys.path.insert(0, str(root))
    return {m: importlib.import_module(f"{name}.{m}") for m in modules}
