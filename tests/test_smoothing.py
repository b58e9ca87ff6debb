"""kNN smoothing: softmax(-d) weights and hand-computed neighbourhoods."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from leap_core.errors import DatasetError
from leap_core.fusion import VoxelGrid, voxel_keys
from leap_core.smoothing import (
    SmoothedGrid,
    SmoothingConfig,
    grid_row_probs,
    knn_smooth,
    knn_smooth_blocks,
    knn_weights,
    smooth_grid,
)


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


def test_smooth_grid_by_hand() -> None:
    """Voxels (0,0,0), (1,0,0), (5,0,0) at 0.5 m: centres 0.25, 0.75 and 2.75 m along x.
    k = 2, unbounded: voxel 0 and 1 mix with weights softmax(-[0, 0.5]); voxel 2's nearest other voxel is
    voxel 1, 2 m away: weights softmax(-[0, 2]). With max_distance 0.6 (default) voxel 2 keeps its own."""
    keys = voxel_keys(np.array([[0.1, 0.1, 0.1], [0.6, 0.1, 0.1], [2.6, 0.1, 0.1]]), 0.5)
    logp = np.log(np.array([[0.75, 0.25], [0.25, 0.75], [0.5, 0.5]]))
    grid = VoxelGrid(keys, (logp - logp.max(axis=1, keepdims=True)).astype(np.float16), 0.5)
    p = grid.probs()
    a, b = 1 / (1 + math.exp(-0.5)), 1 / (1 + math.exp(-2.0))
    out = smooth_grid(grid, SmoothingConfig(k=2, max_distance=None))
    np.testing.assert_allclose(
        out, [a * p[0] + (1 - a) * p[1], a * p[1] + (1 - a) * p[0], b * p[2] + (1 - b) * p[1]], rtol=1e-6
    )
    bounded = smooth_grid(grid, SmoothingConfig(k=2))
    np.testing.assert_allclose(bounded[:2], out[:2], rtol=1e-6)
    np.testing.assert_allclose(bounded[2], p[2], rtol=1e-6)


# ------------------------------------------------------------------------------------- SmoothedGrid
def test_smoothed_grid_save_load_labels_and_voxel_grid(tmp_path) -> None:
    keys = np.array([3, 7, 9], np.int64)
    probs = np.array([[0.7, 0.2, 0.1], [0.1, 0.1, 0.8], [0.45, 0.45, 0.1]], np.float16)
    grid = SmoothedGrid(keys, probs, 0.5)
    path = tmp_path / "grid_smooth.npz"
    grid.save(path)
    with np.load(path) as z:
        assert sorted(z.files) == ["keys", "probs", "voxel_size"] and z["probs"].dtype == np.float16
    back = SmoothedGrid.load(path)
    np.testing.assert_array_equal(back.keys, keys)
    np.testing.assert_array_equal(back.probs, probs)
    assert back.voxel_size == 0.5 and back.num_classes == 3 and back.num_voxels == 3
    lab, conf = back.labels_at(np.array([9, 8, 3, 7]))
    assert lab.tolist() == [0, -1, 0, 2]  # voxel 9 ties: lowest index
    np.testing.assert_array_equal(conf, np.array([0.45, 0, 0.7, 0.8], np.float16).astype(np.float32))
    assert back.voxel_labels() is back.voxel_labels()  # computed once per grid
    # As a VoxelGrid: probs come back (to float16 rounding of logp), 0 clips at e^-clip.
    vg = back.to_voxel_grid(logp_clip=20.0)
    np.testing.assert_allclose(vg.probs(), probs.astype(np.float32), atol=2e-3)
    zero = SmoothedGrid(np.array([1], np.int64), np.array([[1.0, 0.0]], np.float16), 0.2).to_voxel_grid(5.0)
    assert zero.logp.tolist() == [[0.0, -5.0]]


def test_smoothed_grid_rejects_bad_files(tmp_path) -> None:
    path = tmp_path / "grid_smooth.npz"
    np.savez(path, keys=np.array([1, 2], np.int64), probs=np.ones((2, 2), np.float16))
    with pytest.raises(DatasetError, match=r"grid_smooth\.npz: no voxel_size"):
        SmoothedGrid.load(path)
    assert SmoothedGrid.load(path, voxel_size=0.3).voxel_size == 0.3
    np.savez(path, keys=np.array([2, 1], np.int64), probs=np.ones((2, 2), np.float16), voxel_size=0.2)
    with pytest.raises(DatasetError, match="not sorted"):
        SmoothedGrid.load(path)
    np.savez(path, keys=np.array([1, 2], np.int64), probs=np.ones((3, 2), np.float16), voxel_size=0.2)
    with pytest.raises(DatasetError, match="'probs'"):
        SmoothedGrid.load(path)
    path.write_bytes(b"junk")
    with pytest.raises(DatasetError, match="unreadable smoothed grid"):
        SmoothedGrid.load(path)


def test_smoothed_grid_centres_and_from_voxel_grid() -> None:
    keys = voxel_keys(np.array([[-0.3, 0.6, 1.2], [0.1, 0.1, 0.1]]), 0.5)  # voxels (-1,1,2), (0,0,0): sorted
    probs = np.array([[0.75, 0.25], [0.5, 0.5]], np.float16)
    grid = SmoothedGrid(keys, probs, 0.5)
    np.testing.assert_array_equal(grid.centres(), [[-0.25, 0.75, 1.25], [0.25, 0.25, 0.25]])
    # A fused grid's posteriors as float16 distributions, same keys and voxel size.
    fused = VoxelGrid(keys, np.array([[0.0, -math.log(3.0)], [0.0, 0.0]], np.float16), 0.5)
    back = SmoothedGrid.from_voxel_grid(fused)
    np.testing.assert_array_equal(back.keys, keys)
    assert back.probs.dtype == np.float16 and back.voxel_size == 0.5
    np.testing.assert_allclose(back.probs.astype(np.float32), probs.astype(np.float32), atol=1e-3)


def test_to_voxel_grid_logp_exactly() -> None:
    """logp = log p − max log p per row, computed in float32 and rounded to float16 once: a row's largest
    class sits at exactly 0 (probs() alone cannot tell, softmax ignores a row shift); log 0 clips silently."""
    p = np.array([[3.9551e-01, 5.9326e-01, 1.1520e-02], [0.25, 0.0, 0.75]], np.float16)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no divide-by-zero warning for the zero probability
        vg = SmoothedGrid(np.array([4, 9], np.int64), p, 0.5).to_voxel_grid(logp_clip=20.0)
    assert vg.logp.dtype == np.float16 and vg.voxel_size == 0.5
    p64 = p.astype(np.float64)
    with np.errstate(divide="ignore"):
        expected = np.maximum(np.log(p64) - np.log(p64.max(axis=1, keepdims=True)), -20.0).astype(np.float16)
    # Row 0: ln(0.3955 / 0.5933) = -0.4055, 0, ln(0.01152 / 0.5933) = -3.941 (float16 logs would give
    # -0.4058 and -3.943).
    np.testing.assert_array_equal(vg.logp, expected)
    assert vg.logp[0].tolist() == [np.float16(-0.4055), 0.0, np.float16(-3.941)]
    assert vg.logp[1, 1] == -20.0


def test_knn_smooth_works_in_float32_whatever_the_input_type() -> None:
    """Centres and distributions are rounded to float32 first (as a stored grid holds them), so float64
    inputs give the bytes of their float32 copies, also at the distance bound."""
    rng = np.random.default_rng(0)
    c = rng.uniform(0, 2, (300, 3))
    p = rng.dirichlet(np.ones(4), 300)
    np.testing.assert_array_equal(knn_smooth(c, p), knn_smooth(c.astype(np.float32), p.astype(np.float32)))
    # 0.5999999999 m is inside a 0.6 m bound, its float32 rounding (0.60000002) is not: no mixing.
    two = np.array([[0.0, 0.0, 0.0], [0.5999999999, 0.0, 0.0]])
    np.testing.assert_array_equal(knn_smooth(two, np.eye(2), SmoothingConfig(max_distance=0.6)), np.eye(2))


def test_knn_smooth_shape_checks_and_empty_input() -> None:
    out = knn_smooth(np.zeros((0, 3)), np.zeros((0, 4)))
    assert out.shape == (0, 4) and out.dtype == np.float32
    with pytest.raises(ValueError, match="centres"):  # probs for another number of voxels
        knn_smooth(np.zeros((3, 3)), np.zeros((2, 4)))
    for centres, probs in (
        (np.zeros(3), np.zeros((3, 4))),
        (np.zeros((3, 2)), np.zeros((3, 4))),
        (np.zeros((3, 3)), np.zeros(3)),
    ):
        with pytest.raises(ValueError, match=r"centres \(V, 3\)"):
            knn_smooth(centres, probs)


def test_knn_smooth_blocks_on_its_own() -> None:
    """The chunked form checks its centres and rounds them to float32 itself (the 0.6 m bound example of
    the float32 test), and smooths a single voxel into itself."""

    def rows(r: np.ndarray) -> np.ndarray:
        return np.eye(2, dtype=np.float32)[r]

    for bad in (np.zeros(3), np.zeros((2, 2)), np.zeros((2, 3, 1))):
        with pytest.raises(ValueError, match=r"centres \(V, 3\)"):
            list(knn_smooth_blocks(bad, rows))
    two = np.array([[0.0, 0.0, 0.0], [0.5999999999, 0.0, 0.0]])
    blocks = list(knn_smooth_blocks(two, rows, SmoothingConfig(max_distance=0.6), chunk=1))
    assert [s for s, _ in blocks] == [0, 1]
    np.testing.assert_array_equal(np.concatenate([b for _, b in blocks]), np.eye(2))
    one = list(knn_smooth_blocks(np.zeros((1, 3)), lambda r: np.array([[0.25, 0.75]], np.float32)[r]))
    assert len(one) == 1 and one[0][0] == 0 and one[0][1].tolist() == [[0.25, 0.75]]
    np.testing.assert_array_equal(knn_smooth(np.zeros((1, 3)), np.array([[0.25, 0.75]])), [[0.25, 0.75]])
    assert list(knn_smooth_blocks(np.zeros((0, 3)), rows)) == []


def test_grid_row_probs_shift_each_row_by_its_own_maximum() -> None:
    """A row far below 0 (here -110: exp underflows in float32 unless the row's own maximum is taken off
    first) gets the distribution of the same row at 0; the values are grid.probs()'s."""
    logp = np.array([[0.0, -1.0, -2.0], [-110.0, -111.0, -112.0], [3.0, 2.0, 1.0]], np.float16)
    grid = VoxelGrid(np.array([1, 2, 3], np.int64), logp, 0.2)
    got = grid_row_probs(grid)(np.array([2, 0, 1], np.int64))
    np.testing.assert_array_equal(got, grid.probs()[[2, 0, 1]])
    np.testing.assert_array_equal(got[2], got[1])
    np.testing.assert_array_equal(got[0], got[1])


def test_knn_weights_of_one_neighbour_and_of_none() -> None:
    np.testing.assert_array_equal(knn_weights(np.array([[0.0]])), [[1.0]])  # the voxel itself, weight 1
    w = knn_weights(np.zeros((2, 0)))
    assert w.shape == (2, 0) and w.dtype == np.float32


def test_k_one_keeps_every_voxel_as_it_is() -> None:
    centres = np.array([[0.0, 0, 0], [0.2, 0, 0], [0.4, 0, 0]], np.float32)
    probs = np.array([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]], np.float32)
    np.testing.assert_array_equal(knn_smooth(centres, probs, SmoothingConfig(k=1)), probs)


def test_knn_weights_shift_each_row_by_its_own_minimum() -> None:
    """A voxel whose nearest neighbours are 200 m away (unbounded kNN) still gets softmax(-d) weights: each
    row is shifted by its own minimum before exp(), where exp(-200) would underflow float32 to 0."""
    s1 = 1 / (1 + math.e**-1)
    w = knn_weights(np.array([[0.0, 1.0], [200.0, 201.0]]))
    np.testing.assert_allclose(w, [[s1, 1 - s1], [s1, 1 - s1]], rtol=1e-6)


def test_smoothed_grid_load_casts_float_probs_but_refuses_others(tmp_path) -> None:
    path = tmp_path / "grid_smooth.npz"
    np.savez(path, keys=np.array([1, 2], np.int64), probs=np.full((2, 2), 0.5, np.float32), voxel_size=0.2)
    back = SmoothedGrid.load(path)
    assert back.probs.dtype == np.float16 and back.probs.tolist() == [[0.5, 0.5], [0.5, 0.5]]
    np.savez(path, keys=np.array([1, 2], np.int64), probs=np.ones((2, 2), np.int64), voxel_size=0.2)
    with pytest.raises(DatasetError, match="'probs'"):
        SmoothedGrid.load(path)


def test_smoothed_grid_checks_each_array_on_its_own() -> None:
    keys = np.array([1, 2], np.int64)
    probs = np.full((2, 2), 0.5, np.float16)
    with pytest.raises(ValueError, match="'keys' must be 1-D int64"):
        SmoothedGrid(keys.astype(np.int32), probs, 0.2)  # right shape, wrong type
    with pytest.raises(ValueError, match="'keys' must be 1-D int64"):
        SmoothedGrid(keys[:, None], probs, 0.2)  # right type, wrong shape
    with pytest.raises(ValueError, match="'probs' must be"):
        SmoothedGrid(keys, probs.astype(np.float32), 0.2)
    with pytest.raises(ValueError, match="'probs' must be"):
        SmoothedGrid(keys, probs[:, 0], 0.2)


def test_config_and_voxel_size_bounds() -> None:
    assert SmoothingConfig(k=1, max_distance=0.01, workers=-1).k == 1  # the smallest valid values
    assert SmoothingConfig(k=64, max_distance=100.0, workers=256).k == 64  # the largest
    for bad in (
        {"k": 65},
        {"k": 10**9},
        {"max_distance": 0.0},
        {"max_distance": 1e-6},
        {"max_distance": 101.0},
        {"workers": 0},
        {"workers": -2},
        {"workers": 257},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            SmoothingConfig(**bad)
    keys, probs = np.array([1], np.int64), np.ones((1, 2), np.float16)
    for vs in (0.0, math.inf, math.nan, -0.2):
        with pytest.raises(ValueError, match="voxel_size"):
            SmoothedGrid(keys, probs, vs)


def _frozen_knn_smooth(centres: np.ndarray, probs: np.ndarray, k: int, bound: float) -> np.ndarray:
    """The smoothing as first written, kept here as the reference: one cKDTree query of all centres, its
    own softmax(-d) weights and one (V × V) CSR product ``csr(w, idx) @ probs`` in float32."""
    import scipy.sparse
    from scipy.spatial import cKDTree

    pts = np.asarray(centres, np.float32)
    p = np.asarray(probs, np.float32)
    v = len(pts)
    k = min(k, v)
    d, idx = cKDTree(pts).query(pts, k=k, distance_upper_bound=bound, workers=1)
    d = np.asarray(d, np.float32).reshape(v, k)
    idx = np.asarray(idx).reshape(v, k)
    dmin = d.min(axis=1, keepdims=True)
    dmin[~np.isfinite(dmin)] = 0.0
    e = np.exp(np.subtract(dmin, d))
    s = e.sum(axis=1, keepdims=True)
    w = np.divide(e, s, out=np.zeros_like(e), where=s > 0)
    idx = np.where(idx >= v, np.arange(v)[:, None], idx)
    mat = scipy.sparse.csr_matrix((w.reshape(-1), idx.reshape(-1), np.arange(0, v * k + 1, k)), shape=(v, v))
    return np.asarray(mat @ p, np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("v", [1, 6, 700, 4000])
def test_knn_smooth_is_bit_identical_to_the_sparse_product(seed: int, v: int) -> None:
    """Random grids, half on a lattice (equidistant neighbours: tie-breaks matter) and half scattered (some
    without neighbours within the bound), every k, bound, thread count and a few chunk sizes: the same
    bytes as the frozen CSR-product smoothing, for knn_smooth, knn_smooth_blocks and smooth_grid."""
    rng = np.random.default_rng(seed)
    lattice = rng.integers(0, 12, size=(v // 2, 3)) * 0.2 + 0.1
    scattered = rng.uniform(-2, 4, size=(v - v // 2, 3))
    keys = np.unique(voxel_keys(np.concatenate([lattice, scattered]), 0.2))
    logp = np.clip(rng.normal(0, 4, size=(len(keys), 7)), -20, None)
    logp -= logp.max(axis=1, keepdims=True)
    grid = VoxelGrid(keys, logp.astype(np.float16), 0.2)
    centres, probs = grid.centres(), grid.probs()
    for k in (1, 4, 9, 17):
        for bound in (None, 0.3, 0.6):
            ref = _frozen_knn_smooth(centres, probs, k, np.inf if bound is None else bound)
            for workers in (1, 2):
                for chunk in (len(keys) // 7 + 1, 333, 1 << 14):
                    cfg = SmoothingConfig(k=k, max_distance=bound, workers=workers)
                    what = (k, bound, workers, chunk)
                    assert knn_smooth(centres, probs, cfg, chunk).tobytes() == ref.tobytes(), what
                    assert smooth_grid(grid, cfg, chunk).tobytes() == ref.tobytes(), what
                    blocks = knn_smooth_blocks(centres, lambda r: probs[r], cfg, chunk)
                    assert np.concatenate([b for _, b in blocks]).tobytes() == ref.tobytes(), what
