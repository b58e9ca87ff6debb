"""Navigation and inspection maths of the viewer (app.viewer.nav_logic), on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.viewer import nav_logic as nl


def test_follow_view_sits_behind_and_above_the_ego_heading() -> None:
    # Ego at (10, 20, 1) heading along world +y (sensor x → world y: a 90° turn about z).
    pose = np.eye(4)
    pose[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    pose[:3, 3] = (10, 20, 1)
    pos, tgt = nl.follow_view(pose, distance=10.0, elevation_deg=30.0, ahead=4.0)
    assert tgt == pytest.approx([10, 24, 1])
    # 10·cos 30° = 8.660 behind the target along -y, 10·sin 30° = 5 above it.
    assert pos == pytest.approx([10, 24 - 10 * math.cos(math.radians(30)), 6])


def test_follow_view_of_a_sensor_pointing_up_looks_along_x() -> None:
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # sensor x → world -z
    pos, tgt = nl.follow_view(pose, distance=2.0, elevation_deg=0.0, ahead=1.0)
    assert tgt == pytest.approx([1, 0, 0]) and pos == pytest.approx([-1, 0, 0])


def test_follow_view_of_a_drone_looks_at_the_ground_ahead() -> None:
    """A sensor 25 m above the ground (a survey drone) is followed looking at the ground 8 + 25 m ahead,
    from 22 + 25 m away; a car's sensor 1.73 m up is followed as without the ground height."""
    pose = np.eye(4)
    pose[:3, 3] = (5, 0, 25)
    pos, tgt = nl.follow_view(pose, distance=22.0, elevation_deg=35.0, ahead=8.0, ground_z=0.0)
    assert tgt == pytest.approx([5 + 33, 0, 0])
    e = math.radians(35)
    assert pos == pytest.approx([38 - 47 * math.cos(e), 0, 47 * math.sin(e)])
    car = np.eye(4)
    car[:3, 3] = (1, 2, 1.73)
    assert np.array_equal(nl.follow_view(car, ground_z=0.0)[0], nl.follow_view(car)[0])
    assert np.array_equal(nl.follow_view(car, ground_z=0.0)[1], nl.follow_view(car)[1])


def test_fit_view_frames_the_percentile_box() -> None:
    # 101 points on x ∈ [0, 100] (y = z = 0): the 2..98 percentile box is x ∈ [2, 98], centre x = 50,
    # diagonal 96 → distance 0.85 · 96 = 81.6.
    pts = np.zeros((101, 3))
    pts[:, 0] = np.arange(101)
    pos, tgt = nl.fit_view(pts, elevation_deg=90.0)  # type: ignore[misc]
    assert tgt == pytest.approx([50, 0, 0])
    assert pos == pytest.approx([50, 0, 81.6])
    assert nl.fit_view(np.zeros((0, 3))) is None
    # A single point still gets min_distance.
    pos1, _ = nl.fit_view([(1.0, 2.0, 3.0)], elevation_deg=90.0)  # type: ignore[misc]
    assert pos1 == pytest.approx([1, 2, 13])


def test_scan_colors_are_grey_outside_the_class_view() -> None:
    palette = np.array([[255, 0, 0], [0, 255, 0]], np.uint8)
    labels = np.array([0, 1, -1], np.int16)
    assert nl.scan_colors("class", labels, palette).tolist() == [[255, 0, 0], [0, 255, 0], [128, 128, 128]]
    for mode in ("confidence", "class_probability"):
        assert nl.scan_colors(mode, labels, palette).tolist() == [list(nl.SCAN_GREY_RGB)] * 3


def test_confidence_histograms_bin_per_class() -> None:
    label = [0, 0, 1, 1, 1, -1]
    conf = [0.05, 1.0, 0.5, 0.55, 0.99, 0.5]
    h = nl.confidence_histograms(label, conf, num_classes=3, bins=4)
    # Bins [0, .25), [.25, .5), [.5, .75), [.75, 1]: class 0 → bins 0 and 3; class 1 → 2, 2, 3.
    assert h.tolist() == [[1, 0, 0, 1], [0, 0, 2, 1], [0, 0, 0, 0]]
    with pytest.raises(ValueError, match="bins"):
        nl.confidence_histograms(label, conf, 3, bins=0)
    with pytest.raises(ValueError, match="same length"):
        nl.confidence_histograms([0], [0.1, 0.2], 1)


def test_object_colors_mark_movers_and_leave_points_of_no_object_grey() -> None:
    # Id 1: hue 0.618 (blue); a moving and a static point of it, a point of id 2 (hue 0.236: green) and
    # one of no object.
    colors = nl.object_colors(np.array([1, 1, 2, 0], np.uint32), np.array([True, False, True, False]))
    moving, static, other, none = (c.astype(int) for c in colors)
    assert tuple(none) == nl.SCAN_GREY_RGB
    assert moving.argmax() == 2 and other.argmax() == 1  # blue-ish for id 1, green-ish for id 2
    # Saturation 0.85 at value 0.95: the strongest channel 242, the weakest 36.
    assert moving.max() == 242 and moving.min() == 36
    # The static point is the same hue faded toward white.
    assert tuple(static) == tuple(np.rint(0.55 * moving + 0.45 * 255).astype(int))
    # Only the objects view colours by object; the class view keeps class colours.
    labels = np.array([0, 1, 0, -1], np.int16)
    palette = np.array([[10, 20, 30], [40, 50, 60]], np.uint8)
    inst, mov = np.array([1, 1, 2, 0], np.uint32), np.array([True, False, True, False])
    assert (nl.scan_colors("objects", labels, palette, inst, mov) == colors).all()
    assert nl.scan_colors("class", labels, palette, inst, mov)[1].tolist() == [40, 50, 60]


def test_the_inspected_object_line_escapes_class_names() -> None:
    from app.viewer.panel_nav import object_html
    from app.viewer.records import ObjectInfo

    found = ObjectInfo(
        run_id=1,
        track=7,
        class_index=0,
        scans=12,
        moving=True,
        speed=1.44,
        points=85,
        frame_id="000003",
        corrected_to=1,
    )
    text = object_html(found, ["<b>car</b>", "truck"])
    assert "Object <b>7</b>" in text and "&lt;b&gt;car&lt;/b&gt;" in text and "<b>truck</b>" in text
    assert "seen in <b>12</b> scans" in text and "<b>moving</b> at 1.4 m/s" in text and "85 points" in text
