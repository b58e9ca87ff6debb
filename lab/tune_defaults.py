"""Sweep of the defaults that were first chosen on the demo's own ground truth, on tuning seeds apart from
the seeds the README reports (docs/METHOD.md, "How defaults were chosen").

The 3D-CN settings below were once picked by their camera-view mIoU on the demo sequence (seed 0), the very
sequence whose figures the README prints. Here each is swept one at a time around a centre (the current
defaults, or the ``--set`` overrides), every other setting at the centre, on generated sequences of two
seed groups:

- **tuning** seeds (default 101, 102, 103): the choice is made on these alone;
- **report** seeds (default 0 = the demo's seed, 201, 202): shown beside them, never used to choose.

Rule: per setting, the value with the highest mean camera-view ``+3D-CN x1`` mIoU over the tuning seeds
wins; the centre's value stays unless another value beats it there by more than ``--tie`` points.

Values that differ only after training (``temperature``) reuse the round's checkpoint; the others train
the network again. Stages up to smoothing run once per seed (the pipeline's cache). Figures are cached per
seed and configuration under ``--work`` (``results*.json``), so a sweep cut off by a time limit resumes,
and one run elsewhere (a GPU machine) can be tabulated here with ``--cached-only``.

Usage::

    .venv/bin/python -m lab.tune_defaults --work /tmp/tune        # the whole sweep (long on a CPU)
    .venv/bin/python -m lab.tune_defaults --work /tmp/tune --only temperature --frames 30
    # the sweep of record (docs/METHOD.md): around the former defaults, 3D-CN on a GPU, 6 seeds at once
    .venv/bin/python -m lab.tune_defaults --work /tmp/tune --jobs 6 --device cuda --threads 2 \
        --set consistency.temperature=0.25 --set 'consistency.selection_scope="sequence"'
    .venv/bin/python -m lab.tune_defaults --from-json benchmarks/results/tune_defaults.json

Prints one table per setting (rows: values; columns: mIoU per seed and the mean of each seed group) and
writes ``benchmarks/results/tune_defaults.json`` (the benchmarks' results folder and its JSON form,
``benchmarks/common.py``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

# benchmarks/ is a folder of scripts, not an installed package: its helpers import from the checkout.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import print_table, write_results
from leap_core.config import PipelineConfig, config_from_dict, config_to_dict
from leap_core.io_utils import atomic_write_json
from leap_core.pipeline import SequenceSpec, run_pipeline
from leap_core.schema import builtin_schema

SETTINGS: dict[str, tuple[str, list[Any]]] = {
    # name: (config path, values swept); the first value listed is not special, the default is read from
    # PipelineConfig() so the table marks it whatever it currently is.
    "temperature": ("consistency.temperature", [0.25, 0.5, 1.0, 2.0]),
    "selection_scope": ("consistency.selection_scope", ["sequence", "scan"]),
    "rank_by_views": ("consistency.rank_by_views", [True, False]),
    "use_intensity": ("consistency.backbone.use_intensity", [True, False]),
}
"""The settings chosen on the demo before (docs/METHOD.md C.1-C.3) and the values swept."""

ROW = "+3D-CN x1"


def _get(cfg: PipelineConfig, path: str) -> Any:
    obj: Any = cfg
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _override(path: str, value: Any) -> dict[str, Any]:
    """``"a.b.c", v`` → ``{"a": {"b": {"c": v}}}``."""
    out: dict[str, Any] = {}
    node = out
    *parents, leaf = path.split(".")
    for p in parents:
        node = node.setdefault(p, {})
    node[leaf] = value
    return out


def _figures(metrics: dict[str, Any]) -> dict[str, float]:
    cam, all_ = metrics["camera"], metrics["all"]
    return {
        "camera_voxel": 100 * cam["voxel"]["miou"],
        "camera_3dcn": 100 * cam[ROW]["miou"],
        "all_voxel": 100 * all_["voxel"]["miou"],
        "all_3dcn": 100 * all_[ROW]["miou"],
    }


def base_config(device: str, threads: int, sets: dict[str, Any]) -> PipelineConfig:
    """The centre of the sweep: the defaults with the 3D-CN on (one round) and the ``--set`` overrides."""
    base = config_from_dict(
        {"consistency": {"enabled": True, "iterations": 1, "device": device, "num_threads": threads}},
        PipelineConfig(),
    )
    for path, value in sets.items():
        base = config_from_dict(_override(path, value), base)
    return base


def variants(base: PipelineConfig, only: list[str]) -> list[tuple[str, str, PipelineConfig, str]]:
    """``(setting, value as JSON, config, cache key)`` of every swept value, in sweep order."""
    out = []
    for name in only:
        path, values = SETTINGS[name]
        for value in values:
            cfg = config_from_dict(_override(path, value), base)
            out.append((name, json.dumps(value), cfg, json.dumps(config_to_dict(cfg), sort_keys=True)))
    return out


def read_caches(root: Path) -> dict[str, Any]:
    """Figures by cache key from every ``results*.json`` of one seed's folder (runs split over processes
    or machines write one file each)."""
    cache: dict[str, Any] = {}
    for f in sorted(root.glob("results*.json")):
        cache.update(json.loads(f.read_text()))
    return cache


def sweep_seed(  # noqa: PLR0917  one worker's whole job, picklable arguments
    seed: int,
    frames: int,
    work: str,
    only: list[str],
    device: str,
    threads: int,
    sets: dict[str, Any],
    run: bool = True,
) -> dict[str, Any]:
    """Every value of every setting in ``only`` on the sequence of ``seed``: ``{setting: {value: figures}}``
    (figures None for a value neither run nor cached when ``run`` is False).

    Runs in its own process (one per seed); the run folder is reused across values, so only the 3D-CN and
    the stages after it run again (and training only when the selected labels or the network change)."""
    from leap_core.synth import SynthConfig, generate_sequence

    root = Path(work) / f"seed{seed}_f{frames}"
    seq_dir = root / "sequences" / "00"
    schema = builtin_schema("semantickitti")
    run_dir = root / "run"
    # Figures per full configuration: a value equal to the centre repeats the base run, and a sweep
    # stopped half-way (a time limit) resumes here without running anything twice.
    cache_path = root / "results.json"
    cache = read_caches(root)
    out: dict[str, Any] = {name: {} for name in only}
    for name, value, cfg, key in variants(base_config(device, threads, sets), only):
        if key not in cache and run:
            scans = seq_dir / "velodyne"
            if not scans.is_dir() or len(list(scans.glob("*.bin"))) != frames:
                generate_sequence(root, SynthConfig(frames=frames, seed=seed), "00", force=True, workers=1)
            t = time.perf_counter()
            res = run_pipeline([SequenceSpec.of(seq_dir)], schema, cfg, run_dir, until="evaluate").only()
            if res.metrics is None:
                raise SystemExit(f"{seq_dir}: no metrics (the sequence needs ground-truth labels)")
            cache[key] = _figures(res.metrics.to_dict()) | {"seconds": time.perf_counter() - t}
            own = json.loads(cache_path.read_text()) if cache_path.is_file() else {}
            atomic_write_json(cache_path, own | {key: cache[key]})
        figs = cache.get(key)
        out[name][value] = figs
        if figs is not None:
            print(
                f"seed {seed} {name}={value}: camera x1 {figs['camera_3dcn']:.1f} "
                f"(voxel {figs['camera_voxel']:.1f}), all x1 {figs['all_3dcn']:.1f}, "
                f"{figs['seconds']:.0f} s",
                flush=True,
            )
    return out


def choose(values: dict[str, dict[int, Any]], default: str, tune: list[int], tie: float) -> str | None:
    """The winning value (JSON text) on the tuning seeds: highest mean camera-view ``+3D-CN x1`` mIoU; the
    default is kept unless the best beats it by more than ``tie`` points. None when a value lacks a tuning
    seed's figures."""
    if any(values[v][s] is None for v in values for s in tune):
        return None

    def mean(v: str) -> float:
        return sum(values[v][s]["camera_3dcn"] for s in tune) / len(tune)

    best = max(values, key=mean)
    return default if default in values and mean(best) - mean(default) <= tie else best


def report(results: dict[str, Any], tie: float) -> dict[str, str | None]:
    """Print one table per setting; returns ``{setting: chosen value (JSON text)}``."""
    tune, rep = results["tune_seeds"], results["report_seeds"]
    per_seed: dict[str, dict[str, Any]] = {str(k): v for k, v in results["seeds"].items()}
    chosen: dict[str, str | None] = {}
    for name in results["settings"]:
        path, _ = SETTINGS[name]
        values = list(per_seed[str(tune[0])][name])
        table = {v: {s: per_seed[str(s)][name][v] for s in tune + rep} for v in values}
        default = json.dumps(results["centre"][name])
        pick = choose(table, default, tune, tie)
        chosen[name] = pick

        def row(label: str, v: str, cam: str, all_: str, table: dict[str, Any] = table) -> list[str]:
            def one(s: int, key: str) -> str:
                return "n/a" if table[v][s] is None else f"{table[v][s][key]:.1f}"

            def mean(seeds: list[int], key: str) -> str:
                got = [table[v][s][key] for s in seeds if table[v][s] is not None]
                return f"{sum(got) / len(got):.1f}" if len(got) == len(seeds) else "n/a"

            return (
                [label]
                + [one(s, cam) for s in tune]
                + [mean(tune, cam)]
                + [one(s, cam) for s in rep]
                + [mean(rep, cam)]
                + [mean(tune, all_), mean(rep, all_)]
            )

        rows = []
        for v in values:
            mark = ("centre " if v == default else "") + ("chosen" if v == pick else "")
            rows.append(row(f"{v} {mark}".strip(), v, "camera_3dcn", "all_3dcn"))
        rows.append(row("(voxel, no 3D-CN)", default, "camera_voxel", "all_voxel"))
        head = (
            [path]
            + [f"tune {s}" for s in tune]
            + ["tune mean"]
            + [f"report {s}" for s in rep]
            + ["report mean"]
            + ["all pts: tune", "all pts: report"]
        )
        print_table(
            f"{name}: camera-view mIoU of +3D-CN x1 ({results['frames']} frames per seed; chosen on the "
            f"tuning seeds, tie margin {tie}); last two columns: all-points mIoU, group means",
            head,
            rows,
        )
    return chosen


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/tune_defaults", help="Folder for the sequences and run folders.")
    ap.add_argument("--frames", type=int, default=30, help="Frames per generated sequence.")
    ap.add_argument("--tune-seeds", default="101,102,103", help="Generator seeds the choice is made on.")
    ap.add_argument("--report-seeds", default="0,201,202", help="Held-apart seeds (0 = the demo's seed).")
    ap.add_argument("--only", default=",".join(SETTINGS), help=f"Settings to sweep: {', '.join(SETTINGS)}.")
    ap.add_argument("--jobs", type=int, default=1, help="Seeds swept at once (one process each).")
    ap.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="3D-CN device.")
    ap.add_argument("--threads", type=int, default=0, help="Torch threads per process (0 = torch's choice).")
    ap.add_argument("--tie", type=float, default=0.5, help="mIoU points within which the default is kept.")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="PATH=JSON",
        help="Extra override of every run, e.g. consistency.min_steps=5 (a quick smoke test).",
    )
    ap.add_argument("--from-json", default=None, help="Print the tables of a results file; run nothing.")
    ap.add_argument(
        "--cached-only",
        action="store_true",
        help="Run nothing: tables from the figures cached under --work (e.g. copied from the "
        "machine that ran the sweep); values without figures show n/a.",
    )
    ap.add_argument("--name", default="tune_defaults", help="Result file: benchmarks/results/NAME.json.")
    args = ap.parse_args()

    if args.from_json:
        results = json.loads(Path(args.from_json).read_text())
        print(json.dumps(report(results, args.tie)))
        return
    only = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = [s for s in only if s not in SETTINGS]
    if unknown:
        sys.exit(f"--only: unknown setting(s) {', '.join(unknown)} (known: {', '.join(SETTINGS)})")
    # Temperature first: its values reuse the checkpoint trained at the defaults.
    only.sort(key=lambda s: s != "temperature")
    tune = [int(s) for s in args.tune_seeds.split(",")]
    rep = [int(s) for s in args.report_seeds.split(",")]
    if set(tune) & set(rep):
        sys.exit(f"--tune-seeds and --report-seeds overlap: {sorted(set(tune) & set(rep))}")
    seeds = tune + rep
    sets: dict[str, Any] = {}
    for item in args.set:
        key, eq, val = item.partition("=")
        if not eq:
            sys.exit(f"--set {item!r}: expected PATH=JSON, e.g. consistency.min_steps=5")
        sets[key.strip()] = json.loads(val)
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futs = {
            s: pool.submit(
                sweep_seed,
                s,
                args.frames,
                args.work,
                only,
                args.device,
                args.threads,
                sets,
                not args.cached_only,
            )
            for s in seeds
        }
        per_seed = {str(s): f.result() for s, f in futs.items()}
    base = base_config(args.device, args.threads, sets)
    results: dict[str, Any] = {
        "frames": args.frames,
        "tune_seeds": tune,
        "report_seeds": rep,
        "settings": only,
        "centre": {n: _get(base, SETTINGS[n][0]) for n in only},
        "device": args.device,
        "overrides": sets,
        "seconds": time.perf_counter() - start,
        "config": config_to_dict(base),
        "seeds": per_seed,
    }
    chosen = report(results, args.tie)
    results["chosen"] = chosen
    path = write_results(args.name, results)
    print(f"chosen on tuning seeds {tune}: {json.dumps(chosen)}")
    print(f"wrote {path} ({results['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
