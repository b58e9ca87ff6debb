"""Scan → network input: features, kNN neighbourhoods, 2D grid cells, augmentation (numpy / scipy).

The model (:mod:`leap_core.consistency.backbone`) sees tensors only; everything that needs a kd-tree or
per-scan bookkeeping lives here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch
from scipy.spatial import cKDTree

from leap_core.consistency.backbone import PLANES, CloudTensors, PlaneIndex
from leap_core.consistency.config import BackboneConfig

POSITION_SCALE = 20.0
"""Metres per unit of the horizontal position and range features: LiDAR scenes span tens of metres, so
this keeps them O(1) without per-scan statistics (which would differ between a subsample and a full scan)."""
HEIGHT_SCALE = 2.0
"""Metres per unit of the height features: a kerb (15 cm) must stay visible next to a 2 m car."""
GROUND_CELL = 2.0
"""Horizontal cell (metres) in which the lowest point is taken as the local ground height."""
LOCAL_SCALE = 0.25
"""Metres per unit of the neighbour offsets: typical kNN distances of a 64-beam scan are 0.05-1 m."""
GRID_EXTENT = 100.0
"""Coordinates are clipped to ±this many metres before gridding, so a stray far point cannot blow up the
size of the dense 2D grids; points beyond it share the border cells."""


@dataclass
class PreparedCloud:
    """One scan prepared for the network (numpy side of :class:`CloudTensors`).

    Attributes:
        feats: (N, D_in) float32.
        local: (N, K, D_loc) float32.
        cell_uv: (3, N, 2) int64 grid coordinates (u, v) of every point on each plane.
        grid_hw: (3, 2) int64 grid size (H, W) on each plane.
    """

    feats: npt.NDArray[np.float32]
    local: npt.NDArray[np.float32]
    cell_uv: npt.NDArray[np.int64]
    grid_hw: npt.NDArray[np.int64]


def augment_points(points: npt.NDArray[np.float32], rng: np.random.Generator) -> npt.NDArray[np.float32]:
    """Random rotation about z, random mirror of y and a scale in [0.95, 1.05] (x, y, z only).

    ``p' = s · R_z(θ) · diag(1, ±1, 1) · p`` with ``θ ~ U[0, 2π)``. Gravity (z) is kept, since height is
    the strongest cue a LiDAR backbone has.
    """
    theta = rng.uniform(0.0, 2.0 * np.pi)
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if rng.random() < 0.5:
        rot = rot @ np.diag([1.0, -1.0, 1.0])
    rot *= rng.uniform(0.95, 1.05)
    out = np.copy(points, order="C")
    out[:, :3] = (points[:, :3].astype(np.float64) @ rot.T).astype(np.float32)
    return out


def inference_view(points: npt.NDArray[np.float32], j: int, n: int) -> npt.NDArray[np.float32]:
    """View ``j`` of ``n`` of a scan for test-time averaging: a turn about z by ``2πj/n``, and a mirror of y
    in odd views (x, y, z only; remission kept).

    ``p' = R_z(2πj/n) · diag(1, (-1)^j, 1) · p``. View 0 is the scan itself (a copy). The views are the
    rotations and mirrors :func:`augment_points` trains on, without its scale.
    """
    if not 0 <= j < n:
        raise ValueError(f"view {j} of {n}: need 0 <= j < n")
    theta = 2.0 * np.pi * j / n
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([1.0, (-1.0) ** j, 1.0])
    out = np.copy(points, order="C")
    if j:
        out[:, :3] = (points[:, :3].astype(np.float64) @ rot.T).astype(np.float32)
    return out


def shape_features(offsets: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """Covariance (PCA) shape descriptors of each point's neighbourhood.

    With ``λ1 ≥ λ2 ≥ λ3 ≥ 0`` the eigenvalues of the neighbours' covariance
    ``Σ = (1/K) Σ_m (q_m - q̄)(q_m - q̄)ᵀ`` and ``n`` the eigenvector of ``λ3`` (the surface normal), the
    features are
    ``[|n_z|, (λ1-λ2)/λ1, (λ2-λ3)/λ1, λ3/λ1, sqrt(λ1)/LOCAL_SCALE]``: verticality of the normal, linearity,
    planarity, scattering and spread. Road, walls, poles and foliage differ most in exactly these.

    Args:
        offsets: (N, K, 3) neighbour positions relative to each point.

    Returns:
        (N, 5) float32.
    """
    centred = offsets - offsets.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / max(offsets.shape[1], 1)
    # eigh returns ascending eigenvalues: λ3, λ2, λ1.
    evals, evecs = np.linalg.eigh(cov.astype(np.float64))
    evals = np.maximum(evals, 0.0)
    l3, l2, l1 = evals[:, 0], evals[:, 1], evals[:, 2]
    denom = np.maximum(l1, 1e-12)
    out = np.stack(
        [np.abs(evecs[:, 2, 0]), (l1 - l2) / denom, (l2 - l3) / denom, l3 / denom, np.sqrt(l1) / LOCAL_SCALE],
        axis=1,
    )
    # Degenerate neighbourhoods (all neighbours identical) carry no shape: zeros, not NaN.
    out[l1 <= 1e-12] = 0.0
    return out.astype(np.float32)


def height_above_ground(xyz: npt.NDArray[np.float32], cell: float = GROUND_CELL) -> npt.NDArray[np.float32]:
    """``z - min z`` over the points of the same ``cell × cell`` column in x, y: height above local ground.

    Args:
        xyz: (N, 3) positions.
        cell: column size in metres.

    Returns:
        (N,) float32, ≥ 0.
    """
    ij = np.floor(xyz[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    col = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((xyz[:, 2], col))
    sorted_col = col[order]
    first = np.empty(len(order), dtype=bool)
    first[:1] = True
    np.not_equal(sorted_col[1:], sorted_col[:-1], out=first[1:])
    group = np.cumsum(first) - 1
    ground = xyz[order[first], 2][group]
    out = np.empty(len(order), dtype=np.float32)
    out[order] = xyz[order, 2] - ground
    return out


def prepare_cloud(
    points: npt.NDArray[np.float32],
    cfg: BackboneConfig,
    subset: npt.NDArray[np.int64] | None = None,
    workers: int = 1,
) -> PreparedCloud:
    """Features, neighbourhoods and grid cells of (a subset of) one scan.

    The kNN neighbours of a point are searched among *all* points of the scan even when only ``subset`` is
    kept, so a training subsample sees the same neighbourhood density as inference on the full scan.

    Args:
        points: (M, 4) float32 x, y, z, remission in the LiDAR frame.
        cfg: backbone sizes (``knn``, ``grid_cells``, ``use_intensity``).
        subset: (N,) indices of the points to prepare; ``None`` for all M.
        workers: threads of the kd-tree query.

    Returns:
        Per point n of the subset: ``feats = [(x/S, y/S, z/H, ‖p‖/S,) height above ground/H,``
        :func:`shape_features` ``(+ remission)]`` (the first four with ``cfg.position_inputs``) with
        S = ``POSITION_SCALE``, H = ``HEIGHT_SCALE``,
        ``local[n, j] = [(p_m - p_n) / LOCAL_SCALE, ‖p_m - p_n‖ / LOCAL_SCALE (+ r_m - r_n)]`` for its j-th
        nearest neighbour m (itself first), and its (u, v) cell on each plane:
        ``u = floor((clip(p_a) - min_a) / cell_p)`` over the subset's minimum.
    """
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] < 4:
        raise ValueError(f"points must be (N, 4) x, y, z, remission, got {pts.shape}")
    sel = pts if subset is None else pts[subset]
    xyz_all = pts[:, :3]
    xyz = sel[:, :3]
    n = xyz.shape[0]
    k = min(cfg.knn, xyz_all.shape[0])
    if n == 0:
        raise ValueError("cannot prepare an empty point cloud")
    tree = cKDTree(xyz_all)
    _, nbr = tree.query(xyz, k=k, workers=workers)
    nbr = np.asarray(nbr, dtype=np.int64).reshape(n, k)
    if k < cfg.knn:
        # Tiny clouds: repeat the farthest neighbour so the tensor shape does not depend on the scan size.
        nbr = np.concatenate([nbr, np.repeat(nbr[:, -1:], cfg.knn - k, axis=1)], axis=1)
    offsets = xyz_all[nbr] - xyz[:, None, :]
    dist = np.linalg.norm(offsets, axis=2, keepdims=True)
    local_parts = [offsets / LOCAL_SCALE, dist / LOCAL_SCALE]
    feat_parts = (
        [
            xyz[:, :2] / POSITION_SCALE,
            xyz[:, 2:3] / HEIGHT_SCALE,
            np.linalg.norm(xyz, axis=1, keepdims=True) / POSITION_SCALE,
        ]
        if cfg.position_inputs
        else []
    )
    feat_parts += [
        height_above_ground(xyz_all)[subset if subset is not None else slice(None), None] / HEIGHT_SCALE,
        shape_features(offsets),
    ]
    if cfg.use_intensity:
        feat_parts.append(sel[:, 3:4])
        local_parts.append(pts[nbr, 3][..., None] - sel[:, None, 3:4])
    feats = np.concatenate(feat_parts, axis=1).astype(np.float32)
    local = np.concatenate(local_parts, axis=2).astype(np.float32)

    clipped = np.clip(xyz, -GRID_EXTENT, GRID_EXTENT)
    cell_uv = np.empty((len(PLANES), n, 2), dtype=np.int64)
    grid_hw = np.empty((len(PLANES), 2), dtype=np.int64)
    for p, (a, b) in enumerate(PLANES):
        size = cfg.grid_cells[p]
        for j, axis in enumerate((a, b)):
            coord = clipped[:, axis]
            idx = np.floor((coord - coord.min()) / size).astype(np.int64)
            cell_uv[p, :, j] = idx
            grid_hw[p, j] = int(idx.max()) + 1
    return PreparedCloud(feats=feats, local=local, cell_uv=cell_uv, grid_hw=grid_hw)


def collate(clouds: Sequence[PreparedCloud]) -> CloudTensors:
    """Concatenate B prepared clouds into one batch.

    Each plane's grid is ``(B, H, W)`` with ``H, W`` the largest over the batch; a point of cloud ``b`` at
    cell ``(u, v)`` gets the flat index ``b · H · W + u · W + v``.
    """
    if not clouds:
        raise ValueError("cannot collate an empty list of clouds")
    b = len(clouds)
    hw = np.max(np.stack([c.grid_hw for c in clouds]), axis=0)
    planes = []
    for p in range(len(PLANES)):
        h, w = int(hw[p, 0]), int(hw[p, 1])
        cells = np.concatenate(
            [i * h * w + c.cell_uv[p, :, 0] * w + c.cell_uv[p, :, 1] for i, c in enumerate(clouds)]
        )
        planes.append(PlaneIndex.from_cells(torch.from_numpy(cells), (b, h, w)))
    return CloudTensors(
        feats=torch.from_numpy(np.concatenate([c.feats for c in clouds])),
        local=torch.from_numpy(np.concatenate([c.local for c in clouds])),
        planes=tuple(planes),
    )


__all__ = [
    "GRID_EXTENT",
    "GROUND_CELL",
    "HEIGHT_SCALE",
    "LOCAL_SCALE",
    "POSITION_SCALE",
    "PreparedCloud",
    "augment_points",
    "collate",
    "height_above_ground",
    "prepare_cloud",
    "shape_features",
]
