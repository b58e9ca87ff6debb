"""leap_core.selection: screen masks, front-surface depth test and the composed selection, on tiny cases
computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from leap_core.selection import (
    PinholeCamera,
    front_surface,
    pixel_of,
    polygon_mask,
    rect_mask,
    select_points,
    stroke_mask,
)


def test_polygon_mask_square_covers_pixel_centres_inside() -> None:
    # Pixel centres of a 4×4 canvas sit at 0.125, 0.375, 0.625, 0.875: the square [0.25, 0.75]² holds the
    # middle 2×2.
    mask = polygon_mask([(0.25, 0.25), (0.75, 0.25), (0.75, 0.75), (0.25, 0.75)], 4, 4)
    expected = np.zeros((4, 4), bool)
    expected[1:3, 1:3] = True
    np.testing.assert_array_equal(mask, expected)


def test_polygon_mask_concave_l_shape() -> None:
    # An L on a 4×4 canvas (pixel units ×4): the left column band x∈[0,2], y∈[0,4] plus the bottom band
    # x∈[2,4], y∈[2,4]; the top-right 2×2 quadrant is outside.
    l_shape = np.array([(0, 0), (2, 0), (2, 2), (4, 2), (4, 4), (0, 4)], float) / 4.0
    mask = polygon_mask(l_shape, 4, 4)
    expected = np.ones((4, 4), bool)
    expected[0:2, 2:4] = False
    np.testing.assert_array_equal(mask, expected)


def test_polygon_mask_self_intersecting_bow_tie_fills_both_triangles() -> None:
    # In pixel units: (0, 0.2) → (4, 3.8) → (4, 0.2) → (0, 3.8). Row centre y = 1.5 cuts the diagonals at
    # x = (1.5 - 0.2) · 4 / 3.6 ≈ 1.44 and 4 - 1.44 ≈ 2.56, so columns 0 and 3 (centres 0.5, 3.5) are
    # inside and the two middle ones are not; rows 0 and 3 cut at ≈ 0.33 / 3.67, leaving no centre inside.
    bowtie = np.array([(0, 0.2), (4, 3.8), (4, 0.2), (0, 3.8)], float) / 4.0
    mask = polygon_mask(bowtie, 4, 4)
    np.testing.assert_array_equal(
        mask,
        np.array(
            [
                [False, False, False, False],
                [True, False, False, True],
                [True, False, False, True],
                [False, False, False, False],
            ]
        ),
    )


def test_polygon_mask_rejects_a_degenerate_outline() -> None:
    with pytest.raises(ValueError, match="polygon"):
        polygon_mask([(0.1, 0.1), (0.2, 0.2)], 4, 4)
    with pytest.raises(ValueError, match="non-finite"):
        polygon_mask([(0.1, 0.1), (0.2, np.nan), (0.3, 0.1)], 4, 4)


def test_stroke_mask_single_dab_is_a_disc() -> None:
    # Centre pixel (2, 2) of a 5×5 canvas; radius 1 px reaches the four neighbours (distance 1) but not the
    # diagonals (√2).
    mask = stroke_mask([(0.5, 0.5)], 1.0, 5, 5)
    expected = np.zeros((5, 5), bool)
    expected[2, 1:4] = True
    expected[1:4, 2] = True
    np.testing.assert_array_equal(mask, expected)


def test_stroke_mask_fills_the_gap_between_far_samples() -> None:
    # Two samples 8 px apart along row 1 of a 10×3 canvas, radius 0.5: every pixel of the row between them
    # is painted although the drag reported only its ends.
    mask = stroke_mask([(0.5 / 10, 1.5 / 3), (8.5 / 10, 1.5 / 3)], 0.5, 10, 3)
    expected = np.zeros((3, 10), bool)
    expected[1, 0:9] = True
    np.testing.assert_array_equal(mask, expected)
    with pytest.raises(ValueError, match="radius_px"):
        stroke_mask([(0.5, 0.5)], 0.0, 5, 5)


def test_rect_mask_accepts_swapped_corners() -> None:
    a = rect_mask((0.75, 0.75), (0.25, 0.5), 4, 4)
    expected = np.zeros((4, 4), bool)
    expected[2, 1:3] = True
    np.testing.assert_array_equal(a, expected)


def test_front_surface_keeps_the_first_hit_within_distance() -> None:
    # Three points in the same pixel, depths 5, 5.4 and 10: with 0.5 m the first two are the front surface.
    col = np.array([3, 3, 3, 0])
    row = np.array([2, 2, 2, 0])
    depth = np.array([5.0, 5.4, 10.0, 1.0])
    splat = np.ones(4)
    occ = np.ones(4, bool)
    cand = np.array([True, True, True, False])
    np.testing.assert_array_equal(
        front_surface(col, row, depth, splat, occluder=occ, candidate=cand, distance=0.5),
        [True, True, False, False],
    )
    np.testing.assert_array_equal(
        front_surface(col, row, depth, splat, occluder=occ, candidate=cand, distance=6.0),
        [True, True, True, False],
    )
    # A front point that is not a candidate still hides the one behind it.
    cand2 = np.array([False, False, True, False])
    np.testing.assert_array_equal(
        front_surface(col, row, depth, splat, occluder=occ, candidate=cand2, distance=0.5),
        [False, False, False, False],
    )
    # A point three pixels away (beyond the 3×3 erosion at 1 px cells) hides nothing.
    col3, row3 = np.array([0, 3]), np.array([0, 0])
    np.testing.assert_array_equal(
        front_surface(
            col3,
            row3,
            np.array([1.0, 9.0]),
            np.ones(2),
            occluder=np.ones(2, bool),
            candidate=np.array([False, True]),
            distance=0.5,
        ),
        [False, True],
    )
    with pytest.raises(ValueError, match="distance"):
        front_surface(col, row, depth, splat, occluder=occ, candidate=cand, distance=-1.0)


def _camera(width: int = 9, height: int = 9) -> PinholeCamera:
    # At the origin looking along +z (identity rotation), 90° vertical field of view: f = H/2 px.
    return PinholeCamera((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), math.radians(90), width, height)


def test_select_points_front_surface_versus_through() -> None:
    cam = _camera()
    assert cam.focal_px == pytest.approx(4.5)
    # Two points straight ahead (u = v = 0.5, the centre pixel (4, 4)), 5 m and 10 m away, and one at
    # x = 5 m, z = 5 m (u = 0.5 + 0.5·1 = 1.0: the right edge, off the canvas).
    pts = np.array([(0, 0, 5.0), (0, 0, 10.0), (5.0, 0, 5.0)])
    col, row, on = pixel_of(np.array([[0.5, 0.5], [1.0, 0.5]]), 9, 9)
    assert (col.tolist(), row.tolist(), on.tolist()) == ([4, 0], [4, 0], [True, False])
    mask = rect_mask((0.4, 0.4), (0.6, 0.6), 9, 9)
    np.testing.assert_array_equal(select_points(pts, cam, mask, depth_mode="through"), [True, True, False])
    np.testing.assert_array_equal(
        select_points(pts, cam, mask, depth_mode="front", distance=0.5), [True, False, False]
    )
    np.testing.assert_array_equal(
        select_points(pts, cam, mask, depth_mode="front", distance=5.5), [True, True, False]
    )
    # Class filter after the depth test: an ineligible front point still hides the eligible one behind.
    eligible = np.array([False, True, True])
    np.testing.assert_array_equal(
        select_points(pts, cam, mask, depth_mode="front", eligible=eligible), [False, False, False]
    )
    np.testing.assert_array_equal(
        select_points(pts, cam, mask, depth_mode="through", eligible=eligible), [False, True, False]
    )
    # Behind the camera is never selected.
    behind = np.array([(0, 0, -5.0)])
    np.testing.assert_array_equal(select_points(behind, cam, mask, depth_mode="through"), [False])


def test_select_points_checks_its_inputs() -> None:
    cam = _camera()
    with pytest.raises(ValueError, match="mask"):
        select_points(np.zeros((1, 3)), cam, np.zeros((3, 3), bool))
    with pytest.raises(ValueError, match="depth_mode"):
        select_points(np.zeros((1, 3)), cam, np.zeros((9, 9), bool), depth_mode="deep")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="fov_y"):
        PinholeCamera((0, 0, 0), (1, 0, 0, 0), 0.0, 9, 9)
    with pytest.raises(ValueError, match="width_px"):
        PinholeCamera((0, 0, 0), (1, 0, 0, 0), 1.0, 0, 9)
