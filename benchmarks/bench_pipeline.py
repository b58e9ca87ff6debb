"""End-to-end time of ``run_pipeline`` on the demo sequence (a run of that one sequence), per stage, plus
cache and resume behaviour.

Target: the default demo (≈ 60 frames × ~100k points, simulated labeler,
no 3D-CN) runs end to end in well under a minute on 2 cores. Baseline, in the same process: the I/O
floor, i.e. just reading every scan, ground-truth label file and 2D ground-truth PNG once (what any
pipeline must at least do); the ratio says how much the labeling work costs on top of reading the data.

Also measured: a second run on the same folder (every stage cached), a run after changing the smoothing
``k`` (smooth and later stages only), and the peak memory the cold run added.

Usage::

    .venv/bin/leap synth /tmp/demo                      # once: the default demo sequence
    .venv/bin/python benchmarks/bench_pipeline.py --sequence /tmp/demo/sequences/00 [--3dcn]

Prints a table and writes ``benchmarks/results/bench_pipeline.json``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import PeakMemory, print_table, write_results

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.datasets.kitti import KittiSequence
from leap_core.pipeline import (
    STAGES,
    SequenceResult,
    SequenceSpec,
    load_metrics,
    result_tables,
    run_pipeline,
)
from leap_core.schema import builtin_schema


def io_floor(seq: KittiSequence) -> float:
    """Seconds to read every scan, label file and 2D ground-truth image once (no processing)."""
    t = time.perf_counter()
    for frame in seq:
        _ = frame.points
        if frame.has_labels:
            _ = frame.labels
        if seq.has_gt2d:
            _ = frame.gt2d_semantic, frame.gt2d_instance
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="/tmp/demo/sequences/00", help="KITTI-layout sequence folder.")
    ap.add_argument("--3dcn", dest="cn", action="store_true", help="Also run the 3D Consistency Network.")
    ap.add_argument("--work", default=None, help="Folder for the run directories (default: a temp folder).")
    ap.add_argument("--name", default="bench_pipeline", help="Result file: benchmarks/results/NAME.json.")
    args = ap.parse_args()

    seq_dir = Path(args.sequence)
    if not (seq_dir / "velodyne").is_dir():
        sys.exit(f"{seq_dir}: not a sequence folder; generate the demo first: leap synth /tmp/demo")
    seq = KittiSequence(seq_dir)
    n_points = sum(f.points.shape[0] for f in seq)
    schema = builtin_schema("semantickitti")
    cfg = config_from_dict({"consistency": {"enabled": bool(args.cn)}}, PipelineConfig())

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    run_dir = work / "run"
    shutil.rmtree(run_dir, ignore_errors=True)
    specs = [SequenceSpec.of(seq_dir)]

    floor = min(io_floor(seq) for _ in range(2))  # second pass: page cache warm, as in the timed run
    pm = PeakMemory()
    t0 = time.perf_counter()
    with pm.measure():
        cold_run = run_pipeline(specs, schema, cfg, run_dir)
    total = time.perf_counter() - t0
    cold = cold_run.only()
    # Tables of the default config, before the k-change rerun below overwrites the metrics.
    tables = result_tables(cold.folder)
    metrics = load_metrics(cold.folder)

    def again(config: PipelineConfig) -> tuple[SequenceResult, float]:
        t = time.perf_counter()
        result = run_pipeline(specs, schema, config, run_dir).only()
        return result, time.perf_counter() - t

    cached, t_cached = again(cfg)
    k_cfg = config_from_dict({"smoothing": {"k": cfg.smoothing.k + 2}}, cfg)
    k_run, t_k = again(k_cfg)

    # The 3D-CN's rounds run over the run's sequences between their smooth and 3dcn stages: their time is
    # the run's (joint_seconds); a sequence's own 3dcn stage only links their grids.
    stage_seconds = {s: r.seconds for s, r in cold.stages.items()}
    if cold_run.joint_seconds:
        stage_seconds["3dcn"] += cold_run.joint_seconds
    rows = [
        [s, f"{stage_seconds[s]:.2f}", f"{100 * stage_seconds[s] / total:.0f}%", r.status]
        for s, r in cold.stages.items()
    ]
    rows.append(["total (cold)", f"{total:.2f}", "100%", ""])
    print_table(
        f"run_pipeline on {seq_dir} ({len(seq)} frames, {n_points / 1e6:.2f} M points, simulated labeler"
        f"{', 3D-CN' if args.cn else ''})",
        ["stage", "seconds", "share", "status"],
        rows,
    )
    summary = [
        ["I/O floor (read scans, labels, 2D GT)", f"{floor:.2f}", "1.0x"],
        ["cold run, all stages", f"{total:.2f}", f"{total / floor:.1f}x"],
        ["second run, all cached", f"{t_cached:.2f}", f"{t_cached / floor:.2f}x"],
        [
            f"smoothing k → {k_cfg.smoothing.k} (reruns {', '.join(k_run.ran)})",
            f"{t_k:.2f}",
            f"{t_k / floor:.1f}x",
        ],
        ["points per second (cold)", f"{n_points / total / 1e6:.2f} M/s", ""],
        ["peak memory added (cold)", f"{pm.added / 2**20:.0f} MiB", "" if pm.exact else "lower bound"],
    ]
    print_table("time against the I/O floor (same process)", ["what", "value", "ratio"], summary)
    if tables:
        print(tables + "\n")
    path = write_results(
        args.name,
        {
            "sequence": str(seq_dir),
            "frames": len(seq),
            "points": n_points,
            "config": {"labeler": cfg.labeler, "3dcn": bool(args.cn)},
            "stage_seconds": stage_seconds,
            "total_seconds": total,
            "io_floor_seconds": floor,
            "ratio_vs_io_floor": total / floor,
            "cached_rerun_seconds": t_cached,
            "cached_rerun_ran": cached.ran,
            "k_change_seconds": t_k,
            "k_change_ran": k_run.ran,
            "peak_memory_added_bytes": pm.added,
            "peak_memory_exact": pm.exact,
            "metrics": None
            if metrics is None
            else {
                p: {
                    r: {"miou": m.miou, "category_miou": m.category_miou, "labeled_share": m.labeled_share}
                    for r, m in rows_.items()
                }
                for p, rows_ in metrics.items()
            },
            "coverage_ratio": None if cold.metrics is None else cold.metrics.coverage_ratio,
        },
    )
    print(f"wrote {path}")
    assert list(cold.stages) == list(STAGES)
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
