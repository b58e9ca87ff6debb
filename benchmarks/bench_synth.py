"""Benchmark: generating the default demo sequence (``leap synth``), target ≤ 60 s on the 2-core CPU.

Rows:

- the default sequence (60 frames, full-size image, 64 beams) with 2 worker processes (the CLI default on
  a 2-core machine) and, as the baseline measured in the same process, with 1 process; the ratio is the
  pool's speed-up. Wall seconds, CPU seconds (this process and its children), points per scan and the share
  of points that project into the image.
- a per-stage CPU breakdown of single frames (LiDAR sweep, camera image + 2D ground truth, file writing),
  and the ray-casting work with per-primitive rectangle culling against a brute-force baseline (every
  primitive in range against every ray) on a 4× coarser LiDAR grid, so the baseline stays affordable.

The machine is shared with other work: wall times stretch under load while CPU times stay near what an
idle machine needs. Usage::

    .venv/bin/python benchmarks/bench_synth.py            # full run (~2-3 minutes)
    .venv/bin/python benchmarks/bench_synth.py --quick    # 12 frames, no 1-process baseline

Writes ``benchmarks/results/bench_synth.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import print_table, write_results

from leap_core.synth import LidarConfig, SynthConfig, generate_sequence
from leap_core.synth.camera import camera_to_world, render
from leap_core.synth.generator import _Worker
from leap_core.synth.lidar import beam_elevations, ray_grid, scan
from leap_core.synth.raycast import cast_grid, spherical_tasks


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def run_sequence(cfg: SynthConfig, workers: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        c0, t0 = _cpu(), time.perf_counter()
        stats = generate_sequence(tmp, cfg, workers=workers)
        wall, cpu = time.perf_counter() - t0, _cpu() - c0
    return {
        "workers": workers,
        "frames": cfg.frames,
        "wall_s": wall,
        "cpu_s": cpu,
        "points_per_scan": float(stats.points.mean()),
        "points_min": int(stats.points.min()),
        "points_max": int(stats.points.max()),
        "in_image_share": stats.in_image_share,
    }


def stage_breakdown(cfg: SynthConfig, frames: list[int]) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        for sub in ("velodyne", "labels", "image_2", "gt2d/semantic", "gt2d/instance"):
            (Path(tmp) / sub).mkdir(parents=True)
        c0 = time.process_time()
        w = _Worker(cfg, Path(tmp))
        init = time.process_time() - c0
        lidar, camera, total = [], [], []
        for i in frames:
            prims = w.scene.primitives_at(i)
            rng = np.random.default_rng(i)
            c = time.process_time()
            scan(prims, w.poses[i], cfg.lidar, rng, w.lidar_rays)
            lidar.append(time.process_time() - c)
            c = time.process_time()
            render(
                prims,
                len(w.scene.static),
                camera_to_world(cfg.camera, w.poses[i]),
                cfg.camera,
                sun=w.scene.sun,
                shadows=w.shadows,
                rng=rng,
                rays=w.pixel_rays,
            )
            camera.append(time.process_time() - c)
            c = time.process_time()
            w.frame(i)
            total.append(time.process_time() - c)
    return {
        "init_cpu_s": init,
        "lidar_cpu_s": float(np.median(lidar)),
        "camera_cpu_s": float(np.median(camera)),
        "frame_cpu_s": float(np.median(total)),
        "primitives_static": len(w.scene.static),
    }


def culling_vs_brute(cfg: SynthConfig, frame: int) -> dict:
    """Rectangle-culled casting vs every in-range primitive against every ray (coarse LiDAR grid)."""
    coarse = LidarConfig(azimuth_step_deg=cfg.lidar.azimuth_step_deg * 4)
    with tempfile.TemporaryDirectory() as tmp:
        w = _Worker(cfg, Path(tmp))
    prims = w.scene.primitives_at(frame)
    pose = w.poses[frame]
    rays = ray_grid(coarse)
    dirs = np.einsum("ij,jba->iba", pose[:3, :3].astype(np.float32), rays)
    tasks = spherical_tasks(
        prims, np.linalg.inv(pose), beam_elevations(coarse), rays.shape[2], coarse.max_range
    )
    c = time.process_time()
    _, p1 = cast_grid(prims, pose[:3, 3], dirs, tasks, coarse.min_range, coarse.max_range)
    culled = time.process_time() - c
    in_range = np.unique(tasks[:, 0])
    full = np.array([[p, 0, rays.shape[1], 0, rays.shape[2]] for p in in_range])
    c = time.process_time()
    _, p2 = cast_grid(prims, pose[:3, 3], dirs, full, coarse.min_range, coarse.max_range)
    brute = time.process_time() - c
    return {
        "rays": int(rays.shape[1] * rays.shape[2]),
        "primitives_in_range": len(in_range),
        "culled_cpu_s": culled,
        "brute_cpu_s": brute,
        "same_result": bool((p1 == p2).all()),
        "ray_tests_culled": int(((tasks[:, 2] - tasks[:, 1]) * (tasks[:, 4] - tasks[:, 3])).sum()),
        "ray_tests_brute": int(len(in_range) * rays.shape[1] * rays.shape[2]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--quick", action="store_true", help="12 frames, no 1-process baseline")
    args = ap.parse_args()
    frames = 12 if args.quick else args.frames
    cfg = SynthConfig(frames=frames)

    runs = [run_sequence(cfg, 2)]
    if not args.quick:
        runs.append(run_sequence(cfg, 1))
    base = runs[-1]
    rows = [
        [
            f"{r['frames']} frames, {r['workers']} worker(s)",
            r["wall_s"],
            r["cpu_s"],
            base["wall_s"] / r["wall_s"],
            r["points_per_scan"],
            100 * r["in_image_share"],
        ]
        for r in runs
    ]
    print_table(
        "leap synth, default config (target: default 60-frame sequence <= 60 s wall on 2 cores)",
        ["run", "wall s", "cpu s", "x vs 1 proc", "points/scan", "% in image"],
        rows,
    )

    stages = stage_breakdown(cfg, [0, frames // 2, frames - 1])
    print_table(
        "CPU seconds per frame (median of 3 frames, one process)",
        ["stage", "cpu s"],
        [
            ["scene + caches (once)", stages["init_cpu_s"]],
            ["LiDAR sweep", stages["lidar_cpu_s"]],
            ["camera + 2D GT (incl. shadow tiles)", stages["camera_cpu_s"]],
            ["whole frame incl. writing", stages["frame_cpu_s"]],
        ],
    )

    cull = culling_vs_brute(cfg, frames // 2)
    print_table(
        f"ray casting, LiDAR at 4x coarser azimuth ({cull['rays']} rays, "
        f"{cull['primitives_in_range']} primitives)",
        ["method", "cpu s", "ray tests", "x vs brute"],
        [
            [
                "rectangle culling",
                cull["culled_cpu_s"],
                cull["ray_tests_culled"],
                cull["brute_cpu_s"] / cull["culled_cpu_s"],
            ],
            ["brute force (baseline)", cull["brute_cpu_s"], cull["ray_tests_brute"], 1.0],
        ],
    )
    path = write_results(
        "bench_synth", {"target_s": 60.0, "sequence_runs": runs, "stages": stages, "culling": cull}
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
