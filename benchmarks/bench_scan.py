"""Benchmark: time per scan of the 3D stages (project, fuse, label_points, export) against a baseline commit.

Target: projection + depth clustering + painting (``project``) + fusion (``fuse``) +
point labeling (``label_points``) + export ≤ 40 ms per 120 000-point scan on the project's 2 cores.

Baseline, in the same process on the same data: the package as it was at ``--baseline`` (default
``c472ae0``, main before this work), taken from git (``git archive``) into a temporary folder and imported
under another name (``leap_core`` → ``leap_base_<commit>`` in its source text), so both versions run side by
side in one interpreter, alternating, on the same page cache and the same machine load. The baseline is
given today's default settings restricted to those it knows (:func:`known_settings`): settings added since
(e.g. ``pipeline.simulated.class_confusion``) would make its parser refuse the whole config. The dropped
settings are printed; whether they changed what the timed stages do is what the byte comparison of the
outputs answers.

Data: ``--sequence`` (the demo, ``leap synth --frames 60 --seed 0``) and a copy of it whose scans are
padded to ``--points`` points (each added point a copy of a scan point moved by a few centimetres; images,
calibration and poses shared), so the figure per 120 k-point scan is measured, not extrapolated. Each copy
is first run up to ``smooth`` once (untimed) to give the stages their inputs. Then, ``--repeat`` times and
for each version in turn (the baseline; this tree with 1 frame thread; this tree with ``--threads``), the
four stages' outputs are removed and the stage functions of ``STAGE_TABLE`` run on a fresh run context.
Per stage: median wall milliseconds per scan of each version, the ratio baseline / this tree with
``--threads``, and the process CPU milliseconds per scan (all threads) of those two. CPU time hardly
depends on what else runs on the machine; wall time does (the project's 2 cores are shared), so the
figures are printed with the load average. The outputs of all versions are compared file by file (they
must be identical).

Usage::

    .venv/bin/leap synth /tmp/demo --frames 60 --seed 0        # once: the demo sequence
    .venv/bin/python benchmarks/bench_scan.py --sequence /tmp/demo/sequences/00
    .venv/bin/python benchmarks/bench_scan.py --quick           # smoke run: 2 generated frames, 1 repeat

Prints the tables and writes ``benchmarks/results/bench_scan.json``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, import_commit, print_table, write_results

from leap_core.config import PipelineConfig, config_to_dict
from leap_core.datasets.kitti import KittiSequence, write_scan
from leap_core.pipeline import SequenceSpec, run_pipeline
from leap_core.runtime import Runtime
from leap_core.schema import builtin_schema

TIMED = ("project", "fuse", "label_points", "export")
"""The per-scan 3D stages of the target, in pipeline order (each reads the previous one's files)."""
OUTPUTS = {
    "project": ("observations",),
    "fuse": ("grid.npz",),
    "label_points": ("points",),
    "export": ("export",),
}
"""What each timed stage writes in a run folder (removed before it runs, compared after)."""
QUICK_FRAMES = 2
QUICK_POINTS = 120_000
"""``--quick``: frames of the generated street and points per scan of its padded copy."""
SHARED = ("calib.txt", "poses.txt", "times.txt", "image_2", "gt2d")


# ------------------------------------------------------------------------------------- the baseline
@dataclass
class Version:
    """One implementation of the pipeline: its modules, as imported."""

    name: str
    runner: ModuleType
    stages: ModuleType
    config: ModuleType
    schema: ModuleType
    runtime: Any = None


def import_baseline(commit: str, into: Path) -> Version:
    """``leap_core`` and ``projects/`` as of ``commit`` (:func:`common.import_commit`)."""
    mods = import_commit(commit, into, ("pipeline.runner", "pipeline.stages", "config", "schema"))
    return Version(commit, mods["pipeline.runner"], mods["pipeline.stages"], mods["config"], mods["schema"])


def current_version(threads: int) -> Version:
    import leap_core.config
    import leap_core.pipeline.runner
    import leap_core.pipeline.stages
    import leap_core.schema

    return Version(
        f"{threads} thread{'s' if threads > 1 else ''}",
        leap_core.pipeline.runner,
        leap_core.pipeline.stages,
        leap_core.config,
        leap_core.schema,
        Runtime(frame_threads=threads),
    )


def known_settings(
    today: dict[str, Any], theirs: dict[str, Any], path: str = ""
) -> tuple[dict[str, Any], list[str]]:
    """``today``'s settings restricted to the keys of ``theirs`` (another version's defaults, the same
    nesting), and the dotted paths of those left out. Example: today ``{"a": 1, "s": {"b": 2, "c": 3}}``,
    theirs ``{"a": 0, "s": {"b": 0}}`` → ``({"a": 1, "s": {"b": 2}}, ["s.c"])``."""
    kept: dict[str, Any] = {}
    dropped: list[str] = []
    for key, value in today.items():
        where = f"{path}{key}"
        if key not in theirs:
            dropped.append(where)
        elif isinstance(value, dict) and isinstance(theirs[key], dict):
            kept[key], more = known_settings(value, theirs[key], where + ".")
            dropped += more
        else:
            kept[key] = value
    return kept, dropped


def baseline_config(version: Version) -> tuple[Any, list[str]]:
    """Today's default config as ``version`` can parse it, and the settings it had to leave out."""
    theirs = version.config.config_to_dict(version.config.PipelineConfig())
    today = config_to_dict(PipelineConfig())
    # The timed stages do not include ``tracks``: with objects on, export would read its tracks.npz, and its
    # labels would differ from a baseline without objects by them (benchmarks/bench_objects.py times it).
    today["tracking"] = {**today["tracking"], "enabled": False}
    kept, dropped = known_settings(today, theirs)
    return version.config.config_from_dict(kept), dropped


# ------------------------------------------------------------------------------------------- data
def padded_copy(src: Path, dst: Path, points: int, seed: int = 0) -> Path:
    """A copy of sequence ``src`` whose scans have at least ``points`` points (added: copies of the scan's
    points moved by N(0, 3 cm) per axis); the other files are linked."""
    dst.mkdir(parents=True, exist_ok=True)
    for entry in SHARED:
        if (src / entry).exists() and not (dst / entry).exists():
            (dst / entry).symlink_to((src / entry).resolve())
    rng = np.random.default_rng(seed)
    for scan in sorted((src / "velodyne").glob("*.bin")):
        pts = np.fromfile(scan, np.float32).reshape(-1, 4)
        extra = max(points - pts.shape[0], 0)
        pick = pts[rng.integers(0, pts.shape[0], extra)].copy()
        pick[:, :3] += rng.normal(0.0, 0.03, (extra, 3)).astype(np.float32)
        write_scan(dst / "velodyne" / scan.name, np.concatenate([pts, pick]))
    return dst


def prepare(seq_dir: Path, root: Path, cache: Path) -> Path:
    """Run the current pipeline up to ``smooth`` (untimed) in the run folder ``root``: the timed stages'
    inputs, in the sequence's folder of the run (returned). The 2D labels go through a shared cache, so the
    padded copy (same images) reuses the demo's."""
    run = run_pipeline(
        [SequenceSpec.of(seq_dir)],
        builtin_schema("semantickitti"),
        PipelineConfig(),
        root,
        until="smooth",
        runtime=Runtime(cache_dir=cache),
    )
    return run.only().folder


def digest_outputs(run_dir: Path) -> dict[str, str]:
    out = {}
    for stage in TIMED:
        for name in OUTPUTS[stage]:
            path = run_dir / name
            files = sorted(path.iterdir()) if path.is_dir() else [path]
            h = hashlib.sha256()
            for f in files:
                h.update(f.name.encode())
                h.update(f.read_bytes())
            out[name] = h.hexdigest()
    return out


# ----------------------------------------------------------------------------------------- timing
@dataclass
class StageTimes:
    wall: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in TIMED})
    cpu: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in TIMED})


def run_once(
    version: Version, seq_dir: Path, prepared: Path, work: Path, times: StageTimes
) -> dict[str, str]:
    run_dir = work / "timed"
    shutil.rmtree(run_dir, ignore_errors=True)
    shutil.copytree(prepared, run_dir, copy_function=shutil.copyfile)
    for stage in TIMED:
        for name in OUTPUTS[stage]:
            p = run_dir / name
            shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
    schema = version.schema.builtin_schema("semantickitti")
    cfg, _ = baseline_config(version)
    ctx = version.runner._context(
        seq_dir, schema, cfg, run_dir, progress=None, frames=None, runtime=version.runtime
    )
    table = {s.name: s for s in version.stages.STAGE_TABLE}
    n = len(ctx.frames)
    for stage in TIMED:
        c, t = time.process_time(), time.perf_counter()
        table[stage].run(ctx)
        times.wall[stage].append((time.perf_counter() - t) / n)
        times.cpu[stage].append((time.process_time() - c) / n)
    return digest_outputs(run_dir)


def bench_sequence(
    label: str, seq_dir: Path, prepared: Path, versions: list[Version], repeat: int, work: Path
) -> dict[str, Any]:
    seq = KittiSequence(seq_dir)
    n_pts = statistics.mean(seq.frame(i).points.shape[0] for i in range(len(seq)))
    times = {v.name: StageTimes() for v in versions}
    digests: dict[str, dict[str, str]] = {}
    for _ in range(repeat):
        for v in versions:  # alternating, so both see the same machine load
            digests[v.name] = run_once(v, seq_dir, prepared, work, times[v.name])
    base, new = versions[0], versions[-1]
    identical = all(digests[v.name] == digests[base.name] for v in versions)
    ms = {v.name: {s: 1e3 * statistics.median(times[v.name].wall[s]) for s in TIMED} for v in versions}
    cpu = {v.name: {s: 1e3 * statistics.median(times[v.name].cpu[s]) for s in TIMED} for v in versions}
    rows = []
    for s in (*TIMED, "total"):

        def get(d: dict[str, float], s: str = s) -> float:
            return sum(d.values()) if s == "total" else d[s]

        walls = [get(ms[v.name]) for v in versions]
        rows.append([s, *walls, f"{walls[0] / walls[-1]:.2f}x", get(cpu[base.name]), get(cpu[new.name])])
    print_table(
        f"{label}: {seq_dir} ({len(seq)} scans, {n_pts / 1e3:.1f} k points per scan), ms per scan, median of "
        f"{repeat}; outputs identical: {'yes' if identical else 'NO'}",
        ["stage", *(f"{v.name} wall" for v in versions), "ratio", "baseline CPU", "new CPU"],
        rows,
    )
    return {
        "sequence": str(seq_dir),
        "scans": len(seq),
        "points_per_scan": n_pts,
        "identical": identical,
        "wall_ms_per_scan": ms,
        "cpu_ms_per_scan": cpu,
        "runs_s_per_scan": {v.name: {"wall": times[v.name].wall, "cpu": times[v.name].cpu} for v in versions},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="/tmp/demo/sequences/00", help="KITTI-layout sequence folder.")
    ap.add_argument("--points", type=int, default=120_000, help="Points per scan of the padded copy.")
    ap.add_argument("--repeat", type=int, default=3, help="Timed runs per version and sequence.")
    ap.add_argument(
        "--threads", type=int, default=Runtime().frame_threads, help="frame_threads of this tree."
    )
    ap.add_argument("--baseline", default="c472ae0", help="Git commit of the baseline.")
    ap.add_argument("--work", default=None, help="Folder for data and runs (default: a temp folder).")
    ap.add_argument("--name", default=None, help="Result file: RESULTS_DIR/NAME.json (bench_scan[_quick]).")
    ap.add_argument("--results-dir", type=Path, default=RESULTS_DIR, help="Folder of the result file.")
    ap.add_argument(
        "--quick",
        action="store_true",
        help=f"Smoke run: a generated {QUICK_FRAMES}-frame street in the work folder (no --sequence), padded "
        f"to {QUICK_POINTS:,} points, 1 repeat.",
    )
    args = ap.parse_args()

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_scan_"))
    if args.quick:
        from leap_core.synth import SynthConfig, generate_sequence

        args.sequence = str(generate_sequence(work / "synth", SynthConfig(frames=QUICK_FRAMES)).path)
        args.points, args.repeat = QUICK_POINTS, 1
    seq_dir = Path(args.sequence)
    if not (seq_dir / "velodyne").is_dir():
        sys.exit(f"{seq_dir}: not a sequence folder; generate the demo first: leap synth /tmp/demo")
    versions = [import_baseline(args.baseline, work), current_version(1)]
    if args.threads != 1:
        versions.append(current_version(args.threads))
    _, dropped = baseline_config(versions[0])
    print(
        f"baseline {args.baseline}: today's default settings it does not know, left out: "
        f"{', '.join(dropped) or 'none'}\n"
    )

    # The stage functions of both versions run on a copy of the prepared sequence folder (the baseline's
    # run folder held its one sequence's files at the top: the same files).
    demo_run = prepare(seq_dir, work / "prepared_demo", work / "cache2d")
    padded = padded_copy(seq_dir, work / "padded" / "sequences" / "00", args.points)
    padded_run = prepare(padded, work / "prepared_padded", work / "cache2d")

    results = {
        "demo": bench_sequence("demo", seq_dir, demo_run, versions, args.repeat, work),
        "padded": bench_sequence(
            f"padded to {args.points} points", padded, padded_run, versions, args.repeat, work
        ),
    }
    total = sum(results["padded"]["wall_ms_per_scan"][versions[-1].name].values())
    cpu_total = sum(results["padded"]["cpu_ms_per_scan"][versions[-1].name].values())
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(
        f"this tree, {args.points} points per scan: {total:.1f} ms wall, {cpu_total:.1f} ms CPU per scan "
        f"for the four stages (target 40 ms); load average {load} (1, 5, 15 min) on {os.cpu_count()} CPUs"
    )
    path = write_results(
        args.name or ("bench_scan_quick" if args.quick else "bench_scan"),
        {
            "baseline": args.baseline,
            "baseline_settings_left_out": dropped,
            "frame_threads": args.threads,
            "repeat": args.repeat,
            **results,
        },
        args.results_dir,
    )
    print(f"wrote {path}")
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
