"""The Ray engine against the local one: the same run (a cut of the demo sequence) in fresh run folders, once
in this process and once with ``Runtime(ray_address="auto")`` on a local Ray instance, per stage; the exported
``.label`` / ``.conf`` bytes are compared.

Baseline, in the same process: the local run (``ray_address=None``). Ray's start (``ray.init``) is timed
apart, since a cluster is started once and serves many runs. Each engine runs ``--repeat`` times in fresh
folders; the table shows the median wall seconds per stage and the ratio Ray / local.

Usage::

    .venv/bin/python benchmarks/bench_ray.py --sequence data/demo/sequences/00 --frames 0:10 --cpus 2

Prints a table and writes ``benchmarks/results/bench_ray.json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.common import machine_info, print_table, write_results  # noqa: E402
from leap_core.pipeline import STAGES, run_pipeline  # noqa: E402
from leap_core.presets import builtin_preset  # noqa: E402
from leap_core.runtime import Runtime  # noqa: E402


def _exports(run_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((run_dir / "export").iterdir())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", type=Path, required=True, help="KITTI-layout sequence (the demo).")
    ap.add_argument("--frames", default="0:10", help="Frame numbers A:B.")
    ap.add_argument("--cpus", type=int, default=2, help="CPUs of the local Ray instance.")
    ap.add_argument("--repeat", type=int, default=2, help="Runs per engine.")
    ap.add_argument("--preset", default="demo")
    args = ap.parse_args()
    a, b = (int(x) for x in args.frames.split(":"))
    frames = range(a, b)
    preset = builtin_preset(args.preset)

    import ray

    t0 = time.perf_counter()
    # address="local": a new instance of --cpus CPUs even where a cluster runs (ray.init would join it).
    ray.init(address="local", num_cpus=args.cpus, include_dashboard=False, logging_level="ERROR",
             log_to_driver=False, object_store_memory=512 * 1024 * 1024)
    ray_start = time.perf_counter() - t0

    engines = {"local": Runtime(), "ray": Runtime(ray_address="auto")}
    walls: dict[str, list[float]] = {e: [] for e in engines}
    stage_s: dict[str, dict[str, list[float]]] = {e: {s: [] for s in STAGES} for e in engines}
    exports: dict[str, dict[str, bytes]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_ray_") as tmp:
        for rep in range(args.repeat):
            for name, runtime in engines.items():  # alternate, so load changes hit both alike
                run_dir = Path(tmp) / f"{name}{rep}"
                t = time.perf_counter()
                result = run_pipeline(args.sequence, preset.schema, preset.pipeline, run_dir, frames=frames,
                                      runtime=runtime)
                walls[name].append(time.perf_counter() - t)
                for s, r in result.stages.items():
                    stage_s[name][s].append(r.seconds)
                exports[name] = _exports(run_dir)
    ray.shutdown()
    same = exports["local"] == exports["ray"]

    rows = []
    for s in STAGES:
        lo, ra = statistics.median(stage_s["local"][s]), statistics.median(stage_s["ray"][s])
        rows.append([s, f"{lo:.2f}", f"{ra:.2f}", f"{ra / lo:.2f}" if lo > 0.005 else "-"])
    lo, ra = statistics.median(walls["local"]), statistics.median(walls["ray"])
    rows.append(["whole run", f"{lo:.2f}", f"{ra:.2f}", f"{ra / lo:.2f}"])
    print_table(
        f"{args.sequence} frames {args.frames}: local vs Ray ({args.cpus} CPUs), median of {args.repeat} "
        f"(ray.init {ray_start:.1f} s apart); exports identical: {same}",
        ["stage", "local s", "ray s", "ray / local"], rows,
    )
    write_results("bench_ray", {
        "machine": machine_info(), "sequence": str(args.sequence), "frames": args.frames, "cpus": args.cpus,
        "ray_init_s": ray_start, "wall_s": walls, "stage_s": stage_s, "exports_identical": same,
        "label_files": len([n for n in exports["ray"] if n.endswith(".label")]),
    })


if __name__ == "__main__":
    main()
