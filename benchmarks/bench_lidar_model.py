"""Benchmark of the LiDAR-only model (`leap predict`, `leap train`): scans per second and training points
per second of the real-size network (the project's default backbone, ``BackboneConfig()``).

Target (docs/METHOD.md "A LiDAR-only model"): ``leap predict`` ≥ 2 scans/s of 120k points on the 2 CPU
cores (≥ 20 on one H100); training throughput is reported, with no target.

Data: a generated street (``leap synth``, its 64-beam LiDAR at a 0.18° azimuth step: about 120k points a
scan). The model is trained for ``--train-steps`` steps on the sequence's ground truth first (its weights
do not change the cost of a forward pass).

Measured, each beside a baseline doing the same work in the same process:

- **predict**: :func:`leap_core.lidar_model.predict.predict_sequence` end to end (read the scan, build the
  kNN graph and grid cells, forward pass, write ``points/`` and ``export/``), scans/s, and its parts;
  baseline: the same reading, a per-point MLP with about the same number of parameters on the same
  features, and the same writing (what a network that needs no neighbourhood costs);
- **train**: steps of ``points_per_scan`` points (data preparation, forward, backward, AdamW), points/s;
  baseline: the MLP's training step on the same points.

Usage::

    .venv/bin/python benchmarks/bench_lidar_model.py                 # 6 scans, real-size network
    .venv/bin/python benchmarks/bench_lidar_model.py --device cuda   # on a GPU
    .venv/bin/python benchmarks/bench_lidar_model.py --quick         # smallest mode (the tests' smoke run)

Prints two tables and writes ``benchmarks/results/bench_lidar_model.json``.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F_

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import print_table, write_results  # the benchmarks' own helpers

from leap_core.consistency.backbone import count_parameters
from leap_core.consistency.config import BackboneConfig
from leap_core.consistency.data import collate, prepare_cloud
from leap_core.datasets.kitti import KittiSequence
from leap_core.export import export_labels
from leap_core.io_utils import atomic_save_npz
from leap_core.lidar_model.config import LidarModelConfig
from leap_core.lidar_model.data import split_scans, truth_sequence
from leap_core.lidar_model.model import load_model
from leap_core.lidar_model.predict import predict_sequence
from leap_core.lidar_model.train import resolve_device, train_lidar_model
from leap_core.run_layout import RunLayout
from leap_core.schema import builtin_schema
from leap_core.synth import CameraConfig, LidarConfig, SynthConfig, generate_sequence


class PointMLP(nn.Module):
    """The baseline: a per-point MLP (no neighbourhood, no grid) over the backbone's input features."""

    def __init__(self, in_features: int, hidden: int, layers: int, num_classes: int) -> None:
        super().__init__()
        dims = [in_features, *([hidden] * layers)]
        self.body = nn.Sequential(
            *(m for a, b in itertools.pairwise(dims) for m in (nn.Linear(a, b), nn.GELU()))
        )
        self.head = nn.Linear(hidden, num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.head(self.body(x))
        return out


def matched_mlp(params: int, in_features: int, num_classes: int, layers: int = 4) -> PointMLP:
    """A :class:`PointMLP` whose width gives about ``params`` parameters."""
    width = 8
    while count_parameters(PointMLP(in_features, width + 8, layers, num_classes)) <= params:
        width += 8
    return PointMLP(in_features, width, layers, num_classes)


def _generate(root: Path, frames: int, azimuth: float) -> Path:
    cfg = SynthConfig(
        frames=frames, lidar=LidarConfig(azimuth_step_deg=azimuth), camera=CameraConfig().scaled(0.25)
    )
    return generate_sequence(root, cfg).path


def bench_predict(model_file: Path, seq: KittiSequence, out: Path, device: str) -> dict[str, Any]:
    """``predict_sequence`` over every scan, and the MLP baseline doing the same reading and writing."""
    model = load_model(model_file)
    dev = resolve_device(device)
    predict_sequence(model, seq, RunLayout(out / "warm").sequence("s"), name="s", indices=[0], device=device)
    t0 = time.perf_counter()
    res = predict_sequence(model, seq, RunLayout(out / "model").sequence("s"), name="s", device=device)
    wall = time.perf_counter() - t0
    # the parts, on the first scan
    points = seq.frame(0).points
    t = time.perf_counter()
    cloud = prepare_cloud(points, model.network.cfg, None, workers=max(1, torch.get_num_threads()))
    t_prep = time.perf_counter() - t
    batch = collate([cloud]).to(dev)
    with torch.inference_mode():
        t = time.perf_counter()
        model.network(batch)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t_net = time.perf_counter() - t

    mlp = matched_mlp(
        count_parameters(model.network), model.network.cfg.in_features, model.schema.num_classes
    )
    mlp = mlp.to(dev).eval()
    ids = model.schema.export_ids()
    lay = RunLayout(out / "mlp").sequence("s")
    t0 = time.perf_counter()
    for i in range(len(seq)):
        pts = seq.frame(i).points
        # the features the backbone gets, without the neighbourhood: the baseline's input stays comparable
        feats = torch.from_numpy(prepare_cloud(pts, replace(model.network.cfg, knn=1), None).feats).to(dev)
        with torch.inference_mode():
            logp = F_.log_softmax(mlp(feats), dim=1).cpu().numpy()
        label = logp.argmax(1).astype(np.int16)
        conf = np.exp(logp.max(1)).astype(np.float32)
        atomic_save_npz(lay.points(seq.frame_ids[i]), label=label, conf=conf.astype(np.float16))
        export_labels(lay.export_label(seq.frame_ids[i]), lay.export_conf(seq.frame_ids[i]), label, conf, ids)
    base = time.perf_counter() - t0
    return {
        "scans": res.scans,
        "points_per_scan": res.points / res.scans,
        "seconds": wall,
        "scans_per_s": res.scans / wall,
        "first_scan_prepare_s": t_prep,
        "first_scan_network_s": t_net,
        "baseline_seconds": base,
        "baseline_scans_per_s": res.scans / base,
        "parameters": count_parameters(model.network),
        "baseline_parameters": count_parameters(mlp),
    }


def bench_train(seq_path: Path, cfg: LidarModelConfig, out: Path) -> tuple[Path, dict[str, Any]]:
    """Train ``cfg.steps`` steps (the model file the prediction benchmark loads), and the MLP's steps on the
    same number of points."""
    schema = builtin_schema("semantickitti")
    train, val = split_scans([truth_sequence(seq_path)], [], 0, 2)
    model_file = out / "model.pt"
    res = train_lidar_model(model_file, train, val, schema, cfg)
    model = load_model(model_file)
    dev = resolve_device(cfg.device)
    mlp = matched_mlp(count_parameters(model.network), cfg.backbone.in_features, schema.num_classes).to(dev)
    opt = torch.optim.AdamW(mlp.parameters(), lr=cfg.lr)
    seq = KittiSequence(seq_path)
    rng = np.random.default_rng(0)
    n_base, t0 = 0, time.perf_counter()
    for s in range(cfg.steps):
        pts = seq.frame(s % len(seq)).points
        pick = np.sort(rng.choice(pts.shape[0], min(cfg.points_per_scan, pts.shape[0]), replace=False))
        feats = torch.from_numpy(prepare_cloud(pts, replace(cfg.backbone, knn=1), pick).feats).to(dev)
        tgt = torch.from_numpy(rng.integers(0, schema.num_classes, feats.shape[0])).to(dev)
        loss = F_.cross_entropy(mlp(feats), tgt)
        opt.zero_grad()
        torch.autograd.backward(loss)
        opt.step()
        n_base += feats.shape[0]
    base = time.perf_counter() - t0
    return model_file, {
        "steps": res.steps,
        "points_per_step": cfg.points_per_scan,
        "seconds": res.seconds,
        "points_per_s": res.points_seen / res.seconds,
        "baseline_seconds": base,
        "baseline_points_per_s": n_base / base,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=6, help="Scans to predict (and train on).")
    ap.add_argument("--train-steps", type=int, default=10, help="Training steps measured.")
    ap.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda"))
    ap.add_argument(
        "--azimuth", type=float, default=0.18, help="LiDAR azimuth step (degrees): the scan size."
    )
    ap.add_argument("--quick", action="store_true", help="Smallest mode: 2 coarse scans, a tiny network.")
    args = ap.parse_args(argv)
    backbone = BackboneConfig()
    points_per_scan = LidarModelConfig().points_per_scan
    if args.quick:
        args.scans, args.train_steps, args.azimuth = 2, 2, 2.0
        backbone = BackboneConfig(channels=8, layers=2, embed_channels=4)
        points_per_scan = 1024
    cfg = LidarModelConfig(
        steps=args.train_steps,
        points_per_scan=points_per_scan,
        val_block=0,
        device=args.device,
        backbone=backbone,
        checkpoint_every=10_000,
    )
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        seq_path = _generate(root / "data", args.scans, args.azimuth)
        model_file, train = bench_train(seq_path, cfg, root)
        pred = bench_predict(model_file, KittiSequence(seq_path), root / "runs", args.device)
    print_table(
        f"leap predict: {pred['scans']} scans of {pred['points_per_scan']:,.0f} points, {args.device}, "
        f"{torch.get_num_threads()} torch threads",
        ["", "scans/s", "seconds"],
        [
            ["model (read, kNN + grid, network, write)", pred["scans_per_s"], pred["seconds"]],
            ["  first scan: kNN + grid cells", "", pred["first_scan_prepare_s"]],
            ["  first scan: network", "", pred["first_scan_network_s"]],
            [
                "per-point MLP, same reading and writing (baseline)",
                pred["baseline_scans_per_s"],
                pred["baseline_seconds"],
            ],
            ["ratio model / baseline time", pred["seconds"] / pred["baseline_seconds"], ""],
        ],
    )
    print_table(
        f"leap train: {train['steps']} steps of {train['points_per_step']:,} points",
        ["", "points/s", "seconds"],
        [
            ["model step (prepare, forward, backward, AdamW)", train["points_per_s"], train["seconds"]],
            ["per-point MLP step (baseline)", train["baseline_points_per_s"], train["baseline_seconds"]],
            [
                "ratio model / baseline time per point",
                train["baseline_points_per_s"] / train["points_per_s"],
                "",
            ],
        ],
    )
    mode = "quick" if args.quick else "full"
    write_results(
        "bench_lidar_model",
        {"mode": mode, "device": args.device, "backbone": backbone.__dict__, "predict": pred, "train": train},
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
