"""Benchmark: what a camera rig costs the 2D stage and the projection, per frame and per camera.

Data: the demo street generated twice from the same seed, with the front camera alone and with a surround
rig of ``--cameras`` cameras (``leap synth --cameras``; the front camera's files are the same bytes in
both). Work: the pipeline's own ``labels2d`` stage (the simulated labeler, no 2D cache: every image is
labeled) and ``project`` stage (projection, depth clustering and painting per camera, the cameras'
observations joined), each run on the same frames in fresh run folders, ``--repeat`` times. The baseline
is the one-camera sequence, timed in the same process.

Rows: per sequence and stage, seconds per frame, seconds per camera image and the ratio to the one-camera
run (a rig of N cameras costing N× is "linear in the cameras"). A model labeler (Grounding DINO + SAM,
SAM 3) labels each camera's image as one more image, so its per-camera cost is its per-image cost of
``bench_2d.py``.

Run: ``.venv/bin/python benchmarks/bench_rig.py`` (6 frames at the demo's size, a minute or two on a CPU);
``--quick``: 2 frames at a quarter of the image size (seconds). Writes
``benchmarks/results/bench_rig[_quick].json``.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, print_table, write_results

from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import KittiSequence
from leap_core.pipeline import SequenceSpec, run_pipeline
from leap_core.schema import builtin_schema
from leap_core.synth import SynthConfig, generate_sequence
from leap_core.synth.camera import CameraConfig
from leap_core.synth.lidar import LidarConfig


def time_stages(seq: Path, out: Path, repeat: int) -> dict[str, float]:
    """Median seconds of the ``labels2d`` and the ``project`` stage on ``seq``, each repeat in a fresh run
    folder under ``out``."""
    schema = builtin_schema("semantickitti")
    spec = SequenceSpec.of(seq)
    times: dict[str, list[float]] = {"labels2d": [], "project": []}
    for r in range(repeat):
        run = out / f"run{r}"
        for stage, runs in times.items():  # the second call resumes: only ``project`` runs
            t = time.perf_counter()
            run_pipeline([spec], schema, PipelineConfig(), run, until=stage)
            runs.append(time.perf_counter() - t)
        shutil.rmtree(run)
    return {k: statistics.median(v) for k, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 frames at a quarter of the image size")
    ap.add_argument("--frames", type=int, default=6, help="frames of each sequence")
    ap.add_argument("--cameras", type=int, default=4, choices=(2, 4), help="cameras of the rig")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per sequence (median reported)")
    ap.add_argument("--results-dir", type=Path, default=None, help="where the JSON goes")
    args = ap.parse_args()
    base = SynthConfig(frames=args.frames)
    if args.quick:
        base = replace(
            base,
            frames=2,
            lidar=LidarConfig(beams=24, azimuth_step_deg=0.8),
            camera=CameraConfig().scaled(0.25),
        )
        args.repeat = 1
    rows: list[list[Any]] = []
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bench_rig_") as tmp:
        root = Path(tmp)
        for n in (1, args.cameras):
            path = generate_sequence(root / f"data{n}", replace(base, cameras=n)).path
            images = sum(v.has_image for f in KittiSequence(path) for v in f.cameras())
            got = time_stages(path, root / f"runs{n}", args.repeat)
            figures[f"{n}"] = {"images": images, **got}
        frames = base.frames
        for n, fig in figures.items():
            for stage in ("labels2d", "project"):
                ratio = fig[stage] / figures["1"][stage]
                rows.append(
                    [
                        f"{stage}, {n} camera{'s' if n != '1' else ''}" + (" (baseline)" if n == "1" else ""),
                        fig[stage] / frames,
                        fig[stage] / fig["images"],
                        ratio,
                    ]
                )
    size = f"{base.camera.width}×{base.camera.height}"
    title = f"bench_rig: {frames} frames, {size} images, median of {args.repeat}"
    print_table(title, ["stage, rig", "s / frame", "s / camera image", "ratio to 1 camera"], rows)
    n = str(args.cameras)
    print(
        f"ratio {n} cameras / 1 camera: labels2d {figures[n]['labels2d'] / figures['1']['labels2d']:.2f}×, "
        f"project {figures[n]['project'] / figures['1']['project']:.2f}× (linear in the cameras = {n}×)"
    )
    name = "bench_rig_quick" if args.quick else "bench_rig"
    payload = {"frames": frames, "repeat": args.repeat, "figures": figures}
    write_results(name, payload, args.results_dir or RESULTS_DIR)


if __name__ == "__main__":
    main()
