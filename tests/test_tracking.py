"""Segments, tracks, class votes and motion (leap_core.tracking) on small hand-made scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from leap_core.errors import ConfigError
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.tracking import (
    TrackingConfig,
    associate,
    box_gap,
    euclidean_segments,
    mask_segments,
    present_ids,
    recent_velocity,
    segment_summary,
    track_ids,
    track_table,
)


def _blob(centre: tuple[float, float, float], n: int, rng: np.random.Generator) -> np.ndarray:
    return np.asarray(centre) + rng.uniform(-0.3, 0.3, (n, 3))


def test_euclidean_segments_split_at_the_radius_and_drop_small_ones() -> None:
    rng = np.random.default_rng(0)
    xyz = np.concatenate([_blob((5, 0, 0), 20, rng), _blob((0, 0, 0), 30, rng), _blob((9, 9, 0), 3, rng)])
    seg = euclidean_segments(xyz, radius=0.5, min_points=5)
    # Numbered by first point: the blob at x = 5 comes first in the array, so it is segment 0.
    assert seg.tolist() == [0] * 20 + [1] * 30 + [-1] * 3
    centroid, hist, box = segment_summary(xyz, seg, np.eye(2)[np.r_[np.zeros(20, int), np.ones(33, int)]], 2)
    assert centroid[0] == pytest.approx(xyz[:20].mean(axis=0))
    assert hist.tolist() == [[20, 0], [0, 30]]
    assert box[1] == pytest.approx([*xyz[20:50, :2].min(axis=0), *xyz[20:50, :2].max(axis=0)])
    assert euclidean_segments(np.zeros((0, 3)), 0.5, 1).shape == (0,)


def test_associate_is_one_to_one_within_the_gate() -> None:
    rows, cols = associate([[0, 0, 0], [1, 0, 0]], [[0.9, 0, 0], [0.1, 0, 0], [50, 0, 0]], gate=2.0)
    assert dict(zip(rows.tolist(), cols.tolist(), strict=True)) == {0: 1, 1: 0}
    rows, cols = associate([[0, 0, 0]], [[5, 0, 0]], gate=2.0)
    assert rows.size == cols.size == 0


def test_constant_velocity_keeps_ids_of_fast_neighbours_apart() -> None:
    # Two cars 1.5 m apart side by side, both at 7 m/s (0.7 m a scan at 10 Hz), and one parked car; the
    # moving cars' segments are closer to the other car's last position than a gate would separate
    # without the motion model after a missed scan.
    cfg = TrackingConfig(gate=1.0, max_missed=2)
    times = np.arange(12) * 0.1
    cents = []
    for k, t in enumerate(times):
        frame = [[7 * t, 0, 0], [7 * t, 1.5, 0], [20, 5, 0]]
        cents.append(np.array(frame if k != 5 else frame[2:]))  # scan 5 misses both movers
    ids = track_ids(cents, times, cfg)
    assert ids[0].tolist() == [1, 2, 3]
    for k, row in enumerate(ids):
        assert row.tolist() == ([1, 2, 3] if k != 5 else [3])
    votes = [np.tile([[1.0, 0], [1, 0], [0, 1]], (1, 1))[-len(c) :] for c in cents]
    boxes = [np.c_[c[:, :2] - 2, c[:, :2] + 2] for c in cents]  # 4 m boxes around each centroid
    table = track_table(ids, cents, votes, boxes, times, cfg)
    assert table.moving.tolist() == [True, True, False]
    assert table.velocity[0] == pytest.approx([7, 0, 0])
    assert table.scans.tolist() == [11, 11, 12]
    assert table.label.tolist() == [0, 0, 1]


def test_a_track_gone_longer_than_max_missed_comes_back_with_a_new_id() -> None:
    cfg = TrackingConfig(max_missed=1)
    cents = [np.array([[0.0, 0, 0]]), np.zeros((0, 3)), np.zeros((0, 3)), np.array([[0.0, 0, 0]])]
    assert [x.tolist() for x in track_ids(cents, np.arange(4) * 0.1, cfg)] == [[1], [], [], [2]]


def test_class_vote_is_over_all_scans_and_a_growing_view_is_not_motion() -> None:
    cfg = TrackingConfig()
    times = np.arange(30) * 0.1
    # A parked car 10..14 m ahead seen first on its near end only, then whole: its centroid moves 2 m in
    # 3 s (0.7 m/s) while its footprint never leaves the box of its widest view.
    far = [10 + 4 * min(1.0, 0.1 + k / 20) for k in range(30)]
    cents = [np.array([[(10 + x) / 2, 0, 0]]) for x in far]
    boxes = [np.array([[10, -1, x, 1]]) for x in far]
    votes = [np.array([[0.0, 5, 1]]) if k < 20 else np.array([[0.0, 0, 7]]) for k in range(30)]
    ids = track_ids(cents, times, cfg)
    table = track_table(ids, cents, votes, boxes, times, cfg)
    assert [x.tolist() for x in ids] == [[1]] * 30
    assert table.label.tolist() == [1]  # 100 votes for class 1 against 20 + 70 for class 2
    assert np.linalg.norm(table.velocity[0]) > cfg.moving_speed and table.sweep[0] == pytest.approx(0)
    assert table.moving.tolist() == [False]


def test_config_bounds() -> None:
    with pytest.raises(ConfigError, match="cluster_radius"):
        TrackingConfig(cluster_radius=0)
    with pytest.raises(ConfigError, match="vote: must be 'moving' or 'all'"):
        TrackingConfig(vote="static")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="segments: must be 'masks' or 'euclidean'"):
        TrackingConfig(segments="voxels")  # type: ignore[arg-type]


def _two_tracks(cfg: TrackingConfig) -> SequenceTracks:
    """One scan's view of two tracks: a car at 7 m/s (track 1) and a static segment of a person beside a
    bicycle (track 2, 3 person and 2 bicycle points of classes 0-2: car 0, person 1, bicycle 2; the vote
    over its 12 scans says person). Scan 0's rows: 0-3 the car, 4-8 the pair, 9 untracked."""
    times = np.arange(12) * 0.1
    cents = [np.array([[7 * t, 0, 0], [20, 5, 0]]) for t in times]
    votes = [np.array([[4.0, 0, 0], [0, 3, 2]]) for _ in times]
    boxes = [np.c_[c[:, :2] - 1, c[:, :2] + 1] for c in cents]
    ids = track_ids(cents, times, cfg)
    table = track_table(ids, cents, votes, boxes, times, cfg)
    assert table.moving.tolist() == [True, False] and table.label.tolist() == [0, 1]
    rows = np.arange(9, dtype=np.int32)
    track = np.array([1] * 4 + [2] * 5, np.int32)
    return SequenceTracks(("000000",), np.array([0, 9]), rows, track, table)


def test_static_tracks_keep_their_points_classes_by_default() -> None:
    own = np.array([2, 2, 0, 0, 1, 1, 1, 2, 2, -1], np.int16)  # the car's points partly called bicycle
    label, instance, moving = _two_tracks(TrackingConfig()).point_objects("000000", own)
    # The mover's points take its class (the map's label at a mover is its trail); the static pair keeps
    # person and bicycle, each with the track's id.
    assert label.tolist() == [0, 0, 0, 0, 1, 1, 1, 2, 2, -1]
    assert instance.tolist() == [1] * 4 + [2] * 5 + [0]
    assert moving.tolist() == [True] * 4 + [False] * 6
    label, instance, _ = _two_tracks(TrackingConfig(vote="all")).point_objects("000000", own)
    assert label.tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 1, -1]
    assert instance.tolist() == [1] * 4 + [2] * 5 + [0]


def test_the_vote_setting_survives_tracks_npz(tmp_path: Path) -> None:
    for vote in ("moving", "all"):
        tracks = _two_tracks(TrackingConfig(vote=vote))  # type: ignore[arg-type]
        tracks.save(tmp_path / "tracks.npz")
        back = SequenceTracks.load(tmp_path / "tracks.npz")
        assert back.table.voted.tolist() == ([True, False] if vote == "moving" else [True, True])


def test_grid_clustering_joins_chains_and_keeps_two_metres_apart() -> None:
    chain = np.c_[np.arange(0, 10, 0.45), np.zeros(23), np.zeros(23)]  # a wall's row of returns
    assert set(euclidean_segments(chain, 0.5, 1).tolist()) == {0}
    two = np.array([[0.0, 0, 0], [0.2, 0, 0], [2.2, 0, 0], [2.4, 0, 0]])
    assert euclidean_segments(two, 0.5, 1).tolist() == [0, 0, 1, 1]


def test_two_people_side_by_side_with_a_mask_each_are_two_segments() -> None:
    # Two people 0.3 m apart (one Euclidean cluster at 0.5 m), one 2D instance mask each (ids 3 and 7);
    # a point outside the image (instance 0) at person B's shoulder; a third person outside the image,
    # 5 m away; a 2-point instance under the size floor.
    rng = np.random.default_rng(1)
    a = rng.uniform([0.0, 0, 0], [0.3, 0.3, 1.7], (40, 3))
    b = rng.uniform([0.6, 0, 0], [0.9, 0.3, 1.7], (40, 3))
    limb = np.array([[1.05, 0.1, 1.2]])  # 0.15 m beyond B's edge, nearest to B's points
    far = rng.uniform([5.0, 0, 0], [5.3, 0.3, 1.7], (30, 3))
    tiny = np.array([[9.0, 0, 0], [9.1, 0, 0]])
    xyz = np.concatenate([a, b, limb, far, tiny])
    ins = np.r_[np.full(40, 3), np.full(40, 7), 0, np.zeros(30, int), [9, 9]]
    seg = mask_segments(xyz, ins, radius=0.5, min_points=5)
    assert seg.tolist() == [0] * 40 + [1] * 41 + [2] * 30 + [-1, -1]
    # Euclidean clustering alone joins the two people.
    assert set(euclidean_segments(xyz[:81], 0.5, 5).tolist()) == {0}
    # A mask's points stay one segment even where they are apart in 3D (depth clustering kept them).
    apart = np.concatenate([a, a + np.array([3.0, 0, 0])])
    assert set(mask_segments(apart, np.full(80, 4), 0.5, 5).tolist()) == {0}
    # An uncovered point takes no mask whose points are in another Euclidean cluster.
    lone = np.concatenate([a, far])
    got = mask_segments(lone, np.r_[np.full(40, 2), np.zeros(30, int)], 0.5, 5)
    assert got.tolist() == [0] * 40 + [1] * 30
    assert mask_segments(np.zeros((0, 3)), np.zeros(0, int), 0.5, 1).shape == (0,)
    with pytest.raises(ValueError, match="instance ids"):
        mask_segments(xyz, ins[:-1], 0.5, 5)


def test_an_oncoming_car_whose_visible_part_jumps_keeps_one_track() -> None:
    # A car driving at 7 m/s whose segment, in three scans, takes in a neighbour's points or loses its
    # rear: its centroid jumps 0.8 m aside and 0.9 m back. The step between the last two centroids would
    # predict the next scan 2.4 m off (beyond the 2 m gate); the slope over the last five does not.
    times = np.arange(20) * 0.1
    jump = np.array([0.8, -0.9, 0])
    cents = [np.array([[0.0, 7 * t, -1]]) + (jump if k in (6, 11, 15) else 0) for k, t in enumerate(times)]
    assert [x.tolist() for x in track_ids(cents, times, TrackingConfig())] == [[1]] * 20
    two_step = track_ids(cents, times, TrackingConfig(velocity_scans=2, max_speed=0))
    assert len({int(x[0]) for x in two_step}) == 4  # the last two observations: cut three times


def test_a_mover_passing_a_parked_car_does_not_take_its_id() -> None:
    # A car at 8 m/s passes 1.2 m beside a parked car (centroids 2.8 m apart). In scan 9 the parked car's
    # visible part is pulled 0.8 m towards the mover (the mover hides its middle); in scan 10 the mover
    # shows a second, small segment on that side. A velocity from the last two centroids sends the parked
    # car's track after the mover's fragment and gives the parked car a new id.
    times = np.arange(20) * 0.1
    cents = []
    for k, t in enumerate(times):
        mover, parked = [2 + 8 * t, 0.0, -1.0], [10.0, 2.8 - (0.8 if k == 9 else 0), -1.0]
        cents.append(np.array([mover, parked] + ([[mover[0] + 0.5, 1.0, -1.0]] if k == 10 else [])))
    ids = track_ids(cents, times, TrackingConfig())
    assert all(x[:2].tolist() == [1, 2] for x in ids)
    assert ids[10][2] == 3  # the fragment starts a short track of its own
    old = track_ids(cents, times, TrackingConfig(velocity_scans=2, max_speed=0))
    assert old[10].tolist() == [1, 3, 2] and old[11].tolist() == [1, 3]


def test_a_new_track_may_move_up_to_max_speed_before_it_has_a_velocity() -> None:
    # A car first seen at 20 m/s: 2 m, then 2.3 m between its first two scans (its view grows).
    times = np.arange(6) * 0.1
    cents = [np.array([[0.0, 0, 0]])] + [np.array([[2.3 + 2 * k, 0, 0]]) for k in range(5)]
    assert [x.tolist() for x in track_ids(cents, times, TrackingConfig(max_speed=5))] == [[1]] * 6
    assert [x.tolist() for x in track_ids(cents, times, TrackingConfig(max_speed=0))][:2] == [[1], [2]]


def test_recent_velocity_is_the_least_squares_slope() -> None:
    t = np.array([[np.nan, 0.0, 0.1, 0.2], [np.nan, np.nan, np.nan, 0.3]])
    c = np.zeros((2, 4, 3))
    c[0, 1:, 0] = [0.0, 1.2, 1.6]  # slope: Σ(t - t̄)(x - x̄) / Σ(t - t̄)² = 0.16 / 0.02 = 8
    assert recent_velocity(t, c).ravel().tolist() == pytest.approx([8, 0, 0, 0, 0, 0])


def test_box_distance_is_the_gap_between_ground_boxes() -> None:
    gap = box_gap([[0, 0, 4, 2]], [[1, 1, 2, 3], [7, 6, 8, 7], [5, -1, 6, 1]])
    assert gap[0].tolist() == pytest.approx([0.0, 5.0, 1.0])
    # A partial view's box overlaps its track's predicted box though its centroid is 1.9 m off.
    rows, cols = associate([[2.0, 1, 0]], [[0.1, 1, 0]], 0.5, [[0, 0, 4, 2]], [[0, 0.5, 0.2, 1.5]])
    assert (rows.tolist(), cols.tolist()) == ([0], [0])
    assert associate([[2.0, 1, 0]], [[0.1, 1, 0]], 0.5)[0].size == 0


def test_only_tracks_with_points_keep_an_id_in_order_of_birth() -> None:
    # Tracks 1..5; track 2's points were all stuff in the map and track 4's all corrected: ids close up.
    new_id, present = present_ids([np.array([1, 1, 3]), np.array([], np.int64), np.array([5, 3])], 5)
    assert present.tolist() == [True, False, True, False, True]
    assert new_id.tolist() == [0, 1, 0, 2, 0, 3]
    table = track_table(
        [np.arange(1, 6)], [np.zeros((5, 3))], [np.eye(5)], [np.zeros((5, 4))], np.zeros(1), TrackingConfig()
    ).take(present)
    assert table.label.tolist() == [0, 2, 4] and table.vote_evidence().share.size == 3
