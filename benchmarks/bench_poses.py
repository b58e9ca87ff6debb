"""Estimated poses (KISS-ICP, ``leap poses``) against a sequence's true poses, and what they do to the labels.

Per sequence: a copy without ``poses.txt`` (files hard-linked) gets KISS-ICP poses as ``leap poses`` writes
them; then

- **odometry**: the KITTI odometry benchmark's relative translation error (%) and rotation error
  (deg/100 m), computed as its devkit does (``leap_core.trajectory.segment_errors``: a segment from every
  10th frame per length), on KITTI's lengths (100..800 m) where the drive is long enough and on eight
  lengths of a tenth of the drive each (the same ratio to the drive on short sequences); the absolute
  trajectory error (RMSE after a rigid alignment); KISS-ICP's time per frame, beside the same process's
  time to only read the scans (the I/O floor any odometry pays);
- **labels**: ``run_pipeline`` on the copy (estimated poses) and on the original (true poses), the same
  settings otherwise (the schema's preset, simulated labeler, 3D-CN off): mIoU of the point and voxel
  labels on both protocols, and the difference.

Target: translation drift ≤ 2 % and voxel mIoU within 2 points of the true-pose run.

Usage::

    leap synth /tmp/demo --frames 60 --seed 0              # the demo sequence
    leap synth /tmp/long --frames 240 --seed 11            # a >= 200-frame drive (another seed)
    .venv/bin/python benchmarks/bench_poses.py \
        --sequence /tmp/demo/sequences/00 --sequence /tmp/long/sequences/00

Prints a table and writes ``benchmarks/results/bench_poses.json``.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import print_table, write_results

from leap_core.config import config_from_dict
from leap_core.datasets.kitti import KittiSequence
from leap_core.odometry import OdometryConfig, estimate_sequence_poses, write_estimated_poses
from leap_core.pipeline import SequenceSpec, run_pipeline
from leap_core.presets import load_preset
from leap_core.runtime import Runtime
from leap_core.trajectory import (
    KITTI_SEGMENT_LENGTHS,
    ate_rmse,
    fitting_segment_lengths,
    path_distances,
    segment_errors,
)


def linked_copy_without_poses(src: Path, dst: Path) -> Path:
    """``dst``: every file of ``src`` hard-linked (copied across file systems), except ``poses.txt``."""
    for path in sorted(src.rglob("*")):
        rel = path.relative_to(src)
        if rel == Path("poses.txt") or not path.is_file():
            continue
        target = dst / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, target)
        except OSError:
            shutil.copy2(path, target)
    return dst


def read_floor(seq: KittiSequence) -> float:
    """Seconds to read every scan once."""
    t = time.perf_counter()
    for frame in seq:
        _ = frame.points
    return time.perf_counter() - t


def mious(folder: Path) -> dict[str, dict[str, float]]:
    """Protocol → row → mIoU (%) of a run's sequence folder."""
    from leap_core.pipeline.evaluation import read_metrics_json

    m = read_metrics_json(folder)
    if m is None:
        raise SystemExit(f"{folder}: no metrics (the sequence needs ground-truth labels)")
    return {p: {r: _pct(m.miou(p, r)) for r in m.rows} for p in ("camera", "all")}


def _pct(v: float | None) -> float:
    """A share in percent; NaN where the row has none (no class to average)."""
    return math.nan if v is None else 100.0 * v


def _num(v: float) -> float | None:
    """NaN (no segment of that length fits the drive) as JSON null."""
    return None if math.isnan(v) else v


def bench_sequence(seq_dir: Path, work: Path, preset: str, config: OdometryConfig) -> dict[str, Any]:
    true_seq = KittiSequence(seq_dir)
    if not true_seq.has_poses:
        raise SystemExit(f"{seq_dir}: needs its true poses.txt to compare against")
    copy = linked_copy_without_poses(seq_dir, work / "no-poses" / "sequences" / seq_dir.name)
    est_seq = KittiSequence(copy)
    assert not est_seq.has_poses

    floor = read_floor(est_seq)
    est = estimate_sequence_poses(KittiSequence(copy), config)
    write_estimated_poses(copy / "poses.txt", est)
    gt = true_seq.poses
    kitti = segment_errors(gt, est.lidar, KITTI_SEGMENT_LENGTHS)
    lengths = fitting_segment_lengths(gt)
    fitted = segment_errors(gt, est.lidar, lengths)

    p = load_preset(preset)
    cfg = config_from_dict({"labeler": "simulated", "consistency": {"enabled": False}}, p.pipeline)
    runtime = Runtime(cache_dir=work / "cache2d")  # the 2D labels are computed once, for both runs
    seconds, folders = {}, {}
    for name, dataset in (("true", seq_dir), ("estimated", copy)):
        t = time.perf_counter()
        run = run_pipeline([SequenceSpec.of(dataset)], p.schema, cfg, work / f"run-{name}", runtime=runtime)
        seconds[name] = time.perf_counter() - t
        folders[name] = run.only().folder
    m_true, m_est = mious(folders["true"]), mious(folders["estimated"])
    n = len(true_seq)
    return {
        "sequence": str(seq_dir),
        "frames": n,
        "path_m": float(path_distances(gt)[-1]),
        "kiss_icp": est.note()["settings"],
        "kitti_lengths": {
            "lengths_m": list(KITTI_SEGMENT_LENGTHS),
            "segments": kitti.count,
            "translation_pct": _num(kitti.translation_pct),
            "rotation_deg_per_100m": _num(kitti.rotation_deg_per_100m),
        },
        "fitted_lengths": {
            "lengths_m": list(lengths),
            "segments": fitted.count,
            "translation_pct": fitted.translation_pct,
            "rotation_deg_per_100m": fitted.rotation_deg_per_100m,
        },
        "ate_rmse_m": ate_rmse(gt, est.lidar),
        "kiss_icp_ms_per_frame": 1000.0 * est.seconds / n,
        "read_scans_ms_per_frame": 1000.0 * floor / n,
        "miou_true": m_true,
        "miou_estimated": m_est,
        "pipeline_seconds": seconds,
        "preset": preset,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--sequence",
        action="append",
        required=True,
        help="Sequence folder with true poses and ground truth (repeatable).",
    )
    ap.add_argument("--schema", default="semantickitti", help="Preset of the runs (the demo project's).")
    ap.add_argument("--work", default=None, help="Folder for copies and runs (default: a temp folder).")
    ap.add_argument("--name", default="bench_poses", help="Result file: benchmarks/results/NAME.json.")
    args = ap.parse_args()

    config = OdometryConfig()
    results = []
    for k, seq in enumerate(args.sequence):
        with tempfile.TemporaryDirectory(dir=args.work) as tmp:
            work = Path(tmp) / f"s{k}"
            work.mkdir()
            results.append(bench_sequence(Path(seq), work, args.schema, config))

    def fmt(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.2f}"  # no segment fits

    rows = []
    for r in results:
        fl, kl = r["fitted_lengths"], r["kitti_lengths"]
        vt, ve = r["miou_true"]["camera"]["voxel"], r["miou_estimated"]["camera"]["voxel"]
        at, ae = r["miou_true"]["all"]["voxel"], r["miou_estimated"]["all"]["voxel"]
        rows.append(
            [
                f"{Path(r['sequence']).parent.parent.name} ({r['frames']} frames, {r['path_m']:.0f} m)",
                f"{fl['lengths_m'][0]:.0f}-{fl['lengths_m'][-1]:.0f} m: {fl['translation_pct']:.2f} %",
                f"{fmt(kl['translation_pct'])} %",
                f"{fl['rotation_deg_per_100m']:.2f}",
                f"{100 * r['ate_rmse_m']:.1f} cm",
                f"{r['kiss_icp_ms_per_frame']:.0f} ({r['read_scans_ms_per_frame']:.0f})",
                f"{vt:.1f} / {ve:.1f} ({ve - vt:+.1f})",
                f"{at:.1f} / {ae:.1f} ({ae - at:+.1f})",
            ]
        )
    print_table(
        "Estimated (KISS-ICP) vs true poses",
        [
            "sequence",
            "transl. err (segments)",
            "at 100-800 m",
            "rot. deg/100 m",
            "ATE RMSE",
            "ms/frame (read only)",
            "voxel mIoU cam: true / est",
            "voxel mIoU all: true / est",
        ],
        rows,
    )
    path = write_results(args.name, {"sequences": results})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
