"""Scan → network input: features, kNN neighbourhoods, 2D grid cells, augmentation.

The model (:mod:`leap_core.consistency.backbone`) sees tensors only; everything that needs a neighbour
search or per-scan bookkeeping lives here, twice over the same formulas: :func:`prepare_cloud` in numpy /
scipy, and :func:`prepare_cloud_tensors` in torch on the network's device, so a GPU is not left waiting on
the CPU. Both take the neighbours from a kd-tree (:func:`neighbours`), an exact search on the CPU's threads:
brute force on a GPU would compare 120 k × 120 k pairs for a whole scan.
"""

from __future__ import annotations

import math
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


@dataclass
class TensorCloud:
    """:class:`PreparedCloud`'s fields as torch tensors on one device (:func:`prepare_cloud_tensors`).

    Attributes:
        feats: (N, D_in) float32.
        local: (N, K, D_loc) float32.
        cell_uv: (3, N, 2) int64.
        grid_hw: (3, 2) int64, on the CPU (the batch's grid sizes are Python numbers).
    """

    feats: torch.Tensor
    local: torch.Tensor
    cell_uv: torch.Tensor
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
    if int(col.max()) >= 4 * len(col) + 4096:
        # Far-flung points would make the column table larger than the cloud: number the columns instead.
        col = np.unique(col, return_inverse=True)[1].reshape(-1)
    ground = np.full(int(col.max()) + 1, np.inf, dtype=xyz.dtype)
    np.minimum.at(ground, col, xyz[:, 2])
    out: npt.NDArray[np.float32] = (xyz[:, 2] - ground[col]).astype(np.float32)
    return out


def neighbours(
    xyz_all: npt.NDArray[np.float32], xyz: npt.NDArray[np.float32], knn: int, workers: int = 1
) -> npt.NDArray[np.int64]:
    """(N, knn) int64 rows of ``xyz_all`` (M, 3) nearest to each of ``xyz`` (N, 3), nearest first (the
    point itself when it is among them), by a kd-tree queried on ``workers`` threads. A cloud of fewer than
    ``knn`` points repeats its farthest neighbour, so the shape does not depend on the scan's size."""
    k = min(knn, xyz_all.shape[0])
    # A median-free build would be 2-3x faster, but which of equally distant points a query returns
    # depends on the tree's shape, and so would the features of scans with repeated points.
    tree = cKDTree(xyz_all)
    _, nbr = tree.query(xyz, k=k, workers=workers)
    nbr = np.asarray(nbr, dtype=np.int64).reshape(xyz.shape[0], k)
    if k < knn:
        nbr = np.concatenate([nbr, np.repeat(nbr[:, -1:], knn - k, axis=1)], axis=1)
    return nbr


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
    if n == 0:
        raise ValueError("cannot prepare an empty point cloud")
    nbr = neighbours(xyz_all, xyz, cfg.knn, workers)
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


def prepare_input(
    points: npt.NDArray[np.float32],
    cfg: BackboneConfig,
    subset: npt.NDArray[np.int64] | None = None,
    device: torch.device | None = None,
    workers: int = 1,
) -> PreparedCloud | TensorCloud:
    """(A subset of) one scan prepared for the network: on ``device`` (a GPU) the neighbours by kd-tree on
    ``workers`` CPU threads and the rest there (:func:`prepare_cloud_tensors`); with None all on the CPU
    (:func:`prepare_cloud`)."""
    if device is None:
        return prepare_cloud(points, cfg, subset, workers=workers)
    nbr = neighbours(
        points[:, :3], points[subset if subset is not None else slice(None), :3], cfg.knn, workers
    )
    on_device = torch.from_numpy(np.ascontiguousarray(points)).to(device)
    sub = None if subset is None else torch.from_numpy(subset).to(device)
    return prepare_cloud_tensors(on_device, cfg, torch.from_numpy(nbr).to(device), sub)


def collate(clouds: Sequence[PreparedCloud | TensorCloud]) -> CloudTensors:
    """Concatenate B prepared clouds into one batch, on the clouds' device (numpy clouds: the CPU).

    Each plane's grid is ``(B, H, W)`` with ``H, W`` the largest over the batch; a point of cloud ``b`` at
    cell ``(u, v)`` gets the flat index ``b · H · W + u · W + v``.
    """
    if not clouds:
        raise ValueError("cannot collate an empty list of clouds")
    b = len(clouds)
    hw = np.max(np.stack([c.grid_hw for c in clouds]), axis=0)
    uv = [torch.as_tensor(c.cell_uv) for c in clouds]
    planes = []
    for p in range(len(PLANES)):
        h, w = int(hw[p, 0]), int(hw[p, 1])
        cells = torch.cat([i * h * w + c[p, :, 0] * w + c[p, :, 1] for i, c in enumerate(uv)])
        planes.append(PlaneIndex.from_cells(cells, (b, h, w)))
    return CloudTensors(
        feats=torch.cat([torch.as_tensor(c.feats) for c in clouds]),
        local=torch.cat([torch.as_tensor(c.local) for c in clouds]),
        planes=tuple(planes),
    )


def shape_features_tensors(offsets: torch.Tensor) -> torch.Tensor:
    """:func:`shape_features` in torch: (N, K, 3) offsets -> (N, 5) float32, on their device."""
    centred = offsets - offsets.mean(dim=1, keepdim=True)
    cov = torch.einsum("nki,nkj->nij", centred, centred) / max(offsets.shape[1], 1)
    evals, evecs = torch.linalg.eigh(cov.double())
    evals = evals.clamp_min(0.0)
    l3, l2, l1 = evals[:, 0], evals[:, 1], evals[:, 2]
    denom = l1.clamp_min(1e-12)
    out = torch.stack(
        [evecs[:, 2, 0].abs(), (l1 - l2) / denom, (l2 - l3) / denom, l3 / denom, l1.sqrt() / LOCAL_SCALE],
        dim=1,
    )
    out[l1 <= 1e-12] = 0.0
    return out.float()


def height_above_ground_tensors(xyz: torch.Tensor, cell: float = GROUND_CELL) -> torch.Tensor:
    """:func:`height_above_ground` in torch: (N, 3) -> (N,) float32 ``z − min z`` of its column."""
    ij = torch.floor(xyz[:, :2] / cell).long()
    col = torch.unique(ij, dim=0, return_inverse=True)[1]
    ground = torch.full((int(col.max()) + 1,), math.inf, dtype=xyz.dtype, device=xyz.device)
    ground = ground.scatter_reduce(0, col, xyz[:, 2], reduce="amin")
    return (xyz[:, 2] - ground[col]).float()


def prepare_cloud_tensors(
    points: torch.Tensor, cfg: BackboneConfig, nbr: torch.Tensor, subset: torch.Tensor | None = None
) -> TensorCloud:
    """:func:`prepare_cloud` in torch on ``points``' device, by the same formulas (its docstring has
    them), given the neighbours; the features agree with :func:`prepare_cloud`'s to float32 rounding.

    Args:
        points: (M, 4) float32 x, y, z, remission in the LiDAR frame.
        cfg: backbone sizes.
        nbr: (N, knn) int64 :func:`neighbours` of the prepared points among all M, on the same device.
        subset: (N,) int64 indices of the points to prepare (on the same device); None for all M.
    """
    if points.ndim != 2 or points.shape[1] < 4:
        raise ValueError(f"points must be (N, 4) x, y, z, remission, got {tuple(points.shape)}")
    pts = points.float()
    sel = pts if subset is None else pts[subset]
    xyz_all, xyz = pts[:, :3], sel[:, :3]
    n = xyz.shape[0]
    if n == 0:
        raise ValueError("cannot prepare an empty point cloud")
    offsets = xyz_all[nbr] - xyz[:, None, :]
    dist = offsets.norm(dim=2, keepdim=True)
    local_parts = [offsets / LOCAL_SCALE, dist / LOCAL_SCALE]
    feat_parts = (
        [
            xyz[:, :2] / POSITION_SCALE,
            xyz[:, 2:3] / HEIGHT_SCALE,
            xyz.norm(dim=1, keepdim=True) / POSITION_SCALE,
        ]
        if cfg.position_inputs
        else []
    )
    ground = height_above_ground_tensors(xyz_all)
    feat_parts += [
        (ground if subset is None else ground[subset])[:, None] / HEIGHT_SCALE,
        shape_features_tensors(offsets),
    ]
    if cfg.use_intensity:
        feat_parts.append(sel[:, 3:4])
        local_parts.append(pts[nbr, 3][..., None] - sel[:, None, 3:4])
    clipped = xyz.clamp(-GRID_EXTENT, GRID_EXTENT)
    cell_uv = torch.empty((len(PLANES), n, 2), dtype=torch.int64, device=pts.device)
    for p, (a, b) in enumerate(PLANES):
        for j, axis in enumerate((a, b)):
            coord = clipped[:, axis]
            cell_uv[p, :, j] = torch.floor((coord - coord.min()) / cfg.grid_cells[p]).long()
    grid_hw = (cell_uv.amax(dim=1) + 1).cpu().numpy().astype(np.int64)
    return TensorCloud(
        feats=torch.cat(feat_parts, dim=1).float(),
        local=torch.cat(local_parts, dim=2).float(),
        cell_uv=cell_uv,
        grid_hw=grid_hw,
    )


__all__ = [
    "GRID_EXTENT",
    "GROUND_CELL",
    "HEIGHT_SCALE",
    "LOCAL_SCALE",
    "POSITION_SCALE",
    "PreparedCloud",
    "TensorCloud",
    "augment_points",
    "collate",
    "height_above_ground",
    "height_above_ground_tensors",
    "neighbours",
    "prepare_cloud",
    "prepare_cloud_tensors",
    "prepare_input",
    "shape_features",
    "shape_features_tensors",
]
