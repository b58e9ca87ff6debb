"""Estimated poses (``leap poses``) against a sequence's true poses: the previous estimator (KISS-ICP alone)
beside the current one (KISS-ICP refined by the pose graph), on the same scans in the same process.

Per sequence, each estimator gives:

- **drift**: the KITTI odometry devkit's mean translation error (%) and rotation error (deg/100 m)
  (``leap_core.trajectory.segment_errors``: a segment from every 10th frame per length) on eight lengths of
  a tenth of the drive each (KITTI's 100..800 m on drives of 800 m or more; also reported where the drive
  is long enough);
- **first step**: the estimate's first step over its second, relative to the truth's (1 = as right as the
  second; ``leap_core.trajectory.first_step_ratio``), where the car is moving at the start;
- the absolute trajectory error (RMSE after a rigid alignment), the median point-to-plane residual between
  neighbouring scans at the estimated poses, and the time per scan (both passes), beside the same
  process's time to only read the scans (the I/O floor any odometry pays).

With ``--labels`` it also runs ``run_pipeline`` on a copy without poses (current estimator) and on the
original (true poses), the same settings otherwise (the schema's preset, simulated labeler, 3D-CN off):
voxel mIoU on both protocols, and the difference.

Worlds (``--world``, generated in a temp folder; the street worlds with a tiny camera, which changes no
scan and no pose): *report* worlds ``demo`` (street seed 0, 60 frames: `leap synth`'s demo), ``demo-hard``
(street seed 0, 80 frames, the car pulling away from rest at 1.6 m/s², 5 cm range noise), ``long``
(street seed 11, 240 frames), ``street-32`` (seed 0, 80 frames), ``agri-uav`` (seed 0, 40 frames);
*tuning* worlds, on which the refinement's settings were chosen: ``tune-street`` (seed 21, 80 frames),
``tune-hard`` (seed 21, from rest, 5 cm noise), ``tune-street-32`` (seed 22), ``tune-agri-uav`` (seed 101);
``tiny`` (12 frames of a coarse 32-beam street) is the smallest run, which ``--quick`` picks.

Usage::

    .venv/bin/python benchmarks/bench_poses.py --world demo --world demo-hard --world long \\
        --world street-32 --world agri-uav
    .venv/bin/python benchmarks/bench_poses.py --sequence /data/sequences/00   # a sequence with poses.txt
    .venv/bin/python benchmarks/bench_poses.py --quick                          # smallest, for a test

Prints a table and writes ``benchmarks/results/bench_poses.json`` (``--results-dir`` elsewhere).
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, print_table, write_results

from leap_core.datasets.kitti import KittiSequence
from leap_core.odometry import OdometryConfig, estimate_sequence_poses, write_estimated_poses
from leap_core.synth import CameraConfig, EgoConfig, LidarConfig, SceneConfig, SynthConfig, generate_sequence
from leap_core.synth.agri import AgriSynthConfig
from leap_core.synth.domains import domain_config
from leap_core.trajectory import KITTI_SEGMENT_LENGTHS, compare_with_truth, segment_errors

ESTIMATORS: dict[str, OdometryConfig] = {
    "KISS-ICP (previous)": OdometryConfig(refine=None),
    "+ pose graph (current)": OdometryConfig(),
}
"""The estimators compared, by the name the table gives them."""


def _street(domain: str, frames: int, seed: int, *, from_rest: bool = False) -> SynthConfig:
    """A street world's generator config with a tiny camera (scans and poses do not depend on it);
    ``from_rest``: the car starts at rest and the range noise is 5 cm."""
    base = domain_config(domain, frames, seed)
    assert isinstance(base, SynthConfig)
    cfg = replace(base, camera=CameraConfig().scaled(0.1), shadows=False)
    if from_rest:
        cfg = replace(cfg, ego=EgoConfig(start_speed=0.0), lidar=replace(cfg.lidar, range_noise=0.05))
    return cfg


WORLDS: dict[str, Callable[[], SynthConfig | AgriSynthConfig]] = {
    "demo": lambda: _street("street", 60, 0),
    "demo-hard": lambda: _street("street", 80, 0, from_rest=True),
    "long": lambda: _street("street", 240, 11),
    "street-32": lambda: _street("street-32", 80, 0),
    "agri-uav": lambda: AgriSynthConfig(frames=40, seed=0),
    "tune-street": lambda: _street("street", 80, 21),
    "tune-hard": lambda: _street("street", 80, 21, from_rest=True),
    "tune-street-32": lambda: _street("street-32", 80, 22),
    "tune-agri-uav": lambda: AgriSynthConfig(frames=40, seed=101),
    "tiny": lambda: SynthConfig(
        frames=12,
        seed=3,
        lidar=LidarConfig(beams=32, azimuth_step_deg=0.6),
        camera=CameraConfig().scaled(0.1),
        scene=SceneConfig(margin=90.0),
        shadows=False,
    ),
}
"""World name → its generator config."""


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


def _num(v: float | None) -> float | None:
    """NaN (no segment of that length fits the drive) as JSON null."""
    return None if v is None or math.isnan(v) else float(v)


def measure(seq: KittiSequence, config: OdometryConfig) -> dict[str, Any]:
    """One estimator on ``seq`` (which has true poses) and its figures."""
    est = estimate_sequence_poses(seq, config)
    gt = seq.poses
    truth = compare_with_truth(gt, est.lidar)
    kitti = segment_errors(gt, est.lidar, KITTI_SEGMENT_LENGTHS)
    return {
        "method": config.method,
        **truth.to_dict(),
        "kitti_lengths_drift_pct": _num(kitti.translation_pct),
        "kitti_lengths_segments": kitti.count,
        "residual_median_m": est.residual,
        "ms_per_scan": 1000.0 * est.seconds / len(seq),
        "_estimate": est,
    }


def bench_sequence(seq_dir: Path, name: str, work: Path, labels: str | None) -> dict[str, Any]:
    """Both estimators on one sequence; with ``labels`` (a preset) also the label runs."""
    seq = KittiSequence(seq_dir)
    if not seq.has_poses:
        raise SystemExit(f"{seq_dir}: needs its true poses.txt to compare against")
    floor = read_floor(seq)
    out: dict[str, Any] = {"sequence": name, "path": str(seq_dir), "frames": len(seq)}
    out["read_scans_ms_per_frame"] = 1000.0 * floor / len(seq)
    runs = {label: measure(seq, cfg) for label, cfg in ESTIMATORS.items()}
    out["estimators"] = {label: {k: v for k, v in r.items() if k != "_estimate"} for label, r in runs.items()}
    out["path_m"] = runs["+ pose graph (current)"]["path_m"]
    if labels is not None:
        out["labels"] = label_runs(seq_dir, work, labels, runs["+ pose graph (current)"]["_estimate"])
    return out


def label_runs(seq_dir: Path, work: Path, preset: str, est: Any) -> dict[str, Any]:
    """The pipeline on the true poses and on the current estimate: voxel mIoU (%) per protocol."""
    from leap_core.config import config_from_dict
    from leap_core.pipeline import SequenceSpec, run_pipeline
    from leap_core.pipeline.evaluation import read_metrics_json
    from leap_core.presets import load_preset
    from leap_core.runtime import Runtime

    copy = linked_copy_without_poses(seq_dir, work / "no-poses" / "sequences" / seq_dir.name)
    write_estimated_poses(copy / "poses.txt", est)
    p = load_preset(preset)
    cfg = config_from_dict({"labeler": "simulated", "consistency": {"enabled": False}}, p.pipeline)
    runtime = Runtime(cache_dir=work / "cache2d")  # the 2D labels are computed once, for both runs
    result: dict[str, Any] = {"preset": preset}
    for name, dataset in (("true", seq_dir), ("estimated", copy)):
        run = run_pipeline([SequenceSpec.of(dataset)], p.schema, cfg, work / f"run-{name}", runtime=runtime)
        m = read_metrics_json(run.only().folder)
        if m is None:
            raise SystemExit(f"{dataset}: no metrics (the sequence needs ground-truth labels)")
        result[name] = {proto: _pct(m.miou(proto, "voxel")) for proto in ("camera", "all")}
    return result


def _pct(v: float | None) -> float:
    """A share in percent; NaN where the row has none (no class to average)."""
    return math.nan if v is None else 100.0 * v


def table_rows(results: list[dict[str, Any]]) -> list[list[str]]:
    """One row per sequence and estimator."""

    def fmt(v: float | None, spec: str, unit: str = "") -> str:
        return "n/a" if v is None else f"{v:{spec}}{unit}"

    rows = []
    for r in results:
        for label, e in r["estimators"].items():
            lengths = e["segment_lengths_m"]
            rows.append(
                [
                    f"{r['sequence']} ({r['frames']} frames, {r['path_m']:.0f} m)",
                    label,
                    f"{fmt(e['drift_pct'], '.2f', ' %')} ({lengths[0]:.0f}-{lengths[-1]:.0f} m)",
                    fmt(e["rotation_deg_per_100m"], ".2f"),
                    fmt(e["first_step_ratio"], ".3f"),
                    f"{100 * e['ate_m']:.1f} cm",
                    f"{100 * e['residual_median_m']:.2f} cm",
                    f"{e['ms_per_scan']:.0f} ({r['read_scans_ms_per_frame']:.0f})",
                ]
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", action="append", default=[], help="A sequence folder with true poses.")
    ap.add_argument("--world", action="append", default=[], choices=sorted(WORLDS), help="A generated world.")
    ap.add_argument("--quick", action="store_true", help="The smallest run: the 'tiny' world, no labels.")
    ap.add_argument("--labels", default=None, help="Also compare labels, with this preset (semantickitti).")
    ap.add_argument(
        "--work", default=None, help="Folder for generated worlds and runs (default: a temp one)."
    )
    ap.add_argument("--name", default=None, help="Result file: RESULTS_DIR/NAME.json.")
    ap.add_argument("--results-dir", default=str(RESULTS_DIR), help="Folder of the result file.")
    args = ap.parse_args()
    worlds = ["tiny"] if args.quick else args.world
    if not worlds and not args.sequence:
        ap.error("name at least one --world or --sequence (or --quick)")

    results = []
    with tempfile.TemporaryDirectory(dir=args.work) as tmp:
        for k, seq in enumerate(args.sequence):
            work = Path(tmp) / f"s{k}"
            results.append(bench_sequence(Path(seq), Path(seq).name, work, args.labels))
        for world in worlds:
            t = time.perf_counter()
            seq_dir = generate_sequence(Path(tmp) / world, WORLDS[world](), workers=1).path
            print(f"generated {world} in {time.perf_counter() - t:.0f} s", flush=True)
            results.append(bench_sequence(seq_dir, world, Path(tmp) / f"work-{world}", args.labels))

    print_table(
        "Estimated vs true poses: the previous estimator beside the current one (same scans, same process)",
        [
            "sequence",
            "estimator",
            "drift (segments)",
            "rot. deg/100 m",
            "first step",
            "ATE RMSE",
            "residual",
            "ms/scan (read only)",
        ],
        table_rows(results),
    )
    for r in results:
        if "labels" in r:
            lab = r["labels"]
            print(
                f"{r['sequence']}: voxel mIoU camera view true {lab['true']['camera']:.1f} / estimated "
                f"{lab['estimated']['camera']:.1f}, all points {lab['true']['all']:.1f} / "
                f"{lab['estimated']['all']:.1f}"
            )
    name = args.name or ("bench_poses_quick" if args.quick else "bench_poses")
    path = write_results(name, {"sequences": results}, Path(args.results_dir))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
