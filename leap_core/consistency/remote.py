"""The 3D-CN's inference on some frames in a process of its own (a Ray task, docs/ARCHITECTURE.md "The
distributed engine"): the network comes from its checkpoint file, never as an object, and each frame's
values are those of :func:`leap_core.consistency.stage.iter_3dcn_round`'s own inference loop, so the
round's grids are the same bytes wherever its frames were predicted.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch

from leap_core.consistency.config import ConsistencyConfig
from leap_core.consistency.stage import predict_frames
from leap_core.consistency.train import load_checkpoint, resolve_device, torch_threads
from leap_core.datasets.kitti import KittiSequence


def inference_threads(cfg: ConsistencyConfig) -> int:
    """The torch threads the round's inference uses in this process: ``cfg.num_threads``, or with 0 the
    process's own setting. Another process must use this same number (:func:`predict_from_checkpoint`'s
    ``threads``): a forward pass's float sums are split by thread, so its bytes may depend on it."""
    with torch_threads(cfg.num_threads):
        return max(1, torch.get_num_threads())


def predict_from_checkpoint(
    seq: KittiSequence,
    indices: Sequence[int],
    checkpoint: Path,
    cfg: ConsistencyConfig,
    voxel_size: float,
    threads: int,
) -> list[tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]]:
    """Per frame index of ``indices``, in order: its points' voxel keys ``(N,) int64`` (pose applied, as
    the fusion keys them) and the network's log-probabilities ``(N, C) float32``
    (:func:`~leap_core.consistency.train.predict_log_probs`).

    Args:
        seq: the sequence (with the poses the run uses).
        indices: frame indices into ``seq``.
        checkpoint: the round's checkpoint (loaded once for all ``indices``).
        cfg: the 3D-CN settings (device).
        voxel_size: the fusion's voxel size.
        threads: torch threads, the driver's :func:`inference_threads`.
    """
    device = resolve_device(cfg)
    model = load_checkpoint(checkpoint, device).model
    return list(predict_frames(model, seq, indices, replace(cfg, num_threads=threads), voxel_size))


__all__ = ["inference_threads", "predict_from_checkpoint"]
