"""Voxel keys and Bayesian log-space fusion, on hand-computed cases and properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leap_core.errors import DatasetError
from leap_core.fusion import (
    AXIS_OFFSET,
    FusionConfig,
    FusionPaths,
    Observations,
    VoxelGrid,
    VoxelLabels,
    apply_overrides,
    fold_blocks,
    fuse,
    fuse_dense,
    fusion_blocks,
    key_centres,
    key_coords,
    last_per_key,
    log_table,
    reduce_block,
    rows_in_sorted,
    union_sorted,
    voxel_keys,
    world_points,
)

F16_ATOL = 0.02  # float16 step is 1/64 for |logp| in [8, 16]; a float32 rounding difference can flip one step


def _key(ix: int, iy: int, iz: int) -> int:
    return ((ix + AXIS_OFFSET) << 42) | ((iy + AXIS_OFFSET) << 21) | (iz + AXIS_OFFSET)


def _obs(keys, rows, table, floor=1e-3) -> Observations:
    return Observations(np.asarray(keys, np.int64), np.asarray(rows, np.int32), log_table(table, floor))


# ---------------------------------------------------------------------------------------------- keys
def test_voxel_keys_with_negative_coordinates_and_round_trip() -> None:
    xyz = np.array([[0.1, 0.1, 0.1], [-0.1, 0.3, -0.5], [-0.39, -0.01, 0.59]], np.float32)
    keys = voxel_keys(xyz, 0.2)
    assert keys.tolist() == [_key(0, 0, 0), _key(-1, 1, -3), _key(-2, -1, 2)]
    np.testing.assert_array_equal(key_coords(keys), [[0, 0, 0], [-1, 1, -3], [-2, -1, 2]])
    centres = key_centres(keys, 0.2)
    np.testing.assert_allclose(centres, [[0.1, 0.1, 0.1], [-0.1, 0.3, -0.5], [-0.3, -0.1, 0.5]], atol=1e-6)
    np.testing.assert_array_equal(voxel_keys(centres, 0.2), keys)
    assert key_coords(keys).dtype == np.int64 and centres.dtype == np.float32


def test_voxel_keys_sort_by_x_then_y_then_z() -> None:
    coords = np.array([[-3, 5, 1], [-3, -7, 2], [2, -1, -1], [-3, 5, -4]])
    keys = voxel_keys((coords + 0.5) * 0.2, 0.2)
    np.testing.assert_array_equal(np.argsort(keys), np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0])))


def test_voxel_keys_reject_out_of_range_and_nan() -> None:
    with pytest.raises(ValueError, match="re-base"):
        voxel_keys(np.array([[0.0, 0.0, 0.2 * AXIS_OFFSET + 1.0]]), 0.2)
    with pytest.raises(ValueError, match="finite"):
        voxel_keys(np.array([[np.nan, 0.0, 0.0]]), 0.2)
    with pytest.raises(ValueError, match="shape"):
        voxel_keys(np.zeros((4, 2)), 0.2)


# ----------------------------------------------------------------------------------------- log table
def test_log_table_floor_clips_and_renormalises() -> None:
    lt = log_table(np.array([[0.5, 0.5, 0.0], [1 / 3, 1 / 3, 1 / 3]]), 1e-3)
    np.testing.assert_allclose(lt[0], np.log([0.5 / 1.001, 0.5 / 1.001, 0.001 / 1.001]), rtol=1e-6)
    np.testing.assert_allclose(lt[1], np.log([1 / 3] * 3), rtol=1e-6)
    assert lt.dtype == np.float32  # the dtype Observations hold (fuse's chunks are float32 sums)


# -------------------------------------------------------------------------------------------- fusion
def test_two_class_posterior_by_hand() -> None:
    # Two points in one voxel: [0.8, 0.2] and [0.6, 0.4]. Posterior ∝ [0.48, 0.08] = [6/7, 1/7].
    k = _key(4, -2, 0)
    batches = [_obs([k], [0], [[0.8, 0.2]]), _obs([k], [0], [[0.6, 0.4]])]
    grid = fuse(batches, 2, FusionConfig(prob_floor=1e-6))
    assert grid.keys.tolist() == [k]
    assert grid.logp.dtype == np.float16
    np.testing.assert_allclose(grid.logp[0], [0.0, math.log(0.08 / 0.48)], atol=1e-3)
    np.testing.assert_allclose(grid.probs()[0], [6 / 7, 1 / 7], atol=1e-3)
    labels, conf = grid.labels_and_confidence()
    assert labels.tolist() == [0] and labels.dtype == np.int16
    np.testing.assert_allclose(conf, [6 / 7], atol=1e-3)


def test_same_table_row_counted_per_point() -> None:
    # Three points of one image in one voxel with the same row = three observations: ∝ [0.6³, 0.4³].
    grid = fuse([_obs([7, 7, 7], [0, 0, 0], [[0.6, 0.4]])], 2, FusionConfig(prob_floor=1e-6))
    np.testing.assert_allclose(grid.logp[0], [0.0, 3 * math.log(0.4 / 0.6)], atol=2e-3)


def test_uniform_observation_changes_nothing() -> None:
    rng = np.random.default_rng(3)
    prior = fuse([_obs(rng.integers(0, 5, 40), rng.integers(0, 4, 40), rng.dirichlet(np.ones(3), 4))], 3)
    uniform = _obs(prior.keys, np.zeros(len(prior.keys)), [[1 / 3, 1 / 3, 1 / 3]])
    after = fuse([uniform, uniform], 3, grid=prior)
    np.testing.assert_array_equal(after.keys, prior.keys)
    np.testing.assert_array_equal(after.logp, prior.logp)
    # A voxel seen only uniformly exists but is uniform.
    fresh = fuse([_obs([99], [0], [[1 / 3, 1 / 3, 1 / 3]])], 3)
    np.testing.assert_array_equal(fresh.logp, [[0, 0, 0]])


def test_floor_keeps_a_class_recoverable() -> None:
    # A confident wrong mask [1, 0] adds only log(1e-3/1.001) ≈ -6.908 against class 0 ...
    cfg = FusionConfig(prob_floor=1e-3)
    wrong = _obs([1], [0], [[1.0, 0.0]])
    g1 = fuse([wrong], 2, cfg)
    np.testing.assert_allclose(g1.logp[0], [0.0, math.log(1e-3)], atol=0.01)
    # ... so two observations of [0.02, 0.98] (each log(0.02/0.98) ≈ -3.892 for class 0) flip it.
    right = _obs([1, 1], [0, 0], [[0.02, 0.98]])
    g2 = fuse([wrong, right], 2, cfg)
    assert g2.labels_and_confidence()[0].tolist() == [1]
    np.testing.assert_allclose(g2.logp[0], [math.log(1e3) + 2 * math.log(0.02 / 0.98), 0.0], atol=0.01)


def test_stored_logp_is_clipped() -> None:
    g = fuse([_obs([5] * 5, [0] * 5, [[1.0, 0.0]])], 2, FusionConfig(logp_clip=20.0))
    np.testing.assert_array_equal(g.logp, [[0.0, -20.0]])  # 5 × -6.9 = -34.5, clipped


def test_weight_scales_log_likelihoods() -> None:
    obs = [_obs([3], [0], [[0.8, 0.2]])]
    g = fuse(obs, 2, FusionConfig(prob_floor=1e-6), weight=0.5)
    np.testing.assert_allclose(g.logp[0], [0.0, 0.5 * math.log(0.25)], atol=1e-3)
    with pytest.raises(ValueError, match="weight"):
        fuse(obs, 2, weight=-1.0)


def _reference(batches, c: int, clip: float = 20.0):
    keys = np.concatenate([b.keys for b in batches])
    lp = np.concatenate([b.log_table[b.rows] for b in batches]).astype(np.float64)
    uk, inv = np.unique(keys, return_inverse=True)
    acc = np.zeros((len(uk), c))
    np.add.at(acc, inv, lp)
    acc -= acc.max(axis=1, keepdims=True)
    return uk, np.maximum(acc, -clip)


@st.composite
def _batches(draw):
    c = draw(st.integers(2, 6))
    n_batches = draw(st.integers(1, 6))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_batches):
        p, k = int(rng.integers(0, 40)), int(rng.integers(1, 5))
        coords = rng.integers(-3, 3, (p, 3))
        keys = voxel_keys((coords + 0.5) * 0.2, 0.2)
        out.append(_obs(keys, rng.integers(0, k, p), rng.dirichlet(np.ones(c), k)))
    return c, out, seed


@settings(max_examples=40, deadline=None)
@given(_batches())
def test_fusion_is_order_and_batching_independent(data) -> None:
    c, batches, seed = data
    rng = np.random.default_rng(seed + 1)
    base = fuse(batches, c)
    uk, ref = _reference(batches, c)
    np.testing.assert_array_equal(base.keys, uk)
    np.testing.assert_allclose(base.logp.astype(np.float64), ref, atol=F16_ATOL)
    # Shuffled batch order, and points re-split into different batches, fused in small chunks.
    shuffled = [batches[i] for i in rng.permutation(len(batches))]
    split = []
    for b in shuffled:
        cut = int(rng.integers(0, len(b.keys) + 1))
        split += [
            Observations(b.keys[:cut], b.rows[:cut], b.log_table),
            Observations(b.keys[cut:], b.rows[cut:], b.log_table),
        ]
    other = fuse(split, c, FusionConfig(chunk_points=int(rng.integers(1, 30))))
    np.testing.assert_array_equal(other.keys, base.keys)
    np.testing.assert_allclose(other.logp.astype(np.float64), base.logp, atol=F16_ATOL)


def test_fusing_into_a_grid_adds_new_voxels_and_equals_one_call() -> None:
    a = _obs([_key(0, 0, 0), _key(1, 0, 0)], [0, 1], [[0.7, 0.3], [0.4, 0.6]])
    b = _obs([_key(1, 0, 0), _key(-1, 0, 0)], [0, 0], [[0.9, 0.1]])
    step = fuse([b], 2, grid=fuse([a], 2))
    once = fuse([a, b], 2)
    np.testing.assert_array_equal(step.keys, [_key(-1, 0, 0), _key(0, 0, 0), _key(1, 0, 0)])
    np.testing.assert_array_equal(step.keys, once.keys)
    np.testing.assert_allclose(step.logp.astype(float), once.logp.astype(float), atol=F16_ATOL)


def test_fuse_rejects_inconsistent_input() -> None:
    with pytest.raises(ValueError, match="log_table must be"):
        fuse([_obs([1], [0], [[0.5, 0.5]])], 3)
    with pytest.raises(ValueError, match="rows must index"):
        fuse([Observations(np.array([1]), np.array([2], np.int32), np.zeros((2, 2), np.float32))], 2)
    with pytest.raises(ValueError, match="voxel_size"):
        fuse([], 2, FusionConfig(voxel_size=0.5), grid=VoxelGrid.empty(2, 0.2))
    empty = fuse([], 4)  # no grid, no observations: an empty grid of the documented dtypes
    assert empty.keys.shape == (0,) and empty.logp.shape == (0, 4)
    assert empty.keys.dtype == np.int64 and empty.logp.dtype == np.float16


def test_fuse_dense_with_weight_and_floor() -> None:
    keys = np.array([9, 2, 9], np.int64)
    with np.errstate(divide="ignore"):
        logp = np.log(np.array([[0.8, 0.2], [1.0, 0.0], [0.6, 0.4]], np.float32))  # log 0 = -inf, floored
    g = fuse_dense(None, keys, logp, 2, FusionConfig(prob_floor=1e-3), weight=0.5)
    assert g.keys.tolist() == [2, 9]
    np.testing.assert_allclose(g.logp[0], [0.0, 0.5 * math.log(1e-3)], atol=0.01)
    np.testing.assert_allclose(g.logp[1], [0.0, 0.5 * math.log(0.08 / 0.48)], atol=2e-3)
    # Fusing into a prior adds to it.
    g2 = fuse_dense(g, np.array([9]), np.array([[0.0, -1.0]], np.float32), 2)
    np.testing.assert_allclose(g2.logp[1], [0.0, 0.5 * math.log(1 / 6) - 1.0], atol=3e-3)


def test_fuse_dense_matches_fuse_on_the_same_observations() -> None:
    rng = np.random.default_rng(0)
    obs = _obs(rng.integers(0, 50, 500), rng.integers(0, 6, 500), rng.dirichlet(np.ones(5), 6))
    a = fuse([obs], 5)
    b = fuse_dense(None, obs.keys, obs.log_table[obs.rows], 5)
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_allclose(a.logp.astype(float), b.logp.astype(float), atol=F16_ATOL)


def test_fuse_dense_takes_any_numeric_input_and_refuses_wrong_shapes() -> None:
    """fuse_dense casts keys to int64 and log-probabilities to float32 (float64 and int32 arrays give
    the float32 result), applies any weight (2 as well as 0.5), and names the expected shapes when one
    dimension alone is wrong. (Survivors of the fusion mutation run of 2026-11-27.)"""
    rng = np.random.default_rng(5)
    keys = rng.integers(0, 30, 200)
    logp = np.log(rng.dirichlet(np.ones(4), 200))
    ref = fuse_dense(None, keys.astype(np.int64), logp.astype(np.float32), 4, weight=2.0)
    got = fuse_dense(None, keys.astype(np.int32), logp, 4, weight=2.0)  # int32 keys, float64
    assert got.keys.dtype == np.int64 and got.logp.tobytes() == ref.logp.tobytes()
    once = fuse_dense(None, keys, logp, 4)
    twice = fuse_dense(once, keys, logp, 4)
    assert ref.logp.tobytes() == twice.logp.tobytes() != once.logp.tobytes()  # weight 2 = the same twice
    for bad_keys, bad_logp in (
        (keys, logp[:, :3]),
        (keys, logp[:-1]),
        (keys.reshape(20, 10), logp),
        (keys, logp[:, 0]),
    ):
        with pytest.raises(ValueError, match=r"keys \(N,\) and logp \(N, 4\) expected"):
            fuse_dense(None, bad_keys, bad_logp, 4)


def test_empty_grid_has_the_documented_layout() -> None:
    g = VoxelGrid.empty(3)
    assert g.voxel_size == 0.2 and VoxelGrid.empty(3, 0.5).voxel_size == 0.5
    assert g.keys.dtype == np.int64 and g.keys.shape == (0,)
    assert g.logp.dtype == np.float16 and g.logp.shape == (0, 3) and g.num_classes == 3


def test_apply_overrides_by_hand_and_its_argument_checks() -> None:
    """Each correction adds -strength to every class but its own (no clip at strength 1): voxel 7 corrected
    once to class 0 gets [0, -1, -1]; voxel 9 corrected to classes 0 and 1 gets -(2 - hits) = [-1, -1, -2],
    stored as [0, 0, -1]. Bad arguments are refused before anything is computed."""
    empty = VoxelGrid.empty(3)
    g = apply_overrides(empty, [9, 7, 9], [0, 0, 1], strength=1.0)
    assert g.keys.tolist() == [7, 9]
    assert g.logp.tolist() == [[0.0, -1.0, -1.0], [0.0, 0.0, -1.0]]
    assert apply_overrides(empty, [], [], strength=0.5).num_voxels == 0
    for keys, cls, strength, msg in (
        ([1, 2], [0], 1.0, "must have the same length"),
        ([1], [3], 1.0, r"class_idx must be in 0\.\.2"),
        ([1], [-1], 1.0, r"class_idx must be in 0\.\.2"),
        ([1], [0], 0.0, "strength must be > 0"),
        ([], [], -1.0, "strength must be > 0"),
    ):
        with pytest.raises(ValueError, match=msg):
            apply_overrides(empty, keys, cls, strength=strength)


# ---------------------------------------------------------------------------------------------- grid
def test_grid_lookup_nbytes_and_save_load(tmp_path) -> None:
    g = fuse([_obs([5, 10, 20], [0, 0, 0], [[0.5, 0.25, 0.25]])], 3)
    np.testing.assert_array_equal(g.lookup(np.array([10, 11, 20, 5, -4, 99])), [1, -1, 2, 0, -1, -1])
    np.testing.assert_array_equal(VoxelGrid.empty(3).lookup(np.array([1])), [-1])
    big = VoxelGrid(np.arange(100, dtype=np.int64), np.zeros((100, 20), np.float16))
    assert big.nbytes / big.num_voxels == 48
    path = tmp_path / "grid.npz"
    g.save(path)
    back = VoxelGrid.load(path)
    np.testing.assert_array_equal(back.keys, g.keys)
    np.testing.assert_array_equal(back.logp, g.logp)
    assert back.voxel_size == g.voxel_size and back.num_classes == 3


def test_grid_load_rejects_bad_files(tmp_path) -> None:
    bad = tmp_path / "grid.npz"
    bad.write_bytes(b"garbage")
    with pytest.raises(DatasetError, match=r"grid\.npz: unreadable voxel grid"):
        VoxelGrid.load(bad)
    np.savez(bad, keys=np.array([3, 1], np.int64), logp=np.zeros((2, 2), np.float16), voxel_size=0.2)
    with pytest.raises(DatasetError, match="not sorted"):
        VoxelGrid.load(bad)
    np.savez(bad, keys=np.array([1, 3], np.int64), logp=np.zeros((3, 2), np.float16), voxel_size=0.2)
    with pytest.raises(DatasetError, match="'logp'"):
        VoxelGrid.load(bad)
    np.savez(bad, keys=np.array([1, 3], np.int64), logp=np.zeros((2, 2), np.float16))
    with pytest.raises(DatasetError, match="voxel_size"):
        VoxelGrid.load(bad)
    for keys, logp, what in (
        (np.array([1.0, 3.0]), np.zeros((2, 2), np.float16), "'keys' must be 1-D int64"),
        (np.array([1, 3], np.int64), np.zeros((2, 2), np.float32), "'logp' must be"),
    ):
        np.savez(bad, keys=keys, logp=logp, voxel_size=0.2)
        with pytest.raises(DatasetError, match=what):
            VoxelGrid.load(bad)
    for vs in (0.0, -0.2, np.inf):
        np.savez(bad, keys=np.array([1, 3], np.int64), logp=np.zeros((2, 2), np.float16), voxel_size=vs)
        with pytest.raises(DatasetError, match="'voxel_size' must be positive"):
            VoxelGrid.load(bad)
    np.savez(bad, keys=np.array([1, 3], np.int64), logp=np.zeros((2, 2), np.float16), voxel_size=0.5)
    assert VoxelGrid.load(bad).voxel_size == 0.5


def test_apply_overrides() -> None:
    g = fuse([_obs([1, 2], [0, 0], [[0.9, 0.05, 0.05]])], 3)
    out = apply_overrides(g, np.array([2, 7]), np.array([2, 1]))
    assert out.keys.tolist() == [1, 2, 7]
    labels, conf = out.labels_and_confidence()
    assert labels.tolist() == [0, 2, 1]
    np.testing.assert_array_equal(out.logp[0], g.logp[0])  # untouched voxel
    np.testing.assert_array_equal(out.logp[1], [-20.0, -20.0, 0.0])  # strength 50 saturates at the clip
    assert conf[1] > 0.999999
    with pytest.raises(ValueError, match="class_idx"):
        apply_overrides(g, np.array([1]), np.array([3]))


def test_extent_too_wide_to_pack_gives_the_same_result() -> None:
    # Axis ranges of 2^21 voxels leave no bits for table rows in one int64: the np.unique path runs.
    rng = np.random.default_rng(5)
    coords = np.concatenate(
        [rng.integers(-3, 3, (60, 3)), [[-AXIS_OFFSET, -AXIS_OFFSET, -AXIS_OFFSET], [AXIS_OFFSET - 1] * 3]]
    )
    keys = voxel_keys((coords + 0.5) * 0.2, 0.2)
    obs = _obs(keys, rng.integers(0, 3, len(keys)), rng.dirichlet(np.ones(4), 3))
    grid = fuse([obs], 4)
    uk, ref = _reference([obs], 4)
    np.testing.assert_array_equal(grid.keys, uk)
    np.testing.assert_allclose(grid.logp.astype(float), ref, atol=F16_ATOL)


# ------------------------------------------------------------------------- implementation switches
# Each FusionPaths switch picks one of two implementations of the same maths; the defaults only reach one
# side on small data, so each test forces the other side and requires the same bytes.


def _confident_batches(seed: int = 3) -> tuple[int, list[Observations]]:
    """Random voxels and tables, with many confident points in some voxels: their rows fall far below
    -logp_clip, so the clip acts (the row shift always acts: raw sums of log-probabilities are < 0)."""
    rng = np.random.default_rng(seed)
    c, out = 5, []
    for _ in range(4):
        p = 300
        coords = rng.integers(-4, 4, (p, 3))
        table = np.vstack([rng.dirichlet(np.ones(c), 6), np.eye(c)[:2] * 0.999 + 0.0002])
        out.append(_obs(voxel_keys((coords + 0.5) * 0.2, 0.2), rng.integers(0, len(table), p), table))
    return c, out


def test_unique_numbering_and_block_size_give_the_same_sums() -> None:
    """The np.unique path of a fusion chunk (wide extents) and any packing block size give the exact sums of
    the default packed path."""
    c, batches = _confident_batches(seed=8)
    base = fuse(batches, c)
    for paths in (FusionPaths(pack_max_bits=0), FusionPaths(block=7), FusionPaths(block=1)):
        other = fuse(batches, c, paths=paths)
        np.testing.assert_array_equal(other.keys, base.keys)
        np.testing.assert_array_equal(other.logp, base.logp)
    _, ref = _reference(batches, c)
    np.testing.assert_allclose(base.logp.astype(np.float64), ref, atol=F16_ATOL)


def test_fusion_paths_reject_bad_values() -> None:
    with pytest.raises(ValueError, match=r"pack_max_bits: must be in 0\.\.62"):
        FusionPaths(pack_max_bits=63)
    with pytest.raises(ValueError, match="block: must be"):
        FusionPaths(block=0)


# ------------------------------------------------------------------------------------ labels at keys
def test_voxel_labels_from_probs_ties_and_absent_keys() -> None:
    # float16 probabilities as stored: row 2 is an exact tie; row 3 ties only after float16 rounding
    # (0.35 and 0.35001 are one float16), so both take the lowest index, as numpy's argmax does.
    probs = np.array(
        [[0.6, 0.4, 0.0], [0.1, 0.2, 0.7], [0.25, 0.375, 0.375], [0.35, 0.35001, 0.3]], np.float32
    ).astype(np.float16)
    labels = VoxelLabels.from_probs([10, 20, 30, 40], probs)
    assert labels.label.dtype == np.int16 and labels.conf.dtype == np.float32
    assert labels.label.tolist() == [0, 2, 1, 0]
    np.testing.assert_array_equal(labels.conf, probs[[0, 1, 2, 3], [0, 2, 1, 0]].astype(np.float32))
    lab, conf = labels.at(np.array([20, 15, 10, 40, 99, 30]))
    assert lab.dtype == np.int16 and conf.dtype == np.float32
    assert lab.tolist() == [2, -1, 0, 0, -1, 1]
    np.testing.assert_allclose(conf, [0.7, 0.0, 0.6, 0.35, 0.0, 0.375], atol=1e-3)
    empty = VoxelLabels.from_probs(np.zeros(0, np.int64), np.zeros((0, 3), np.float16))
    assert empty.at(np.array([1, 2]))[0].tolist() == [-1, -1]
    with pytest.raises(ValueError, match="keys"):
        VoxelLabels.from_probs([1, 2], probs)


def test_voxel_labels_in_chunks_equal_one_pass() -> None:
    rng = np.random.default_rng(3)
    probs = rng.dirichlet(np.ones(5), 1000).astype(np.float16)
    probs[::7, 1] = probs[::7, 3] = np.float16(0.5)  # ties in some rows
    keys = np.arange(1000, dtype=np.int64) * 3
    one = VoxelLabels.from_probs(keys, probs)
    chunked = VoxelLabels.from_probs(keys, probs, chunk=7)
    np.testing.assert_array_equal(one.label, probs.argmax(axis=1))
    np.testing.assert_array_equal(chunked.label, one.label)
    np.testing.assert_array_equal(chunked.conf, one.conf)


def test_voxel_grid_labels_at() -> None:
    # Voxel 10: logp (0, -ln 3) → class 0 with 1/(1 + 1/3) = 0.75; voxel 20: class 1 with 1/(1 + e^-2).
    grid = VoxelGrid(np.array([10, 20], np.int64), np.array([[0, -math.log(3)], [-2, 0]], np.float16))
    lab, conf = grid.labels_at(np.array([20, 15, 10]))
    assert lab.tolist() == [1, -1, 0]
    np.testing.assert_allclose(conf, [1 / (1 + math.exp(-2)), 0.0, 0.75], atol=1e-3)
    chunked = grid.voxel_labels(chunk=1)
    np.testing.assert_array_equal(chunked.label, grid.voxel_labels().label)
    np.testing.assert_array_equal(chunked.conf, grid.voxel_labels().conf)


def test_grid_probs_in_chunks_and_float16() -> None:
    logp = np.array([[0.0, 0.0], [0.0, -math.log(3.0)], [-20.0, 0.0]], np.float16)
    grid = VoxelGrid(np.array([1, 2, 3], np.int64), logp)
    p = grid.probs()
    np.testing.assert_allclose(p, [[0.5, 0.5], [0.75, 0.25], [2.06e-9, 1.0]], rtol=1e-3, atol=1e-10)
    np.testing.assert_array_equal(grid.probs(chunk=2), p)
    half = grid.probs(np.float16, chunk=1)
    assert half.dtype == np.float16
    np.testing.assert_array_equal(half, p.astype(np.float16))
    assert VoxelGrid.empty(4).probs().shape == (0, 4)


def test_last_per_key_keeps_the_last_value() -> None:
    keys, vals = last_per_key(np.array([4, 1, 4, 2, 1]), np.array([10, 11, 12, 13, 14]))
    assert keys.tolist() == [1, 2, 4] and vals.tolist() == [14, 13, 12]
    keys, vals = last_per_key(np.zeros(0, np.int64), np.zeros(0, np.int16))
    assert keys.size == 0 and vals.dtype == np.int16
    with pytest.raises(ValueError, match="same length"):
        last_per_key(np.array([1, 2]), np.array([1]))


def test_world_points() -> None:
    # 90° about z, then +(10, 20, 30): (1, 2, 3) → (-2, 1, 3) + t.
    pose = np.eye(4)
    pose[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    pose[:3, 3] = [10, 20, 30]
    pts = np.array([[1, 2, 3, 0.5], [0, 0, 0, 0.1]], np.float32)
    out = world_points(pts, pose)
    assert out.dtype == np.float64 and out.shape == (2, 3)
    np.testing.assert_array_equal(out, [[8, 21, 33], [10, 20, 30]])


def test_world_points_blocked_equals_the_one_call_product_byte_for_byte() -> None:
    # world_points computes in row blocks (leap_core.geometry) to keep OpenBLAS's threads out; a whole
    # scan's voxel keys depend on its last bits, so the blocks must give the one-call product's bytes,
    # including the rows left over after the last full block.
    rng = np.random.default_rng(3)
    pts = (rng.normal(size=(20_003, 4)) * 40).astype(np.float32)
    a = rng.normal(size=(3, 3))
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(a)[0]
    pose[:3, 3] = [123.4, -56.7, 8.9]
    ref = pts[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    assert world_points(pts, pose).tobytes() == ref.tobytes()


def test_rows_in_sorted_finds_present_keys_and_marks_absent_ones() -> None:
    keys = np.array([3, 7, 9], np.int64)
    assert rows_in_sorted(keys, np.array([9, 4, 3, 10, 0, 7])).tolist() == [2, -1, 0, -1, -1, 1]
    assert rows_in_sorted(np.zeros(0, np.int64), np.array([1, 2])).tolist() == [-1, -1]
    assert rows_in_sorted(keys, np.array([[7, 8]])).shape == (1, 2)


def test_union_sorted_by_hand_and_against_union1d() -> None:
    a = np.array([1, 4, 9], np.int64)
    assert union_sorted(a, np.array([0, 4, 10], np.int64)).tolist() == [0, 1, 4, 9, 10]
    assert union_sorted(a, np.array([4, 9], np.int64)).tolist() == [1, 4, 9]  # nothing new
    assert union_sorted(np.zeros(0, np.int64), a).tolist() == [1, 4, 9]
    assert union_sorted(a, np.zeros(0, np.int64)).tolist() == [1, 4, 9]
    rng = np.random.default_rng(3)
    for _ in range(50):
        x = np.unique(rng.integers(-50, 50, rng.integers(0, 40)))
        y = np.unique(rng.integers(-60, 60, rng.integers(0, 40)))
        got = union_sorted(x, y)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, np.union1d(x, y))


# -------------------------------------------------------------- fusion in blocks (the Ray engine's fusion)
def _random_obs(rng: np.random.Generator, n: int, c: int) -> Observations:
    keys = rng.integers(0, 40, n).astype(np.int64) * 7919 + (1 << 62) // 3
    table = rng.dirichlet(np.ones(c), size=5).astype(np.float32)
    return Observations(keys, rng.integers(0, 5, n).astype(np.int32), np.log(table))


def test_fusion_blocks_follow_fuse_chunking() -> None:
    assert fusion_blocks([5, 0, 4, 3], 8) == [[0, 2], [3]]
    assert fusion_blocks([9, 1, 1], 8) == [[0], [1, 2]]
    assert fusion_blocks([0, 0], 8) == []


def test_blocks_folded_in_order_are_fuse_byte_for_byte() -> None:
    rng = np.random.default_rng(3)
    c = 6
    batches = [_random_obs(rng, int(n), c) for n in (300, 0, 250, 400, 120, 380, 90)]
    cfg = FusionConfig(chunk_points=500)
    blocks = fusion_blocks([len(b.keys) for b in batches], cfg.chunk_points)
    assert len(blocks) >= 3
    partials = [reduce_block([batches[i] for i in block], c) for block in blocks]
    for keys, sums in partials:  # as Ray's object store hands them out: read-only
        keys.setflags(write=False)
        sums.setflags(write=False)
    folded = fold_blocks(partials, c, cfg)
    expected = fuse(batches, c, cfg)
    assert folded.keys.tobytes() == expected.keys.tobytes()
    assert folded.logp.tobytes() == expected.logp.tobytes()


def test_fold_order_matters_and_is_kept() -> None:
    """Three one-voxel chunks whose float32 sum depends on the order: (1e8 - 1e8) + 1 = 1, but
    (1 - 1e8) + 1e8 = 0. The fold must add them in block order, as fuse does."""
    c = 2
    key = np.array([5], np.int64)
    rows = np.zeros(1, np.int32)
    tables = [np.array([[v, 0.0]], np.float32) for v in (1e8, -1e8, 1.0)]
    batches = [Observations(key, rows, t) for t in tables]
    cfg = FusionConfig(chunk_points=1, logp_clip=20.0)
    blocks = fusion_blocks([1, 1, 1], cfg.chunk_points)
    partials = [reduce_block([batches[i] for i in b], c) for b in blocks]
    expected = fuse(batches, c, cfg)
    assert expected.logp.tolist() == [[0.0, -1.0]]
    assert fold_blocks(partials, c, cfg).logp.tobytes() == expected.logp.tobytes()
    assert fold_blocks(partials[::-1], c, cfg).logp.tobytes() != expected.logp.tobytes()


def test_fold_blocks_adds_to_a_prior_grid_with_the_given_config() -> None:
    """fold_blocks starts from ``grid`` and stores with ``cfg`` (its clip), as fuse does; empty blocks give an
    empty partial of the documented layout."""
    rng = np.random.default_rng(11)
    c = 4
    batches = [_random_obs(rng, n, c) for n in (200, 150, 300)]
    prior = fuse(batches[:1], c)
    cfg = FusionConfig(chunk_points=180, logp_clip=3.0)
    blocks = fusion_blocks([len(b.keys) for b in batches[1:]], cfg.chunk_points)
    partials = [reduce_block([batches[1:][i] for i in block], c) for block in blocks]
    folded = fold_blocks(partials, c, cfg, grid=prior, weight=1.0)
    expected = fuse(batches[1:], c, cfg, grid=prior)
    assert folded.logp.min() == -3.0  # the given clip acted
    assert folded.keys.tobytes() == expected.keys.tobytes()
    assert folded.logp.tobytes() == expected.logp.tobytes()
    keys, sums = reduce_block(
        [Observations(np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros((1, c), np.float32))], c
    )
    assert keys.dtype == np.int64 and keys.shape == (0,)
    assert sums.dtype == np.float32 and sums.shape == (0, c)


def test_grow_resizes_an_owned_array_in_place_and_copies_a_view() -> None:
    from leap_core.fusion import _grow

    # An array that owns its memory grows in place (no second copy of a large accumulator) ...
    owned = np.arange(6, dtype=np.float32).reshape(3, 2).copy()  # reshape alone returns a view
    grown = _grow(owned, 5)
    assert grown is owned and grown.shape == (5, 2)
    np.testing.assert_array_equal(grown[:3], np.arange(6).reshape(3, 2))
    # ... a view of another array is copied (resizing would move memory its base still points at).
    base = np.arange(10, dtype=np.int64)
    view = base[2:8].reshape(3, 2)
    copy = _grow(view, 4)
    assert copy is not view and copy.dtype == np.int64 and copy.shape == (4, 2)
    np.testing.assert_array_equal(copy, [[2, 3], [4, 5], [6, 7], [0, 0]])
    np.testing.assert_array_equal(base, np.arange(10))


def test_labels_and_confidence_and_probs_are_the_softmax_of_any_row() -> None:
    """The softmax is taken of each row as stored, also of rows whose maximum is not 0 (a grid made by
    hand), computed in float32: label = argmax, conf = 1 / Σ_j exp(logp_j - max logp)."""
    logp = np.array([[-1.0, -2.0, -4.0], [-3.0, -1.0, -1.5], [0.5, 2.0, 2.0]], np.float16)
    grid = VoxelGrid(np.array([3, 8, 9], np.int64), logp)
    x = logp.astype(np.float64)
    want = np.exp(x - x.max(1, keepdims=True))
    want /= want.sum(1, keepdims=True)
    labels, conf = grid.labels_and_confidence()
    assert labels.tolist() == [0, 1, 1]  # a tie goes to the lower index
    assert conf.dtype == np.float32
    np.testing.assert_allclose(conf, want.max(1), rtol=1e-6)
    np.testing.assert_allclose(grid.probs(), want, rtol=1e-6)
    chunked = grid.labels_and_confidence(chunk=2)
    assert chunked[0].tolist() == labels.tolist() and chunked[1].tobytes() == conf.tobytes()


def test_fold_blocks_skips_empty_partials_and_refuses_malformed_ones() -> None:
    c = 2
    one = (np.array([4, 7], np.int64), np.array([[0.0, -2.0], [-1.0, 0.0]], np.float32))
    empty = (np.zeros(0, np.int64), np.zeros((0, c), np.float32))
    alone = fold_blocks([one], c)
    for partials in ([empty, one], [empty, one, empty]):
        got = fold_blocks(partials, c)
        assert got.keys.tobytes() == alone.keys.tobytes() and got.logp.tobytes() == alone.logp.tobytes()
    with pytest.raises(ValueError, match="partial keys"):
        fold_blocks([(one[0], one[1][:, :1])], c)  # sums of another class count
    with pytest.raises(ValueError, match="partial keys"):
        fold_blocks([(one[0][:, None], one[1])], c)  # keys not 1-D


def test_last_per_key_and_overrides_take_column_vectors() -> None:
    keys, vals = np.array([4, 1, 4, 2]), np.array([10, 11, 12, 13])
    flat = last_per_key(keys, vals)
    column = last_per_key(keys[:, None], vals[:, None])
    assert column[0].tolist() == flat[0].tolist() == [1, 2, 4] and column[1].tolist() == flat[1].tolist()
    grid = VoxelGrid(np.array([1, 2], np.int64), np.zeros((2, 3), np.float16))
    want = apply_overrides(grid, [2, 5], [1, 2])
    got = apply_overrides(grid, np.array([[2], [5]]), np.array([[1], [2]]))
    assert got.keys.tolist() == want.keys.tolist() == [1, 2, 5]
    assert got.logp.tobytes() == want.logp.tobytes()


def test_merge_sparse_refuses_accumulator_lists_of_different_lengths() -> None:
    from leap_core.fusion import merge_sparse

    a = [np.ones((2, 2), np.float32), np.ones(2, np.int32)]
    b = [np.ones((1, 2), np.float32)]
    for keys_b in (np.array([3]), np.array([4])):  # every key of b in a; a new key
        with pytest.raises(ValueError, match="zip"):
            merge_sparse(np.array([3, 7]), [x.copy() for x in a], keys_b, b)


def test_weight_zero_adds_the_voxels_without_evidence() -> None:
    k = _key(1, 2, 3)
    grid = fuse([_obs([k], [0], [[0.9, 0.1]])], 2, weight=0.0)
    assert grid.keys.tolist() == [k] and grid.logp.tolist() == [[0.0, 0.0]]
    for bad in (-0.5, math.inf, math.nan):
        with pytest.raises(ValueError, match="finite number"):
            fuse([], 2, weight=bad)


def test_union_sorted_with_one_key_on_either_side() -> None:
    assert union_sorted(np.array([5]), np.array([3])).tolist() == [3, 5]
    assert union_sorted(np.array([3, 8]), np.array([5])).tolist() == [3, 5, 8]
    assert union_sorted(np.zeros(0, np.int64), np.array([2, 4])).tolist() == [2, 4]
    assert union_sorted(np.array([1, 4, 9]), np.array([0, 4, 10])).tolist() == [0, 1, 4, 9, 10]


def test_a_chunk_closes_when_its_points_reach_chunk_points() -> None:
    assert fusion_blocks([7, 1], 8) == [[0, 1]]  # 7 + 1 reaches 8 with the second batch, not before
    assert fusion_blocks([7, 1, 1], 8) == [[0, 1], [2]]
    assert fusion_blocks([8, 7, 1, 1], 8) == [[0], [1, 2], [3]]  # the count starts again at 0


def test_a_bad_batch_is_named_by_its_position() -> None:
    good = _obs([_key(0, 0, 0)], [0], [[0.5, 0.5]])
    bad = Observations(np.array([1, 2], np.int64), np.zeros(3, np.int32), np.zeros((1, 2), np.float32))
    with pytest.raises(ValueError, match=r"observation batch 1: keys \(2,\) and rows \(3,\)"):
        fuse([good, bad], 2)


def test_fusion_config_refuses_floors_and_clips_outside_their_ranges() -> None:
    for kwargs in ({"prob_floor": 0.0}, {"prob_floor": 1.0}, {"prob_floor": 1.5}, {"logp_clip": 0.0}):
        with pytest.raises(ValueError):
            FusionConfig(**kwargs)
    FusionConfig(prob_floor=0.999, logp_clip=1e-3)  # just inside


def test_keys_sorted_unique_checks_every_pair_across_chunks() -> None:
    from leap_core.fusion import keys_sorted_unique

    assert keys_sorted_unique(np.array([1, 3, 4, 8, 9], np.int64), chunk=2)
    assert not keys_sorted_unique(np.array([1, 1, 2], np.int64))  # a repeated key
    assert not keys_sorted_unique(np.array([1, 3, 2], np.int64))  # not only the first is compared
    for i in range(4):  # a step down at every position, chunk boundaries included
        keys = np.arange(6, dtype=np.int64)
        keys[i + 1] = keys[i] - 1
        assert not keys_sorted_unique(keys, chunk=2), i
    assert keys_sorted_unique(np.zeros(0, np.int64)) and keys_sorted_unique(np.array([7], np.int64))


def test_grids_keep_the_voxel_size_and_many_classes() -> None:
    cfg = FusionConfig(voxel_size=0.5)
    assert fuse([], 3, cfg).voxel_size == 0.5  # the empty grid (not stored in place)
    k = voxel_keys(np.array([[1.0, 2.0, 3.0]]), 0.5)
    assert fuse([_obs(k, [0], [[0.7, 0.2, 0.1]])], 3, cfg).voxel_size == 0.5  # stored in place
    c = 100  # more than 64 classes: _finalise's rows per block are 2²² // C
    table = np.full((1, c), 0.5 / (c - 1))
    table[0, 7] = 0.5
    grid = fuse([_obs(k, [0], table)], c, cfg)
    assert grid.num_classes == c and grid.labels_and_confidence()[0].tolist() == [7]


def test_voxel_keys_ignore_extra_columns_and_stop_at_the_last_packable_index() -> None:
    xyz = np.array([[0.1, 0.3, -0.5, np.nan], [1.0, 2.0, 3.0, 1e30]])  # a 4th column (remission) ignored
    np.testing.assert_array_equal(voxel_keys(xyz, 0.2), voxel_keys(xyz[:, :3], 0.2))
    top = (AXIS_OFFSET - 1) * 0.5 + 0.25  # centre of the last index that fits in 21 bits
    assert voxel_keys(np.array([[top, 0.0, 0.0]]), 0.5).tolist() == [_key(AXIS_OFFSET - 1, 0, 0)]
    for x in (AXIS_OFFSET * 0.5 + 0.25, -AXIS_OFFSET * 0.5 - 0.25):  # one index beyond either end
        with pytest.raises(ValueError, match="within"):
            voxel_keys(np.array([[x, 0.0, 0.0]]), 0.5)


def _exact_reference(batches, c: int, cfg: FusionConfig, weight: float = 1.0):
    """fuse's arithmetic written out point by point in float32: per chunk (the chunking of
    fusion_blocks), per voxel, ``Σ (count · weight) · log_table[row]`` over its distinct global table rows in
    ascending order starting from 0; the chunk sums added in chunk order; then each row shifted to max 0,
    clipped at -logp_clip and rounded to float16."""
    totals: dict[int, np.ndarray] = {}
    for chunk in fusion_blocks([len(b.keys) for b in batches], cfg.chunk_points):
        pairs: dict[tuple[int, int], int] = {}
        tables = []
        for pos in chunk:
            b = batches[pos]
            base = sum(len(t) for t in tables)
            tables.append(b.log_table)
            for k, r in zip(b.keys.tolist(), b.rows.tolist(), strict=True):
                pairs[(k, base + r)] = pairs.get((k, base + r), 0) + 1
        table = np.concatenate(tables).astype(np.float32)
        sums: dict[int, np.ndarray] = {}
        for k, r in sorted(pairs):
            s = sums.setdefault(k, np.zeros(c, np.float32))
            s += (np.float32(pairs[(k, r)]) * np.float32(weight)) * table[r]
        for k, s in sums.items():
            totals[k] = totals[k] + s if k in totals else s
    keys = np.array(sorted(totals), np.int64)
    rows = np.array([totals[k] for k in keys.tolist()], np.float32).reshape(len(keys), c)
    rows -= rows.max(axis=1, keepdims=True)
    return keys, np.maximum(rows, np.float32(-cfg.logp_clip)).astype(np.float16)


@pytest.mark.parametrize("seed", range(6))
def test_fuse_is_byte_identical_to_the_reference_arithmetic(seed: int) -> None:
    """Keys and float16 log-probabilities equal, bit for bit, to the point-by-point reference on random
    batches (repeated pairs, several chunks, voxels seen in some chunks only, a weight)."""
    rng = np.random.default_rng(seed)
    c = int(rng.integers(2, 24))
    batches = []
    for _ in range(int(rng.integers(1, 9))):
        p, k = int(rng.integers(0, 3000)), int(rng.integers(1, 12))
        coords = rng.integers(-8, 8, (p, 3)) + rng.integers(-2, 2, 3) * 4
        keys = voxel_keys((coords + 0.5) * 0.2, 0.2)
        batches.append(_obs(keys, rng.integers(0, k, p), rng.dirichlet(np.full(c, 0.3), k)))
    cfg = FusionConfig(chunk_points=int(rng.integers(500, 8000)))
    weight = 0.37 if seed % 2 else 1.0
    got = fuse(batches, c, cfg, weight=weight)
    keys, logp = _exact_reference(batches, c, cfg, weight)
    np.testing.assert_array_equal(got.keys, keys)
    assert got.logp.tobytes() == logp.tobytes()
