"""Benchmark of one 3D-CN iteration (selection + training + inference + fusion back) on a demo-sized sequence.

Target: training + inference on the default demo sequence (≈ 60 scans × ~100k points) ≤ 10 min
on the 2-core CPU. Baseline, in the same process: the training step of a plain per-point MLP with about the
same number of parameters on the same points. Both steps (forward, backward, optimiser) run on the same
prepared batch; the data preparation (``prepare_cloud`` + ``collate``: the kNN graph and grid indices the
backbone needs, the features both use) is timed apart. Two ratios are printed, each named by what it
includes: backbone step / MLP step (what the kNN embedding and 2D-grid mixing cost in the network), and
(preparation + backbone step) / MLP step (what a training step costs end to end against a network that
needs no neighbourhood).

The training-step table times the whole ``train_model`` loop (reading, sampling and preparing scans,
forward, backward, optimiser; seconds per step, wall and CPU) of git commit ``--baseline`` (default
``25c0286``: before mixed precision, the background preparation and the reused step memory), imported into
this process (``common.import_commit``), beside this tree in float32 and in the config's resolved precision,
on the same scans, alternating. ``--steps-only`` prints the two step tables alone (minutes, not a round).

Inputs: with ``--run-dir``, the fused and smoothed grids and camera-view masks of a finished ``leap run``
(the pipeline's own stage B output, so the label table matches ``leap run --3dcn``). Without it, a "camera"
grid is built from the ground truth: points in a frontal field of view are fused with a confident
observation, with per-observation and per-voxel label noise (``--noise``). Either way the table shows the
voxel labels before and after one 3D-CN iteration (both kNN-smoothed like the pipeline does).

Usage::

    # the demo sequence, with the fused grids of a finished `leap run` (the acceptance setting)
    .venv/bin/python benchmarks/bench_3dcn.py --sequence /tmp/demo/sequences/00 --run-dir /tmp/demo_run
    # any labeled sequence, camera grid simulated from its ground truth; or a built-in stand-in street
    .venv/bin/python benchmarks/bench_3dcn.py --sequence /tmp/demo/sequences/00
    .venv/bin/python benchmarks/bench_3dcn.py

With ``--source CKPT`` (a 3D-CN another run wrote, e.g. of a tuning sequence) a second iteration on the
same inputs starts from that network and fine-tunes it (``leap run --3dcn-init``: one epoch at
``finetune_lr``); its time and labels are printed beside the random-weight iteration's, with the ratio of
the two totals, both measured in this process.

Prints the tables and writes ``benchmarks/results/bench_3dcn[_quick][_steps].json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F_

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import import_commit

from leap_core.consistency.backbone import PointSegmenter, count_parameters
from leap_core.consistency.config import ConsistencyConfig
from leap_core.consistency.data import collate, prepare_cloud
from leap_core.consistency.selection import view_counts
from leap_core.consistency.stage import run_3dcn_iteration
from leap_core.consistency.train import (
    config_from_dict,
    config_to_dict,
    load_source,
    num_train_steps,
    resolve_device,
    resolve_precision,
    train_model,
)
from leap_core.datasets.kitti import Calib, KittiSequence, write_calib, write_label, write_poses, write_scan
from leap_core.fusion import FusionConfig, VoxelGrid, fuse_dense, voxel_keys, world_points
from leap_core.heap import cap_heap_growth
from leap_core.io_utils import atomic_write_json
from leap_core.metrics import evaluate
from leap_core.pipeline import SequenceSpec
from leap_core.projection import Painted
from leap_core.run_layout import RunLayout, SequenceLayout
from leap_core.schema import builtin_schema
from leap_core.smoothing import SmoothedGrid, SmoothingConfig, knn_smooth
from leap_core.types import UNLABELED

# $LEAP_BENCH_RESULTS: another folder for the result file, as in benchmarks/common.py (the tests' smoke runs).
RESULTS = Path(os.environ.get("LEAP_BENCH_RESULTS") or Path(__file__).resolve().parent / "results")
QUICK_FRAMES = 2
QUICK_CONFIG: dict[str, Any] = {
    "min_steps": 0,
    "points_per_scan": 4096,
    "backbone": {"channels": 16, "layers": 2, "embed_channels": 8},
}
"""``--quick``: scans of the stand-in, and ConsistencyConfig overrides that keep every phase but shrink it."""
QUICK_STEPS = 3
"""``--quick``: training steps each version of the training-step table is timed over."""
BASELINE_COMMIT = "25c0286"
"""The training-step table's baseline: ``train_model`` before mixed precision, prefetching and the cheaper
exact preparation."""


# --------------------------------------------------------------------------------- stand-in sequence
def _boxes_for_street(length: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes (lo, hi) and raw SemanticKITTI ids of a straight street along +x."""
    boxes: list[tuple[list[float], list[float], int]] = [
        ([-30, -5, -0.2], [length + 30, 5, 0.0], 40),  # road
        ([-30, 5, -0.2], [length + 30, 8, 0.15], 48),  # sidewalks
        ([-30, -8, -0.2], [length + 30, -5, 0.15], 48),
        ([-30, 8, -0.2], [length + 30, 40, 0.1], 72),  # terrain behind the left sidewalk
    ]
    x = -30.0
    while x < length + 30:  # building facades with gaps on the right, fence on the left
        w = rng.uniform(8, 20)
        boxes.append(([x, -20, 0.0], [x + w, -8.5, rng.uniform(6, 15)], 50))
        x += w + rng.uniform(2, 6)
    boxes.append(([-30, 12, 0.0], [length + 30, 12.1, 1.5], 51))
    for x_row in np.arange(-25, length + 30, 11.0):
        xt = x_row + rng.uniform(-2, 2)
        boxes.append(([xt - 0.2, 6.3, 0.0], [xt + 0.2, 6.7, 2.5], 71))  # trunk
        r = rng.uniform(1.5, 2.5)
        boxes.append(([xt - r, 6.5 - r, 2.5], [xt + r, 6.5 + r, 2.5 + 1.6 * r], 70))  # crown
    for xp in np.arange(-20, length + 30, 17.0):
        boxes.append(([xp - 0.1, -5.6, 0.0], [xp + 0.1, -5.4, 5.0], 80))  # pole
        boxes.append(([xp - 0.4, -5.55, 3.0], [xp + 0.4, -5.45, 3.6], 81))  # sign
    for xc in np.arange(-25, length + 30, 7.5):
        if rng.random() < 0.7:
            side = rng.choice([-1, 1])
            yc = side * 3.6
            boxes.append(([xc - 2.1, yc - 0.9, 0.2], [xc + 2.1, yc + 0.9, 1.5], 10))  # parked car
    lo = np.array([b[0] for b in boxes], np.float64)
    hi = np.array([b[1] for b in boxes], np.float64)
    ids = np.array([b[2] for b in boxes], np.uint16)
    return np.stack([lo, hi], axis=1), ids


def _cast(
    origin: np.ndarray, dirs: np.ndarray, boxes: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray]:
    """Slab-method ray casting: nearest hit distance (R,) (inf = none) and box index (R,) per ray."""
    best_t = np.full(dirs.shape[0], np.inf)
    best_i = np.full(dirs.shape[0], -1)
    inv = 1.0 / np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
    for i, (lo, hi) in enumerate(boxes):
        t1 = (lo - origin) * inv
        t2 = (hi - origin) * inv
        tmin = np.minimum(t1, t2).max(axis=1)
        tmax = np.maximum(t1, t2).min(axis=1)
        hit = (tmax >= np.maximum(tmin, 0.0)) & (tmin > 0.5) & (tmin < best_t) & (tmin < max_range)
        best_t[hit] = tmin[hit]
        best_i[hit] = i
    return best_t, best_i


def write_standin_sequence(root: Path, n_frames: int, seed: int = 0) -> Path:
    """Write a KITTI-layout street sequence: 64 beams × 1700 columns (~100k points per scan), 1 m per
    frame."""
    rng = np.random.default_rng(seed)
    boxes, ids = _boxes_for_street(float(n_frames), rng)
    seq = root / "sequences" / "00"
    elev = np.deg2rad(np.linspace(-24.9, 2.0, 64))
    azim = np.linspace(-np.pi, np.pi, 1700, endpoint=False)
    ee, aa = np.meshgrid(elev, azim, indexing="ij")
    dirs = np.stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)], axis=-1).reshape(-1, 3)
    tr = np.eye(4)
    tr[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    calib = Calib(P2=np.array([[700.0, 0, 600, 0], [0, 700.0, 180, 0], [0, 0, 1, 0]]), Tr=tr)
    cam_poses = []
    for f in range(n_frames):
        origin = np.array([float(f), 0.0, 1.73])
        near = (boxes[:, 0, 0] < origin[0] + 80) & (boxes[:, 1, 0] > origin[0] - 80)
        t, bi = _cast(origin, dirs, boxes[near], 80.0)
        ok = np.isfinite(t)
        t = t[ok] + rng.normal(0, 0.02, ok.sum())
        xyz = dirs[ok] * t[:, None]  # LiDAR frame = world shifted by the origin (no rotation)
        pts = np.column_stack([xyz, rng.uniform(0, 1, len(t))]).astype(np.float32)
        write_scan(seq / "velodyne" / f"{f:06d}.bin", pts)
        write_label(seq / "labels" / f"{f:06d}.label", ids[near][bi[ok]])
        lidar_pose = np.eye(4)
        lidar_pose[:3, 3] = origin - [0, 0, 1.73]
        cam_poses.append(tr @ lidar_pose @ np.linalg.inv(tr))
    write_calib(seq / "calib.txt", calib)
    write_poses(seq / "poses.txt", np.stack(cam_poses))
    return seq


# ----------------------------------------------------------------------------------- camera-like grid
def camera_grid(
    seq: KittiSequence, gt: list[np.ndarray], num_classes: int, noise: float, fov_deg: float, seed: int
) -> tuple[VoxelGrid, list[np.ndarray]]:
    """Fuse ground truth seen in a frontal field of view, with ``noise`` of the voxels given a wrong class.

    Returns the grid and, per scan, the (N,) bool "in camera view" mask.
    """
    rng = np.random.default_rng(seed)
    keys_all, lab_all, views = [], [], []
    half = np.deg2rad(fov_deg / 2)
    for i in range(len(seq)):
        pts = seq.frame(i).points
        view = (pts[:, 0] > 0.5) & (np.abs(np.arctan2(pts[:, 1], pts[:, 0])) < half) & (gt[i] >= 0)
        views.append(view)
        keys_all.append(voxel_keys(world_points(pts[view], seq.poses[i]), 0.2))
        lab_all.append(gt[i][view])
    keys = np.concatenate(keys_all)
    labels = np.concatenate(lab_all).astype(np.int64)
    scan_of = np.repeat(np.arange(len(keys_all)), [len(k) for k in keys_all])
    uk, inv = np.unique(keys, return_inverse=True)
    # Two kinds of wrong labels, each a class of the scene (real noise confuses classes that are there):
    # per observation (one scan's view of a voxel, e.g. a bad mask) with probability ``noise``, and
    # systematic per voxel (every view wrong, e.g. a foreground label bleeding onto it) with ``noise / 3``.
    _, obs_id = np.unique(scan_of * (len(uk) + 1) + inv, return_inverse=True)
    present = np.unique(labels)
    pos = np.searchsorted(present, labels)
    wrong_obs = (rng.random(obs_id.max() + 1) < noise)[obs_id]
    wrong_vox = (rng.random(len(uk)) < noise / 3)[inv]
    shift_obs = rng.integers(1, max(len(present), 2), obs_id.max() + 1)[obs_id]
    shift_vox = rng.integers(1, max(len(present), 2), len(uk))[inv]
    labels = np.where(wrong_vox, present[(pos + shift_vox) % len(present)], labels)
    pos = np.searchsorted(present, labels)
    labels = np.where(wrong_obs, present[(pos + shift_obs) % len(present)], labels)
    obs = np.full((len(labels), num_classes), np.log(0.2 / (num_classes - 1)), np.float32)
    obs[np.arange(len(labels)), labels] = np.log(0.8)
    return fuse_dense(None, keys, obs, num_classes, FusionConfig()), views


# ------------------------------------------------------------------------------------------ baseline
class PlainMLP(nn.Module):
    """Per-point MLP on the same input features, no neighbourhood and no grid mixing."""

    def __init__(self, d_in: int, width: int, depth: int, num_classes: int) -> None:
        super().__init__()
        layers: list[nn.Module] = [nn.Linear(d_in, width), nn.GELU()]
        for _ in range(depth):
            layers += [nn.LayerNorm(width), nn.Linear(width, width), nn.GELU()]
        layers.append(nn.Linear(width, num_classes))
        self.net = nn.Sequential(*layers)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        return self.net(feats)


def step_times(
    cfg: ConsistencyConfig, points: np.ndarray, num_classes: int, repeats: int = 5
) -> dict[str, float]:
    """Median training-step seconds of the backbone and of a plain MLP of similar size on the same points."""
    rng = np.random.default_rng(0)
    n = min(cfg.points_per_scan or len(points), len(points))
    subset = np.sort(rng.choice(len(points), n, replace=False))
    target = torch.from_numpy(rng.integers(0, num_classes, n))
    torch.manual_seed(0)
    model = PointSegmenter(cfg.backbone, num_classes)
    params = count_parameters(model)
    width = 64
    per_layer = width * width + 3 * width
    depth = max(1, round((params - width * (cfg.backbone.in_features + num_classes)) / per_layer))
    mlp = PlainMLP(cfg.backbone.in_features, width, depth, num_classes)
    opt_a = torch.optim.AdamW(model.parameters())
    opt_b = torch.optim.AdamW(mlp.parameters())
    tp, ta, tb = [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        batch = collate([prepare_cloud(points, cfg.backbone, subset, workers=torch.get_num_threads())])
        tp.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        loss = F_.cross_entropy(model(batch), target)
        opt_a.zero_grad()
        loss.backward()
        opt_a.step()
        ta.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        loss = F_.cross_entropy(mlp(batch.feats), target)
        opt_b.zero_grad()
        loss.backward()
        opt_b.step()
        tb.append(time.perf_counter() - t0)
    return {
        "points_per_step": n,
        "backbone_params": params,
        "mlp_params": count_parameters(mlp),
        "prepare_s": float(np.median(tp)),
        "backbone_step_s": float(np.median(ta)),
        "mlp_step_s": float(np.median(tb)),
    }


def training_step_versions(  # noqa: PLR0917  the step's settings, data and the baseline to compare with
    cfg: ConsistencyConfig,
    scans: list[tuple[np.ndarray, np.ndarray]],
    num_classes: int,
    steps: int,
    baseline: str,
    work: Path,
    repeats: int = 2,
) -> list[dict[str, Any]]:
    """Seconds per training step of ``train_model`` (reading, sampling and preparing the scans, forward,
    backward, optimiser) as of git commit ``baseline`` and as of this tree in float32 and in ``cfg``'s
    precision, each ``steps`` steps on the same ``scans`` (points, targets), alternating ``repeats`` times.

    The baseline gets ``cfg``'s settings minus those it does not know (listed in its row's ``left_out``).
    glibc's mmap threshold is capped first, as the 3D-CN stage does before it trains (leap_core.heap).
    """
    cap_heap_growth()
    base = import_commit(baseline, work, ("consistency.config", "consistency.train"))
    base_train = base["consistency.train"]
    base_cfg_cls = base["consistency.config"].ConsistencyConfig
    plain = config_to_dict(replace(cfg, min_steps=steps, epochs=1))
    known = {f.name for f in fields(base_cfg_cls)}
    known_bb = {f.name for f in fields(base["consistency.config"].BackboneConfig)}
    left_out = [k for k in plain if k not in known] + [
        f"backbone.{k}" for k in plain["backbone"] if k not in known_bb
    ]
    base_plain = {k: v for k, v in plain.items() if k in known}
    base_plain["backbone"] = {k: v for k, v in plain["backbone"].items() if k in known_bb}
    resolved = resolve_precision(cfg, resolve_device(cfg))
    versions: list[tuple[str, Any, Any]] = [
        (f"baseline {baseline}", base_train.train_model, base_train.config_from_dict(base_plain)),
        ("this tree, float32", train_model, config_from_dict({**plain, "precision": "float32"})),
    ]
    if resolved is not None:
        name = str(resolved).removeprefix("torch.")
        versions.append((f"this tree, {name} ({cfg.precision})", train_model, config_from_dict(plain)))
    indices = list(range(min(len(scans), steps)))  # one pass over them is at most ``steps`` steps
    wall: dict[str, list[float]] = {name: [] for name, _, _ in versions}
    cpu: dict[str, list[float]] = {name: [] for name, _, _ in versions}
    if repeats > 1:  # a warm-up round (lazy imports, first allocations), not timed
        for _, train, vcfg in versions:
            train(scans.__getitem__, indices[:1], num_classes, replace(vcfg, min_steps=1))
    for _ in range(repeats):
        for name, train, vcfg in versions:
            c0 = time.process_time()
            _, stats = train(scans.__getitem__, indices, num_classes, vcfg)
            cpu[name].append((time.process_time() - c0) / stats.steps)
            wall[name].append(stats.seconds / stats.steps)
    first = versions[0][0]
    return [
        {
            "version": name,
            "steps": steps,
            "wall_s_per_step": float(np.median(wall[name])),
            "cpu_s_per_step": float(np.median(cpu[name])),
            "speedup_vs_baseline": float(np.median(wall[first]) / np.median(wall[name])),
            "left_out": left_out if name == first else [],
        }
        for name, _, _ in versions
    ]


def print_training_steps(rows: list[dict[str, Any]]) -> None:
    """The per-version training-step table, with the ratio to the baseline commit."""
    print(f"\n{'training step (train_model)':<40}{'wall s':>9}{'CPU s':>9}{'speed-up':>10}")
    for r in rows:
        print(
            f"{r['version']:<40}{r['wall_s_per_step']:>9.3f}{r['cpu_s_per_step']:>9.3f}{r['speedup_vs_baseline']:>9.2f}x"
        )
    if rows[0]["left_out"]:
        print(f"(baseline settings left out, unknown to it: {', '.join(rows[0]['left_out'])})")


def print_step_times(base: dict[str, float]) -> None:
    """The training-step table and its two ratios, each labelled by what it includes."""
    print(f"\n{'training step':<32}{'params':>10}{'seconds':>10}")
    print(f"{'data preparation (kNN, grid)':<32}{'':>10}{base['prepare_s']:>10.3f}")
    print(f"{'3D-CN backbone step':<32}{base['backbone_params']:>10,}{base['backbone_step_s']:>10.3f}")
    print(f"{'plain MLP step (baseline)':<32}{base['mlp_params']:>10,}{base['mlp_step_s']:>10.3f}")
    print(
        f"ratio backbone step / MLP step (same prepared batch): "
        f"{base['backbone_step_s'] / base['mlp_step_s']:.1f}x; "
        f"(preparation + backbone step) / MLP step: "
        f"{(base['prepare_s'] + base['backbone_step_s']) / base['mlp_step_s']:.1f}x "
        f"({base['points_per_step']:,} points/step)"
    )


def step_tables(
    args: argparse.Namespace,
    cfg: ConsistencyConfig,
    seq: KittiSequence,
    frames: range,
    gt: list[np.ndarray],
    num_classes: int,
) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """The backbone-vs-MLP step (:func:`step_times`) and the training step per version
    (:func:`training_step_versions`) on the first scans of ``seq``."""
    base = step_times(cfg, seq.frame(frames[0]).points, num_classes, repeats=2 if args.quick else 5)
    # The scans' targets: the ground truth with 4 of 5 points unlabeled (the selection keeps a share of
    # each class's labels); what a step costs does not depend on which labels they are.
    mask_rng = np.random.default_rng(0)
    scans = [
        (seq.frame(i).points, np.where(mask_rng.random(len(g)) < 0.2, g, UNLABELED))
        for i, g in zip(frames[: args.steps], gt, strict=False)
    ]
    with tempfile.TemporaryDirectory(prefix="bench3dcn_base_") as work:
        rows = training_step_versions(
            cfg, scans, num_classes, args.steps, args.baseline, Path(work), repeats=1 if args.quick else 3
        )
    return base, rows


def steps_only(  # noqa: PLR0917  main's parsed inputs
    args: argparse.Namespace,
    cfg: ConsistencyConfig,
    seq: KittiSequence,
    frames: range,
    gt: list[np.ndarray],
    num_classes: int,
    source: str,
) -> int:
    """``--steps-only``: the two training-step tables, printed and written."""
    load_before = os.getloadavg()[0]
    base, rows = step_tables(args, cfg, seq, frames, gt, num_classes)
    load_after = os.getloadavg()[0]
    print(
        f"3D-CN training steps on {source}; torch threads {args.threads}, device {cfg.device}, "
        f"load average {load_before:.1f} -> {load_after:.1f}"
    )
    print_step_times(base)
    print_training_steps(rows)
    payload = {
        "source": source,
        "threads": args.threads,
        "load_average": [load_before, load_after],
        "points_per_scan": cfg.points_per_scan,
        "baseline": base,
        "training_steps": rows,
    }
    atomic_write_json(args.out, payload)
    print(f"\nwrote {args.out}")
    return 0


# ----------------------------------------------------------------------------------------------- main
def load_run_inputs(
    run_dir: Path, seq: KittiSequence, frames: range, logp_clip: float
) -> tuple[VoxelGrid, VoxelGrid, list[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The fused and smoothed grids of ``seq`` in a finished ``leap run`` (its run folder, where the
    sequence's folder is ``sequences/<name of seq's folder>``), each scan's camera-view mask, and how many
    frames observed each voxel (the selection's tie-break, as the pipeline computes it)."""
    if not RunLayout.is_run(run_dir):
        raise SystemExit(f"{run_dir}: not a run folder (no {RunLayout.SPEC}); give the --out of `leap run`")
    layout = RunLayout(run_dir).sequence(SequenceSpec.of(seq.root).name)
    if not layout.grid_smooth.is_file():
        raise SystemExit(f"{layout.folder}: no {SequenceLayout.GRID_SMOOTH}; run `leap run` on the sequence")
    fused = VoxelGrid.load(layout.grid)
    smoothed = SmoothedGrid.load(layout.grid_smooth).to_voxel_grid(logp_clip)
    views = []
    observed = []
    for i in frames:
        path = layout.observation(seq.frame_ids[i])
        with np.load(path) as z:
            views.append(np.unpackbits(z["in_view"], count=int(z["n_points"])).astype(bool))
        frame = seq.frame(i)
        painted = frame.points[Painted.load(path).point_idx]
        observed.append(voxel_keys(world_points(painted, frame.pose), fused.voxel_size))
    return fused, smoothed, views, view_counts(observed)


def smoothed_labels(seq: KittiSequence, frames: range, grid: VoxelGrid) -> list[np.ndarray]:
    """Per scan, each point's label in ``grid`` after the pipeline's kNN smoothing."""
    probs = knn_smooth(grid.centres(), grid.probs(), SmoothingConfig())
    sm = VoxelGrid(grid.keys, np.log(np.maximum(probs, 1e-9)).astype(np.float16), grid.voxel_size)
    labels = sm.voxel_labels()
    out = []
    for i in frames:
        keys = voxel_keys(world_points(seq.frame(i).points, seq.poses[i]), grid.voxel_size)
        out.append(labels.at(keys)[0])
    return out


def main(argv: list[str] | None = None) -> int:  # noqa: PLR0912  arguments, run and report, top to bottom
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, default=None, help="KITTI sequence folder (default: a stand-in)")
    ap.add_argument(
        "--run-dir",
        type=Path,
        default=None,
        help="finished `leap run` folder of --sequence: use its fused/smoothed grids and camera view",
    )
    ap.add_argument("--frames", type=int, default=60, help="scans of the stand-in / first scans used")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--noise", type=float, default=0.15, help="without --run-dir: camera label noise")
    ap.add_argument("--fov", type=float, default=90.0, help="without --run-dir: camera field of view (deg)")
    ap.add_argument(
        "--config",
        type=str,
        default="{}",
        help="JSON overrides of ConsistencyConfig, e.g. '{\"temperature\": 2}'",
    )
    ap.add_argument("--device", default="cpu", choices=["auto", "cpu", "cuda"])
    ap.add_argument("--paper-scale", action="store_true", help="WaffleIron sizes (GPU)")
    ap.add_argument(
        "--source",
        type=Path,
        default=None,
        help="also time an iteration fine-tuned from this 3D-CN checkpoint (--3dcn-init)",
    )
    ap.add_argument(
        "--baseline",
        default=BASELINE_COMMIT,
        help="git commit whose train_model the training-step table compares with (default: the last "
        "before mixed precision and prefetching)",
    )
    ap.add_argument("--steps", type=int, default=30, help="training steps each version is timed over")
    ap.add_argument(
        "--steps-only",
        action="store_true",
        help="only the training-step tables (no 3D-CN round, no labels table)",
    )
    ap.add_argument(
        "--out", type=Path, default=None, help="result file (default RESULTS/bench_3dcn[_quick][_steps].json)"
    )
    ap.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke run: {QUICK_FRAMES} scans of the stand-in, a small network and one pass of training "
        f"({json.dumps(QUICK_CONFIG)} under --config)",
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.frames = QUICK_FRAMES
        args.steps = QUICK_STEPS
        args.config = json.dumps({**QUICK_CONFIG, **json.loads(args.config)})
    if args.out is None:
        suffix = ("_quick" if args.quick else "") + ("_steps" if args.steps_only else "")
        args.out = RESULTS / f"bench_3dcn{suffix}.json"
    torch.set_num_threads(args.threads)

    tmp = None
    t0 = time.perf_counter()
    if args.sequence is None:
        if args.run_dir is not None:
            print("error: --run-dir needs the --sequence it was run on")
            return 2
        tmp = tempfile.TemporaryDirectory(prefix="bench3dcn_")
        seq_path = write_standin_sequence(Path(tmp.name), args.frames)
        source = f"built-in stand-in street ({args.frames} scans)"
    else:
        seq_path = args.sequence
        source = str(seq_path)
    gen_s = time.perf_counter() - t0
    seq = KittiSequence(seq_path)
    frames = range(min(args.frames, len(seq)))
    schema = builtin_schema("semantickitti")
    c = schema.num_classes
    if not seq.has_labels:
        print(f"error: {seq_path} has no labels/ (the benchmark evaluates against ground truth)")
        return 2
    gt = [schema.map_gt(seq.frame(i).labels) for i in frames]

    base_cfg = ConsistencyConfig.paper_scale() if args.paper_scale else ConsistencyConfig(enabled=True)
    overrides = json.loads(args.config)
    if "backbone" in overrides:
        overrides["backbone"] = replace(base_cfg.backbone, **overrides["backbone"])
    cfg = replace(base_cfg, device=args.device, num_threads=args.threads, **overrides)
    fusion_cfg = FusionConfig()
    if args.steps_only:
        return steps_only(args, cfg, seq, frames, gt, c, source)

    if args.run_dir is not None:
        fused, smoothed, views, seen = load_run_inputs(args.run_dir, seq, frames, fusion_cfg.logp_clip)
        inputs = f"fused + smoothed grids of {args.run_dir}"
    else:
        fused, views = camera_grid(seq, gt, c, args.noise, args.fov, seed=0)
        smoothed = fused
        seen = None
        inputs = f"ground truth in a {args.fov:.0f} deg view with {args.noise:.0%} label noise"
    n_points = sum(seq.frame(i).points.shape[0] for i in frames)
    marks: list[tuple[float, int]] = []
    n = len(frames)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench3dcn_work_") as work:
        t_start = time.perf_counter()
        new = run_3dcn_iteration(
            seq,
            fused,
            smoothed,
            c,
            cfg,
            fusion_cfg,
            Path(work),
            1,
            progress=lambda d, _t: marks.append((time.perf_counter(), d)),
            frames=frames,
            views=seen,
        )
        total_s = time.perf_counter() - t_start
    tuned, tuned_s = None, None
    if args.source is not None:
        src = load_source(args.source, cfg.backbone, c)
        with tempfile.TemporaryDirectory(prefix="bench3dcn_work_") as work:
            t_tuned = time.perf_counter()
            tuned = run_3dcn_iteration(
                seq, fused, smoothed, c, cfg, fusion_cfg, Path(work), 1, frames=frames, views=seen, source=src
            )
            tuned_s = time.perf_counter() - t_tuned
    load_after = os.getloadavg()[0]
    steps = num_train_steps(n, cfg)

    def at(done: int) -> float:
        return next(t for t, d in marks if d >= done) - t_start

    sel_s, train_end = at(n), at(n + steps)
    phases = {
        "selection_s": sel_s,
        "training_s": train_end - sel_s,
        "inference_fusion_s": total_s - train_end,
        "total_s": total_s,
    }

    gt_f = np.concatenate(gt)
    view_f = np.concatenate(views)
    rows = {}
    if args.run_dir is not None:
        smooth_lookup = smoothed.voxel_labels()
        before = [
            smooth_lookup.at(voxel_keys(world_points(seq.frame(i).points, seq.poses[i]), 0.2))[0]
            for i in frames
        ]
    else:
        before = smoothed_labels(seq, frames, fused)
    columns = [("voxel", before), ("+3D-CN x1", smoothed_labels(seq, frames, new))]
    if tuned is not None:
        columns.append(("+3D-CN x1, from source", smoothed_labels(seq, frames, tuned)))
    for name, labels in columns:
        pred = np.concatenate(labels)
        cam = evaluate(
            gt_f[view_f], pred[view_f], schema.names, schema.categories(), ignore_unlabeled_pred=True
        )
        every = evaluate(gt_f, pred, schema.names, schema.categories(), ignore_unlabeled_pred=False)
        rows[name] = {
            "miou_camera_view": cam.miou,
            "category_miou_camera_view": cam.category_miou,
            "miou_all_points": every.miou,
            "labeled_share_all": float((pred >= 0).mean()),
        }
    base, training_steps = step_tables(args, cfg, seq, frames, gt, c)

    print(f"3D-CN benchmark on {source}: {n} scans, {n_points:,} points; inputs: {inputs}")
    print(
        f"torch threads {args.threads}, {platform.machine()}, device {cfg.device}, "
        f"load average {load_before:.1f} -> {load_after:.1f} (other processes share the cores)"
    )
    print(f"{'phase':<24}{'seconds':>10}")
    for k, v in phases.items():
        print(f"{k:<24}{v:>10.1f}")
    print(f"{'target (train+infer)':<24}{600:>10.1f}   ratio total/target = {total_s / 600:.2f}")
    if tuned_s is not None:
        print(
            f"{'fine-tuned from source':<24}{tuned_s:>10.1f}   ratio to the random-weight total = "
            f"{tuned_s / total_s:.2f} ({num_train_steps(n, cfg, finetune=True)} steps against {steps})"
        )
    print_step_times(base)
    print_training_steps(training_steps)
    print(f"\n{'labels':<24}{'mIoU cam':>10}{'cat cam':>10}{'mIoU all':>10}{'labeled':>10}")
    for name, r in rows.items():
        print(
            f"{name:<24}{100 * r['miou_camera_view']:>10.1f}{100 * r['category_miou_camera_view']:>10.1f}"
            f"{100 * r['miou_all_points']:>10.1f}{100 * r['labeled_share_all']:>9.1f}%"
        )
    result = {
        "source": source,
        "inputs": inputs,
        "scans": n,
        "points": n_points,
        "threads": args.threads,
        "load_average": [load_before, load_after],
        "stand_in_seconds": gen_s,
        "config": {
            "temperature": cfg.temperature,
            "points_per_scan": cfg.points_per_scan,
            "min_steps": cfg.min_steps,
            "channels": cfg.backbone.channels,
            "layers": cfg.backbone.layers,
            "use_intensity": cfg.backbone.use_intensity,
            "device": cfg.device,
            "train_steps": steps,
        },
        "phases": phases,
        "target_s": 600.0,
        "ratio_to_target": total_s / 600.0,
        "baseline": base,
        "ratio_backbone_to_mlp_step": base["backbone_step_s"] / base["mlp_step_s"],
        "ratio_prepare_and_backbone_to_mlp_step": (base["prepare_s"] + base["backbone_step_s"])
        / base["mlp_step_s"],
        "labels": rows,
        "training_steps": training_steps,
    }
    if tuned_s is not None:
        result["source_network"] = {
            "path": str(args.source),
            "total_s": tuned_s,
            "ratio_to_random_total": tuned_s / total_s,
            "train_steps": num_train_steps(n, cfg, finetune=True),
        }
    atomic_write_json(args.out, result)
    print(f"\nwrote {args.out}")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
