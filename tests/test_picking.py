"""Ray picking of voxels (leap_core.picking), on hand-computed rays and cubes."""

from __future__ import annotations

import numpy as np
import pytest

from leap_core.picking import pick_voxel, ray_box_entry


def test_ray_along_x_enters_the_nearest_cube_on_its_line() -> None:
    centres = [(5.0, 0.0, 0.0), (3.0, 0.0, 0.0), (3.0, 2.0, 0.0), (-3.0, 0.0, 0.0)]
    # Cubes of edge 1: x ∈ [4.5, 5.5] enters at 4.5, [2.5, 3.5] at 2.5; y = 2 is off the line; x = -3 is
    # behind the origin.
    t = ray_box_entry((0, 0, 0), (2, 0, 0), centres, 1.0)
    assert t.tolist() == [4.5, 2.5, np.inf, np.inf]
    pick = pick_voxel((0, 0, 0), (1, 0, 0), centres, 1.0)
    assert pick is not None and pick.index == 1 and pick.distance == 2.5


def test_diagonal_ray_distance_is_in_metres() -> None:
    # Ray (1, 1, 0)/√2 from the origin; cube around (4, 4, 0) with edge 2 spans [3, 5]² in x, y: both slabs
    # are entered at parameter 3 along (1, 1, 0), i.e. 3·√2 metres.
    t = ray_box_entry((0, 0, 0), (1, 1, 0), [(4.0, 4.0, 0.0)], 2.0)
    assert t[0] == pytest.approx(3 * np.sqrt(2))


def test_ray_grazing_a_cube_parallel_to_a_face() -> None:
    # d_y = d_z = 0: the cube counts only if the origin's y and z lie within half an edge of its centre.
    centres = [(3.0, 0.5, 0.0), (3.0, 0.51, 0.0)]
    t = ray_box_entry((0, 0, 0), (1, 0, 0), centres, 1.0)
    assert t[0] == 2.5 and t[1] == np.inf


def test_origin_inside_a_cube_picks_it_at_distance_zero() -> None:
    pick = pick_voxel((0.1, 0, 0), (0, 0, -1), [(0.0, 0.0, -5.0), (0.0, 0.0, 0.0)], 1.0)
    assert pick is not None and pick.index == 1 and pick.distance == 0.0


def test_miss_and_max_distance_give_none() -> None:
    assert pick_voxel((0, 0, 0), (0, 0, 1), [(5.0, 0.0, 0.0)], 1.0) is None
    assert pick_voxel((0, 0, 0), (1, 0, 0), [(5.0, 0.0, 0.0)], 1.0, max_distance=4.0) is None
    assert pick_voxel((0, 0, 0), (1, 0, 0), np.zeros((0, 3)), 1.0) is None


def test_bad_rays_are_refused() -> None:
    with pytest.raises(ValueError, match="non-zero direction"):
        ray_box_entry((0, 0, 0), (0, 0, 0), [(1.0, 0.0, 0.0)], 1.0)
    with pytest.raises(ValueError, match="edge"):
        ray_box_entry((0, 0, 0), (1, 0, 0), [(1.0, 0.0, 0.0)], 0.0)
    with pytest.raises(ValueError, match=r"centres must be \(N, 3\)"):
        ray_box_entry((0, 0, 0), (1, 0, 0), [1.0, 0.0, 0.0], 1.0)
