"""Labeling scans with a trained LiDAR-only model: no camera, frame by frame, into a run folder.

The output is a run folder of the usual layout (:mod:`leap_core.run_layout`), so the app, the viewer and
``leap run``'s exports read it as any run: per sequence ``points/<frame_id>.npz`` (``label``, ``conf``:
the argmax class and its probability; ``point_label`` all unlabeled, as no camera painted anything) and
``export/<frame_id>.label|.conf`` (raw export ids). ``run.json`` lists the sequences, and
``<run>/model.json`` the model that labeled them (its file, digest and card). Where the sequence has
ground truth, every point is scored (``sequences/<name>/model-metrics.json``).

Memory: one scan's points, features and activations at a time (the network chunks its widest tensor), so
a sequence of any length runs in the memory of its largest scan.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from leap_core.consistency.train import predict_log_probs, torch_threads
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import LeapError
from leap_core.export import export_labels
from leap_core.io_utils import atomic_save_npz, atomic_write_json, file_digest
from leap_core.lidar_model.model import LidarModel
from leap_core.lidar_model.train import resolve_device
from leap_core.metrics import Metrics, confusion_matrix, metrics_from_confusion
from leap_core.progress import ProgressFn, report
from leap_core.run_layout import RunLayout, SequenceLayout, write_run_spec
from leap_core.schema import Schema
from leap_core.types import UNLABELED


@dataclass
class PredictedSequence:
    """One sequence :func:`predict_run` labeled."""

    name: str
    scans: int = 0
    points: int = 0
    seconds: float = 0.0
    """Wall time of its scans (reading, network, writing)."""
    metrics: Metrics | None = None
    """Every point against the ground truth (None without it)."""
    confusion: npt.NDArray[np.int64] | None = field(default=None, repr=False)
    raw_counts: dict[int, int] = field(default_factory=dict)
    """Points per export id written (for the export's label map)."""


def scan_labels(
    model: LidarModel, points: npt.NDArray[np.float32], device: torch.device, views: int = 1
) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
    """``(label (N,) int16, conf (N,) float32)`` of one scan: ``label = argmax_c log P(c)`` and
    ``conf = max_c P(c)``, P the network's class probabilities (averaged over ``views`` test-time views)."""
    logp = predict_log_probs(
        model.network, points, device, workers=max(1, torch.get_num_threads()), views=views
    )
    label = logp.argmax(axis=1).astype(np.int16)
    conf = np.exp(np.take_along_axis(logp, label[:, None].astype(np.int64), axis=1)[:, 0]).astype(np.float32)
    return label, conf


def predict_sequence(  # noqa: PLR0913  keyword options of one labeling
    model: LidarModel,
    seq: KittiSequence,
    layout: SequenceLayout,
    *,
    name: str,
    indices: Sequence[int] | None = None,
    views: int = 1,
    device: str = "auto",
    progress: ProgressFn | None = None,
    truth: Schema | None = None,
) -> PredictedSequence:
    """Label the scans ``indices`` (default all) of ``seq`` into ``layout`` (points + export), one at a
    time; score them when every one has ground truth, its raw ids read by ``truth``'s ground-truth ids
    (default the model's schema; the same classes: a model trained on another domain's ids is scored
    on this one's)."""
    dev = resolve_device(device)
    net = model.network.to(dev)
    model.network = net
    idx = list(range(len(seq))) if indices is None else list(indices)
    c = model.schema.num_classes
    gt_schema = model.schema if truth is None else truth
    if gt_schema.names != model.schema.names:
        raise LeapError(f"the ground truth's classes ({', '.join(gt_schema.names)}) are not the model's")
    with_truth = all(seq.label_path(i).is_file() for i in idx)
    cm = np.zeros((c, c + 1), np.int64) if with_truth else None
    ids = model.schema.export_ids()
    out = PredictedSequence(name)
    per_class = np.zeros(c, np.int64)
    t0 = time.perf_counter()
    for k, i in enumerate(idx):
        frame = seq.frame(i)
        points = frame.points
        label, conf = scan_labels(model, points, dev, views)
        fid = seq.frame_ids[i]
        atomic_save_npz(
            layout.points(fid),
            label=label,
            conf=conf.astype(np.float16),
            point_label=np.full(label.shape, UNLABELED, np.int16),
        )
        export_labels(layout.export_label(fid), layout.export_conf(fid), label, conf, ids)
        if cm is not None:
            cm += confusion_matrix(gt_schema.map_gt(frame.labels), label, c)
        per_class += np.bincount(label, minlength=c)
        out.scans += 1
        out.points += int(points.shape[0])
        report(progress, k + 1, len(idx))
    out.seconds = time.perf_counter() - t0
    out.raw_counts = {int(ids[k]): int(n) for k, n in enumerate(per_class) if n}
    if cm is not None:
        out.confusion = cm
        out.metrics = metrics_from_confusion(
            cm, model.schema.names, model.schema.categories(), ignore_unlabeled_pred=False
        )
        atomic_write_json(layout.model_metrics, {"all": out.metrics.to_dict()})
    return out


def predict_run(  # noqa: PLR0913  keyword options of one labeling
    model: LidarModel,
    model_path: str | Path,
    datasets: Sequence[tuple[str, str | Path, range | None]],
    out: str | Path,
    *,
    views: int = 1,
    device: str = "auto",
    num_threads: int = 0,
    progress: Any = None,
    truth: Schema | None = None,
) -> list[PredictedSequence]:
    """Label sequences with ``model`` into the run folder ``out``.

    Args:
        model: the loaded model; model_path: its file (recorded in ``model.json``).
        datasets: ``(name, sequence folder, frame numbers or None = all)`` per sequence.
        out: the run folder (created; a folder holding another run's results is refused).
        views: test-time views per scan.
        device: ``auto``, ``cpu`` or ``cuda``.
        num_threads: torch threads (0: torch's setting).
        progress: ``progress(name, done, total)`` per scan.
        truth: the classes' ground-truth ids to score with (:func:`predict_sequence`).

    Raises:
        LeapError: ``out`` holds results of another run, or a sequence's frames are out of range.
    """
    layout = RunLayout(Path(out))
    if layout.holds_results() and not layout.model_note.is_file():
        raise LeapError(f"{layout.root}: holds another run's results; give another --out")
    seqs = [(name, KittiSequence(path), frames) for name, path, frames in datasets]
    chosen = [(name, seq, seq.select(frames)) for name, seq, frames in seqs]
    write_run_spec(layout, [(name, seq.root, frames) for name, seq, frames in seqs])
    atomic_write_json(
        layout.model_note,
        {"path": str(Path(model_path).resolve()), "sha256": file_digest(model_path), "card": model.card},
    )
    results = []
    with torch_threads(num_threads):
        for name, seq, idx in chosen:

            def tick(done: int, total: int, name: str = name) -> None:
                if progress is not None:
                    progress(name, done, total)

            results.append(
                predict_sequence(
                    model,
                    seq,
                    layout.sequence(name),
                    name=name,
                    indices=idx,
                    views=views,
                    device=device,
                    progress=tick,
                    truth=truth,
                )
            )
    return results


__all__ = ["PredictedSequence", "predict_run", "predict_sequence", "scan_labels"]
