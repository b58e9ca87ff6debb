"""How ``leap run`` scales with the sequence length: per-stage time per scan, CPU time, peak memory and
voxels on sequences of 60, 240 and 1,000 frames, fitted and extrapolated to a full SemanticKITTI sequence
(4,541 frames).

Each length is one ``leap run`` (the simulated labeler, 3D-CN off unless ``--3dcn``) in a child process on
a fresh run folder, its 3D stages run ``--repeat`` − 1 more times on the same folder (their records
made stale, so the runner clears and recomputes them; each 3D stage's figure is its least time over the
runs, since a few-second stage on shared cores varies by ±30 % from one run to the next), then two fully
cached reruns of the same command (every stage unchanged), one after
deleting the run's ``export-coverage.json`` (the export counts are taken again: what every cached rerun
paid before they were kept) and one reading it: the bookkeeping a cached rerun costs, with its baseline
measured on the same folder.

Measured, per length:

- per stage: wall seconds from the run's ``stages.json`` (``seconds``), CPU seconds of the child process
  tree between the stage's ``started`` and ``finished`` times (from the sampling below), per scan;
- the child tree's CPU time and ``ru_maxrss`` (``os.wait4``: the exact peak of the largest process) and its
  summed RSS sampled with psutil every ``--interval`` seconds (the peak of every process together; it can
  miss a peak shorter than the interval); the peak per stage is the sampled one;
- voxels: the largest grid the run built (``voxels`` of the fuse and 3D-CN records).

Fits (least squares, :func:`power_law_fit` on log-log axes and :func:`linear_fit`): each stage's seconds
and the peak RSS against frames (``a · frames^b``: ``b`` = 1 is linear), voxels against frames, and peak RSS
as ``a + b × voxels``; each extrapolated to 4,541 frames.

Checks (on the default run, 3D-CN off): (1) the 3D stages (every stage from ``fuse`` on) together take at
most 40 ms per scan at the longest length; (2) every 3D stage's seconds per scan at the longest length is
within 1.3× of those at 60 frames; memory target: peak RSS ≤ 1.5 GB + 64 B × voxels (GB = 10⁹ bytes) at
every length and at the extrapolation (with ``--3dcn``: 3 GB + 64 B × voxels). Checks are printed for
wall time (what a user waits on this machine) and CPU time (closer to an idle machine when other jobs
share the cores); nothing is asserted.

Usage::

    .venv/bin/python benchmarks/bench_scale.py --data data/demo/sequences/00 data/s11/sequences/00 \\
        data/s12/sequences/00 [--3dcn] [--markdown]
    .venv/bin/python benchmarks/bench_scale.py --frames 60 240 1000 --seeds 0 11 12 --work /tmp/scale
    .venv/bin/python benchmarks/bench_scale.py --report     # print the last results again

Without ``--data`` the sequences are generated with ``leap synth`` into ``WORK/data/f<frames>-s<seed>``
(kept for later runs; a folder is complete when its ``synth_version.txt`` exists). Writes
``benchmarks/results/bench_scale.json`` (``bench_scale_3dcn.json`` with ``--3dcn``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, print_table, write_results

from leap_core.extras import MissingExtra
from leap_core.pipeline import SequenceSpec
from leap_core.pipeline.stages import STAGES
from leap_core.run_layout import RunLayout

try:  # the bench extra
    import psutil
except ModuleNotFoundError as exc:
    raise SystemExit(f"error: {MissingExtra('bench', exc.name)}") from None

REPO = Path(__file__).resolve().parents[1]
"""The child processes run this checkout's code (its folder first on PYTHONPATH)."""

FULL_SEQUENCE = 4541
"""Frames of SemanticKITTI's sequence 00, the extrapolation target."""
FIRST_3D_STAGE = "fuse"
"""The 3D stages of check (1) and (2): this one and every later one (the world map and its points)."""
BUDGET_S_PER_SCAN = 0.040
"""Check (1): the 3D stages together, seconds per scan."""
MAX_PER_SCAN_GROWTH = 1.3
"""Check (2): seconds per scan at the longest length over those at the shortest, per 3D stage."""
MEMORY_BASE_B = 1.5e9
MEMORY_BASE_3DCN_B = 3.0e9
MEMORY_PER_VOXEL_B = 64.0
"""Memory target: peak RSS ≤ MEMORY_BASE_B (MEMORY_BASE_3DCN_B with ``--3dcn``) + MEMORY_PER_VOXEL_B ×
voxels."""
SYNTH_VERSION_FILE = "synth_version.txt"


# ------------------------------------------------------------------------------------------- fits
def power_law_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """``(a, b)`` of ``y = a · x^b``, least squares on ``log y = log a + b · log x``.

    Args:
        x, y: (n,) positive values, n ≥ 2 (pairs with y ≤ 0 are dropped; fewer than 2 left: (nan, nan)).
    """
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    ok = (x > 0) & (y > 0)
    if ok.sum() < 2 or np.unique(x[ok]).size < 2:
        return math.nan, math.nan
    b, log_a = np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)
    return float(math.exp(log_a)), float(b)


def linear_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """``(a, b)`` of ``y = a + b · x``, least squares; (nan, nan) with fewer than 2 distinct x."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if x.size < 2 or np.unique(x).size < 2:
        return math.nan, math.nan
    b, a = np.polyfit(x, y, 1)
    return float(a), float(b)


def memory_target(voxels: float, cn: bool = False) -> float:
    """Bytes the peak RSS may reach for a grid of ``voxels`` voxels (``cn``: with the 3D-CN on)."""
    return (MEMORY_BASE_3DCN_B if cn else MEMORY_BASE_B) + MEMORY_PER_VOXEL_B * voxels


# ------------------------------------------------------------------------------ child process watch
@dataclass
class Watch:
    """A child process tree sampled with psutil: ``samples`` rows of (epoch seconds, CPU seconds of the
    tree so far, summed RSS bytes)."""

    pid: int
    interval: float
    samples: list[tuple[float, float, int]] = field(default_factory=list)
    _cpu_done: dict[int, float] = field(default_factory=dict)
    _stop: threading.Event = field(default_factory=threading.Event)

    def run(self) -> None:
        try:
            root = psutil.Process(self.pid)
        except psutil.NoSuchProcess:
            return
        while not self._stop.is_set():
            try:
                procs = [root, *root.children(recursive=True)]
            except psutil.NoSuchProcess:
                break
            rss = 0
            for p in procs:
                try:
                    with p.oneshot():
                        ct = p.cpu_times()
                        mem = p.memory_info().rss
                except (psutil.NoSuchProcess, psutil.ZombieProcess, psutil.AccessDenied):
                    continue
                # A process's last reading stays counted after it exits.
                self._cpu_done[p.pid] = ct.user + ct.system
                rss += mem
            self.samples.append((time.time(), sum(self._cpu_done.values()), rss))
            self._stop.wait(self.interval)

    def stop(self) -> None:
        self._stop.set()

    def cpu_at(self, t: float) -> float:
        """CPU seconds of the tree at epoch ``t`` (linear between samples)."""
        if not self.samples:
            return math.nan
        s = np.asarray(self.samples)
        return float(np.interp(t, s[:, 0], s[:, 1]))

    def peak_between(self, t0: float, t1: float) -> int:
        """Largest sampled RSS in [t0, t1] (the sample before t0 too: a stage starts where it was)."""
        if not self.samples:
            return 0
        s = np.asarray(self.samples)
        lo = max(int(np.searchsorted(s[:, 0], t0)) - 1, 0)
        hi = int(np.searchsorted(s[:, 0], t1, side="right"))
        return int(s[lo : max(hi, lo + 1), 2].max())


def run_child(cmd: list[str], log: Path, interval: float) -> dict[str, Any]:
    """Run ``cmd`` (output to ``log``) under a :class:`Watch`; wall, CPU and RSS figures of the tree.

    Raises:
        SystemExit: the command failed (the log's tail is printed).
    """
    path = [str(REPO), *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path)}
    with open(log, "w") as out:
        start = time.time()
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=REPO, env=env)
        watch = Watch(proc.pid, interval)
        thread = threading.Thread(target=watch.run, daemon=True)
        thread.start()
        # wait4, not Popen.wait: its rusage is the child's exact CPU time and peak RSS (its waited-for
        # children included).
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        end = time.time()
        proc.returncode = os.waitstatus_to_exitcode(status)
        watch.stop()
        thread.join()
    if proc.returncode != 0:
        tail = log.read_text(errors="replace")[-3000:]
        sys.exit(f"{' '.join(cmd)} failed ({proc.returncode}); end of {log}:\n{tail}")
    sampled = max((r for _, _, r in watch.samples), default=0)
    return {
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "maxrss_b": usage.ru_maxrss * 1024,  # Linux: KiB
        "sampled_peak_rss_b": sampled,
        "peak_rss_b": max(sampled, usage.ru_maxrss * 1024),
        "start_epoch": start,
        "end_epoch": end,
        "watch": watch,
    }


# ------------------------------------------------------------------------------------------- data
def is_complete(seq: Path) -> bool:
    return (seq / SYNTH_VERSION_FILE).is_file()


def ensure_sequence(root: Path, frames: int, seed: int, interval: float) -> Path:
    """``root/sequences/00``, generated with ``leap synth`` unless complete."""
    seq = root / "sequences" / "00"
    if is_complete(seq):
        return seq
    print(f"generating {frames} frames (seed {seed}) into {root} with leap synth ...", flush=True)
    root.mkdir(parents=True, exist_ok=True)
    run_child(
        [
            sys.executable,
            "-m",
            "app.cli",
            "synth",
            str(root),
            "--frames",
            str(frames),
            "--seed",
            str(seed),
            "--force",
        ],
        root / "synth.log",
        interval,
    )
    return seq


def count_frames(seq: Path) -> int:
    return sum(1 for p in (seq / "velodyne").iterdir() if p.suffix == ".bin")


# ------------------------------------------------------------------------------------------ one length
def stage_times(seq_dir: Path, watch: Watch) -> dict[str, Any]:
    """Per stage of the sequence's ``stages.json`` (``seq_dir``: its folder in the run): status, wall
    seconds, the child tree's CPU seconds between the stage's start and finish, the sampled peak RSS in
    that span and the record's voxels. The 3D-CN's rounds run between the sequence's ``smooth`` and
    ``3dcn`` stages (that stage only links their grids), so in this run of one sequence the ``3dcn`` span
    starts when ``smooth`` finished."""
    state = json.loads((seq_dir / "stages.json").read_text())
    stages: dict[str, Any] = {}
    for name in STAGES:
        rec = state.get(name, {})
        started, finished = rec.get("started"), rec.get("finished")
        wall = float(rec.get("seconds", 0.0))
        if name == "3dcn" and rec.get("status") == "done" and finished is not None:
            started = state.get("smooth", {}).get("finished", started)
            wall = float(finished) - float(started)
        timed = started is not None and finished is not None
        stages[name] = {
            "status": rec.get("status"),
            "wall_s": wall,
            "cpu_s": watch.cpu_at(finished) - watch.cpu_at(started) if timed else math.nan,
            "peak_rss_b": watch.peak_between(started, finished) if timed else 0,
            "voxels": rec.get("voxels"),
        }
    return stages


def invalidate_3d_stages(seq_dir: Path) -> None:
    """Make the next ``leap run`` compute the 3D stages of the sequence whose folder is ``seq_dir`` again:
    their ``stages.json`` fingerprints no longer match, so the runner clears their outputs and reruns them
    (the 2D labels and observations stay)."""
    path = seq_dir / "stages.json"
    state = json.loads(path.read_text())
    for name in STAGES[STAGES.index(FIRST_3D_STAGE) :]:
        if isinstance(state.get(name), dict):
            state[name]["fingerprint"] = "bench_scale: run again"
    path.write_text(json.dumps(state))


def least_of(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The first run's stage times (each run a :func:`stage_times` result), where each 3D stage that ran
    in every run gets its least wall and its least CPU seconds over the runs (the stages before were
    computed once: the later runs' records of them are the first run's)."""
    out = dict(runs[0])
    for name in STAGES[STAGES.index(FIRST_3D_STAGE) :]:
        if all(r[name]["status"] == "done" for r in runs):
            out[name] = {
                **runs[0][name],
                "wall_s": min(r[name]["wall_s"] for r in runs),
                "cpu_s": min(r[name]["cpu_s"] for r in runs),
            }
    return out


def measure_length(
    seq: Path, work: Path, cn: bool, interval: float, cached: bool, repeat: int = 1
) -> dict[str, Any]:
    """One cold ``leap run`` on ``seq`` into a fresh folder, its 3D stages ``repeat - 1`` more times on
    the same folder (per stage the least time counts), then the cached reruns."""
    frames = count_frames(seq)
    run_dir = work / f"run-{frames}"
    shutil.rmtree(run_dir, ignore_errors=True)
    cmd = [
        sys.executable,
        "-m",
        "app.cli",
        "run",
        str(seq),
        "--out",
        str(run_dir),
        "--labeler",
        "simulated",
        "--3dcn" if cn else "--no-3dcn",
    ]
    print(f"{frames} frames: leap run ...", flush=True)
    cold = run_child(cmd, work / f"run-{frames}.log", interval)
    watch: Watch = cold.pop("watch")
    seq_dir = RunLayout(run_dir).sequence(SequenceSpec.of(seq).name).folder
    state = json.loads((seq_dir / "stages.json").read_text())
    runs = [stage_times(seq_dir, watch)]
    for k in range(1, repeat):
        print(f"{frames} frames: 3D stages again ({k}/{repeat - 1}) ...", flush=True)
        invalidate_3d_stages(seq_dir)
        again = run_child(cmd, work / f"run-{frames}-3d{k}.log", interval)
        runs.append(stage_times(seq_dir, again.pop("watch")))
    stages = least_of(runs) if repeat > 1 else runs[0]
    voxels = max(int(stages[s]["voxels"] or 0) for s in STAGES)
    firsts = [state[s]["started"] for s in STAGES if "started" in state.get(s, {})]
    lasts = [state[s]["finished"] for s in STAGES if "finished" in state.get(s, {})]
    result: dict[str, Any] = {
        "sequence": str(seq),
        "frames": frames,
        "voxels": voxels,
        "points": sum((seq / "velodyne" / f).stat().st_size // 16 for f in os.listdir(seq / "velodyne")),
        "cold": cold,
        "before_stages_s": min(firsts) - cold["start_epoch"] if firsts else math.nan,
        "after_stages_s": cold["end_epoch"] - max(lasts) if lasts else math.nan,
        "stages": stages,
        "stage_runs": runs,
        "samples": [list(s) for s in watch.samples],
    }
    if cached:
        cov = seq_dir / "export-coverage.json"
        print(f"{frames} frames: cached reruns ...", flush=True)
        cov.unlink(missing_ok=True)
        recount = run_child(cmd, work / f"run-{frames}-recount.log", interval)
        recount.pop("watch")
        reread = run_child(cmd, work / f"run-{frames}-cached.log", interval)
        reread.pop("watch")
        result["cached_recount"] = recount
        result["cached"] = reread
    return result


# ------------------------------------------------------------------------------------------ analysis
def three_d_stages(results: list[dict[str, Any]]) -> list[str]:
    """The 3D stages that ran (not skipped) at every length."""
    first = STAGES.index(FIRST_3D_STAGE)
    return [s for s in STAGES[first:] if all(r["stages"][s]["status"] == "done" for r in results)]


def analyse(results: list[dict[str, Any]], cn: bool = False) -> dict[str, Any]:
    """Fits, extrapolation and checks over the lengths (sorted by frames); ``cn``: runs with the 3D-CN,
    whose memory target is 3 GB + 64 B × voxels."""
    results = sorted(results, key=lambda r: r["frames"])
    n = np.array([r["frames"] for r in results], np.float64)
    ran = [s for s in STAGES if any(r["stages"][s]["status"] == "done" for r in results)]
    d3 = three_d_stages(results)
    out: dict[str, Any] = {"stages": {}, "three_d_stages": d3, "extrapolate_frames": FULL_SEQUENCE}
    for s in ran:
        entry: dict[str, Any] = {}
        for kind in ("wall_s", "cpu_s"):
            y = np.array([r["stages"][s][kind] for r in results], np.float64)
            a, b = power_law_fit(n, y)
            entry[kind] = {
                "per_scan": (y / n).tolist(),
                "fit_a": a,
                "fit_b": b,
                "extrapolated_per_scan": a * FULL_SEQUENCE**b / FULL_SEQUENCE if np.isfinite(b) else math.nan,
                "growth": float(y[-1] / n[-1] / (y[0] / n[0])) if y[0] > 0 else math.nan,
            }
        out["stages"][s] = entry
    totals: dict[str, Any] = {}
    for kind in ("wall_s", "cpu_s"):
        per_scan = np.array([sum(r["stages"][s][kind] for s in d3) for r in results]) / n
        extrap = sum(out["stages"][s][kind]["extrapolated_per_scan"] for s in d3)
        growth = {s: out["stages"][s][kind]["growth"] for s in d3}
        totals[kind] = {
            "three_d_per_scan": per_scan.tolist(),
            "three_d_extrapolated_per_scan": extrap,
            "check1_budget_ok": bool(per_scan[-1] <= BUDGET_S_PER_SCAN),
            "check2_growth": growth,
            "check2_ok": bool(len(results) > 1 and all(g <= MAX_PER_SCAN_GROWTH for g in growth.values())),
        }
    out["totals"] = totals
    peak = np.array([r["cold"]["peak_rss_b"] for r in results], np.float64)
    vox = np.array([r["voxels"] for r in results], np.float64)
    wall = np.array([r["cold"]["wall_s"] for r in results], np.float64)
    cpu = np.array([r["cold"]["cpu_s"] for r in results], np.float64)
    va, vb = power_law_fit(n, vox)
    vox_x = va * FULL_SEQUENCE**vb
    ma, mb = linear_fit(vox, peak)
    pa, pb = power_law_fit(n, peak)
    wa, wb = power_law_fit(n, wall)
    ca, cb = power_law_fit(n, cpu)
    out["fits"] = {
        "voxels_vs_frames": [va, vb],
        "peak_rss_vs_voxels_linear": [ma, mb],
        "peak_rss_vs_frames": [pa, pb],
        "wall_vs_frames": [wa, wb],
        "cpu_vs_frames": [ca, cb],
    }
    out["extrapolated"] = {
        "frames": FULL_SEQUENCE,
        "voxels": vox_x,
        "peak_rss_b_from_voxels": ma + mb * vox_x,
        "peak_rss_b_from_frames": pa * FULL_SEQUENCE**pb,
        "wall_s": wa * FULL_SEQUENCE**wb,
        "cpu_s": ca * FULL_SEQUENCE**cb,
        "memory_target_b": memory_target(vox_x, cn),
    }
    x = out["extrapolated"]
    worst = max(x["peak_rss_b_from_voxels"], x["peak_rss_b_from_frames"])
    x["memory_ok"] = bool(worst <= x["memory_target_b"])
    out["memory"] = [
        {
            "frames": r["frames"],
            "peak_rss_b": r["cold"]["peak_rss_b"],
            "target_b": memory_target(r["voxels"], cn),
            "ok": bool(r["cold"]["peak_rss_b"] <= memory_target(r["voxels"], cn)),
        }
        for r in results
    ]
    return out


# ------------------------------------------------------------------------------------------ report
def _ms(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{1000 * x:.1f}"


def _mb(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{x / 1e6:,.0f}"


def _ok(flag: bool) -> str:
    return "yes" if flag else "NO"


def report_tables(doc: dict[str, Any]) -> list[tuple[str, list[str], list[list[Any]]]]:
    """(title, header, rows) of each table the script prints (plain text or Markdown)."""
    results = sorted(doc["results"], key=lambda r: r["frames"])
    an = doc["analysis"]
    lengths = [r["frames"] for r in results]
    d3 = set(an["three_d_stages"])
    tables = []

    header = [
        "stage (ms per scan, wall / CPU)",
        *(f"{f:,} frames" for f in lengths),
        "exponent b (wall / CPU)",
        f"{lengths[-1]:,} vs {lengths[0]:,} (wall / CPU)",
        f"{FULL_SEQUENCE:,} frames (extrap.)",
    ]
    rows = []
    for s, e in an["stages"].items():
        w, c = e["wall_s"], e["cpu_s"]
        rows.append(
            [
                s + (" (3D)" if s in d3 else ""),
                *(f"{_ms(pw)} / {_ms(pc)}" for pw, pc in zip(w["per_scan"], c["per_scan"], strict=True)),
                f"{w['fit_b']:.2f} / {c['fit_b']:.2f}",
                f"{w['growth']:.2f}x / {c['growth']:.2f}x",
                f"{_ms(w['extrapolated_per_scan'])} / {_ms(c['extrapolated_per_scan'])}",
            ]
        )
    tw, tc = an["totals"]["wall_s"], an["totals"]["cpu_s"]
    rows.append(
        [
            "3D stages together",
            *(
                f"{_ms(a)} / {_ms(b)}"
                for a, b in zip(tw["three_d_per_scan"], tc["three_d_per_scan"], strict=True)
            ),
            "",
            "",
            f"{_ms(tw['three_d_extrapolated_per_scan'])} / {_ms(tc['three_d_extrapolated_per_scan'])}",
        ]
    )
    repeat = max(len(r.get("stage_runs", [None])) for r in results)
    title = (
        "time per scan by stage (cold run)"
        if repeat <= 1
        else f"time per scan by stage (cold run; each 3D stage: the least of {repeat} runs)"
    )
    tables.append((title, header, rows))

    header = [
        "frames",
        "points / scan",
        "voxels",
        "wall s",
        "CPU s",
        "before / after stages s",
        "peak RSS MB (sampled / wait4)",
        "peak RSS / target",
        "cached rerun s (counts kept / counted)",
    ]
    rows = []
    for r, m in zip(results, an["memory"], strict=True):
        cold = r["cold"]
        cached = (
            f"{r['cached']['wall_s']:.1f} / {r['cached_recount']['wall_s']:.1f}" if "cached" in r else "-"
        )
        rows.append(
            [
                f"{r['frames']:,}",
                f"{r['points'] / r['frames']:,.0f}",
                f"{r['voxels']:,}",
                f"{cold['wall_s']:.1f}",
                f"{cold['cpu_s']:.1f}",
                f"{r['before_stages_s']:.1f} / {r['after_stages_s']:.1f}",
                f"{_mb(cold['sampled_peak_rss_b'])} / {_mb(cold['maxrss_b'])}",
                f"{_mb(m['peak_rss_b'])} / {_mb(m['target_b'])} ({_ok(m['ok'])})",
                cached,
            ]
        )
    x = an["extrapolated"]
    rows.append(
        [
            f"{FULL_SEQUENCE:,} (extrap.)",
            "",
            f"{x['voxels']:,.0f}",
            f"{x['wall_s']:,.0f}",
            f"{x['cpu_s']:,.0f}",
            "",
            f"{_mb(x['peak_rss_b_from_voxels'])} (a + b·voxels) / "
            f"{_mb(x['peak_rss_b_from_frames'])} (power law)",
            f"{_mb(max(x['peak_rss_b_from_voxels'], x['peak_rss_b_from_frames']))} / "
            f"{_mb(x['memory_target_b'])} "
            f"({_ok(x['memory_ok'])})",
            "",
        ]
    )
    tables.append(("whole run (cold), memory and cached reruns", header, rows))

    f = an["fits"]
    rows = [
        ["voxels = a · frames^b", f"{f['voxels_vs_frames'][0]:,.4g}", f"{f['voxels_vs_frames'][1]:.3f}"],
        [
            "peak RSS bytes = a + b · voxels",
            f"{f['peak_rss_vs_voxels_linear'][0]:,.4g}",
            f"{f['peak_rss_vs_voxels_linear'][1]:.1f}",
        ],
        [
            "peak RSS bytes = a · frames^b",
            f"{f['peak_rss_vs_frames'][0]:,.4g}",
            f"{f['peak_rss_vs_frames'][1]:.3f}",
        ],
        ["wall s = a · frames^b", f"{f['wall_vs_frames'][0]:.4g}", f"{f['wall_vs_frames'][1]:.3f}"],
        ["CPU s = a · frames^b", f"{f['cpu_vs_frames'][0]:.4g}", f"{f['cpu_vs_frames'][1]:.3f}"],
    ]
    tables.append(("fitted growth", ["fit", "a", "b"], rows))

    rows = []
    for kind, label in (("wall_s", "wall"), ("cpu_s", "CPU")):
        t = an["totals"][kind]
        growth = t["check2_growth"]
        worst = max(growth.items(), key=lambda kv: kv[1]) if growth else ("-", math.nan)
        rows.append(
            [
                f"(1) 3D stages ≤ {1000 * BUDGET_S_PER_SCAN:.0f} ms per scan at {lengths[-1]:,} frames, "
                f"{label}",
                f"{_ms(t['three_d_per_scan'][-1])} ms",
                _ok(t["check1_budget_ok"]),
            ]
        )
        rows.append(
            [
                f"(2) every 3D stage within {MAX_PER_SCAN_GROWTH}x per scan, {lengths[-1]:,} vs "
                f"{lengths[0]:,} frames, {label}",
                f"worst {worst[0]} {worst[1]:.2f}x",
                _ok(t["check2_ok"]),
            ]
        )
    mem_ok = all(m["ok"] for m in an["memory"]) and x["memory_ok"]
    rows.append(
        [
            f"memory: peak RSS ≤ {MEMORY_BASE_B / 1e9:.1f} GB + {MEMORY_PER_VOXEL_B:.0f} B × voxels "
            f"(measured lengths and {FULL_SEQUENCE:,} extrapolated)",
            "",
            _ok(mem_ok),
        ]
    )
    tables.append(("checks", ["check", "value", "met"], rows))
    return tables


def markdown(title: str, header: list[str], rows: list[list[Any]]) -> str:
    lines = [
        f"**{title}**",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(str(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def print_report(doc: dict[str, Any], as_markdown: bool) -> None:
    m = doc.get("machine", {})
    note = (
        f"{doc.get('config', {}).get('labeler', 'simulated')} labeler, 3D-CN "
        f"{'on' if doc.get('config', {}).get('3dcn') else 'off'}; {m.get('cpu', '?')}, "
        f"{m.get('affinity_cpus', '?')} cores, OPENBLAS_NUM_THREADS "
        f"{doc.get('config', {}).get('openblas_threads') or 'unset'}, load average at the end "
        f"{m.get('load_average_1_5_15_min')}"
    )
    for title, header, rows in report_tables(doc):
        if as_markdown:
            sys.stdout.write(markdown(title, header, rows) + "\n\n")
        else:
            print_table(title, header, rows)
    sys.stdout.write(note + "\n")


# ------------------------------------------------------------------------------------------ main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data",
        nargs="+",
        type=Path,
        default=None,
        help="Sequence folders (.../sequences/NN) to run, each complete (synth_version.txt).",
    )
    ap.add_argument(
        "--frames",
        nargs="+",
        type=int,
        default=[60, 240, 1000],
        help="Without --data: lengths to generate with leap synth (default 60 240 1000).",
    )
    ap.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        default=[0, 11, 12],
        help="Without --data: the seed of each length (default 0 11 12).",
    )
    ap.add_argument("--3dcn", dest="cn", action="store_true", help="Run with the 3D Consistency Network.")
    ap.add_argument(
        "--work",
        type=Path,
        default=None,
        help="Folder for the runs (and generated data); default: a temporary folder, removed.",
    )
    ap.add_argument("--interval", type=float, default=0.05, help="psutil sampling interval, seconds.")
    ap.add_argument("--no-cached", dest="cached", action="store_false", help="Skip the cached reruns.")
    ap.add_argument(
        "--repeat",
        type=int,
        default=None,
        help="Runs of the 3D stages per length: the cold run, then its 3D stages again on the "
        "same folder; each stage's figure is its least time (default 3; 1 with --3dcn). "
        "On shared cores a single run of a few-second stage varies by ±30 %%.",
    )
    ap.add_argument(
        "--blas-threads",
        type=int,
        default=None,
        help="OPENBLAS_NUM_THREADS of the runs (default: inherited). On a loaded machine numpy's "
        "threaded matrix products of N×3 points by 3×3 rotations wait on each other.",
    )
    ap.add_argument("--markdown", action="store_true", help="Print the tables as Markdown (the README's).")
    ap.add_argument("--report", action="store_true", help="Only print the last results file again.")
    ap.add_argument("--name", default=None, help="Result file benchmarks/results/NAME.json.")
    args = ap.parse_args()
    name = args.name or ("bench_scale_3dcn" if args.cn else "bench_scale")

    if args.report:
        print_report(json.loads((RESULTS_DIR / f"{name}.json").read_text()), args.markdown)
        return

    work = args.work or Path(tempfile.mkdtemp(prefix="bench_scale_"))
    work.mkdir(parents=True, exist_ok=True)
    if args.data:
        seqs = [Path(d) for d in args.data]
        for s in seqs:
            if not is_complete(s):
                sys.exit(
                    f"{s}: not a complete sequence (no {SYNTH_VERSION_FILE}); generate it with "
                    "leap synth or leave out --data"
                )
    else:
        if len(args.seeds) != len(args.frames):
            sys.exit(f"--seeds: {len(args.seeds)} seeds for {len(args.frames)} lengths")
        seqs = [
            ensure_sequence(work / "data" / f"f{n}-s{seed}", n, seed, args.interval)
            for n, seed in zip(args.frames, args.seeds, strict=True)
        ]

    if args.blas_threads is not None:
        os.environ["OPENBLAS_NUM_THREADS"] = str(args.blas_threads)  # the children inherit it
    repeat = args.repeat if args.repeat is not None else (1 if args.cn else 3)
    if repeat < 1:
        sys.exit("--repeat: at least 1")
    results = [measure_length(s, work, args.cn, args.interval, args.cached, repeat) for s in seqs]
    doc = {
        "config": {
            "labeler": "simulated",
            "3dcn": bool(args.cn),
            "repeat": repeat,
            "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        },
        "results": results,
        "analysis": analyse(results, args.cn),
    }
    path = write_results(name, doc)
    doc = json.loads(path.read_text())
    print_report(doc, args.markdown)
    print(f"wrote {path}")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
