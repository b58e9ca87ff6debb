"""Pure maths of the viewer's navigation and inspection: camera placements, scan colours, histograms.

Like :mod:`app.viewer.view_logic`, everything here takes and returns numpy arrays and does no I/O; the
session (:mod:`app.viewer.session`) moves the results into the scene and the panel.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from app.viewer import view_logic as vl

SCAN_GREY_RGB: tuple[int, int, int] = (150, 150, 150)
"""Colour of every scan point in the confidence and probability views: class colours there would mean a
second thing beside the colour scale of the voxels."""
INSPECT_RGB: tuple[int, int, int] = (0, 255, 255)
"""Marker of the inspected voxel: cyan, a colour neither the demo's class palette nor the colour scale uses
(the selection highlight is near-black)."""


HIGH_SENSOR_M = 5.0
"""A sensor more than this far above the ground under it (a drone, not a car's roof) is followed from above
the ground it looks at rather than from its own height (:func:`follow_view`)."""


def follow_view(
    pose: npt.ArrayLike,
    *,
    distance: float = 22.0,
    elevation_deg: float = 35.0,
    ahead: float = 8.0,
    ground_z: float | None = None,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Camera ``(position, look_at)`` behind and above the ego vehicle, looking along its heading.

    The heading is the sensor's +x axis (KITTI's LiDAR points forward along x), flattened onto the ground:
    ``f = (R₀₀, R₁₀, 0) / ‖·‖`` with ``R`` the rotation of ``pose`` (sensor → world). With ego position
    ``t``: ``look_at = t + ahead · f`` and
    ``position = look_at - distance · cos(e) · f + distance · sin(e) · ẑ``.
    A sensor pointing straight up (no horizontal heading) looks along world +x.

    A sensor high above the ground (``h = t_z − ground_z > HIGH_SENSOR_M``: a drone) would put ``look_at``
    in the empty air at its own height, with its points out of view below. Then ``look_at`` is on the
    ground, ``ahead + h`` in front of the sensor's foot (where a forward-and-down sensor looks), and the
    camera stands ``distance + h`` from it. A car's sensor (h ≈ 1.7 m) is followed as without ``ground_z``.

    Args:
        pose: (4, 4) sensor-to-world transform of the scan.
        distance: camera distance from ``look_at`` (metres).
        elevation_deg: angle of the camera above the ground plane.
        ahead: how far ahead of the ego position the camera looks (metres).
        ground_z: world height of the ground under the sensor (e.g. a low percentile of the scan's point
            heights), or None when unknown.
    """
    m = np.asarray(pose, dtype=np.float64).reshape(4, 4)
    f = np.array([m[0, 0], m[1, 0], 0.0])
    n = float(np.linalg.norm(f))
    f = f / n if n > 1e-9 else np.array([1.0, 0.0, 0.0])
    e = math.radians(elevation_deg)
    target = m[:3, 3] + ahead * f
    h = 0.0 if ground_z is None else float(m[2, 3] - ground_z)
    if h > HIGH_SENSOR_M:
        target = target + h * f
        target[2] = float(ground_z)  # type: ignore[arg-type]  # h > 0 only when ground_z is given
        distance += h
    position = target - distance * math.cos(e) * f + np.array([0.0, 0.0, distance * math.sin(e)])
    return position, target


def fit_view(
    points: npt.ArrayLike,
    *,
    elevation_deg: float = 50.0,
    azimuth_deg: float = 200.0,
    min_distance: float = 10.0,
    spread: float = 0.85,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None:
    """Camera ``(position, look_at)`` that shows ``points`` whole (the map, or one scan), or None when empty.

    Outliers do not stretch the view: the box is the 2nd..98th percentile per axis, ``lo``..``hi``.
    ``look_at`` is its centre, lowered to the 20th height percentile (the ground, where most content is);
    the camera orbits it (:func:`app.viewer.view_logic.orbit_view`) at
    ``max(min_distance, spread · ‖hi_xy - lo_xy‖)``.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] == 0:
        return None
    lo = np.percentile(p, 2, axis=0)
    hi = np.percentile(p, 98, axis=0)
    centre = (lo + hi) / 2.0
    centre[2] = float(np.percentile(p[:, 2], 20))
    extent = float(np.linalg.norm(hi[:2] - lo[:2]))
    return vl.orbit_view(centre, max(min_distance, spread * extent), elevation_deg, azimuth_deg)


def object_colors(instance: npt.ArrayLike, moving: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """(N, 3) colours of a scan's points by object: hue ``h = frac(id · φ⁻¹)`` (φ⁻¹ ≈ 0.618, the golden
    ratio's step: consecutive ids far apart on the colour wheel), full value for a moving object's points
    and :data:`STATIC_OBJECT_ALPHA` of the way to white for a static one's, :data:`SCAN_GREY_RGB` for
    points of no object (id 0)."""
    ids = np.asarray(instance, np.int64).reshape(-1)
    hue = np.mod(ids * 0.6180339887498949, 1.0)
    # HSV → RGB at saturation 0.85, value 0.95: each channel is v · (1 - s · clip(|6h - c| - 1, 0, 1)).
    k = np.abs(np.mod(hue[:, None] * 6.0 + np.array([0.0, 4.0, 2.0]), 6.0) - 3.0) - 1.0
    rgb = 0.95 * (1.0 - 0.85 * (1.0 - np.clip(k, 0.0, 1.0)))
    out: npt.NDArray[np.uint8] = np.rint(rgb * 255).astype(np.uint8)
    static = ~np.asarray(moving, bool).reshape(-1)
    out[static] = vl.blend(out[static], (255, 255, 255), STATIC_OBJECT_ALPHA)
    out[ids == 0] = SCAN_GREY_RGB
    return out


STATIC_OBJECT_ALPHA = 0.45
"""How far a static object's colour fades toward white in the objects view (movers keep full colour)."""


def scan_colors(
    mode: vl.ColorMode,
    labels: npt.NDArray[np.integer],
    palette: npt.ArrayLike,
    instance: npt.NDArray[np.uint32] | None = None,
    moving: npt.NDArray[np.bool_] | None = None,
) -> npt.NDArray[np.uint8]:
    """(N, 3) colours of a scan's points: class colours in the class view, object colours in the objects
    view (:func:`object_colors`; every point grey when the run has no objects), :data:`SCAN_GREY_RGB` in
    the confidence and probability views (where the voxels carry a colour scale)."""
    if mode == "class":
        return vl.class_colors(labels, palette)
    if mode == "objects" and instance is not None and moving is not None:
        return object_colors(instance, moving)
    out = np.empty((np.asarray(labels).shape[0], 3), np.uint8)
    out[:] = SCAN_GREY_RGB
    return out


SCAN_DIM_ALPHA = 0.85
"""How far a scan's points fade toward the map's dim colour while a review region is focused."""


def focus_scan_colors(colors: npt.NDArray[np.uint8], focused: bool) -> npt.NDArray[np.uint8]:
    """A scan's point colours while a review region is (``focused``) or is not focused: faded
    :data:`SCAN_DIM_ALPHA` of the way toward the map's dim colour (:func:`app.viewer.view_logic.blend`), so
    the region's highlight is the only strong colour around it; unchanged otherwise."""
    return vl.blend(colors, (235, 235, 235), SCAN_DIM_ALPHA) if focused else colors


def confidence_histograms(
    label: npt.ArrayLike, conf: npt.ArrayLike, num_classes: int, bins: int = 10
) -> npt.NDArray[np.int64]:
    """Per class, how many voxels of that label fall in each confidence bin.

    Bin ``b`` of ``bins`` equal bins over [0, 1] holds ``b/bins ≤ conf < (b+1)/bins`` (the last bin also
    holds 1.0; values outside [0, 1] are clipped into the end bins). Unlabeled voxels (label -1) count
    nowhere.

    Args:
        label: (V,) class index per voxel, -1 unlabeled.
        conf: (V,) confidence per voxel.
        num_classes: C.
        bins: number of bins ≥ 1.

    Returns:
        (C, bins) int64 counts.
    """
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    lab = np.asarray(label, dtype=np.int64).reshape(-1)
    c = np.asarray(conf, dtype=np.float64).reshape(-1)
    if lab.shape != c.shape:
        raise ValueError(f"label {lab.shape} and conf {c.shape} must have the same length")
    ok = (lab >= 0) & (lab < num_classes)
    b = np.clip(np.floor(c[ok] * bins), 0, bins - 1).astype(np.int64)
    flat = np.bincount(lab[ok] * bins + b, minlength=num_classes * bins)
    return flat.reshape(num_classes, bins).astype(np.int64)


__all__ = [
    "HIGH_SENSOR_M",
    "INSPECT_RGB",
    "SCAN_GREY_RGB",
    "confidence_histograms",
    "fit_view",
    "follow_view",
    "object_colors",
    "scan_colors",
]
