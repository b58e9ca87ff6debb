"""Review regions: identity, content signature, ranking, best observing scan, image box (hand-computed)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from app.viewer import region_logic as rl
from app.viewer import view_logic as vl
from leap_core import review
from leap_core.fusion import voxel_keys

# Six voxels: three in cell (2, 0, 0) at 4 m, two in cell (0, 0, 0), one far away in (7, 7, 0).
CENTRES = np.array(
    [[0.5, 0.5, 0], [1.5, 0.5, 0], [10.5, 0, 0], [11, 1, 0], [11.5, 0.5, 0], [30, 30, 0]], np.float32
)


def test_region_id_is_the_cell_in_world_coordinates() -> None:
    cell = int(voxel_keys(np.array([[5.0, -1.0, 0.5]]), 4.0)[0])
    assert review.region_id(cell, 4.0) == "4m:1,-1,0"
    # Every point of the same 4 m cell has the same identity, whatever run produced it.
    other = int(voxel_keys(np.array([[7.9, -3.99, 3.9]]), 4.0)[0])
    assert review.region_id(other, 4.0) == "4m:1,-1,0"
    assert review.region_id(int(voxel_keys(np.array([[8.0, -1.0, 0.5]]), 4.0)[0]), 4.0) == "4m:2,-1,0"
    assert review.region_id(int(voxel_keys(np.array([[1.0, 1.0, 1.0]]), 2.5)[0]), 2.5) == "2.5m:0,0,0"


def test_rank_cells_groups_rows_and_breaks_ties() -> None:
    score = np.array([0.25, 0.75, 0.0, 1.0, 0.5, 0.0], np.float32)
    cand = np.array([True, True, True, True, True, False])
    cells = review.rank_cells(CENTRES, score, cand, 4.0)
    # Both cells average 0.5; the cell with more candidates comes first.
    assert [c.rows.tolist() for c in cells] == [[2, 3, 4], [0, 1]]
    assert [c.score for c in cells] == [0.5, 0.5]
    assert review.region_id(cells[0].cell, 4.0) == "4m:2,0,0"
    assert review.region_id(cells[1].cell, 4.0) == "4m:0,0,0"
    assert cells[1].centre == pytest.approx((1.0, 0.5, 0.0)) and cells[1].extent == pytest.approx(0.5)
    # Equal score and count: the smaller cell key first ((0,0,0) packs below (7,7,0)).
    tie = review.rank_cells(CENTRES, np.zeros(6), np.array([True, False, False, False, False, True]), 4.0)
    assert [review.region_id(c.cell, 4.0) for c in tie] == ["4m:0,0,0", "4m:7,7,0"]
    # Highest first for the disagreement queue, and the limit.
    top = review.rank_cells(CENTRES, score, cand, 4.0, ascending=False, min_count=1, limit=1)
    assert len(top) == 1 and top[0].rows.tolist() == [2, 3, 4]
    low = review.rank_cells(CENTRES, np.array([0.1, 0.3, 0.9, 0.9, 0.9, 0]), cand, 4.0)
    assert [c.score for c in low] == pytest.approx([0.2, 0.9])


def test_view_logic_regions_carry_identity_and_rows() -> None:
    score = np.array([0.25, 0.75, 0.0, 1.0, 0.5, 0.0], np.float32)
    regions = rl.rank_regions(CENTRES, score, np.array([True] * 5 + [False]), 4.0)
    assert [(r.id, r.count, r.rows.tolist()) for r in regions] == [
        ("4m:2,0,0", 3, [2, 3, 4]),
        ("4m:0,0,0", 2, [0, 1]),
    ]


def _sig(keys: list[int], labels: list[int]) -> str:
    blob = np.asarray(keys, "<i8").tobytes() + np.asarray(labels, "<i2").tobytes()
    return hashlib.blake2b(blob, digest_size=8).hexdigest()


def test_region_signature_changes_exactly_when_the_cells_content_changes() -> None:
    keys = voxel_keys(CENTRES, 0.5)
    order = np.argsort(keys)
    centres, keys = CENTRES[order], keys[order]
    label = np.array([1, 2, 3, 4, 5, 6], np.int16)[order]
    cells = voxel_keys(np.array([[0.5, 0.5, 0], [10.5, 0, 0], [50, 50, 0]]), 4.0)
    sigs = review.region_signatures(centres, keys, label, cells, 4.0)
    in_a = np.flatnonzero(np.isin(order, [0, 1]))
    in_b = np.flatnonzero(np.isin(order, [2, 3, 4]))
    # The formula: BLAKE2b-64 of the cell's keys (ascending) then their labels; an empty cell hashes b"".
    assert sigs[0] == _sig(keys[in_a].tolist(), label[in_a].tolist())
    assert sigs[1] == _sig(keys[in_b].tolist(), label[in_b].tolist())
    assert sigs[2] == hashlib.blake2b(b"", digest_size=8).hexdigest()
    # A class change in cell B changes B's signature only.
    relabelled = label.copy()
    relabelled[in_b[0]] = 9
    again = review.region_signatures(centres, keys, relabelled, cells, 4.0)
    assert again[0] == sigs[0] and again[1] != sigs[1] and again[2] == sigs[2]
    # Same content, cells asked in another order: same signatures (identity does not depend on rank).
    assert review.region_signatures(centres, keys, label, cells[::-1], 4.0) == sigs[::-1]


def test_nearest_scans_and_best_observer() -> None:
    positions = np.array([[0, 0, 0], [10, 0, 0], [3, 4, 0], [-3, 0, 0]], float)
    assert review.nearest_scans(positions, (0, 0, 0), 3).tolist() == [0, 3, 2]
    assert review.nearest_scans(positions, (0, 0, 0), 0).tolist() == []
    # Most points seen by the camera wins over most LiDAR points; then most points; then the earliest.
    assert review.best_observer([0, 5, 5, 2], [40, 6, 9, 50]) == 2
    assert review.best_observer([0, 0], [3, 7]) == 1
    assert review.best_observer([1, 1], [4, 4]) == 0
    assert review.best_observer([0, 0], [0, 0]) is None
    assert review.best_observer([], []) is None
    with pytest.raises(ValueError, match="same length"):
        review.best_observer([1], [1, 2])


def test_image_box_and_draw_box() -> None:
    assert review.image_box(np.zeros((0, 2)), 100, 50) is None
    assert review.image_box([[10.2, 20.0], [30.0, 25.7]], 100, 50, pad=2) == (8, 18, 32, 28)
    assert review.image_box([[1.0, 1.0], [99.5, 49.9]], 100, 50, pad=6) == (0, 0, 99, 49)
    img = np.zeros((6, 8, 3), np.uint8)
    out = review.draw_box(img, (1, 1, 5, 4), (255, 0, 200), thickness=1)
    painted = out[:, :, 0] == 255
    expected = np.zeros((6, 8), bool)
    expected[1, 1:6] = expected[4, 1:6] = True
    expected[1:5, 1] = expected[1:5, 5] = True
    assert (painted == expected).all() and not img.any()


def test_dim_outside_keeps_the_focused_voxels() -> None:
    colors = np.array([[0, 0, 0], [200, 100, 0], [40, 40, 40]], np.uint8)
    out = vl.dim_outside(colors, np.array([7, 3, 9]), np.array([3]), toward=(200, 200, 200), alpha=0.75)
    # (1-0.75)*0 + 0.75*200 = 150; (0.25*40 + 150) = 160
    assert out.tolist() == [[150, 150, 150], [200, 100, 0], [160, 160, 160]]


def test_regions_rank_by_expected_wrong_so_a_speck_comes_after_a_large_uncertain_area() -> None:
    # A speck of 2 very uncertain voxels and an area of 3 fairly uncertain ones.
    conf = np.array([0.1, 0.1, 0.6, 0.6, 0.5, 1.0], np.float32)
    cand = np.array([True, True, True, True, True, False])
    wrong = rl.confidence_wrong(conf)
    assert wrong.tolist() == pytest.approx([0.9, 0.9, 0.4, 0.4, 0.5, 0.0])
    by_score = rl.rank_regions(CENTRES, conf, cand, 4.0)
    assert [r.id for r in by_score] == ["4m:0,0,0", "4m:2,0,0"]  # lowest mean confidence first
    ranked = rl.rank_regions(CENTRES, conf, cand, 4.0, wrong=wrong)
    # Expected wrong voxels: speck 0.9 + 0.9 = 1.8, area 0.4 + 0.4 + 0.5 = 1.3 ... the speck still wins here,
    assert [(r.id, r.expected_wrong) for r in ranked] == [
        ("4m:0,0,0", pytest.approx(1.8)),
        ("4m:2,0,0", pytest.approx(1.3)),
    ]
    # ... but not once the area's voxels are a little less sure: 3 × 0.7 = 2.1 > 1.8.
    conf2 = np.array([0.1, 0.1, 0.3, 0.3, 0.3, 1.0], np.float32)
    ranked2 = rl.rank_regions(CENTRES, conf2, cand, 4.0, wrong=rl.confidence_wrong(conf2))
    assert [r.id for r in ranked2] == ["4m:2,0,0", "4m:0,0,0"]
    assert [r.id for r in rl.rank_regions(CENTRES, conf2, cand, 4.0)] == ["4m:0,0,0", "4m:2,0,0"]
    # The minimum size drops the speck.
    sized = rl.rank_regions(CENTRES, conf2, cand, 4.0, wrong=rl.confidence_wrong(conf2), min_count=3)
    assert [r.id for r in sized] == ["4m:2,0,0"]
    # Disagreement: the disagreeing share times the camera-labelled points.
    rate = np.array([1.0, 1.0, 0.5, 0.5, 0.25, 0.0], np.float32)
    observed = np.array([1, 1, 10, 10, 8, 0])
    assert rl.disagreement_wrong(rate, observed).tolist() == [1.0, 1.0, 5.0, 5.0, 2.0, 0.0]
    dis = rl.rank_regions(
        CENTRES, rate, cand, 4.0, wrong=rl.disagreement_wrong(rate, observed), ascending=False
    )
    assert [(r.id, r.expected_wrong) for r in dis] == [("4m:2,0,0", 12.0), ("4m:0,0,0", 2.0)]


def test_the_minimum_region_size_is_bounded() -> None:
    from app.viewer.records import SessionConfig
    from leap_core.errors import ConfigError

    assert SessionConfig().queue_min_count == 10
    with pytest.raises(ConfigError, match=r"queue_min_count: must be in \[1, 100000\], got 0"):
        SessionConfig(queue_min_count=0)
    with pytest.raises(ConfigError, match="queue_min_count"):
        SessionConfig(queue_min_count=10**9)


def test_zoom_box_keeps_the_aspect_and_the_image() -> None:
    # A 4-pixel box in a 200 × 100 image: a crop of a quarter of the width (50 × 25), centred on it.
    assert review.zoom_box((98, 48, 101, 51), 200, 100) == (75, 38, 124, 62)
    # Near a corner the crop shifts inside the image.
    assert review.zoom_box((0, 0, 3, 3), 200, 100) == (0, 0, 49, 24)
    assert review.zoom_box((196, 96, 199, 99), 200, 100) == (150, 75, 199, 99)
    # A box larger than a quarter: the crop holds it (tall box → height rules: 60 px high → 120 wide).
    assert review.zoom_box((10, 20, 29, 79), 200, 100) == (0, 20, 119, 79)
    # Never larger than the image.
    assert review.zoom_box((0, 0, 199, 99), 200, 100) == (0, 0, 199, 99)


def test_crop_zoom_enlarges_the_crop_to_the_image_size() -> None:
    img = np.zeros((4, 8, 3), np.uint8)
    img[1, 2] = (255, 0, 0)
    img[2, 3] = (0, 255, 0)
    out = review.crop_zoom(img, (2, 1, 3, 2))  # 2 × 2 crop → 8 × 4 image, each pixel 4 × 2
    assert out.shape == img.shape
    assert (out[:2, :4] == (255, 0, 0)).all() and (out[2:, 4:] == (0, 255, 0)).all()
    assert (out[:2, 4:] == 0).all() and (out[2:, :4] == 0).all()


def test_focus_highlight_and_faded_scan_colours() -> None:
    from app.viewer import nav_logic as nl

    cols = np.array([[255, 0, 0], [0, 0, 0]], np.uint8)
    hi = rl.highlight_colors(cols)
    # 0.65 · c + 0.35 · (0, 255, 255)
    assert hi.tolist() == [[166, 89, 89], [0, 89, 89]]
    assert nl.focus_scan_colors(cols, False) is cols
    faded = nl.focus_scan_colors(cols, True)
    assert faded.tolist() == [[238, 200, 200], [200, 200, 200]]  # 0.15 · c + 0.85 · 235


def test_disagreement_colour_mode_colours_and_thresholds_the_rate() -> None:
    label = np.array([0, 1, 0], np.int16)
    conf = np.array([0.9, 0.9, 0.9], np.float32)
    rate = np.array([0.0, 1.0, 0.5], np.float32)
    palette = np.array([[10, 20, 30], [40, 50, 60]], np.uint8)
    state = vl.ViewState(mode="disagreement", threshold=0.4)
    rows, colors = vl.render_view(state, label, conf, palette, rate)
    assert rows.tolist() == [1, 2]  # the rate, not the confidence, meets the threshold
    assert colors.tolist() == vl.scalar_colors(rate[[1, 2]]).tolist()
    with pytest.raises(ValueError, match="disagreement mode needs"):
        vl.render_view(state, label, conf, palette, None)
