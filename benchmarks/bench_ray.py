"""The Ray engine against the local one: the same run (a cut of the demo sequence) in fresh run folders, once
in this process and once with ``Runtime(ray_address="auto")`` on a local Ray instance, per stage; the exported
``.label`` / ``.conf`` bytes are compared.

Baseline, in the same process: the local run (``ray_address=None``). Ray's start (``ray.init``) is timed
apart, since a cluster is started once and serves many runs. Each engine runs ``--repeat`` times in fresh
folders; the table shows the median wall seconds per stage and the ratio Ray / local.

``--3dcn`` turns the 3D-CN on (``--cn-steps N``: N training steps, the preset's ``min_steps``); its
inference then runs as Ray tasks too, its training in the driver either way. ``--second SEQ`` adds a
two-sequence run (``--sequence``'s frames and all of ``SEQ``, one run folder), locally (one sequence after
the other) and on Ray (both at once), with the wall seconds of its first pass (every sequence up to
``smooth``), the 3D-CN's rounds and its second pass.

``--inference N`` times only the 3D-CN's inference on the first N frames of ``--sequence`` (a seeded,
untrained network of the preset's backbone saved as a checkpoint: the cost does not depend on the
weights): in this process (``predict_from_checkpoint``, what the local loop computes) against
:class:`~leap_core.pipeline.executor.RayPredictor`, alternating, with the bytes compared.

Usage::

    .venv/bin/python benchmarks/bench_ray.py --sequence data/demo/sequences/00 --frames 0:10 --cpus 2
    .venv/bin/python benchmarks/bench_ray.py --sequence data/demo/sequences/00 --frames 0:60 --3dcn \
        --cn-steps 60 --repeat 1 --second /tmp/s2/sequences/00

Prints a table and writes ``benchmarks/results/bench_ray.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.common import machine_info, print_table, write_results  # noqa: E402
from leap_core.config import PipelineConfig  # noqa: E402
from leap_core.extras import MissingExtra  # noqa: E402
from leap_core.pipeline import STAGES, SequenceSpec, run_pipeline  # noqa: E402
from leap_core.pipeline.context import read_state  # noqa: E402
from leap_core.presets import builtin_preset  # noqa: E402
from leap_core.run_layout import RunLayout  # noqa: E402
from leap_core.runtime import Runtime  # noqa: E402


def _exports(folder: Path) -> dict[str, bytes]:
    """The export files of a run's sequence folder."""
    return {p.name: p.read_bytes() for p in sorted((folder / "export").iterdir())}


def _config(base: PipelineConfig, cn: bool, cn_steps: int | None) -> PipelineConfig:
    if not cn:
        return base
    consistency = dataclasses.replace(base.consistency, enabled=True)
    if cn_steps is not None:
        consistency = dataclasses.replace(consistency, min_steps=cn_steps)
    return dataclasses.replace(base, consistency=consistency)


TRAINING = "3dcn training"
"""The 3D-CN's training (in the driver on either engine), part of the 3dcn row's seconds."""


def _training_seconds(root: Path) -> float:
    """The training loops' seconds of a run's 3D-CN rounds (``meta["seconds"]`` of its checkpoints)."""
    import torch

    return sum(
        float(torch.load(p, weights_only=True)["meta"]["seconds"])
        for p in sorted(RunLayout(root).cn_dir.glob("3dcn_iter*.pt"))
    )


def _ray_tasks(root: Path) -> int:
    """The inference tasks of a run's last 3D-CN rounds computed on Ray (its ``3dcn/joint.json``)."""
    state = RunLayout(root).joint_state
    return int(json.loads(state.read_text()).get("ray_tasks", 0)) if state.is_file() else 0


def _multi_outputs(root: Path) -> dict[str, bytes]:
    """Every sequence's exports and grids of a run folder."""
    layout = RunLayout(root)
    out = {}
    for name in layout.names():
        lay = layout.sequence(name)
        out.update({f"{name}/export/{p.name}": p.read_bytes() for p in sorted(lay.export_dir.iterdir())})
        out.update({f"{name}/{p.name}": p.read_bytes() for p in sorted(lay.folder.glob("grid*.npz"))})
    return out


def _first_pass_spans(root: Path) -> dict[str, tuple[float, float]]:
    """Per sequence, (start, end) of its stages before the 3D-CN's rounds, from its ``stages.json``."""
    layout = RunLayout(root)
    spans = {}
    for name in layout.names():
        rec = read_state(layout.sequence(name))
        first = [rec[s] for s in STAGES[: STAGES.index("3dcn")] if "started" in rec.get(s, {})]
        spans[name] = (min(r["started"] for r in first), max(r["finished"] for r in first))
    return spans


def bench_multi(
    args: argparse.Namespace,
    cfg: PipelineConfig,
    schema,
    frames: range,
    tmp: Path,
    engines: dict[str, Runtime],
) -> dict[str, object]:
    """The two-sequence run, local then Ray, ``--repeat`` times each (fresh folders)."""
    specs = [SequenceSpec("a", args.sequence, frames), SequenceSpec("b", args.second)]
    walls: dict[str, list[float]] = {e: [] for e in engines}
    joint: dict[str, list[float]] = {e: [] for e in engines}
    first: dict[str, list[float]] = {e: [] for e in engines}
    overlap: dict[str, list[float]] = {e: [] for e in engines}
    outputs: dict[str, dict[str, bytes]] = {}
    for rep in range(args.repeat):
        for name, runtime in engines.items():
            root = tmp / f"multi-{name}{rep}"
            t = time.perf_counter()
            result = run_pipeline(specs, schema, cfg, root, runtime=runtime)
            walls[name].append(time.perf_counter() - t)
            joint[name].append(result.joint_seconds)
            spans = _first_pass_spans(root)
            (a0, a1), (b0, b1) = spans["a"], spans["b"]
            first[name].append(max(a1, b1) - min(a0, b0))
            overlap[name].append(max(0.0, min(a1, b1) - max(a0, b0)))
            outputs[name] = _multi_outputs(root)
    same = outputs["local"] == outputs["ray"]
    med = {
        k: {e: statistics.median(v[e]) for e in engines}
        for k, v in (
            ("first pass", first),
            ("3D-CN rounds", joint),
            ("whole run", walls),
            ("overlap", overlap),
        )
    }
    rows = [
        [
            k,
            f"{m['local']:.2f}",
            f"{m['ray']:.2f}",
            f"{m['ray'] / m['local']:.2f}" if m["local"] > 0.005 else "-",
        ]
        for k, m in med.items()
    ]
    print_table(
        f"two sequences ({args.sequence} {args.frames} + {args.second}): local (in turn) vs Ray (at once), "
        f"median of {args.repeat}; 'overlap' = seconds both sequences were in their first pass; outputs "
        f"identical: {same}",
        ["part", "local s", "ray s", "ray / local"],
        rows,
    )
    return {
        "second": str(args.second),
        "wall_s": walls,
        "joint_s": joint,
        "first_pass_s": first,
        "overlap_s": overlap,
        "outputs_identical": same,
        "files_compared": len(outputs["ray"]),
    }


def bench_inference(args: argparse.Namespace, cfg: PipelineConfig, tmp: Path) -> dict[str, object]:
    """The 3D-CN's inference alone, local vs Ray (module docstring)."""
    import torch

    from leap_core.consistency.backbone import PointSegmenter
    from leap_core.consistency.remote import inference_threads, predict_from_checkpoint
    from leap_core.consistency.train import save_checkpoint
    from leap_core.datasets.kitti import KittiSequence
    from leap_core.pipeline.executor import RayExecutor

    cn = cfg.consistency
    torch.manual_seed(0)
    checkpoint = tmp / "3dcn_iter1.pt"
    save_checkpoint(checkpoint, PointSegmenter(cn.backbone, 20), cn)
    seq = KittiSequence(args.sequence)
    frames = range(args.inference)
    threads = inference_threads(cn)
    predictor = RayExecutor("auto").predictor(cfg)

    def local() -> list[tuple[object, object]]:
        return list(
            predict_from_checkpoint(seq, list(frames), checkpoint, cn, cfg.fusion.voxel_size, threads)
        )

    def on_ray() -> list[tuple[object, object]]:
        return list(predictor(seq, frames, checkpoint))

    walls: dict[str, list[float]] = {"local": [], "ray": []}
    outs = {}
    for _ in range(args.repeat):
        for name, fn in (("local", local), ("ray", on_ray)):
            t = time.perf_counter()
            outs[name] = fn()
            walls[name].append(time.perf_counter() - t)
    same = all(
        k.tobytes() == k2.tobytes() and v.tobytes() == v2.tobytes()  # type: ignore[attr-defined]
        for (k, v), (k2, v2) in zip(outs["local"], outs["ray"], strict=True)
    )
    lo, ra = statistics.median(walls["local"]), statistics.median(walls["ray"])
    print_table(
        f"3D-CN inference of {args.sequence} frames 0:{args.inference}: this process ({threads} torch "
        f"threads) vs Ray tasks ({predictor.tasks // args.repeat} per pass), median of {args.repeat}; "
        f"identical: {same}",
        ["", "local s", "ray s", "ray / local"],
        [
            ["inference", f"{lo:.2f}", f"{ra:.2f}", f"{ra / lo:.2f}"],
            ["per frame", f"{lo / len(frames):.3f}", f"{ra / len(frames):.3f}", ""],
        ],
    )
    return {"frames": args.inference, "threads": threads, "wall_s": walls, "identical": same}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", type=Path, required=True, help="KITTI-layout sequence (the demo).")
    ap.add_argument("--frames", default="0:10", help="Frame numbers A:B.")
    ap.add_argument("--cpus", type=int, default=2, help="CPUs of the local Ray instance.")
    ap.add_argument("--repeat", type=int, default=2, help="Runs per engine.")
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--3dcn", dest="cn", action="store_true", help="Turn the 3D-CN on.")
    ap.add_argument("--cn-steps", type=int, default=None, help="3D-CN training steps (min_steps).")
    ap.add_argument("--second", type=Path, default=None, help="Also time a two-sequence run with this one.")
    ap.add_argument("--inference", type=int, default=None, help="Only time the 3D-CN's inference (N frames).")
    args = ap.parse_args()
    a, b = (int(x) for x in args.frames.split(":"))
    frames = range(a, b)
    preset = builtin_preset(args.preset)
    cfg = _config(preset.pipeline, args.cn or args.cn_steps is not None, args.cn_steps)

    try:
        import ray
    except ModuleNotFoundError as exc:  # the ray extra
        raise SystemExit(f"error: {MissingExtra('ray', exc.name)}") from None

    t0 = time.perf_counter()
    # address="local": a new instance of --cpus CPUs even where a cluster runs (ray.init would join it).
    ray.init(
        address="local",
        num_cpus=args.cpus,
        include_dashboard=False,
        logging_level="ERROR",
        log_to_driver=False,
        object_store_memory=512 * 1024 * 1024,
    )
    ray_start = time.perf_counter() - t0
    if args.inference is not None:
        with tempfile.TemporaryDirectory(prefix="bench_ray_") as tmp:
            result = bench_inference(args, cfg, Path(tmp))
        ray.shutdown()
        write_results(
            "bench_ray_inference",
            {"machine": machine_info(), "cpus": args.cpus, "ray_init_s": ray_start, **result},
        )
        return

    engines = {"local": Runtime(), "ray": Runtime(ray_address="auto")}
    walls: dict[str, list[float]] = {e: [] for e in engines}
    stage_s: dict[str, dict[str, list[float]]] = {e: {s: [] for s in (*STAGES, TRAINING)} for e in engines}
    exports: dict[str, dict[str, bytes]] = {}
    tasks: dict[str, int] = {}
    with tempfile.TemporaryDirectory(prefix="bench_ray_") as tmp:
        for rep in range(args.repeat):
            for name, runtime in engines.items():  # alternate, so load changes hit both alike
                root = Path(tmp) / f"{name}{rep}"
                t = time.perf_counter()
                run = run_pipeline(
                    [SequenceSpec.of(args.sequence, frames)], preset.schema, cfg, root, runtime=runtime
                )
                walls[name].append(time.perf_counter() - t)
                result = run.only()
                for s, r in result.stages.items():
                    # The 3D-CN's rounds are the run's (its sequences' 3dcn stages only link their grids).
                    stage_s[name][s].append(r.seconds + (run.joint_seconds if s == "3dcn" else 0.0))
                exports[name] = _exports(result.folder)
                if cfg.consistency.enabled:
                    grids = sorted(result.folder.glob("grid*.npz"))
                    exports[name].update({p.name: p.read_bytes() for p in grids})
                    tasks[name] = _ray_tasks(root)
                    stage_s[name][TRAINING].append(_training_seconds(root))
        multi = (
            bench_multi(args, cfg, preset.schema, frames, Path(tmp), engines)
            if args.second is not None
            else None
        )
    ray.shutdown()
    same = exports["local"] == exports["ray"]

    rows = []
    for s in (*STAGES, TRAINING) if cfg.consistency.enabled else STAGES:
        lo, ra = statistics.median(stage_s["local"][s]), statistics.median(stage_s["ray"][s])
        rows.append([s, f"{lo:.2f}", f"{ra:.2f}", f"{ra / lo:.2f}" if lo > 0.005 else "-"])
    lo, ra = statistics.median(walls["local"]), statistics.median(walls["ray"])
    rows.append(["whole run", f"{lo:.2f}", f"{ra:.2f}", f"{ra / lo:.2f}"])
    print_table(
        f"{args.sequence} frames {args.frames}: local vs Ray ({args.cpus} CPUs), median of {args.repeat} "
        f"(ray.init {ray_start:.1f} s apart); 3D-CN {'on' if cfg.consistency.enabled else 'off'} "
        f"(inference tasks on Ray: {tasks.get('ray', 0)}); exports and grids identical: {same}",
        ["stage", "local s", "ray s", "ray / local"],
        rows,
    )
    write_results(
        "bench_ray",
        {
            "machine": machine_info(),
            "sequence": str(args.sequence),
            "frames": args.frames,
            "cpus": args.cpus,
            "ray_init_s": ray_start,
            "wall_s": walls,
            "stage_s": stage_s,
            "exports_identical": same,
            "label_files": len([n for n in exports["ray"] if n.endswith(".label")]),
            "consistency": cfg.consistency.enabled,
            "cn_min_steps": cfg.consistency.min_steps,
            "inference_tasks": tasks.get("ray", 0),
            "multi": multi,
        },
    )


if __name__ == "__main__":
    main()
