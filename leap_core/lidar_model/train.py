"""Training a LiDAR-only model on labeled scans, resumable step for step (docs/METHOD.md "A LiDAR-only
model").

Every ``checkpoint_every`` steps the whole training state (weights, AdamW moments, the learning-rate
schedule's position, the numpy and torch random states and the current pass's scan order) is written to
``<model>.state.pt``; a later call with the same data and settings continues from it and ends with the
same bytes as a run that was never interrupted (CPU). The state file is removed once the model is saved.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch.nn import functional as F_

from leap_core.consistency.backbone import PointSegmenter
from leap_core.consistency.data import PreparedCloud, augment_points, collate, prepare_cloud
from leap_core.consistency.train import (
    class_counts,
    class_weights,
    draw_points,
    lr_factor,
    predict_log_probs,
    torch_threads,
)
from leap_core.errors import LeapError, ModelLoadError
from leap_core.heap import release_free_memory
from leap_core.io_utils import atomic_write, file_digest
from leap_core.lidar_model.config import LidarModelConfig, model_config_to_dict
from leap_core.lidar_model.data import LabeledScans
from leap_core.lidar_model.model import LidarModel, save_model, state_path
from leap_core.metrics import confusion_matrix, metrics_from_confusion
from leap_core.pipeline.provenance import code_version
from leap_core.progress import ProgressFn, report
from leap_core.schema import Schema
from leap_core.types import UNLABELED

STATE_FORMAT = "leap-lidar-model-state"
_IGNORE = -100


def resolve_device(name: str) -> torch.device:
    """``auto`` → CUDA when available, else CPU; ``cuda`` without CUDA is a one-line error."""
    if name == "cuda" or (name == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise ModelLoadError("device is 'cuda' but torch sees no CUDA device")
        return torch.device("cuda")
    return torch.device("cpu")


@dataclass
class TrainResult:
    """What :func:`train_lidar_model` did."""

    steps: int = 0
    """Steps taken in this call (a resumed call counts only its own)."""
    resumed_from: int = 0
    """The step the saved state was at (0: trained from the start)."""
    losses: list[float] = field(default_factory=list)
    """Cross-entropy of every step of this call."""
    points_seen: int = 0
    """Points fed through the network in this call."""
    seconds: float = 0.0
    """Wall time of this call's training loop."""
    card: dict[str, Any] = field(default_factory=dict)
    """The saved model's card."""


def training_fingerprint(
    cfg: LidarModelConfig, schema: Schema, data: LabeledScans, init_digest: str | None
) -> str:
    """SHA-256 of everything the trained bytes depend on: settings, classes, the scans (where from, which
    frames), the starting checkpoint. A saved state is resumed only under the same fingerprint."""
    plain = {
        "config": {k: v for k, v in model_config_to_dict(cfg).items() if k not in ("checkpoint_every",)},
        "schema": schema.to_dict(),
        "scans": [[data.sequences[s].where, data.sequences[s].seq.frame_ids[i]] for s, i in data.scans],
        "init": init_digest,
    }
    return hashlib.sha256(json.dumps(plain, sort_keys=True, default=str).encode()).hexdigest()


def _batch(
    data: LabeledScans, ids: Sequence[int], schema: Schema, cfg: LidarModelConfig, rng: np.random.Generator
) -> tuple[list[PreparedCloud], list[npt.NDArray[np.int64]]]:
    """One step's clouds and loss targets (``_IGNORE`` where a drawn point has no label); a scan none of
    whose drawn points has a label is left out."""
    clouds, targets = [], []
    for j in ids:
        points, label = data.load(j, schema)
        subset = draw_points(label, cfg.points_per_scan, cfg.labeled_share, rng)
        pts = augment_points(points, rng) if cfg.augment else points
        t = label[subset].astype(np.int64)
        if not (t != UNLABELED).any():
            continue
        clouds.append(prepare_cloud(pts, cfg.backbone, subset, workers=max(1, torch.get_num_threads())))
        targets.append(np.where(t == UNLABELED, _IGNORE, t))
    return clouds, targets


def _step(
    model: PointSegmenter,
    opt: torch.optim.Optimizer,
    batch: tuple[list[PreparedCloud], list[npt.NDArray[np.int64]]],
    weights: torch.Tensor,
    device: torch.device,
) -> tuple[float, int] | None:
    """One AdamW step (gradient norm clipped at 1); ``(loss, points)`` or None for an empty batch."""
    clouds, targets = batch
    if not clouds:
        return None
    tensors = collate(clouds).to(device)
    tgt = torch.from_numpy(np.concatenate(targets)).to(device)
    loss = F_.cross_entropy(model(tensors), tgt, weight=weights, ignore_index=_IGNORE)
    opt.zero_grad(set_to_none=True)
    torch.autograd.backward(loss)
    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
    opt.step()
    return float(loss.detach()), tensors.num_points


def label_counts(data: LabeledScans, schema: Schema) -> npt.NDArray[np.int64]:
    """(C,) labeled points per class over the scans (labels only are read)."""
    counts = np.zeros(schema.num_classes, np.int64)
    for s, i in data.scans:
        counts += class_counts(data.sequences[s].labels(i, schema), schema.num_classes)
    return counts


def _save_state(path: Path, payload: dict[str, Any]) -> None:
    with atomic_write(path, "wb") as fh:
        torch.save(payload, fh)


def _load_state(path: Path, fingerprint: str) -> dict[str, Any] | None:
    """The saved state when it belongs to this training (same fingerprint), else None.

    Raises:
        LeapError: naming the file, when it is unreadable or belongs to other data or settings.
    """
    if not path.is_file():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several unrelated types for corrupt files
        raise LeapError(
            f"{path}: unreadable training state ({type(exc).__name__}); delete it to start over"
        ) from exc
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise LeapError(f"{path}: not a `leap train` training state; delete it to start over")
    if state.get("fingerprint") != fingerprint:
        raise LeapError(
            f"{path}: an interrupted training of other data or settings; delete it (or pass --restart) "
            "to start this one"
        )
    return dict(state)


def validate(
    model: PointSegmenter, data: LabeledScans, schema: Schema, device: torch.device
) -> dict[str, Any] | None:
    """The model's mIoU on the validation scans against their labels (every point predicted; points
    without a label not counted), per class; None without validation scans."""
    if not data.scans:
        return None
    c = schema.num_classes
    cm = np.zeros((c, c + 1), np.int64)
    model = model.to(device)
    for j in range(len(data.scans)):
        points, label = data.load(j, schema)
        pred = predict_log_probs(model, points, device, workers=max(1, torch.get_num_threads())).argmax(1)
        cm += confusion_matrix(label, pred.astype(np.int16), c)
    m = metrics_from_confusion(cm, schema.names, schema.categories(), ignore_unlabeled_pred=True)
    d = m.to_dict()
    return {"scans": len(data.scans), "miou": d["miou"], "iou": d["iou"], "points": d["n_points"]}


def train_lidar_model(  # noqa: PLR0913, PLR0915  keyword-only options of one training; one loop
    out: str | Path,
    train: LabeledScans,
    val: LabeledScans,
    schema: Schema,
    cfg: LidarModelConfig,
    *,
    init: LidarModel | None = None,
    init_path: str | Path | None = None,
    progress: ProgressFn | None = None,
    restart: bool = False,
) -> TrainResult:
    """Train (or resume training) a :class:`PointSegmenter` on ``train`` and save it with its card.

    ``cfg.steps`` steps; per pass the training scans are visited in a seeded random order,
    ``scans_per_step`` per step. From random weights at ``lr``, or from ``init``'s weights at
    ``finetune_lr``. Classes without a training label are masked (``trained_classes``).

    Args:
        out: the model file to write (its state and card beside it, :mod:`leap_core.lidar_model.model`).
        train: training scans; val: validation scans (held apart, never trained on).
        schema: the classes (index order; export ids).
        cfg: settings.
        init: a model to start from (same classes and backbone); init_path: its file, for the card.
        progress: ``progress(step, steps)``; raising ``Cancelled`` stops after the last saved state.
        restart: ignore (and replace) a saved state instead of resuming it.

    Raises:
        ModelLoadError: ``init`` has other classes or another backbone.
        LeapError: a saved state of other data or settings, or no labeled point to train on.
    """
    out = Path(out)
    if init is not None:
        if init.schema.names != schema.names:
            raise ModelLoadError(
                f"{init_path}: --init model predicts {', '.join(init.schema.names)}; this training's classes "
                f"are {', '.join(schema.names)}"
            )
        if init.config.backbone != cfg.backbone:
            raise ModelLoadError(f"{init_path}: --init model has another backbone than these settings")
    init_digest = None if init_path is None else file_digest(init_path)
    fingerprint = training_fingerprint(cfg, schema, train, init_digest)
    spath = state_path(out)
    state = None if restart else _load_state(spath, fingerprint)
    counts = label_counts(train, schema)
    if counts.sum() == 0:
        raise LeapError("no labeled point in the training scans")
    device = resolve_device(cfg.device)
    result = TrainResult()
    t0 = time.perf_counter()
    n = len(train.scans)
    with torch.random.fork_rng(devices=[]), torch_threads(cfg.num_threads):
        torch.manual_seed(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        model = PointSegmenter(cfg.backbone, schema.num_classes)
        if init is not None:
            model.load_state_dict(init.network.state_dict())
        model.trained_classes.copy_(torch.as_tensor(counts > 0))
        model = model.to(device)
        weights = class_weights(counts, cfg.class_balance_power > 0, cfg.class_balance_power).to(device)
        lr = cfg.lr if init is None else cfg.finetune_lr
        opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=cfg.weight_decay)
        total = cfg.steps
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, total))
        step, order, pos, seen = 0, np.zeros(0, np.int64), 0, 0
        if state is not None:
            model.load_state_dict(state["model"])
            opt.load_state_dict(state["optimizer"])
            sched.load_state_dict(state["schedule"])
            rng.bit_generator.state = state["numpy_rng"]
            torch.set_rng_state(state["torch_rng"])
            step, pos, seen = int(state["step"]), int(state["pos"]), int(state["points_seen"])
            order = state["order"].numpy()
            result.resumed_from = step
        model.train()
        while step < total:
            if pos >= len(order):
                order, pos = rng.permutation(n), 0
            ids = [int(j) for j in order[pos : pos + cfg.scans_per_step]]
            pos += cfg.scans_per_step
            done = _step(model, opt, _batch(train, ids, schema, cfg, rng), weights, device)
            release_free_memory()
            sched.step()
            step += 1
            if done is not None:
                result.losses.append(done[0])
                result.points_seen += done[1]
            result.steps += 1
            if step % cfg.checkpoint_every == 0 and step < total:
                _save_state(
                    spath,
                    {
                        "format": STATE_FORMAT,
                        "fingerprint": fingerprint,
                        "step": step,
                        "pos": pos,
                        "order": torch.from_numpy(np.asarray(order, np.int64)),
                        "model": model.state_dict(),
                        "optimizer": opt.state_dict(),
                        "schedule": sched.state_dict(),
                        "numpy_rng": rng.bit_generator.state,
                        "torch_rng": torch.get_rng_state(),
                        "points_seen": seen + result.points_seen,
                    },
                )
            report(progress, step, total)
        model.eval()
        result.seconds = time.perf_counter() - t0
        validation = validate(model, val, schema, device)
    model = model.cpu()
    result.card = model_card(
        schema, cfg, train, val, counts, validation, init_path, init_digest, seen + result.points_seen
    )
    result.card["training"].update(
        steps=total, resumed_from=result.resumed_from, seconds_this_call=round(result.seconds, 3)
    )
    save_model(out, model, cfg, result.card)
    spath.unlink(missing_ok=True)
    return result


def _data_entries(data: LabeledScans) -> list[dict[str, Any]]:
    used: dict[int, list[int]] = {}
    for s, i in data.scans:
        used.setdefault(s, []).append(i)
    out = []
    for s, idx in used.items():
        part = data.sequences[s]
        out.append(
            {
                "kind": part.kind,
                "labels": part.where,
                "dataset": str(part.seq.root),
                "scans": len(idx),
                "frames": [part.seq.frame_ids[idx[0]], part.seq.frame_ids[idx[-1]]],
            }
        )
    return out


def model_card(  # noqa: PLR0913, PLR0917  the parts of a card
    schema: Schema,
    cfg: LidarModelConfig,
    train: LabeledScans,
    val: LabeledScans,
    counts: npt.NDArray[np.int64],
    validation: dict[str, Any] | None,
    init_path: str | Path | None,
    init_digest: str | None,
    points_seen: int,
) -> dict[str, Any]:
    """The card saved with a model (JSON-ready)."""
    ids = schema.export_ids()
    runs = sorted({str(p.layout.folder.parent.parent) for p in train.sequences if p.layout is not None})
    return {
        "model": "WaffleIron-style point backbone (leap_core.consistency.backbone)",
        "classes": [
            {"name": n, "export_id": int(ids[k]), "training_points": int(counts[k])}
            for k, n in enumerate(schema.names)
        ],
        "schema": schema.to_dict(),
        "data": {"train": _data_entries(train), "validation": _data_entries(val), "runs": runs},
        "init": None if init_path is None else {"path": str(init_path), "sha256": init_digest},
        "settings": model_config_to_dict(cfg),
        "training": {"points_seen": int(points_seen)},
        "validation": validation,
        "code": code_version(),
        "written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


__all__ = [
    "TrainResult",
    "label_counts",
    "resolve_device",
    "train_lidar_model",
    "training_fingerprint",
    "validate",
]
