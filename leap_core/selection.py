"""Screen-space selection of 3D points seen by a pinhole camera: lasso, brush, box, front surface.

Pure functions for the review viewer's selection tools (no viewer, no web code). A tool's outline is drawn
on the canvas in *normalised screen coordinates* ``(u, v)``: (0, 0) top-left, (1, 1) bottom-right. It is
rasterised once into a boolean mask of the canvas's pixels (:func:`polygon_mask`, :func:`stroke_mask`,
:func:`rect_mask`), and every point is tested by looking up the pixel it projects to: O(N + W·H) instead of
O(N · polygon vertices), which keeps a lasso over millions of voxels fast.

*Front surface only* keeps the candidates within ``distance`` of the first surface hit along their view
ray, found with a coarse z-buffer (:func:`front_surface`); *through* keeps every candidate.

Camera convention (viser's, OpenCV): ``p_world = R · p_cam + t`` with ``R`` from the quaternion ``wxyz``,
+z forward, +x right, +y down.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

DepthMode = Literal["front", "through"]
"""``front``: only the first surface along each view ray (within a distance); ``through``: everything."""

MAX_CANVAS_PX = 8192
"""Largest canvas edge rasterised (a larger canvas is an error, not a silent multi-GB mask)."""


@dataclass(frozen=True)
class PinholeCamera:
    """A viewer camera: pose, vertical field of view and canvas size.

    Raises ``ValueError`` naming the field when a value is out of range.
    """

    position: tuple[float, float, float]
    """Camera centre t (world)."""
    wxyz: tuple[float, float, float, float]
    """Orientation quaternion (w, x, y, z); normalised on use."""
    fov_y: float
    """Vertical field of view in radians, in (0, π)."""
    width_px: int
    """Canvas width in pixels (1..:data:`MAX_CANVAS_PX`)."""
    height_px: int
    """Canvas height in pixels (1..:data:`MAX_CANVAS_PX`)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.fov_y < math.pi:
            raise ValueError(f"fov_y must lie in (0, π) radians, got {self.fov_y}")
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            if not 1 <= value <= MAX_CANVAS_PX:
                raise ValueError(f"{name} must lie in [1, {MAX_CANVAS_PX}], got {value}")
        if not np.isfinite(np.linalg.norm(self.wxyz)) or np.linalg.norm(self.wxyz) == 0:
            raise ValueError(f"wxyz must be a non-zero quaternion, got {self.wxyz}")

    @property
    def aspect(self) -> float:
        """Canvas width / height."""
        return self.width_px / self.height_px

    @property
    def focal_px(self) -> float:
        """Focal length in pixels: ``f = (H / 2) / tan(fov_y / 2)``."""
        return 0.5 * self.height_px / math.tan(self.fov_y / 2.0)


def quat_to_matrix(wxyz: Sequence[float]) -> npt.NDArray[np.float64]:
    """(3, 3) rotation of a unit quaternion (w, x, y, z) (normalised first)."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def camera_coords(
    points: npt.ArrayLike, position: Sequence[float], wxyz: Sequence[float]
) -> npt.NDArray[np.float64]:
    """(N, 3) camera-frame coordinates ``p_cam = Rᵀ(p - t)`` of (N, 3) world points."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return (p - np.asarray(position, dtype=np.float64)) @ quat_to_matrix(wxyz)  # rows are Rᵀ(p - t)


def project_to_screen(
    points: npt.ArrayLike,
    position: Sequence[float],
    wxyz: Sequence[float],
    fov_y: float,
    aspect: float,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    """Normalised screen coordinates of world points seen by a camera.

    With ``p_cam = Rᵀ(p - t)``: ``u = ½ + ½ · (x/z) / (aspect · tan(fov_y/2))``,
    ``v = ½ + ½ · (y/z) / tan(fov_y/2)``, so (0, 0) is the top-left and (1, 1) the bottom-right corner.

    Args:
        points: (N, 3) world coordinates.
        position: camera position t.
        wxyz: camera orientation quaternion.
        fov_y: vertical field of view in radians.
        aspect: canvas width / height.

    Returns:
        ``(uv (N, 2), in_front (N,) bool)``; uv is meaningless where ``in_front`` is False.
    """
    cam = camera_coords(points, position, wxyz)
    return _screen_of(cam, fov_y, aspect)


def _screen_of(
    cam: npt.NDArray[np.float64], fov_y: float, aspect: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    z = cam[:, 2]
    in_front = z > 1e-6
    safe_z = np.where(in_front, z, 1.0)
    ty = math.tan(fov_y / 2.0)
    uv = np.empty((cam.shape[0], 2))
    uv[:, 0] = 0.5 + 0.5 * cam[:, 0] / safe_z / (aspect * ty)
    uv[:, 1] = 0.5 + 0.5 * cam[:, 1] / safe_z / ty
    return uv, in_front


# ------------------------------------------------------------------------------------ screen masks
def _check_outline(name: str, outline: npt.ArrayLike, min_points: int) -> npt.NDArray[np.float64]:
    arr = np.asarray(outline, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < min_points:
        raise ValueError(
            f"{name} must be (K, 2) normalised screen points with K >= {min_points}, got {arr.shape}"
        )
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} holds non-finite coordinates")
    return arr


def polygon_mask(polygon: npt.ArrayLike, width: int, height: int) -> npt.NDArray[np.bool_]:
    """(H, W) bool: pixels whose centre lies inside a closed polygon (even-odd rule).

    Pixel (row i, column j) has its centre at ``(u, v) = ((j + ½) / W, (i + ½) / H)``. For every pixel row the
    polygon's edges are cut by the row's centre line (an edge counts when its end points straddle it,
    half-open so a vertex on the line is counted once); the crossings toggle "inside" from their column
    on, and a cumulative sum along the row gives the parity.

    Args:
        polygon: (K, 2) normalised screen vertices, K >= 3; the last joins the first.
        width, height: canvas size in pixels.
    """
    poly = _check_outline("polygon", polygon, 3)
    x = poly[:, 0] * width
    y = poly[:, 1] * height
    x2, y2 = np.roll(x, -1), np.roll(y, -1)
    rows = np.arange(height, dtype=np.float64) + 0.5  # (H,)
    yc = rows[:, None]
    straddle = (y[None, :] <= yc) != (y2[None, :] <= yc)  # (H, K)
    dy = np.where(y2 == y, 1.0, y2 - y)
    xcross = x[None, :] + (yc - y[None, :]) * ((x2 - x) / dy)[None, :]  # (H, K)
    # Column from which a crossing flips pixels: the first whose centre lies right of the crossing.
    col = np.clip(np.ceil(xcross - 0.5), 0, width).astype(np.int64)
    toggles = np.zeros((height, width + 1), np.int32)
    ri, ki = np.nonzero(straddle)
    np.add.at(toggles, (ri, col[ri, ki]), 1)
    inside: npt.NDArray[np.bool_] = (np.cumsum(toggles[:, :width], axis=1) & 1).astype(bool)
    return inside


def stroke_mask(stroke: npt.ArrayLike, radius_px: float, width: int, height: int) -> npt.NDArray[np.bool_]:
    """(H, W) bool: pixels whose centre lies within ``radius_px`` of a brush stroke (a polyline).

    The stroke is resampled every ``radius_px / 2`` pixels along each segment, and a disc is stamped at
    every sample, so a fast drag leaves no gaps.

    Args:
        stroke: (K, 2) normalised screen points along the drag, K >= 1.
        radius_px: brush radius in pixels (> 0).
        width, height: canvas size in pixels.
    """
    pts = _check_outline("stroke", stroke, 1) * np.array([width, height], np.float64)
    if not radius_px > 0:
        raise ValueError(f"radius_px must be > 0, got {radius_px}")
    samples = [pts[:1]]
    step = max(radius_px / 2.0, 0.5)
    for a, b in itertools.pairwise(pts):
        n = max(1, math.ceil(float(np.linalg.norm(b - a)) / step))
        t = np.arange(1, n + 1, dtype=np.float64)[:, None] / n
        samples.append(a + t * (b - a))
    centres = np.concatenate(samples)
    mask = np.zeros((height, width), bool)
    r = math.ceil(radius_px)
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    for cx, cy in centres:
        # Pixel centres (j + ½, i + ½) within the radius of (cx, cy).
        j0, i0 = math.floor(cx - 0.5), math.floor(cy - 0.5)
        jj, ii = j0 + dx, i0 + dy
        disc = (jj + 0.5 - cx) ** 2 + (ii + 0.5 - cy) ** 2 <= radius_px * radius_px
        ok = disc & (jj >= 0) & (jj < width) & (ii >= 0) & (ii < height)
        mask[ii[ok], jj[ok]] = True
    return mask


def rect_mask(
    corner_a: Sequence[float], corner_b: Sequence[float], width: int, height: int
) -> npt.NDArray[np.bool_]:
    """(H, W) bool: pixels whose centre lies in the screen rectangle spanned by two normalised corners."""
    lo = np.minimum(np.asarray(corner_a, np.float64), np.asarray(corner_b, np.float64))
    hi = np.maximum(np.asarray(corner_a, np.float64), np.asarray(corner_b, np.float64))
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    rows = (v >= lo[1]) & (v <= hi[1])
    cols = (u >= lo[0]) & (u <= hi[0])
    inside: npt.NDArray[np.bool_] = rows[:, None] & cols[None, :]
    return inside


def pixel_of(
    uv: npt.NDArray[np.float64], width: int, height: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """(column, row, on_screen) of normalised screen positions: ``col = ⌊u·W⌋``, ``row = ⌊v·H⌋``."""
    col = np.floor(uv[:, 0] * width)
    row = np.floor(uv[:, 1] * height)
    on = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    return np.where(on, col, 0).astype(np.int64), np.where(on, row, 0).astype(np.int64), on


# ---------------------------------------------------------------------------------- front surface
def front_surface(
    col: npt.NDArray[np.int64],
    row: npt.NDArray[np.int64],
    depth: npt.NDArray[np.floating],
    splat_px: npt.NDArray[np.floating],
    *,
    occluder: npt.NDArray[np.bool_],
    candidate: npt.NDArray[np.bool_],
    distance: float,
) -> npt.NDArray[np.bool_]:
    """(N,) bool: candidates within ``distance`` of the first surface hit along their view ray.

    A z-buffer over square cells of ``c`` pixels: ``c`` = the median on-screen size ``splat_px`` of the
    candidates (at least 1), so neighbouring points of one surface fall in neighbouring cells. Each
    occluder writes its depth into its cell (the cell keeps the minimum); the buffer is then eroded with a
    3×3 minimum so a surface whose points are spread a little wider than one cell still covers every
    cell it spans (a point just beside a front object's silhouette counts as behind it). A candidate is
    kept when ``depth ≤ zbuf[cell] + distance``.

    Only occluders whose cell lies in the candidates' bounding box (grown by one cell) are buffered, so the
    cost follows the selected area, not the whole map.

    Args:
        col, row: (N,) pixel of each point (:func:`pixel_of`).
        depth: (N,) distance from the camera centre along the point's view ray.
        splat_px: (N,) drawn size of each point on screen in pixels.
        occluder: (N,) bool, points that hide what lies behind them (visible, in front, on screen).
        candidate: (N,) bool, points the tool's outline covers (a subset of ``occluder`` is expected).
        distance: tolerance (m) behind the first hit, >= 0.
    """
    if distance < 0:
        raise ValueError(f"distance must be >= 0, got {distance}")
    keep = np.zeros(candidate.shape[0], bool)
    cand = np.flatnonzero(candidate)
    if cand.size == 0:
        return keep
    cell = max(1.0, float(np.median(splat_px[cand])))
    ccol = (col / cell).astype(np.int64)
    crow = (row / cell).astype(np.int64)
    c0, c1 = ccol[cand].min() - 1, ccol[cand].max() + 1
    r0, r1 = crow[cand].min() - 1, crow[cand].max() + 1
    occ = np.flatnonzero(occluder & (ccol >= c0) & (ccol <= c1) & (crow >= r0) & (crow <= r1))
    gw, gh = c1 - c0 + 1, r1 - r0 + 1
    zbuf = np.full(gh * gw, np.inf)
    np.minimum.at(zbuf, (crow[occ] - r0) * gw + (ccol[occ] - c0), depth[occ])
    z2 = zbuf.reshape(gh, gw)
    padded = np.pad(z2, 1, constant_values=np.inf)
    eroded = z2.copy()
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            np.minimum(eroded, padded[di : di + gh, dj : dj + gw], out=eroded)
    first = eroded[crow[cand] - r0, ccol[cand] - c0]
    keep[cand] = depth[cand] <= first + distance
    return keep


# ------------------------------------------------------------------------------------------ select
def select_points(
    points: npt.ArrayLike,
    camera: PinholeCamera,
    mask: npt.NDArray[np.bool_],
    *,
    depth_mode: DepthMode = "front",
    distance: float = 0.5,
    splat_size: float = 0.2,
    eligible: npt.NDArray[np.bool_] | None = None,
) -> npt.NDArray[np.bool_]:
    """(N,) bool: the points a screen mask selects, seen from ``camera``.

    A point is a candidate when it lies in front of the camera and projects into a True pixel of ``mask``.
    ``depth_mode="front"`` then keeps only candidates on the first surface (:func:`front_surface`, every
    point in front of the camera acting as occluder, each drawn ``splat_size`` metres wide, i.e.
    ``splat_size · f / z`` pixels); ``"through"`` keeps them all. Last, ``eligible`` (e.g. "currently
    labelled class X") filters the result, after the depth test, so an ineligible point in front still hides
    what is behind it.

    Args:
        points: (N, 3) world positions (the points drawn, in draw order irrelevant).
        camera: the viewer camera; ``mask`` must be (camera.height_px, camera.width_px).
        mask: (H, W) bool screen mask of the tool's outline.
        depth_mode: ``front`` or ``through``.
        distance: front-surface tolerance in metres.
        splat_size: on-screen point size in world metres (the voxel edge for a voxel map).
        eligible: (N,) bool filter, or None.
    """
    if mask.shape != (camera.height_px, camera.width_px):
        canvas = (camera.height_px, camera.width_px)
        raise ValueError(f"mask is {mask.shape} but the camera canvas is {canvas}")
    if depth_mode not in ("front", "through"):
        raise ValueError(f"depth_mode must be 'front' or 'through', got {depth_mode!r}")
    cam = camera_coords(points, camera.position, camera.wxyz)
    uv, in_front = _screen_of(cam, camera.fov_y, camera.aspect)
    col, row, on = pixel_of(uv, camera.width_px, camera.height_px)
    visible = in_front & on
    selected = visible & mask[row, col]
    if depth_mode == "front" and selected.any():
        depth = np.sqrt(np.einsum("ij,ij->i", cam, cam))
        z = np.where(in_front, cam[:, 2], 1.0)
        splat = splat_size * camera.focal_px / z
        selected = front_surface(
            col, row, depth, splat, occluder=visible, candidate=selected, distance=distance
        )
    if eligible is not None:
        selected &= eligible
    return selected


__all__ = [
    "MAX_CANVAS_PX",
    "DepthMode",
    "PinholeCamera",
    "camera_coords",
    "front_surface",
    "pixel_of",
    "polygon_mask",
    "project_to_screen",
    "quat_to_matrix",
    "rect_mask",
    "select_points",
    "stroke_mask",
]
