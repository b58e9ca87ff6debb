"""kNN smoothing: softmax(-d) weights and hand-computed neighbourhoods."""

from __future__ import annotations

import math

import numpy as np
import pytest

from leap_core.fusion import VoxelGrid, voxel_keys
from leap_core.smoothing import SmoothingConfig, knn_smooth, knn_weights, smooth_grid


def test_knn_weights_softmax_of_negative_distance() -> None:
    e = np.exp([0.0, -1.0, -2.0])
    w = knn_weights(np.array([[0.0, 1.0, 2.0], [1.0, 1.0, 1.0]]))
    np.testing.assert_allclose(w[0], e / e.sum(), rtol=1e-6)  # [0.6652, 0.2447, 0.0900]
    np.testing.assert_allclose(w[0], [0.66524096, 0.24472847, 0.09003057], rtol=1e-6)
    np.testing.assert_allclose(w[1], [1 / 3] * 3, rtol=1e-6)
    assert w.dtype == np.float32


def test_knn_weights_missing_neighbours_get_zero() -> None:
    w = knn_weights(np.array([[0.0, np.inf, 1.0], [np.inf, np.inf, np.inf]]))
    np.testing.assert_allclose(w[0], [1 / (1 + math.e**-1), 0.0, math.e**-1 / (1 + math.e**-1)], rtol=1e-6)
    np.testing.assert_array_equal(w[1], [0.0, 0.0, 0.0])


def test_two_voxels_one_metre_apart() -> None:
    centres = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], np.float32)
    probs = np.array([[1.0, 0.0], [0.0, 1.0]], np.float32)
    s = 1 / (1 + math.e**-1)  # weight of the voxel itself: 0.7311; of the other: 0.2689
    out = knn_smooth(centres, probs, SmoothingConfig(k=9, max_distance=None, workers=1))
    np.testing.assert_allclose(out, [[s, 1 - s], [1 - s, s]], rtol=1e-6)
    # Beyond max_distance the other voxel carries no weight.
    np.testing.assert_allclose(knn_smooth(centres, probs, SmoothingConfig(max_distance=0.5)), probs)


def test_k_limits_the_neighbourhood() -> None:
    # Voxels on a line at 0, 1, 3: with k = 2 voxel 0 sees only voxel 1, voxel 2 only voxel 1.
    centres = np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]], np.float32)
    probs = np.eye(3, dtype=np.float32)
    out = knn_smooth(centres, probs, SmoothingConfig(k=2, max_distance=None))
    s1 = 1 / (1 + math.e**-1)
    s2 = 1 / (1 + math.e**-2)
    np.testing.assert_allclose(out[0], [s1, 1 - s1, 0.0], rtol=1e-6)
    np.testing.assert_allclose(out[2], [0.0, 1 - s2, s2], rtol=1e-6)
    np.testing.assert_allclose(out.sum(axis=1), 1.0, rtol=1e-6)


def test_smooth_grid_and_edge_cases() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-2, 2, (200, 3))
    keys = np.unique(voxel_keys(xyz, 0.2))
    logp = np.log(rng.dirichlet(np.ones(4), len(keys))).astype(np.float16)
    grid = VoxelGrid(keys, logp - logp.max(axis=1, keepdims=True), 0.2)
    out = smooth_grid(grid)
    assert out.shape == (len(keys), 4) and out.dtype == np.float32
    np.testing.assert_allclose(out.sum(axis=1), 1.0, rtol=1e-5)
    np.testing.assert_array_equal(knn_smooth(np.zeros((0, 3)), np.zeros((0, 4))), np.zeros((0, 4)))
    with pytest.raises(ValueError, match="centres"):
        knn_smooth(np.zeros((3, 2)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="k: must be"):
        SmoothingConfig(k=0)
