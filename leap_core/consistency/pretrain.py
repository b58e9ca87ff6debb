"""Training the 3D-CN's network on ground truth: a *source* network for ``leap run --3dcn-init``.

The paper's 3D-CN fine-tunes "an arbitrary 3D point-cloud semantic segmentation network" on the reliable
camera labels for one epoch (docs/METHOD.md C.2): a network trained before, on the labels of another
dataset (its baselines: WaffleIron trained on nuScenes for SemanticKITTI). This module trains such a
network on sequences that *have* per-point ground truth (another dataset, another domain; here e.g.
``leap synth --domain street-32``), with the same backbone, loss and schedule as a round from random
weights (:func:`leap_core.consistency.train.train_model`), every labeled point a target.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from leap_core.consistency.backbone import PointSegmenter
from leap_core.consistency.config import ConsistencyConfig
from leap_core.consistency.train import TrainStats, class_counts, train_model
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import DatasetError, LeapError
from leap_core.progress import ProgressFn
from leap_core.schema import Schema


@dataclass(frozen=True)
class GroundTruthScans:
    """The labeled scans of some sequences, in order (sequence by sequence, frames in order)."""

    scans: tuple[tuple[KittiSequence, int], ...]
    """(sequence, frame index) of every scan."""
    class_counts: npt.NDArray[np.int64]
    """(C,) ground-truth points per schema class over all scans (points of unmapped raw ids not counted)."""


def ground_truth_scans(sequences: Sequence[KittiSequence], schema: Schema) -> GroundTruthScans:
    """Every scan of ``sequences``, checked to have a label file, with the schema's class counts.

    Raises:
        DatasetError: naming the file, when a scan has no label file or its label count is not its point
            count.
        LeapError: no ground-truth point of any scan maps to a class of ``schema`` (the message names the
            sequences and the schema's classes).
    """
    scans: list[tuple[KittiSequence, int]] = []
    counts = np.zeros(schema.num_classes, np.int64)
    for seq in sequences:
        for i in range(len(seq)):
            frame = seq.frame(i)
            if not frame.has_labels:
                raise DatasetError(
                    seq.label_path(i),
                    "missing ground-truth label file (training on ground "
                    "truth needs a .label file for every scan)",
                )
            counts += class_counts(schema.map_gt(frame.labels), schema.num_classes)
            scans.append((seq, i))
    if counts.sum() == 0:
        where = ", ".join(str(s.root) for s in sequences)
        raise LeapError(
            f"{where}: no ground-truth point maps to a class of the schema "
            f"({', '.join(schema.names)}); is it the schema the labels were made for?"
        )
    return GroundTruthScans(tuple(scans), counts)


def train_on_ground_truth(
    data: GroundTruthScans,
    schema: Schema,
    cfg: ConsistencyConfig,
    progress: ProgressFn | None = None,
) -> tuple[PointSegmenter, TrainStats]:
    """A network trained from random weights on every ground-truth point of ``data``.

    The schedule is a round's from random weights: ``max(epochs · S, min_steps)`` steps over the S scans
    (:func:`~leap_core.consistency.train.num_train_steps`), at ``cfg.lr``, class-weighted by
    ``data.class_counts``; classes without a ground-truth point are masked (``trained_classes``), and a
    round that fine-tunes the network sets them again from its own labels.

    Args:
        data: the scans (:func:`ground_truth_scans`).
        schema: maps each point's raw label to its class (``Schema.map_gt``).
        cfg: the 3D-CN settings (backbone, steps, seed, ...): those of the runs that will start from it.
        progress: ``progress(step, total_steps)``.

    Returns:
        The trained model (eval mode, CPU) and its training statistics.
    """

    def load(j: int) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int16]]:
        seq, i = data.scans[j]
        frame = seq.frame(i)
        return frame.points, schema.map_gt(frame.labels)

    return train_model(
        load,
        range(len(data.scans)),
        schema.num_classes,
        cfg,
        progress=progress,
        class_counts=data.class_counts,
    )


__all__ = ["GroundTruthScans", "ground_truth_scans", "train_on_ground_truth"]
