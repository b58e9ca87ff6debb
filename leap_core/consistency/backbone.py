"""A WaffleIron-style point segmentation backbone in pure PyTorch (docs/METHOD.md stage C.2).

Every point is a token of width F. The network alternates two residual mixers:

- **channel mixing**: a per-point MLP over the F channels;
- **spatial mixing**: the tokens are averaged into the cells of a 2D grid (one of the xy / xz / yz planes,
  in rotation), the grid goes through depth-wise 2D convolutions, and every point reads its cell back.

Points enter through a **kNN embedding** of their local geometry (offsets to their k nearest neighbours,
max-pooled). The modules here see tensors only; :mod:`leap_core.consistency.data` builds them from a scan
(kNN search, grid cell indices), as WaffleIron keeps its numpy preprocessing in the dataset.

Shapes: N points (a batch of B clouds concatenated), F channels, K neighbours, C classes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F_

from leap_core.consistency.config import BackboneConfig

PLANES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (1, 2))
"""Axis pairs of the 2D grids: xy, xz, yz. Layer ``l`` mixes on ``PLANES[l % 3]``."""


def cell_mean_matrix(cells: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The occupied cells of a plane and the matrix that averages the points of each.

    Args:
        cells: (N,) int64 flat cell index of every point.

    Returns:
        ``occupied`` (U,) sorted unique cells, ``inverse`` (N,) row of ``occupied`` of each point, and
        ``mean`` (U, N) sparse COO with ``1 / |cell|`` at (cell of n, n). TorchScript compiles it (the
        exported network builds its planes with it).
    """
    occupied, inverse, counts = torch.unique(cells, sorted=True, return_inverse=True, return_counts=True)
    n = cells.shape[0]
    values = (1.0 / counts.to(torch.float32))[inverse]
    indices = torch.stack([inverse, torch.arange(n, device=cells.device)])
    size = (occupied.shape[0], n)
    # TorchScript's signature lacks check_invariants (off there anyway)
    if torch.jit.is_scripting():  # type: ignore[attr-defined]
        mean = torch.sparse_coo_tensor(indices, values, size)
    else:
        mean = torch.sparse_coo_tensor(indices, values, size, check_invariants=False)
    return occupied, inverse, mean.coalesce()


@dataclass
class PlaneIndex:
    """Where the points of a batch fall on one plane's dense 2D grid, in compressed form.

    Attributes:
        occupied: (U,) int64 flat indices ``b · H · W + u · W + v`` of the U occupied cells, sorted.
        inverse: (N,) int64 row of ``occupied`` holding each point.
        mean: (U, N) sparse COO matrix with ``1 / |cell|`` at (cell of n, n): ``mean @ x`` averages
            the points of every occupied cell.
        grid_shape: ``(B, H, W)``.
    """

    occupied: Tensor
    inverse: Tensor
    mean: Tensor
    grid_shape: tuple[int, int, int]

    @classmethod
    def from_cells(cls, cells: Tensor, grid_shape: tuple[int, int, int]) -> PlaneIndex:
        """Build from the (N,) flat cell index of every point (:func:`cell_mean_matrix`)."""
        occupied, inverse, mean = cell_mean_matrix(cells)
        return cls(occupied=occupied, inverse=inverse, mean=mean, grid_shape=grid_shape)

    def to(self, device: torch.device | str) -> PlaneIndex:
        return PlaneIndex(
            self.occupied.to(device), self.inverse.to(device), self.mean.to(device), self.grid_shape
        )


@dataclass
class CloudTensors:
    """Network input for a batch of B point clouds concatenated along the point axis.

    Attributes:
        feats: (N, D_in) float32 per-point features (see :func:`leap_core.consistency.data.prepare_cloud`).
        local: (N, K, D_loc) float32 geometry of each point's K nearest neighbours (scaled offsets
            ``p_m - p_n``, their length, optional remission difference).
        planes: per plane (xy, xz, yz), the points' cells on its grid (:class:`PlaneIndex`).
    """

    feats: Tensor
    local: Tensor
    planes: tuple[PlaneIndex, ...]

    @property
    def num_points(self) -> int:
        return int(self.feats.shape[0])

    @property
    def grid_shapes(self) -> tuple[tuple[int, int, int], ...]:
        return tuple(p.grid_shape for p in self.planes)

    def to(self, device: torch.device | str) -> CloudTensors:
        return CloudTensors(
            feats=self.feats.to(device),
            local=self.local.to(device),
            planes=tuple(p.to(device) for p in self.planes),
        )


class DropPath(nn.Module):
    """Stochastic depth on a residual branch: in training, drop the whole branch with probability p.

    ``y = b · r / (1 - p)`` with ``b ~ Bernoulli(1 - p)`` drawn once per forward (a batch of clouds shares
    it); identity at evaluation.
    """

    def __init__(self, p: float) -> None:
        super().__init__()
        self.p = p

    def forward(self, residual: Tensor) -> Tensor:
        """``residual · b / (1 - p)`` while training, ``residual`` otherwise."""
        if not self.training or self.p == 0.0:
            return residual
        keep = torch.rand((), device=residual.device) >= self.p
        return residual * keep.to(residual.dtype) / (1.0 - self.p)


class KnnEmbedding(nn.Module):
    """Point tokens from each point's features and its neighbourhood shape.

    ``e_n = W_c BN(f_n) + W_o · max_{m ∈ N_k(n)} GELU(W_l g_nm + b_l)`` where ``f_n`` are the point's features
    and ``g_nm`` the geometry of neighbour m relative to n (offset, distance, optional remission difference).
    BN standardises the input features with running statistics: features whose informative differences are
    small in absolute terms (remission 0.13 vs 0.18, a 15 cm kerb) would otherwise need input weights that
    a few hundred AdamW steps cannot grow to.
    The max over neighbours makes the embedding independent of neighbour order. ``W_l`` maps to a narrower
    hidden width than the tokens: the (N, K, hidden) intermediate is the costliest tensor of a forward pass.
    """

    def __init__(
        self, in_features: int, local_features: int, channels: int, hidden: int, chunk: int = 32768
    ) -> None:
        super().__init__()
        self.norm = nn.BatchNorm1d(in_features)
        self.center = nn.Linear(in_features, channels)
        self.local = nn.Linear(local_features, hidden)
        self.out = nn.Linear(hidden, channels)
        self.chunk = chunk
        """Points per block of the (N, K, hidden) intermediate at evaluation (exact: it is per point)."""

    def forward(self, feats: Tensor, local: Tensor) -> Tensor:
        """``e = W_c BN(f) + W_o max_k GELU(W_l g)``: (N, D_in), (N, K, D_loc) -> (N, F)."""
        if self.training or local.shape[0] <= self.chunk:
            pooled = F_.gelu(self.local(local)).amax(dim=1)
        else:
            # A whole 120k-point scan's intermediate would take hundreds of MB; blocks keep it small.
            pooled = torch.cat(
                [F_.gelu(self.local(blk)).amax(dim=1) for blk in torch.split(local, self.chunk)], dim=0
            )
        tokens: Tensor = self.center(self.norm(feats)) + self.out(pooled)
        return tokens


class ChannelMix(nn.Module):
    """Residual per-point MLP: ``x ← x + γ ⊙ W_2 GELU(W_1 LN(x))``."""

    def __init__(self, channels: int, ratio: int, layer_scale: float, drop_path: float) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(channels)
        self.fc1 = nn.Linear(channels, ratio * channels)
        self.fc2 = nn.Linear(ratio * channels, channels)
        self.gamma = nn.Parameter(torch.full((channels,), float(layer_scale)))
        self.drop = DropPath(drop_path)

    def forward(self, x: Tensor) -> Tensor:
        """``x + γ ⊙ W_2 GELU(W_1 LN(x))``: (N, F) -> (N, F)."""
        update: Tensor = self.drop(self.gamma * self.fc2(F_.gelu(self.fc1(self.norm(x)))))
        return x + update


class SpatialMix(nn.Module):
    """Residual mixing of points through a 2D grid on one plane.

    ``G = scatter_mean(LN(x), cell)`` reshaped to (B, F, H, W);
    ``G' = DW_2(GELU(DW_1(G)))`` with depth-wise k×k convolutions;
    ``x ← x + γ ⊙ G'[cell]``.
    Points in the same cell exchange information through the mean, nearby cells through the convolutions.
    """

    def __init__(self, channels: int, kernel_size: int, layer_scale: float, drop_path: float) -> None:
        super().__init__()
        pad = kernel_size // 2
        self.norm = nn.LayerNorm(channels)
        self.conv1 = nn.Conv2d(channels, channels, kernel_size, padding=pad, groups=channels)
        self.conv2 = nn.Conv2d(channels, channels, kernel_size, padding=pad, groups=channels)
        self.gamma = nn.Parameter(torch.full((channels,), float(layer_scale)))
        self.drop = DropPath(drop_path)

    @torch.jit.unused
    def forward(self, x: Tensor, plane: PlaneIndex) -> Tensor:
        """``x + γ ⊙ DW_2(GELU(DW_1(scatter_mean(LN(x), cells))))[cells]``: (N, F) -> (N, F)."""
        b, h, w = plane.grid_shape
        return self.mix(x, plane.occupied, plane.inverse, plane.mean, b, h, w)

    @torch.jit.export
    def mix(  # noqa: PLR0917  a PlaneIndex's fields, so TorchScript can compile it
        self, x: Tensor, occupied: Tensor, inverse: Tensor, mean: Tensor, b: int, h: int, w: int
    ) -> Tensor:
        """:meth:`forward` on the fields of a :class:`PlaneIndex` (grid ``(b, h, w)``): the one body that
        both the network and its TorchScript export (:mod:`leap_core.lidar_model.export`) run."""
        f = x.shape[1]
        # The TorchScript export runs in float32 only.
        if torch.jit.is_scripting():  # type: ignore[attr-defined]
            normed = self.norm(x)
            cell_mean = torch.sparse.mm(mean, normed)
        else:
            # The cell means in float32 whatever the autocast: sparse products have no bfloat16 backward
            # on the CPU, and an average over many points is what lower precision would round worst.
            with torch.autocast(device_type=x.device.type, enabled=False):
                normed = self.norm(x).float()
                cell_mean = torch.sparse.mm(mean, normed)
        dense = normed.new_zeros(b * h * w, f).index_copy(0, occupied, cell_mean)
        # (B·H·W, F) rows are NHWC: the permuted view is a channels-last NCHW tensor, which the depth-wise
        # convolutions run on faster than on the default layout, and no copy is made either way.
        grid = dense.view(b, h, w, f).permute(0, 3, 1, 2)
        grid = self.conv2(F_.gelu(self.conv1(grid)))
        grid = grid.permute(0, 2, 3, 1).reshape(b * h * w, f)
        back = grid.index_select(0, occupied).index_select(0, inverse)
        update: Tensor = self.drop(self.gamma * back)
        return x + update


class WaffleBackbone(nn.Module):
    """``L`` pairs of (channel mixing, spatial mixing); spatial layer ``l`` uses plane ``PLANES[l % 3]``."""

    def __init__(self, cfg: BackboneConfig) -> None:
        super().__init__()
        n = cfg.layers
        rates = [cfg.drop_path * i / max(n - 1, 1) for i in range(n)]
        self.channel = nn.ModuleList(
            ChannelMix(cfg.channels, cfg.mlp_ratio, cfg.layer_scale, rates[i]) for i in range(n)
        )
        self.spatial = nn.ModuleList(
            SpatialMix(cfg.channels, cfg.kernel_size, cfg.layer_scale, rates[i]) for i in range(n)
        )

    def forward(self, x: Tensor, planes: tuple[PlaneIndex, ...]) -> Tensor:
        """For l = 0..L-1: ``x ← Spatial_l(Channel_l(x), plane l mod 3)``: (N, F) -> (N, F)."""
        for i, (cmix, smix) in enumerate(zip(self.channel, self.spatial, strict=True)):
            x = smix(cmix(x), planes[i % len(PLANES)])
        return x


class PointSegmenter(nn.Module):
    """Embedding, backbone and a linear classifier: ``logits = W_h LN(Backbone(Embed(f, g)))``."""

    trained_classes: Tensor  # a buffer registered in __init__, declared here for the type checker

    def __init__(self, cfg: BackboneConfig, num_classes: int) -> None:
        super().__init__()
        if num_classes < 2:
            raise ValueError(f"num_classes must be >= 2, got {num_classes}")
        self.cfg = cfg
        self.num_classes = num_classes
        local_features = 5 if cfg.use_intensity else 4
        self.embed = KnnEmbedding(cfg.in_features, local_features, cfg.channels, cfg.embed_channels)
        self.backbone = WaffleBackbone(cfg)
        self.norm = nn.LayerNorm(cfg.channels)
        self.head = nn.Linear(cfg.channels, num_classes)
        self.register_buffer("trained_classes", torch.ones(num_classes, dtype=torch.bool))
        """(C,) bool: classes that had training labels. Inference gives the others probability 0: a class
        the network never saw a label of carries no evidence, only noise from its random head row."""

    def forward(self, batch: CloudTensors) -> Tensor:
        """``W_h LN(Backbone(Embed(feats, local)))``: a batch of N points -> (N, C) logits."""
        x = self.embed(batch.feats, batch.local)
        x = self.backbone(x, batch.planes)
        logits: Tensor = self.head(self.norm(x))
        return logits


def count_parameters(module: nn.Module) -> int:
    """Number of trainable scalars."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


__all__ = [
    "PLANES",
    "ChannelMix",
    "CloudTensors",
    "DropPath",
    "KnnEmbedding",
    "PlaneIndex",
    "PointSegmenter",
    "SpatialMix",
    "WaffleBackbone",
    "cell_mean_matrix",
    "count_parameters",
]
