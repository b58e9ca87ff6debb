"""Refinement of LiDAR odometry: neighbouring scans registered to each other with point-to-plane ICP, then
a pose graph over those registrations solved by sparse least squares (docs/METHOD.md E.5a).

KISS-ICP (:mod:`leap_core.odometry`) tracks each scan against a coarse local map with a constant-velocity
prediction. Its errors are those of a tracker: the first step has no motion prior, a vehicle that speeds up
outruns the prediction, and each step carries the jitter of a 0.8 m voxel map. Here every scan k is
registered to each of its next ``neighbours`` scans j directly, at a finer resolution, starting from
KISS-ICP's relative pose or the last registered step, whichever fits better (:class:`GraphBuilder`), which
gives measurements ``Z_kj`` (scan j in scan k's frame) and their information ``H_kj``. The poses
``T_1 … T_{F−1}`` (``T_0`` fixed) then minimise

    Σ_(k,j) ‖ L_kjᵀ · e(T_k⁻¹ · T_j · Z_kj⁻¹) ‖²,     H_kj = L_kj · L_kjᵀ (Cholesky),

where ``e([R | t]) = (t, rotvec(R))``: each scan is placed by every neighbour that saw it, weighted by how
well that registration pins each direction down (a street pins the sideways direction better than the
forward one).

Rigid transforms are (4, 4) float64 arrays; a small motion ``δ = (t, ω)`` (metres, radians) acts as
``X(δ) = [R(ω) | t]`` with ``R(ω)`` the rotation of rotation vector ω.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse
import scipy.sparse.linalg
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from leap_core.errors import ConfigError
from leap_core.trajectory import inverse

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class RefineConfig:
    """Settings of the neighbour registrations and the pose graph (chosen on the tuning worlds of
    docs/RESULTS.md, "Estimated poses")."""

    neighbours: int = 3
    """Each scan is registered to this many following scans (edges k → k+1 … k+neighbours)."""
    target_voxel: float = 0.2
    """Grid (m) a scan is thinned to as a registration target (one centroid per voxel)."""
    source_voxel: float = 0.5
    """Grid (m) a scan is thinned to as the moving side of a registration."""
    normal_neighbours: int = 10
    """Target points whose covariance gives each target normal."""
    min_spread: float = 0.1
    """Target points whose neighbourhood is flatter than a patch (``λ1 / λ2`` below this: points on one
    LiDAR ring or a pole) are dropped as targets (:func:`plane_normals`)."""
    max_correspondence: float = 0.8
    """A source point farther than this (m) from its nearest target point has no correspondence."""
    kernel: float = 0.05
    """Scale (m) of the Geman-McClure kernel that down-weights large point-to-plane residuals."""
    max_iterations: int = 30
    """Gauss-Newton iterations per registration at most."""
    convergence: float = 1e-6
    """A registration stops when its update's norm (m and rad together) falls below this."""

    def __post_init__(self) -> None:
        def within(name: str, value: float, low: float, high: float) -> None:
            if not (low < value <= high and math.isfinite(value)):
                raise ConfigError(f"must be in ({low:g}, {high:g}], got {value}", field=(name,))

        if not (1 <= self.neighbours <= 20):
            raise ConfigError(f"must be in [1, 20], got {self.neighbours}", field=("neighbours",))
        within("target_voxel", self.target_voxel, 0.0, 5.0)
        within("source_voxel", self.source_voxel, 0.0, 5.0)
        if not (3 <= self.normal_neighbours <= 100):
            raise ConfigError(
                f"must be in [3, 100], got {self.normal_neighbours}", field=("normal_neighbours",)
            )
        if not (0.0 <= self.min_spread < 1.0):
            raise ConfigError(f"must be in [0, 1), got {self.min_spread}", field=("min_spread",))
        within("max_correspondence", self.max_correspondence, 0.0, 20.0)
        within("kernel", self.kernel, 0.0, 10.0)
        if not (1 <= self.max_iterations <= 1000):
            raise ConfigError(f"must be in [1, 1000], got {self.max_iterations}", field=("max_iterations",))
        within("convergence", self.convergence, 0.0, 1.0)

    def settings(self) -> dict[str, Any]:
        """The settings as the note file records them."""
        return asdict(self)


# ----------------------------------------------------------------------------------------- rigid motions
def small_motion(delta: F64) -> F64:
    """``X(δ)`` (..., 4, 4) of motions ``δ = (t, ω)`` (..., 6)."""
    d = np.asarray(delta, dtype=np.float64)
    out = np.zeros((*d.shape[:-1], 4, 4))
    out[..., :3, :3] = (
        Rotation.from_rotvec(d[..., 3:].reshape(-1, 3)).as_matrix().reshape(*d.shape[:-1], 3, 3)
    )
    out[..., :3, 3] = d[..., :3]
    out[..., 3, 3] = 1.0
    return out


def motion_error(t: F64) -> F64:
    """``e(T) = (t, rotvec(R))`` (..., 6) of rigid transforms (..., 4, 4), the inverse of
    :func:`small_motion`."""
    m = np.asarray(t, dtype=np.float64)
    rv = Rotation.from_matrix(m[..., :3, :3].reshape(-1, 3, 3)).as_rotvec().reshape(*m.shape[:-2], 3)
    return np.concatenate([m[..., :3, 3], rv], axis=-1)


# ---------------------------------------------------------------------------------------- scan clouds
def voxel_centroids(points: F64, voxel: float) -> F64:
    """(M, 3) centroid of the points of each occupied voxel of edge ``voxel`` (points (N, 3)), in the
    order of the voxels' keys."""
    if len(points) == 0:
        return np.zeros((0, 3))
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    # One int64 key per voxel (21 bits per axis: 2 million voxels, 400 km at 0.2 m): a 1-D unique is
    # several times faster than a row-wise one.
    if int(cells.max()) >= 1 << 21:
        raise ValueError(f"a scan spans more than {1 << 21} voxels of {voxel} m along an axis")
    keys = cells[:, 0] | (cells[:, 1] << 21) | (cells[:, 2] << 42)
    _, inverse_idx, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse_idx, weights=points[:, a], minlength=len(counts)) for a in range(3)])
    return np.asarray(sums.T / counts[:, None], dtype=np.float64)


def plane_normals(points: F64, k: int) -> tuple[F64, F64]:
    """Unit normals (N, 3) of points (N, 3) and how two-dimensional each neighbourhood is (N,).

    From the covariance of each point's ``k`` nearest points (itself included), with eigenvalues
    ``λ0 ≤ λ1 ≤ λ2``: the normal is the eigenvector of ``λ0``, the spread ``λ1 / λ2`` (0 for points on a
    line, 1 for a round patch). A spinning LiDAR draws rings: on a single ring the "normal" is any
    direction across the ring, and fitting to it would hold every scan to the rings' radius, that is to
    zero motion.
    """
    n = len(points)
    if n < 3:
        return np.zeros((n, 3)), np.zeros(n)
    _, idx = cKDTree(points).query(points, k=min(k, n))
    nb = points[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    vals, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    spread = vals[:, 1] / np.maximum(vals[:, 2], 1e-12)
    return np.asarray(vecs[:, :, 0], dtype=np.float64), np.asarray(spread, dtype=np.float64)


@dataclass(frozen=True)
class ScanCloud:
    """One scan prepared for registration.

    Attributes:
        target: (N, 3) points thinned to ``target_voxel``; normals: (N, 3) their unit normals.
        tree: KD-tree of ``target``.
        source: (M, 3) points thinned to ``source_voxel``.
    """

    target: F64
    normals: F64
    tree: cKDTree
    source: F64


def prepare_scan(points: F64, cfg: RefineConfig) -> ScanCloud:
    """A scan's x, y, z (N, ≥3, already cut to the odometry's range) as a :class:`ScanCloud`."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    thinned = voxel_centroids(xyz, cfg.target_voxel)
    normals, spread = plane_normals(thinned, cfg.normal_neighbours)
    # Only patches are targets (see plane_normals); the source keeps every point, since its correspondences
    # take the target's normal.
    keep = spread >= cfg.min_spread
    target = thinned[keep]
    return ScanCloud(
        target=target,
        normals=normals[keep],
        tree=cKDTree(target),
        source=voxel_centroids(thinned, cfg.source_voxel),
    )


# ---------------------------------------------------------------------------------------- registration
@dataclass(frozen=True)
class Registration:
    """Result of :func:`register`.

    Attributes:
        pose: (4, 4) the source scan in the target scan's frame.
        information: (6, 6) ``Σ w_i J_iᵀ J_i / s²`` at ``pose`` (``s`` = the kernel scale), in the
            coordinates of a small motion applied on the left of ``pose``.
        inliers: source points with a correspondence.
        residual: median |point-to-plane distance| (m) of those points at ``pose``.
        iterations: Gauss-Newton iterations run.
    """

    pose: F64
    information: F64
    inliers: int
    residual: float
    iterations: int


def _linear_system(target: ScanCloud, source: F64, pose: F64, cfg: RefineConfig) -> tuple[F64, F64, F64, int]:
    """Point-to-plane residuals ``r_i = n_iᵀ (T p_i − q_i)`` of ``source`` posed by ``pose`` against
    ``target``, and the weighted normal equations ``H = Σ w_i J_iᵀ J_i``, ``g = Σ w_i J_i r_i`` with
    ``J_i = (n_i, (T p_i) × n_i)`` and Geman-McClure weights ``w_i = κ² / (κ² + r_i²)²``.

    Returns:
        H (6, 6), g (6,), the residuals (K,) of the K points with a correspondence, and K.
    """
    moved = source @ pose[:3, :3].T + pose[:3, 3]
    dist, found = target.tree.query(moved, distance_upper_bound=cfg.max_correspondence)
    ok = np.isfinite(dist)
    idx = np.asarray(found, dtype=np.int64)
    p, q, n = moved[ok], target.target[idx[ok]], target.normals[idx[ok]]
    r = np.einsum("ij,ij->i", n, p - q)
    jac = np.concatenate([n, np.cross(p, n)], axis=1)
    k2 = cfg.kernel**2
    w = k2 / (k2 + r**2) ** 2
    h = jac.T @ (w[:, None] * jac)
    g = jac.T @ (w * r)
    return h, g, r, int(ok.sum())


def register(target: ScanCloud, source: F64, initial: F64, cfg: RefineConfig) -> Registration:
    """Point-to-plane ICP of ``source`` (M, 3) onto ``target`` from ``initial`` (4, 4), by Gauss-Newton
    with a Geman-McClure kernel: each step solves ``H δ = −g`` (:func:`_linear_system`) and applies
    ``T ← X(δ) · T``."""
    pose = np.array(initial, dtype=np.float64)
    iterations = 0
    while iterations < cfg.max_iterations:
        h, g, _, count = _linear_system(target, source, pose, cfg)
        if count < 6:
            break
        iterations += 1
        # A tiny damping keeps a degenerate direction (a featureless tunnel) from blowing up the step.
        delta = np.linalg.solve(h + 1e-9 * np.trace(h) * np.eye(6), -g)
        pose = small_motion(delta) @ pose
        if float(np.linalg.norm(delta)) < cfg.convergence:
            break
    h, _, r, count = _linear_system(target, source, pose, cfg)
    return Registration(
        pose=pose,
        information=h / cfg.kernel**2,
        inliers=count,
        residual=float(np.median(np.abs(r))) if count else math.nan,
        iterations=iterations,
    )


def alignment_cost(target: ScanCloud, source: F64, pose: F64, cfg: RefineConfig) -> float:
    """How badly ``source`` posed by ``pose`` fits ``target``, in [0, 1]: the mean Geman-McClure cost
    ``r² / (κ² + r²)`` over the source points, 1 for a point without a correspondence."""
    _, _, r, count = _linear_system(target, source, pose, cfg)
    k2 = cfg.kernel**2
    return float((np.sum(r**2 / (k2 + r**2)) + (len(source) - count)) / max(len(source), 1))


def pair_residual(target: ScanCloud, source: F64, pose: F64, cfg: RefineConfig) -> float:
    """Median |point-to-plane distance| (m) of ``source`` posed by ``pose`` against ``target``, over the
    points with a correspondence (NaN without any)."""
    _, _, r, count = _linear_system(target, source, pose, cfg)
    return float(np.median(np.abs(r))) if count else math.nan


# ------------------------------------------------------------------------------------------ pose graph
@dataclass(frozen=True)
class Edge:
    """A measurement of scan ``j`` in scan ``i``'s frame: ``pose`` (4, 4) with ``sqrt_information``
    (6, 6) = ``Lᵀ`` where ``information = L Lᵀ``."""

    i: int
    j: int
    pose: F64
    sqrt_information: F64


def edge_of(i: int, j: int, reg: Registration) -> Edge | None:
    """The graph edge of a registration, or None when its information is not positive definite (too few
    correspondences to pin every direction down)."""
    try:
        chol = np.linalg.cholesky(reg.information)
    except np.linalg.LinAlgError:
        return None
    return Edge(i, j, reg.pose, chol.T)


def weak_edge(i: int, j: int, pose: F64, sigma_m: float = 1.0, sigma_rad: float = 0.1) -> Edge:
    """An edge that only keeps the graph connected where a registration failed: ``pose`` (the odometry's
    own relative pose) with standard deviations ``sigma_m`` (m) and ``sigma_rad`` (rad)."""
    return Edge(i, j, np.asarray(pose, dtype=np.float64), np.diag([1 / sigma_m] * 3 + [1 / sigma_rad] * 3))


def edge_residuals(poses: F64, edges: list[Edge]) -> F64:
    """(E, 6) whitened residuals ``L_eᵀ · e(T_i⁻¹ T_j Z_e⁻¹)`` of ``edges`` at ``poses`` (F, 4, 4)."""
    g = _Graph.of(edges)
    return g.residuals(poses[g.i], poses[g.j])


@dataclass(frozen=True)
class _Graph:
    """The edges as arrays: ends ``i``, ``j`` (E,), ``Z⁻¹`` (E, 4, 4), ``Lᵀ`` (E, 6, 6)."""

    i: npt.NDArray[np.int64]
    j: npt.NDArray[np.int64]
    z_inv: F64
    sqrt_info: F64

    @classmethod
    def of(cls, edges: list[Edge]) -> _Graph:
        return cls(
            np.array([e.i for e in edges], dtype=np.int64),
            np.array([e.j for e in edges], dtype=np.int64),
            inverse(np.stack([e.pose for e in edges])),
            np.stack([e.sqrt_information for e in edges]),
        )

    def residuals(self, ti: F64, tj: F64) -> F64:
        """(E, 6) residuals with the edges' end poses ``ti``, ``tj`` (E, 4, 4)."""
        err = motion_error(inverse(ti) @ tj @ self.z_inv)
        return np.asarray(np.einsum("eab,eb->ea", self.sqrt_info, err), dtype=np.float64)

    def jacobian(self, poses: F64, step: float = 1e-6) -> scipy.sparse.csr_matrix:
        """(6E, 6(F−1)) Jacobian of the residuals with respect to small motions ``δ_k`` applied as
        ``T_k · X(δ_k)`` (k ≥ 1; pose 0 is fixed), by central differences: each edge's residual depends on
        its two ends only, so 24 evaluations over all edges give every 6×6 block."""
        ti, tj = poses[self.i], poses[self.j]
        blocks = np.zeros((2, len(self.i), 6, 6))
        for k in range(6):
            d = np.zeros(6)
            d[k] = step
            plus, minus = small_motion(d), small_motion(-d)
            blocks[0, :, :, k] = self.residuals(ti @ plus, tj) - self.residuals(ti @ minus, tj)
            blocks[1, :, :, k] = self.residuals(ti, tj @ plus) - self.residuals(ti, tj @ minus)
        blocks /= 2.0 * step
        rows, cols, vals = [], [], []
        # Block entry (a, b): residual component a of edge e, motion component b of node n.
        a, b = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
        for end, node in enumerate((self.i, self.j)):
            keep = node > 0
            e = np.flatnonzero(keep)
            rows.append((6 * e[:, None, None] + a[None]).ravel())
            cols.append((6 * (node[keep] - 1)[:, None, None] + b[None]).ravel())
            vals.append(blocks[end, keep].ravel())
        shape = (6 * len(self.i), 6 * (len(poses) - 1))
        return scipy.sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape
        )


def _moved(poses: F64, delta: F64) -> F64:
    """``poses`` (F, 4, 4) with ``T_k ← T_k · X(δ_k)`` for k ≥ 1 (``delta`` (6(F−1),))."""
    out: F64 = poses.copy()
    out[1:] = poses[1:] @ small_motion(delta.reshape(-1, 6))
    return out


def optimise_poses(initial: F64, edges: list[Edge], max_iterations: int = 50) -> F64:
    """Poses (F, 4, 4) minimising the sum of squared :func:`edge_residuals`, from ``initial`` (F, 4, 4),
    pose 0 held fixed.

    Levenberg-Marquardt on small motions ``T_k · X(δ_k)`` about the current poses: each step solves
    ``(JᵀJ + λ · diag(JᵀJ)) δ = −Jᵀ r`` with scipy's sparse direct solver (the graph's JᵀJ is banded:
    an edge links scans at most ``neighbours`` apart, so a step costs about linear time in the scans);
    λ shrinks tenfold after a step that lowers the cost and grows tenfold until one does.
    """
    poses: F64 = np.array(initial, dtype=np.float64)
    if len(poses) < 2 or not edges:
        return poses
    graph = _Graph.of(edges)

    def cost(t: F64) -> float:
        return float(np.sum(graph.residuals(t[graph.i], t[graph.j]) ** 2))

    current, lam = cost(poses), 1e-4
    for _ in range(max_iterations):
        jac = graph.jacobian(poses)
        r = graph.residuals(poses[graph.i], poses[graph.j]).reshape(-1)
        h = (jac.T @ jac).tocsc()
        g = jac.T @ r
        diag = scipy.sparse.diags(h.diagonal() + 1e-12)
        while lam < 1e10:
            delta = np.asarray(scipy.sparse.linalg.spsolve((h + lam * diag).tocsc(), -g), dtype=np.float64)
            trial = _moved(poses, delta)
            new = cost(trial)
            if new < current:
                break
            lam *= 10.0
        else:
            return poses  # no step lowers the cost: a minimum
        gain = current - new
        poses, current, lam = trial, new, max(lam / 10.0, 1e-12)
        if gain <= 1e-12 * max(current, 1e-300) or float(np.abs(delta).max()) < 1e-10:
            break
    return poses


# ----------------------------------------------------------------------------------------- the stream
@dataclass(frozen=True)
class _Held:
    """A scan kept for registering the next ones: its cloud, the odometry's pose and the pose chained from
    the consecutive registrations so far."""

    index: int
    cloud: ScanCloud
    odometry: F64
    chained: F64


@dataclass
class GraphBuilder:
    """Collects the edges of a sequence scan by scan, holding only the last ``neighbours`` scans.

    Attributes:
        cfg: the settings.
        edges: the edges so far.
        odometry_residuals: :func:`pair_residual` of each scan against the one before at the odometry's
            poses (what the odometry alone achieves, beside the refined poses' residuals).
    """

    cfg: RefineConfig
    edges: list[Edge] = field(default_factory=list)
    odometry_residuals: list[float] = field(default_factory=list)
    _held: list[_Held] = field(default_factory=list)
    _last_step: F64 | None = None

    @classmethod
    def start(cls, cfg: RefineConfig) -> GraphBuilder:
        """An empty builder."""
        return cls(cfg)

    def add(self, index: int, points: F64, odometry_pose: F64) -> None:
        """Scan ``index`` (x, y, z (N, ≥3)) at the odometry's pose (4, 4), registered to each held scan.

        The scan just before comes first, starting from whichever fits better (:func:`alignment_cost`): the
        odometry's relative pose, or the last registered step (a constant-velocity guess from registrations,
        which does not lag where the odometry does, as when the vehicle speeds up). Its result, chained
        onto the earlier ones, is the starting point of the registrations to the older held scans. A failed
        registration to the scan just before becomes a :func:`weak_edge` on the odometry's step, so the
        graph stays connected; one to an older scan gives no edge.
        """
        cloud = prepare_scan(points, self.cfg)
        odometry = np.asarray(odometry_pose, dtype=np.float64)
        chained = np.eye(4)
        if self._held:
            prev = self._held[-1]
            from_odometry = inverse(prev.odometry) @ odometry
            self.odometry_residuals.append(pair_residual(prev.cloud, cloud.source, from_odometry, self.cfg))
            guesses = [from_odometry] if self._last_step is None else [from_odometry, self._last_step]
            initial = min(guesses, key=lambda g: alignment_cost(prev.cloud, cloud.source, g, self.cfg))
            reg = register(prev.cloud, cloud.source, initial, self.cfg)
            edge = edge_of(prev.index, index, reg)
            step = reg.pose if edge is not None else from_odometry
            self.edges.append(edge if edge is not None else weak_edge(prev.index, index, from_odometry))
            self._last_step = step
            chained = prev.chained @ step
            for held in self._held[:-1]:
                older = edge_of(
                    held.index,
                    index,
                    register(held.cloud, cloud.source, inverse(held.chained) @ chained, self.cfg),
                )
                if older is not None:
                    self.edges.append(older)
        self._held.append(_Held(index, cloud, odometry, chained))
        if len(self._held) > self.cfg.neighbours:
            self._held.pop(0)


def neighbour_residuals(scans: Callable[[], Iterable[F64]], poses: F64, cfg: RefineConfig) -> F64:
    """(F−1,) :func:`pair_residual` of each scan k+1 against scan k at ``poses`` (F, 4, 4); ``scans()``
    yields the scans (x, y, z (N, ≥3)) in order."""
    out: list[float] = []
    prev: ScanCloud | None = None
    for k, points in enumerate(scans()):
        cloud = prepare_scan(points, cfg)
        if prev is not None:
            out.append(pair_residual(prev, cloud.source, inverse(poses[k - 1]) @ poses[k], cfg))
        prev = cloud
    return np.asarray(out, dtype=np.float64)


__all__ = [
    "Edge",
    "GraphBuilder",
    "RefineConfig",
    "Registration",
    "ScanCloud",
    "alignment_cost",
    "edge_of",
    "edge_residuals",
    "motion_error",
    "neighbour_residuals",
    "optimise_poses",
    "pair_residual",
    "plane_normals",
    "prepare_scan",
    "register",
    "small_motion",
    "voxel_centroids",
    "weak_edge",
]
