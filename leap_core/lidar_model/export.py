"""A trained model exported for use elsewhere: TorchScript.

The exported module takes plain tensors, built by
:func:`leap_core.consistency.data.prepare_cloud` (or any port of it) from one scan:

``forward(feats (N, D_in) float32, local (N, K, D_loc) float32, cells (3, N) int64, grids (3, 2) int64)
-> (N, C) float32 log-probabilities``

where ``cells[p, n] = u · W_p + v`` is point n's cell on plane p (xy, xz, yz) and ``grids[p] = (H_p, W_p)``.
It builds each plane's cell averaging (:func:`~leap_core.consistency.backbone.cell_mean_matrix`) and runs
the network's own layers (``SpatialMix.mix``), so its output equals the PyTorch model's
(``predict_log_probs``), classes without training labels at ``-inf`` as there.

ONNX is not offered: the spatial mixing averages points per grid cell through a sparse COO matrix product
(``torch.sparse.mm``) and numbers the cells with ``torch.unique``, and the ONNX exporter has no operator
for sparse tensors; a dense rewrite would be another network, not this one.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor, nn
from torch.nn import functional as F_

from leap_core.consistency.backbone import (
    PLANES,
    ChannelMix,
    KnnEmbedding,
    PointSegmenter,
    SpatialMix,
    cell_mean_matrix,
)
from leap_core.consistency.data import PreparedCloud
from leap_core.io_utils import atomic_write


class _Layer(nn.Module):
    """One (channel mixing, spatial mixing) pair of the network, sharing its modules."""

    def __init__(self, channel: ChannelMix, spatial: SpatialMix) -> None:
        super().__init__()
        self.channel = channel
        self.spatial = spatial

    def forward(self, x: Tensor, occupied: Tensor, inverse: Tensor, mean: Tensor, shape: list[int]) -> Tensor:
        return self.spatial.mix(self.channel(x), occupied, inverse, mean, 1, shape[0], shape[1])


class ScriptedSegmenter(nn.Module):
    """The network of a :class:`PointSegmenter` (the same modules), on plain tensors of one scan."""

    def __init__(self, net: PointSegmenter) -> None:
        super().__init__()
        self.embed: KnnEmbedding = net.embed
        self.layers = nn.ModuleList(
            _Layer(c, s)  # type: ignore[arg-type]  # ModuleList items are typed Module
            for c, s in zip(net.backbone.channel, net.backbone.spatial, strict=True)
        )
        self.norm = net.norm
        self.head = net.head
        self.trained_classes: Tensor
        self.register_buffer("trained_classes", net.trained_classes.clone())
        self.planes = len(PLANES)

    def forward(self, feats: Tensor, local: Tensor, cells: Tensor, grids: Tensor) -> Tensor:
        """(N, C) log-probabilities of one scan's points (module docstring)."""
        occ: list[Tensor] = []
        inv: list[Tensor] = []
        mean: list[Tensor] = []
        shapes: list[list[int]] = []
        for p in range(self.planes):
            o, i, m = cell_mean_matrix(cells[p])
            occ.append(o)
            inv.append(i)
            mean.append(m)
            shapes.append([int(grids[p, 0]), int(grids[p, 1])])
        x = self.embed(feats, local)
        for k, layer in enumerate(self.layers):
            p = k % self.planes
            x = layer(x, occ[p], inv[p], mean[p], shapes[p])
        logits = self.head(self.norm(x)).float().masked_fill(~self.trained_classes, -math.inf)
        return F_.log_softmax(logits, dim=1)


def script_model(net: PointSegmenter) -> torch.jit.ScriptModule:
    """The network compiled with TorchScript (eval mode, CPU)."""
    net = net.cpu().eval()
    module = ScriptedSegmenter(net).eval()
    scripted: torch.jit.ScriptModule = torch.jit.script(module)
    return scripted


def export_torchscript(net: PointSegmenter, path: str | Path) -> None:
    """Write the TorchScript module (``torch.jit.load``-able without LeAP) atomically."""
    scripted = script_model(net)
    with atomic_write(path, "wb") as fh:
        torch.jit.save(scripted, fh)


def scripted_inputs(cloud: PreparedCloud) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The exported module's inputs from one prepared scan: ``(feats, local, cells, grids)``."""
    hw = cloud.grid_hw
    cells = cloud.cell_uv[:, :, 0] * hw[:, 1:2] + cloud.cell_uv[:, :, 1]
    return (
        torch.from_numpy(cloud.feats),
        torch.from_numpy(cloud.local),
        torch.from_numpy(np.ascontiguousarray(cells, np.int64)),
        torch.from_numpy(np.ascontiguousarray(hw, np.int64)),
    )


@torch.inference_mode()
def run_scripted(module: torch.jit.ScriptModule, cloud: PreparedCloud) -> npt.NDArray[np.float32]:
    """(N, C) log-probabilities of the exported module on one prepared scan."""
    out: npt.NDArray[np.float32] = module(*scripted_inputs(cloud)).numpy()
    return out


__all__ = ["ScriptedSegmenter", "export_torchscript", "run_scripted", "script_model", "scripted_inputs"]
