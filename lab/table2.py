"""The paper's Table 2 on the two synthetic domains: a LiDAR-only network (the project's WaffleIron-style
backbone, ``leap train``) fine-tuned on LeAP's labels of a target domain, against the same network trained
on another domain only (source-only) and fine-tuned on the target's ground truth (oracle).

Per domain (:data:`DOMAINS`):

- **source-only**: trained from random weights on the ground truth of the *source* domain's sequences
  (``street-32`` → ``street``, as nuScenes → SemanticKITTI; ``street`` → ``agri-uav``, as SemanticKITTI →
  AgriUAV, its raw ids mapped onto the farm's classes by :attr:`Domain.source_classes`);
- **voxel labels**: the source network fine-tuned (``leap train --init``) on the final labels of a
  ``leap run`` (3D-CN off) of the target's *labeled* sequences;
- **+3D-CN labels**: the same, on the labels of a run with the 3D-CN on;
- **oracle**: the source network fine-tuned on the labeled sequences' ground truth.

Every row is scored on *held-apart* target sequences (other generator seeds, never labeled or trained on):
every point of every scan against the ground truth, mIoU over the schema's classes (``leap predict``'s
``model-metrics.json``). The fine-tuned rows are trained with ``--seeds`` training seeds (the source
network once); each row's mean and the per-seed gains over source-only are printed, with the paper's gains
beside them (the paper reports +11.5 mIoU on SemanticKITTI with LeAP's labels; +20.5 on AgriUAV with
them and +34.2 with the 3D-CN's; its absolute figures are not reproduced here).

Sizes are set by the options (a CPU-sized default, ``--quick`` the smallest that runs every step); the
numbers in docs/RESULTS.md say which sizes they come from. Files: ``--data`` (generated sequences) and
``--runs`` (label runs, models, prediction runs); everything already there is reused (runs resume by
their fingerprints, a model file of the same name is loaded instead of trained).

Usage (from the repository root)::

    .venv/bin/python -m lab.table2 --data /tmp/t2/data --runs /tmp/t2/runs          # both domains
    .venv/bin/python -m lab.table2 --quick --data /tmp/t2q/data --runs /tmp/t2q/runs  # smallest
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lab  # noqa: F401  # registers the lab's labelers (simulated-paper)
from leap_core.config import config_from_dict
from leap_core.consistency.config import BackboneConfig
from leap_core.lidar_model.config import LidarModelConfig
from leap_core.lidar_model.data import LabeledScans, run_sequences, split_scans, truth_sequence
from leap_core.lidar_model.model import LidarModel, load_model
from leap_core.lidar_model.predict import predict_run
from leap_core.lidar_model.train import train_lidar_model
from leap_core.metrics import metrics_from_confusion
from leap_core.pipeline import SequenceSpec, run_pipeline
from leap_core.presets import load_preset
from leap_core.schema import Schema
from leap_core.synth import CameraConfig, SynthConfig, generate_sequence
from leap_core.synth.agri import AgriSynthConfig
from leap_core.synth.domains import domain_config

ROOT = Path(__file__).resolve().parents[1]
ROWS = ("source-only", "voxel labels", "+3D-CN labels", "oracle")


@dataclass(frozen=True)
class Domain:
    """One column group of Table 2."""

    key: str
    title: str
    target: str
    """``leap synth --domain`` of the labeled and the held-apart sequences."""
    source: str
    """``leap synth --domain`` of the source-only network's training sequences."""
    project: str
    """The target's project file (classes; relative to the repository root)."""
    pipeline: dict[str, Any]
    """The label runs' settings over the project's (the labeler; the 3D-CN switch is added per run)."""
    paper: tuple[float | None, float | None]
    """The paper's gains over source-only, in mIoU points: voxel labels, +3D-CN labels (None: not given)."""
    paper_title: str
    source_classes: dict[str, tuple[int, ...]] | None = None
    """For a source domain of other raw ids: the source's raw ids of each target class (the classes with
    none get no source labels)."""


DOMAINS: dict[str, Domain] = {
    "street": Domain(
        key="street",
        title="street-32 → street",
        target="street",
        source="street-32",
        project="projects/semantickitti.yaml",
        pipeline={"labeler": "simulated-paper", "simulated_paper": {"preset": "paper"}},
        paper=(11.5, None),
        paper_title="paper, nuScenes → SemanticKITTI",
    ),
    "agri": Domain(
        key="agri",
        title="street → farm (agri-uav)",
        target="agri-uav",
        source="street",
        project="projects/agri_uav.yaml",
        pipeline={"labeler": "simulated"},
        paper=(20.5, 34.2),
        paper_title="paper, SemanticKITTI → AgriUAV",
        # SemanticKITTI raw ids of the street generator (leap_core/synth) for the farm's classes.
        source_classes={
            "tree": (70, 71),
            "pole": (80, 81),
            "fence": (51,),
            "wire": (),
            "person": (30, 31, 32, 254, 255, 256),
            "building": (50,),
            "ground": (40, 44, 48, 49, 60, 72),
        },
    ),
}


@dataclass(frozen=True)
class Sizes:
    """How big a measurement is (the options)."""

    source_seeds: tuple[int, ...]
    labeled_seeds: tuple[int, ...]
    test_seeds: tuple[int, ...]
    frames: int
    coarse: int
    """LiDAR coarsening: the street's azimuth step and the farm's columns, this many times coarser."""
    source_steps: int
    finetune_steps: int
    points_per_scan: int
    cn_min_steps: int
    backbone: BackboneConfig


def synth_config(domain: str, frames: int, seed: int, coarse: int) -> SynthConfig | AgriSynthConfig:
    """The generator config of ``domain`` with a ``coarse`` times coarser LiDAR and a half-size camera."""
    cfg = domain_config(domain, frames, seed)
    if isinstance(cfg, AgriSynthConfig):
        lidar = dataclasses.replace(cfg.lidar, columns=max(16, cfg.lidar.columns // coarse))
        return dataclasses.replace(cfg, lidar=lidar)
    lidar = dataclasses.replace(cfg.lidar, azimuth_step_deg=cfg.lidar.azimuth_step_deg * coarse)
    return dataclasses.replace(cfg, lidar=lidar, camera=CameraConfig().scaled(0.5))


def mapped_schema(schema: Schema, raw_ids: dict[str, tuple[int, ...]]) -> Schema:
    """``schema`` with each class's ground-truth ids replaced by ``raw_ids[name]`` (same names, order and
    export ids): reads another domain's ground truth as these classes."""
    classes = tuple(dataclasses.replace(c, gt_ids=tuple(raw_ids.get(c.name, ()))) for c in schema.classes)
    return dataclasses.replace(schema, classes=classes)


def gains(rows: dict[str, list[float]]) -> dict[str, list[float]]:
    """Per fine-tuned row, each seed's mIoU minus the source-only mIoU (points)."""
    base = rows["source-only"][0]
    return {r: [v - base for v in rows[r]] for r in ROWS[1:] if r in rows}


def _mean(xs: Sequence[float]) -> float:
    return sum(xs) / len(xs) if xs else math.nan


def _std(xs: Sequence[float]) -> float:
    m = _mean(xs)
    return math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1)) if len(xs) > 1 else math.nan


def _cell(xs: Sequence[float], signed: bool = False) -> str:
    if not xs:
        return "—"
    fmt = "{:+.1f}" if signed else "{:.1f}"
    out = fmt.format(_mean(xs))
    return out if len(xs) < 2 else f"{out} ± {_std(xs):.1f}"


def table_markdown(results: Sequence[tuple[Domain, dict[str, list[float]]]]) -> str:
    """Markdown: per domain a row of mIoU (%, mean ± sample std over training seeds) and a row of gains
    over source-only, then the paper's gains."""
    lines = [
        "| domain | | source-only | voxel labels | +3D-CN labels | oracle |",
        "|---|---|---|---|---|---|",
    ]
    for dom, rows in results:
        g = gains(rows)
        lines.append(f"| {dom.title} | mIoU | " + " | ".join(_cell(rows.get(r, [])) for r in ROWS) + " |")
        lines.append("| | gain | — | " + " | ".join(_cell(g.get(r, []), True) for r in ROWS[1:]) + " |")
        v, cn = dom.paper
        paper = [f"*{x:+.1f}*" if x is not None else "—" for x in (v, cn)]
        lines.append(f"| | *{dom.paper_title}*, gain | — | {paper[0]} | {paper[1]} | — |")
    return "\n".join(lines)


def beats_source_only(rows: dict[str, list[float]]) -> bool:
    """The issue's target: fine-tuning on our labels beats source-only for every seed (voxel labels)."""
    return all(x > 0 for x in gains(rows).get("voxel labels", [])) and bool(rows.get("voxel labels"))


# ------------------------------------------------------------------------------------------ the work
def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _sequence(data: Path, domain: str, seed: int, sizes: Sizes) -> Path:
    name = f"{domain}_seed{seed}_f{sizes.frames}_c{sizes.coarse}"
    path = data / name / "sequences" / "00"
    if not path.is_dir():
        _log(f"generate {name}")
        generate_sequence(data / name, synth_config(domain, sizes.frames, seed, sizes.coarse))
    return path


def _label_run(dom: Domain, seqs: Sequence[Path], cn: bool, sizes: Sizes, runs: Path) -> Path:
    preset = load_preset(ROOT / dom.project)
    settings = {
        **dom.pipeline,
        "consistency": {
            "enabled": cn,
            "min_steps": sizes.cn_min_steps,
            "backbone": dataclasses.asdict(sizes.backbone) | {"grid_cells": list(sizes.backbone.grid_cells)},
        },
    }
    cfg = config_from_dict(settings, preset.pipeline)
    out = runs / f"{dom.key}_labels_{'3dcn' if cn else 'voxel'}"
    _log(f"label {out.name}")
    specs = [SequenceSpec.of(s, None, f"s{k}") for k, s in enumerate(seqs)]
    run_pipeline(specs, preset.schema, cfg, out)
    return out


def _model(
    path: Path,
    train: LabeledScans,
    schema: Schema,
    cfg: LidarModelConfig,
    init: tuple[LidarModel, Path] | None = None,
) -> LidarModel:
    if not path.is_file():
        _log(f"train {path.name} ({len(train.scans)} scans, {cfg.steps} steps)")
        empty = LabeledScans(train.sequences, ())
        train_lidar_model(
            path,
            train,
            empty,
            schema,
            cfg,
            init=None if init is None else init[0],
            init_path=None if init is None else init[1],
        )
    return load_model(path)


def _score(model: LidarModel, path: Path, tests: Sequence[Path], out: Path, truth: Schema) -> float:
    if not (out / "scores.json").is_file():
        results = predict_run(
            model, path, [(f"t{k}", s, None) for k, s in enumerate(tests)], out, device="cpu", truth=truth
        )
        cm = sum(r.confusion for r in results if r.confusion is not None)
        m = metrics_from_confusion(
            cm, model.schema.names, model.schema.categories(), ignore_unlabeled_pred=False
        )
        (out / "scores.json").write_text(json.dumps(m.to_dict()))
    return 100.0 * float(json.loads((out / "scores.json").read_text())["miou"])


def measure(
    dom: Domain, seeds: Sequence[int], sizes: Sizes, data: Path, runs: Path
) -> dict[str, list[float]]:
    """Every row of one domain: mIoU (%) per training seed (source-only: one value)."""
    runs.mkdir(parents=True, exist_ok=True)
    schema = load_preset(ROOT / dom.project).schema
    src_schema = schema if dom.source_classes is None else mapped_schema(schema, dom.source_classes)
    sources = [_sequence(data, dom.source, s, sizes) for s in sizes.source_seeds]
    labeled = [_sequence(data, dom.target, s, sizes) for s in sizes.labeled_seeds]
    tests = [_sequence(data, dom.target, s, sizes) for s in sizes.test_seeds]
    base = LidarModelConfig(
        steps=sizes.source_steps,
        points_per_scan=sizes.points_per_scan,
        val_block=0,
        device="cpu",
        backbone=sizes.backbone,
        checkpoint_every=max(1, sizes.source_steps // 4),
    )
    tag = (
        f"f{sizes.frames}_c{sizes.coarse}_s{sizes.source_steps}_{sizes.finetune_steps}"
        f"_p{sizes.points_per_scan}_w{sizes.backbone.channels}x{sizes.backbone.layers}"
    )
    src_path = runs / f"{dom.key}_source_{tag}.pt"
    src_train, _ = split_scans([truth_sequence(s) for s in sources], [], 0, 2)
    source = _model(src_path, src_train, src_schema, base)
    rows: dict[str, list[float]] = {
        "source-only": [_score(source, src_path, tests, runs / f"{dom.key}_pred_source_{tag}", schema)]
    }
    _log(f"{dom.key} source-only {rows['source-only'][0]:.1f}")
    data_of = {
        "voxel labels": lambda: run_sequences(_label_run(dom, labeled, False, sizes, runs)),
        "+3D-CN labels": lambda: run_sequences(_label_run(dom, labeled, True, sizes, runs)),
        "oracle": lambda: [truth_sequence(s) for s in labeled],
    }
    for row, parts in data_of.items():
        train, _ = split_scans(parts(), [], 0, 2)
        key = row.replace(" ", "_").replace("+", "")
        for seed in seeds:
            cfg = dataclasses.replace(base, steps=sizes.finetune_steps, seed=seed)
            path = runs / f"{dom.key}_{key}_{tag}_seed{seed}.pt"
            model = _model(path, train, schema, cfg, init=(source, src_path))
            score = _score(model, path, tests, runs / f"{dom.key}_pred_{key}_{tag}_seed{seed}", schema)
            rows.setdefault(row, []).append(score)
            _log(f"{dom.key} {row} seed {seed}: {score:.1f}")
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data", default=str(ROOT / "data" / "table2"), help="Folder of the generated sequences."
    )
    ap.add_argument("--runs", default=str(ROOT / "runs" / "table2"), help="Folder of runs and models.")
    ap.add_argument("--domains", default="street,agri", help=f"Among {', '.join(DOMAINS)}.")
    ap.add_argument("--seeds", default="0,1,2", help="Training seeds of the fine-tuned rows.")
    ap.add_argument("--frames", type=int, default=10, help="Frames of every generated sequence.")
    ap.add_argument("--coarse", type=int, default=3, help="LiDAR this many times coarser (1: full size).")
    ap.add_argument("--source-steps", type=int, default=300, help="Steps of the source-only network.")
    ap.add_argument("--finetune-steps", type=int, default=150, help="Steps of each fine-tuning.")
    ap.add_argument("--points-per-scan", type=int, default=8192, help="Points per scan per step.")
    ap.add_argument("--cn-min-steps", type=int, default=150, help="The label runs' 3D-CN training steps.")
    ap.add_argument("--channels", type=int, default=BackboneConfig.channels, help="Backbone width.")
    ap.add_argument("--layers", type=int, default=BackboneConfig.layers, help="Backbone layer pairs.")
    ap.add_argument(
        "--labeler", default=None, help="The label runs' labeler instead of the domain's (`simulated`)."
    )
    ap.add_argument("--quick", action="store_true", help="Smallest mode: 3 frames, a tiny network, 1 seed.")
    ap.add_argument("--out", default=None, help="Also write the Markdown table to this file.")
    args = ap.parse_args(argv)
    backbone = BackboneConfig(channels=args.channels, layers=args.layers)
    seeds = [int(s) for s in args.seeds.split(",")]
    if args.quick:
        args.frames, args.coarse, args.source_steps, args.finetune_steps = 3, 6, 3, 2
        args.points_per_scan, args.cn_min_steps, seeds = 1024, 2, seeds[:1]
        backbone = BackboneConfig(channels=8, layers=2, embed_channels=4, knn=8)
    sizes = Sizes(
        source_seeds=(201,),
        labeled_seeds=(0,),
        test_seeds=(1, 2) if not args.quick else (1,),
        frames=args.frames,
        coarse=args.coarse,
        source_steps=args.source_steps,
        finetune_steps=args.finetune_steps,
        points_per_scan=args.points_per_scan,
        cn_min_steps=args.cn_min_steps,
        backbone=backbone,
    )
    results = []
    for key in args.domains.split(","):
        dom = DOMAINS[key]
        if args.labeler is not None:
            dom = dataclasses.replace(
                dom, pipeline={"labeler": args.labeler}, title=f"{dom.title}, `{args.labeler}`"
            )
        rows = measure(dom, seeds, sizes, Path(args.data), Path(args.runs))
        results.append((dom, rows))
    table = table_markdown(results)
    print(table)
    for dom, rows in results:
        print(
            f"{dom.key}: fine-tuning on our voxel labels beats source-only for every seed: "
            f"{beats_source_only(rows)}"
        )
    if args.out:
        Path(args.out).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
