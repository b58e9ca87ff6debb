"""The pose-graph refinement's parts on hand-made data: thinning, normals, point-to-plane ICP, the graph's
least squares, and the first-step metric."""

from __future__ import annotations

import numpy as np
import pytest

from leap_core.errors import ConfigError
from leap_core.pose_graph import (
    Edge,
    RefineConfig,
    alignment_cost,
    edge_residuals,
    motion_error,
    optimise_poses,
    plane_normals,
    prepare_scan,
    register,
    small_motion,
    voxel_centroids,
)
from leap_core.trajectory import compare_with_truth, first_step_ratio, inverse


def _pose(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    return small_motion(np.array([x, y, 0.0, 0.0, 0.0, np.radians(yaw_deg)]))


def _line_poses(xs: list[float]) -> np.ndarray:
    return np.stack([_pose(x) for x in xs])


def test_small_motion_and_motion_error_are_inverse() -> None:
    delta = np.array([[0.3, -0.2, 0.05, 0.01, -0.02, 0.3], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    t = small_motion(delta)
    np.testing.assert_allclose(motion_error(t), delta, atol=1e-12)
    np.testing.assert_allclose(inverse(t[0]) @ t[0], np.eye(4), atol=1e-12)
    # 90° about z by hand.
    np.testing.assert_allclose(_pose(1.0, 2.0, 90.0)[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_voxel_centroids_hand_computed() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.2, 0.2], [-0.5, 0.0, 0.0]])
    got = voxel_centroids(pts, 1.0)
    # Voxels (0,0,0): the first two, centroid 0.2; (1,0,0): the third; (−1,0,0): the fourth.
    assert sorted(map(tuple, np.round(got, 9))) == [(-0.5, 0.0, 0.0), (0.2, 0.2, 0.2), (1.5, 0.2, 0.2)]
    assert voxel_centroids(np.zeros((0, 3)), 0.5).shape == (0, 3)


def test_plane_normals_and_spread_tell_a_patch_from_a_ring() -> None:
    g = np.arange(-1.0, 1.01, 0.1)
    xx, yy = np.meshgrid(g, g)
    patch = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1)
    normals, spread = plane_normals(patch, 10)
    np.testing.assert_allclose(np.abs(normals[:, 2]), 1.0, atol=1e-9)  # the floor's normal is z
    assert spread.min() > 0.2
    a = np.linspace(0.0, 0.5, 60)  # a LiDAR ring on the floor: points on an arc of radius 10 m
    ring = np.stack([10 * np.cos(a), 10 * np.sin(a), np.zeros_like(a)], axis=1)
    assert plane_normals(ring, 10)[1].max() < 0.01


def _room(seed: int = 0) -> np.ndarray:
    """A floor, three walls and a box (points 0.1 m apart): every direction is pinned down."""
    rng = np.random.default_rng(seed)
    g = np.arange(-8.0, 8.0, 0.1)
    h = np.arange(0.0, 3.0, 0.1)
    fx, fy = np.meshgrid(g, g)
    floor = np.stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)], axis=1)
    wx, wz = np.meshgrid(g, h)
    back = np.stack([wx.ravel(), np.full(wx.size, 8.0), wz.ravel()], axis=1)
    left = np.stack([np.full(wx.size, -8.0), wx.ravel(), wz.ravel()], axis=1)
    right = np.stack([np.full(wx.size, 8.0), wx.ravel(), wz.ravel()], axis=1)
    bx, bz = np.meshgrid(np.arange(2.0, 4.0, 0.1), np.arange(0.0, 1.0, 0.1))
    box = np.stack([bx.ravel(), np.full(bx.size, -2.0), bz.ravel()], axis=1)
    pts = np.concatenate([floor, back, left, right, box])
    return pts + rng.normal(0.0, 0.005, pts.shape)


def test_register_recovers_a_known_motion() -> None:
    cfg = RefineConfig()
    room = _room()
    truth = small_motion(np.array([0.6, -0.15, 0.02, 0.002, -0.003, 0.04]))  # scan j in scan i's frame
    target = prepare_scan(room, cfg)
    source = prepare_scan(room @ inverse(truth)[:3, :3].T + inverse(truth)[:3, 3], cfg).source
    # From the identity (60 cm and 2.3° off) to the truth within 2 mm and 0.02° (the thinning's centroids
    # at the walls' cut edges are not quite the same points in both scans).
    reg = register(target, source, np.eye(4), cfg)
    err = motion_error(inverse(truth) @ reg.pose)
    assert np.linalg.norm(err[:3]) < 2e-3 and np.degrees(np.linalg.norm(err[3:])) < 0.02
    assert reg.residual < 0.01 and reg.inliers > 0.9 * len(source)
    assert np.all(np.linalg.eigvalsh(reg.information) > 0)
    assert alignment_cost(target, source, reg.pose, cfg) < alignment_cost(target, source, np.eye(4), cfg)


def test_optimise_poses_hand_computed_least_squares() -> None:
    """Three frames on a line: two steps of 1 m measured, and 2.3 m from the first to the last. In x alone,
    ``(x1 − 1)² + (x2 − x1 − 1)² + w (x2 − 2.3)²`` is least at x1 = 1.1, x2 = 2.2 for w = 1 and at
    x1 = 10.2 / 9, x2 = 10.2 / 4.5 for w = 4 (set the two derivatives to zero)."""
    start = _line_poses([0.0, 0.9, 2.0])
    one = np.eye(6)

    def edges(w: float) -> list[Edge]:
        return [
            Edge(0, 1, _pose(1.0), one),
            Edge(1, 2, _pose(1.0), one),
            Edge(0, 2, _pose(2.3), np.sqrt(w) * one),
        ]

    got = optimise_poses(start, edges(1.0))
    np.testing.assert_allclose(got[:, 0, 3], [0.0, 1.1, 2.2], atol=1e-6)
    np.testing.assert_allclose(got[:, :3, :3], np.eye(3)[None].repeat(3, 0), atol=1e-9)
    got = optimise_poses(start, edges(4.0))
    np.testing.assert_allclose(got[:, 0, 3], [0.0, 10.2 / 9, 10.2 / 4.5], atol=1e-6)
    # Consistent measurements leave no residual; the first pose never moves.
    exact = optimise_poses(start, [Edge(0, 1, _pose(1.0, 0.2, 5.0), one), Edge(1, 2, _pose(1.0), one)])
    np.testing.assert_allclose(exact[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(edge_residuals(exact, [Edge(0, 1, _pose(1.0, 0.2, 5.0), one)]), 0.0, atol=1e-6)


def test_refine_config_names_the_bad_field() -> None:
    with pytest.raises(ConfigError, match=r"^neighbours: must be in \[1, 20\]"):
        RefineConfig(neighbours=0)
    with pytest.raises(ConfigError, match=r"^target_voxel: must be in \(0, 5\]"):
        RefineConfig(target_voxel=float("nan"))
    with pytest.raises(ConfigError, match=r"^min_spread: must be in \[0, 1\)"):
        RefineConfig(min_spread=1.0)


def test_first_step_ratio_hand_computed() -> None:
    gt = _line_poses([0.0, 1.0, 2.0, 3.0])
    assert first_step_ratio(gt, _line_poses([0.0, 0.5, 1.5, 2.5])) == pytest.approx(0.5)  # half a step
    # Speeding up: 1 m then 2 m, estimated as 1 m then 2 m, is right.
    assert first_step_ratio(_line_poses([0.0, 1.0, 3.0]), _line_poses([5.0, 6.0, 8.0])) == pytest.approx(1.0)
    assert first_step_ratio(_line_poses([0.0, 0.05, 0.2]), _line_poses([0.0, 0.05, 0.2])) is None  # at rest
    assert first_step_ratio(gt[:2], gt[:2]) is None
    c = compare_with_truth(gt, _line_poses([0.0, 0.5, 1.5, 2.5]))
    assert c.first_step_ratio == pytest.approx(0.5) and c.path_m == pytest.approx(3.0)
    assert c.segment_lengths_m[0] == 1.0 and c.to_dict()["first_step_ratio"] == pytest.approx(0.5)


def test_optimise_poses_reaches_the_least_squares_minimum_of_a_long_noisy_chain() -> None:
    """400 scans, each measured against its next three with unit noise after whitening, from poses 5 cm and
    0.3° off. The result's cost is at most the true poses' (the minimum is never above the truth's), and
    near its expectation for a linear least-squares problem: residuals minus unknowns,
    6 · 1194 − 6 · 399 = 4770 (standard deviation √(2 · 4770) ≈ 98)."""
    rng = np.random.default_rng(0)
    f = 400
    step = small_motion(np.array([0.8, 0.0, 0.0, 0.0, 0.0, 0.002]))
    true = np.stack([np.linalg.matrix_power(step, k) for k in range(f)])
    info = np.diag([200.0] * 3 + [2000.0] * 3)
    edges = [
        Edge(
            i,
            i + d,
            inverse(true[i]) @ true[i + d] @ small_motion(rng.normal(0, [0.005] * 3 + [0.0005] * 3)),
            info,
        )
        for i in range(f)
        for d in (1, 2, 3)
        if i + d < f
    ]
    start = true @ small_motion(rng.normal(0, [0.05] * 3 + [0.005] * 3, (f, 6)))
    start[0] = np.eye(4)
    got = optimise_poses(start, edges)
    cost = float(np.sum(edge_residuals(got, edges) ** 2))
    assert cost <= float(np.sum(edge_residuals(true, edges) ** 2))
    assert len(edges) == 1194 and cost == pytest.approx(4770, rel=0.05)
    np.testing.assert_allclose(got[0], np.eye(4), atol=1e-12)
    # At the minimum a further step finds nothing to gain.
    np.testing.assert_allclose(optimise_poses(got, edges), got, atol=1e-6)
