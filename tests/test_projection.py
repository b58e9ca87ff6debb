"""Projection, depth clustering and painting, on hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from leap_core.errors import DatasetError
from leap_core.fusion import log_table
from leap_core.labelers.base import SoftMasks
from leap_core.projection import (
    Painted,
    Projected,
    ProjectionConfig,
    cluster_pairs,
    combination_words,
    depth_cluster_filter,
    largest_depth_cluster,
    paint,
    project_points,
    unique_word_rows,
)
from leap_core.types import UNLABELED

# Pixel = (10x + 5z, 10y + 4z) / z: focal 10, principal point (5, 4), camera frame = LiDAR frame.
P = np.array([[10.0, 0, 5, 0], [0, 10, 4, 0], [0, 0, 1, 0]])


def test_project_points_hand_computed() -> None:
    xyz = np.array(
        [
            [0.0, 0.0, 2.0],  # (10, 8)/2 -> u 5, v 4
            [1.0, -0.5, 4.0],  # (30, 11)/4 = (7.5, 2.75) -> rounds to u 8, v 3
            [0.0, 0.0, -3.0],  # behind the camera
            [0.0, 0.0, 0.4],  # closer than min_depth 0.5
            [2.0, 0.0, 1.0],  # u = 25, right of a 10-px-wide image
            [-1.0, 0.0, 2.0],  # u = 0: on the left edge, kept
            [-0.56, 0.0, 1.0],  # u = -0.6 -> rounds to -1, dropped
            [-0.54, 0.0, 1.0],  # u = -0.4 -> rounds to 0, kept
            [0.0, 0.36, 1.0],  # v = 7.6 -> rounds to 8 = height, dropped
        ],
        dtype=np.float32,
    )
    pr = project_points(xyz, P, height=8, width=10, min_depth=0.5)
    np.testing.assert_array_equal(pr.idx, [0, 1, 5, 7])
    np.testing.assert_array_equal(pr.u, [5, 8, 0, 0])
    np.testing.assert_array_equal(pr.v, [4, 3, 4, 4])
    np.testing.assert_allclose(pr.depth, [2, 4, 2, 1])
    assert pr.idx.dtype == np.int64 and pr.u.dtype == np.int32 and pr.depth.dtype == np.float32


def test_project_points_uses_translation_and_ignores_extra_columns() -> None:
    m = P.copy()
    m[:, 3] = [10.0, 0.0, 1.0]  # depth = z + 1, a = 10x + 5z + 10
    xyz = np.array([[0.0, 0.0, 1.0, 0.7]], dtype=np.float32)  # remission column ignored
    pr = project_points(xyz, m, height=8, width=10)
    # a = 15, b = 4, d = 2 -> (7.5, 2) -> u 8, v 2
    np.testing.assert_array_equal([pr.u[0], pr.v[0]], [8, 2])
    assert pr.depth[0] == 2.0


def test_project_points_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="xyz"):
        project_points(np.zeros((3, 2)), P, 8, 10)
    with pytest.raises(ValueError, match="lidar_to_image"):
        project_points(np.zeros((3, 3)), np.eye(3), 8, 10)


def test_largest_cluster_keeps_foreground_person_before_wall() -> None:
    # One mask: a person at ~10 m and the wall behind it at ~25 m bleeding into the mask.
    depth = np.array([25.0, 10.0, 10.2, 25.3, 10.4, 10.5, 25.1, 10.3])
    keep = largest_depth_cluster(depth, gap=1.0)
    np.testing.assert_array_equal(keep, [False, True, True, False, True, True, False, True])


def test_largest_cluster_ties_go_to_the_nearest_and_gap_is_strict() -> None:
    np.testing.assert_array_equal(largest_depth_cluster([20.0, 5.0, 20.5, 5.5], 1.0), [0, 1, 0, 1])
    # A difference equal to the gap does not split (strictly larger splits).
    np.testing.assert_array_equal(largest_depth_cluster([1.0, 2.0, 3.0, 5.0], 1.0), [1, 1, 1, 0])
    # The largest cluster wins even when it is behind.
    np.testing.assert_array_equal(largest_depth_cluster([5.0, 5.2, 30.0, 30.1, 30.2], 1.0), [0, 0, 1, 1, 1])


def test_depth_cluster_filter_is_per_mask_and_respects_min_points() -> None:
    depth = np.array([10.0, 10.2, 10.4, 25.0, 25.2, 40.0])
    member = np.array(
        [
            [1, 1, 1, 1, 1, 0],  # person mask bleeding onto the wall: keeps points 0-2
            [0, 0, 0, 1, 1, 1],  # wall mask with a far outlier: keeps 3, 4
            [1, 0, 0, 0, 0, 1],  # 2 points only: below min_points 3, kept whole
        ],
        dtype=bool,
    )
    out = depth_cluster_filter(member, depth, gap=1.0, min_points=3)
    expected = np.array([[1, 1, 1, 0, 0, 0], [0, 0, 0, 1, 1, 0], [1, 0, 0, 0, 0, 1]], dtype=bool)
    np.testing.assert_array_equal(out, expected)
    # Without the minimum, the 2-point mask keeps its nearest point (tie 1 vs 1).
    out0 = depth_cluster_filter(member, depth, gap=1.0, min_points=0)
    np.testing.assert_array_equal(out0[2], [1, 0, 0, 0, 0, 0])
    assert not depth_cluster_filter(np.zeros((2, 6), bool), depth, 1.0).any()


def _two_mask_image() -> SoftMasks:
    # 2×3 image. Mask A covers row 0 columns 0-1, mask B covers row 0 columns 1-2.
    a = np.array([[1, 1, 0], [0, 0, 0]], bool)
    b = np.array([[0, 1, 1], [0, 0, 0]], bool)
    return SoftMasks.from_dense(np.stack([a, b]), [[1.0, 0.0, 0.0], [0.0, 0.5, 0.5]], [0.8, 0.2])


def test_paint_combo_table_is_confidence_weighted_average() -> None:
    soft = _two_mask_image()
    proj = Projected(
        idx=np.array([10, 11, 12, 13, 14]),
        u=np.array([0, 1, 2, 0, 1], np.int32),
        v=np.array([0, 0, 0, 1, 0], np.int32),
        depth=np.full(5, 5.0, np.float32),
    )
    painted = paint(soft, proj, ProjectionConfig(depth_clustering=False))
    # Point 13 (row 1) is under no mask. Points 11 and 14 share the combination {A, B}.
    np.testing.assert_array_equal(painted.point_idx, [10, 11, 12, 14])
    per_point = painted.table[painted.rows]
    expected = np.array(
        [
            [1.0, 0.0, 0.0],  # A only
            [0.8, 0.1, 0.1],  # (0.8·[1,0,0] + 0.2·[0,.5,.5]) / (0.8 + 0.2)
            [0.0, 0.5, 0.5],  # B only
            [0.8, 0.1, 0.1],
        ]
    )
    np.testing.assert_allclose(per_point, expected, atol=1e-6)
    assert painted.table.shape == (3, 3)  # three distinct combinations, not four points
    assert painted.rows[1] == painted.rows[3]
    np.testing.assert_array_equal(painted.point_labels(16)[[10, 11, 12, 13, 14, 15]], [0, 0, 1, -1, 0, -1])
    np.testing.assert_allclose(painted.point_confidence(16)[[10, 11, 12, 13]], [1.0, 0.8, 0.5, 0.0])


def test_paint_depth_clustering_removes_bleed_onto_background() -> None:
    # 1×8 image: the person mask covers all 8 columns, the wall mask the last 3.
    person = np.ones((1, 8), bool)
    wall = np.zeros((1, 8), bool)
    wall[0, 5:] = True
    soft = SoftMasks.from_dense(np.stack([person, wall]), [[1.0, 0.0], [0.0, 1.0]], [0.9, 0.9])
    depth = np.array([10.0, 10.1, 10.2, 10.3, 10.4, 25.0, 25.1, 25.2], np.float32)
    proj = Projected(np.arange(8), np.arange(8, dtype=np.int32), np.zeros(8, np.int32), depth)
    filtered = paint(soft, proj, ProjectionConfig(cluster_gap=1.0))
    np.testing.assert_array_equal(filtered.point_labels(8), [0, 0, 0, 0, 0, 1, 1, 1])
    np.testing.assert_allclose(filtered.table[filtered.rows][5:], [[0.0, 1.0]] * 3)
    # Without the filter the wall points average both masks: [0.5, 0.5].
    raw = paint(soft, proj, ProjectionConfig(depth_clustering=False))
    np.testing.assert_allclose(raw.table[raw.rows][5:], [[0.5, 0.5]] * 3)


@pytest.mark.parametrize("num_masks", [5, 20, 70])  # 20: one 64-bit word of several bytes; 70: several words
def test_paint_matches_dense_pixel_probabilities(num_masks: int) -> None:
    rng = np.random.default_rng(num_masks)
    h, w, c = 12, 17, 4
    masks = rng.random((num_masks, h, w)) < 0.15
    probs = rng.dirichlet(np.ones(c), num_masks)
    soft = SoftMasks.from_dense(masks, probs, rng.uniform(0.2, 1.0, num_masks))
    n = 300
    proj = Projected(
        idx=np.arange(n) * 2,
        u=rng.integers(0, w, n).astype(np.int32),
        v=rng.integers(0, h, n).astype(np.int32),
        depth=rng.uniform(1, 50, n).astype(np.float32),
    )
    painted = paint(soft, proj, ProjectionConfig(depth_clustering=False))
    dense = soft.pixel_probs()
    covered = masks[:, proj.v, proj.u].any(axis=0)
    np.testing.assert_array_equal(painted.point_idx, proj.idx[covered])
    np.testing.assert_allclose(painted.table[painted.rows], dense[proj.v, proj.u][covered], atol=1e-5)
    assert len(np.unique(painted.rows)) == painted.table.shape[0]


def test_paint_without_masks_or_points_is_empty() -> None:
    soft = SoftMasks.empty(4, 5, 3)
    uv = np.array([0, 1], np.int32)
    proj = Projected(np.arange(2), uv, uv, np.ones(2, np.float32))
    painted = paint(soft, proj)
    assert len(painted) == 0 and painted.table.shape == (0, 3)
    np.testing.assert_array_equal(painted.point_labels(3), [UNLABELED] * 3)


def test_painted_observations_and_save_load(tmp_path) -> None:
    table = np.array([[0.5, 0.5], [1.0, 0.0]], np.float32)
    painted = Painted(np.array([1, 3]), np.array([1, 0], np.int32), table)
    keys = np.array([100, 101, 102, 103], np.int64)
    obs = painted.to_observations(keys, prob_floor=1e-3)
    np.testing.assert_array_equal(obs.keys, [101, 103])
    np.testing.assert_array_equal(obs.rows, [1, 0])
    np.testing.assert_allclose(obs.log_table, log_table(painted.table, 1e-3))
    path = tmp_path / "obs.npz"
    painted.save(path)
    back = Painted.load(path)
    np.testing.assert_array_equal(back.point_idx, painted.point_idx)
    np.testing.assert_array_equal(back.rows, painted.rows)
    np.testing.assert_array_equal(back.table, painted.table)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match=r"bad\.npz"):
        Painted.load(bad)
    np.savez(bad, point_idx=np.array([0]), rows=np.array([5]), table=np.ones((2, 2)))
    with pytest.raises(DatasetError, match="rows index outside"):
        Painted.load(bad)


def test_largest_cluster_flattens_its_input() -> None:
    depth = np.array([25.0, 10.0, 10.2, 25.3, 10.4])
    expected = [False, True, True, False, True]
    np.testing.assert_array_equal(largest_depth_cluster(depth[None, :], 1.0), expected)  # a (1, P) row
    np.testing.assert_array_equal(largest_depth_cluster(depth[:, None], 1.0), expected)  # a (P, 1) column
    assert largest_depth_cluster(depth, 1.0).dtype == np.bool_  # a mask callers index with


def test_painted_types_empty_and_full() -> None:
    """Painted arrays keep their documented types (int64 indices, int32 rows, float32 table) also when
    empty, and per-point outputs are int16 labels and float32 confidences."""
    empty = Painted.empty(3)
    assert (empty.point_idx.shape, empty.rows.shape, empty.table.shape) == ((0,), (0,), (0, 3))
    assert (empty.point_idx.dtype, empty.rows.dtype, empty.table.dtype) == (np.int64, np.int32, np.float32)
    table = np.array([[0.5, 0.5], [0.9, 0.1]], np.float32)
    painted = Painted(np.array([1, 3]), np.array([1, 0], np.int32), table)
    conf = painted.point_confidence(4)
    assert conf.dtype == np.float32 and conf.tolist() == [0.0, np.float32(0.9), 0.0, 0.5]
    labels = painted.point_labels(4)
    assert labels.dtype == np.int16 and labels.tolist() == [UNLABELED, 0, UNLABELED, 0]
    obs = painted.to_observations(np.array([100, 101, 102, 103], np.int32), prob_floor=1e-3)
    assert obs.keys.dtype == np.int64 and obs.keys.tolist() == [101, 103]


def test_project_points_default_min_depth_and_empty_image_size() -> None:
    # Default min_depth 0.5 m: a point 1 m ahead is kept, one 0.4 m ahead is not.
    pr = project_points(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.4]], np.float32), P, height=8, width=10)
    assert pr.idx.tolist() == [0]
    for h, w in ((0, 10), (8, 0), (-1, 10)):
        with pytest.raises(ValueError, match="image size"):
            project_points(np.zeros((1, 3)), P, h, w)


def test_project_points_one_pixel_image_and_depth_exactly_at_the_minimum() -> None:
    # Pixel = (10x + 5z, 10y + 4z) / z: x = -0.5, y = -0.4 at z = 1 lands on pixel (0, 0).
    one = project_points(np.array([[-0.5, -0.4, 1.0]], np.float32), P, height=1, width=1)
    assert (one.u.tolist(), one.v.tolist()) == ([0], [0])
    assert one.u.dtype == np.int32 and one.v.dtype == np.int32
    # Kept only when d > min_depth: a point at exactly 0.5 m is dropped.
    at = project_points(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5001]], np.float32), P, 8, 10, min_depth=0.5)
    assert at.idx.tolist() == [1]


def test_depth_cluster_filter_types_shapes_and_exact_gaps() -> None:
    member = np.array([[1, 1, 1, 0]])  # integer 0/1 membership
    depth = np.array([5.0, 5.1, 9.0, 5.2])
    out = depth_cluster_filter(member, depth, gap=1.0)
    assert out.dtype == np.bool_ and out.tolist() == [[True, True, False, False]]
    np.testing.assert_array_equal(depth_cluster_filter(member, depth[:, None], gap=1.0), out)  # (P, 1) depths
    # float32 depths 0.73531526 and 1.73531532 are 1.0000000596 m apart: more than the 1 m gap, although
    # their float32 difference rounds to exactly 1.0.
    a, b = np.float32(0.7353152632713318), np.float32(1.7353153228759766)
    assert float(b) - float(a) > 1.0 and b - a == np.float32(1.0)
    np.testing.assert_array_equal(largest_depth_cluster(np.array([a, b, b], np.float32), 1.0), [0, 1, 1])


def test_depth_cluster_filter_keeps_masks_apart_in_its_single_sort() -> None:
    # Mask 0: one cluster 10.0-11.5 m (0.5 m steps); mask 1: one point at 10.2 m, inside mask 0's range.
    # The one sort by (mask, depth) must not interleave the masks, which would split mask 0 in two.
    member = np.array([[1, 1, 1, 1, 0], [0, 0, 0, 0, 1]], bool)
    depth = np.array([10.0, 10.5, 11.0, 11.5, 10.2])
    np.testing.assert_array_equal(depth_cluster_filter(member, depth, gap=1.0), member)
    with pytest.raises(ValueError, match="member must be"):
        depth_cluster_filter(member, depth[:4], gap=1.0)


def test_paint_keeps_every_combination_of_64_masks_apart() -> None:
    """Membership patterns are hashed as unsigned 64-bit words: two patterns that share masks 48-51 and
    57-63 (as float64 bits: an all-ones exponent, i.e. NaN) and differ in one more mask get their own rows."""
    shared = [*range(48, 52), *range(57, 64)]
    dense = np.zeros((64, 1, 2), bool)
    dense[shared, 0, :] = True
    dense[0, 0, 0] = True  # pixel (0, 0): the shared masks + mask 0
    dense[1, 0, 1] = True  # pixel (1, 0): the shared masks + mask 1
    probs = np.full((64, 2), 0.5)
    probs[0], probs[1] = [1.0, 0.0], [0.0, 1.0]
    soft = SoftMasks.from_dense(dense, probs, np.ones(64))
    u, v = np.array([0, 1], np.int32), np.zeros(2, np.int32)
    proj = Projected(np.array([0, 1]), u, v, np.ones(2, np.float32))
    painted = paint(soft, proj, ProjectionConfig(depth_clustering=False))
    table = painted.table[painted.rows]
    np.testing.assert_allclose(table, [[6.5 / 12, 5.5 / 12], [5.5 / 12, 6.5 / 12]], rtol=1e-6)


def _at_pixels(u: list[int], v: list[int]) -> Projected:
    """Points 0..n-1 at pixels (u, v), 1 m deep."""
    n = len(u)
    return Projected(np.arange(n), np.array(u, np.int32), np.array(v, np.int32), np.ones(n, np.float32))


def test_paint_edge_cases_one_mask_one_point_and_pixels_outside() -> None:
    one_mask = SoftMasks.from_dense(np.ones((1, 2, 3), bool), [[0.25, 0.75]], [0.5])
    painted = paint(one_mask, _at_pixels([2], [1]))
    assert painted.point_idx.tolist() == [0] and painted.table.tolist() == [[0.25, 0.75]]
    assert painted.rows.dtype == np.int32 and painted.table.dtype == np.float32
    assert len(paint(one_mask, _at_pixels([], []))) == 0  # masks but no point
    for u, v in ((3, 0), (0, 2)):  # one past the 3-wide or the 2-high mask
        with pytest.raises(ValueError, match="exceed"):
            paint(one_mask, _at_pixels([u], [v]))


def test_paint_passes_the_gap_and_the_minimum_to_depth_clustering() -> None:
    # Mask 0 covers row 0 (4 points at 10, 10.5, 12, 12.5 m: two clusters 1.5 m apart with a 1 m gap);
    # mask 1 covers row 1 (2 points at 10 and 20 m: fewer than min_cluster_points = 3, kept whole).
    dense = np.array([[[1, 1, 1, 1], [0, 0, 0, 0]], [[0, 0, 0, 0], [1, 1, 0, 0]]], bool)
    soft = SoftMasks.from_dense(dense, [[1.0, 0.0], [0.0, 1.0]], [1, 1])
    proj = _at_pixels([0, 1, 2, 3, 0, 1], [0, 0, 0, 0, 1, 1])
    proj = Projected(proj.idx, proj.u, proj.v, np.array([10, 10.5, 12, 12.5, 10, 20], np.float32))
    painted = paint(soft, proj, ProjectionConfig(cluster_gap=1.0, min_cluster_points=3))
    # Mask 0 keeps its nearest cluster (a tie of 2 and 2 points); mask 1 keeps both points.
    assert painted.point_idx.tolist() == [0, 1, 4, 5]
    # A mask that covers none of the points: no observation, an empty (0, C) table.
    corner = SoftMasks.from_dense(np.array([[[1, 0, 0, 0], [0, 0, 0, 0]]], bool), [[0.5, 0.5]], [1])
    empty = paint(corner, _at_pixels([3], [1]))
    assert len(empty) == 0 and empty.table.shape == (0, 2)


def test_projection_config_bounds_and_painted_load_checks(tmp_path) -> None:
    ProjectionConfig(min_depth=0.0, cluster_gap=0.01, min_cluster_points=0)  # the smallest valid values
    ProjectionConfig(min_depth=1000.0, cluster_gap=1000.0, min_cluster_points=10**6)  # the largest
    for bad in (
        {"min_depth": -0.1},
        {"min_depth": 1e4},
        {"cluster_gap": 0.0},
        {"cluster_gap": 1e-320},
        {"min_cluster_points": -1},
        {"min_cluster_points": 10**6 + 1},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            ProjectionConfig(**bad)
    path = tmp_path / "obs.npz"
    # Other integer / float types are read into the documented ones.
    np.savez(path, point_idx=np.array([4], np.int32), rows=np.array([0], np.int64), table=np.ones((1, 2)))
    back = Painted.load(path)
    assert (back.point_idx.dtype, back.rows.dtype, back.table.dtype) == (np.int64, np.int32, np.float32)
    for idx, rows, table in (
        (np.array([0, 1]), np.array([0]), np.ones((1, 2))),  # rows for another number of points
        (np.array([[0]]), np.array([[0]]), np.ones((1, 2))),  # 2-D indices
        (np.array([0]), np.array([0]), np.ones(2)),  # 1-D table
    ):
        np.savez(path, point_idx=idx, rows=rows, table=table)
        with pytest.raises(DatasetError, match="inconsistent shapes"):
            Painted.load(path)
    # A row index one past the table, or between its row and column counts, is refused; the error names
    # the file.
    for rows, table in (
        (np.array([-1]), np.ones((2, 2))),
        (np.array([2]), np.ones((2, 2))),
        (np.array([3]), np.ones((2, 5))),
    ):
        np.savez(path, point_idx=np.array([0]), rows=rows, table=table)
        with pytest.raises(DatasetError, match=r"obs\.npz.*rows index outside"):
            Painted.load(path)


def test_unique_word_rows_equals_numpys_unique_over_rows() -> None:
    rng = np.random.default_rng(3)
    for width in (1, 2, 3):
        # six rows repeated; flipping the last word's low bit splits rows that share their first words
        base = rng.integers(0, 2**63, (6, width), dtype=np.uint64)
        words = base[rng.integers(0, 6, 200)]
        words[:, -1] ^= rng.integers(0, 2, 200, dtype=np.uint64)
        uniq, inv = unique_word_rows(words)
        want, want_inv = np.unique(words, axis=0, return_inverse=True)
        np.testing.assert_array_equal(uniq, want)
        np.testing.assert_array_equal(inv, want_inv.reshape(-1))
        assert inv.dtype == np.int64 and uniq.dtype == np.uint64
    uniq, inv = unique_word_rows(np.zeros((0, 2), np.uint64))
    assert uniq.shape == (0, 2) and inv.shape == (0,) and inv.dtype == np.int64


def test_combination_words_are_the_packed_membership_bits() -> None:
    """For 65 masks (two words, the second holding one bit): point p's row is
    ``np.packbits(member, axis=0).T`` padded to 16 bytes and read as little-endian uint64."""
    rng = np.random.default_rng(4)
    member = rng.random((65, 30)) < 0.2
    member[64, :5] = True  # the last mask covers some points
    m_idx, p_idx = np.nonzero(member)
    words = combination_words(m_idx, p_idx, 30, 65)
    assert words.shape == (30, 2) and words.dtype == np.uint64
    packed = np.zeros((30, 16), np.uint8)
    packed[:, :9] = np.packbits(member, axis=0).T
    np.testing.assert_array_equal(words, packed.view("<u8"))


def test_cluster_pairs_compares_depths_in_float64() -> None:
    """float32 depths 0.1 and 0.6 are 0.50000002 m apart (in float64), more than a 0.5 m gap: two clusters of
    one point each, the nearer kept. (In float32 the difference rounds to exactly 0.5: one cluster.)"""
    depth = np.array([0.1, 0.6], np.float32)
    ms, ps = cluster_pairs(np.array([0, 0]), np.array([0, 1]), depth, 1, 0.5)
    assert ms.tolist() == [0] and ps.tolist() == [0]
