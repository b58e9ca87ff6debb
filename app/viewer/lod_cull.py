"""Level of detail for voxel maps larger than the browser budget: culling selections and clicks.

**Culling** (:func:`frustum_blocks`, :func:`ray_blocks`): selections and clicks test coarse cubes (edge ≥
:attr:`app.viewer.lod.LodConfig.query_edge`) of the index (:mod:`app.viewer.lod`) against the selection's
frustum or the click ray first and only then look at the voxels inside the cubes that pass, with a test
that never drops a voxel the full test would keep.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from app.viewer.lod import Blocks, LodIndex, segment_rows
from leap_core.picking import ray_box_entry
from leap_core.selection import (
    DepthMode,
    PinholeCamera,
    camera_coords,
    pixel_of,
    project_to_screen,
    quat_to_matrix,
    select_points,
)


def frustum_blocks(
    cube_centres: npt.NDArray[np.float64],
    edge: float,
    camera: PinholeCamera,
    rect_min: tuple[float, float],
    rect_max: tuple[float, float],
) -> npt.NDArray[np.bool_]:
    """(B,) bool: cubes that may hold a point in front of ``camera`` projecting into the screen rectangle
    (normalised corners, see :func:`leap_core.selection.project_to_screen`).

    Conservative (never drops such a cube): a cube is kept unless its bounding sphere (radius ``edge·√3/2``)
    lies wholly behind the camera or wholly outside one of the four planes through the camera centre and
    the rectangle's edges. In camera coordinates a point projects into ``u ∈ [u0, u1]`` iff
    ``a0·z ≤ x ≤ a1·z`` with ``a = (2u - 1)·aspect·tan(fov_y / 2)`` (likewise y with v and ``tan(fov_y/2)``).
    """
    rho = edge * math.sqrt(3.0) / 2.0
    rot = quat_to_matrix(camera.wxyz)
    cam = (np.asarray(cube_centres, dtype=np.float64) - np.asarray(camera.position)) @ rot
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    ty = math.tan(camera.fov_y / 2.0)
    tx = camera.aspect * ty
    u0, u1 = sorted((rect_min[0], rect_max[0]))
    v0, v1 = sorted((rect_min[1], rect_max[1]))
    keep: npt.NDArray[np.bool_] = z > -rho
    for a, sign, coord in (
        ((2 * u0 - 1) * tx, 1.0, x),
        ((2 * u1 - 1) * tx, -1.0, x),
        ((2 * v0 - 1) * ty, 1.0, y),
        ((2 * v1 - 1) * ty, -1.0, y),
    ):
        # Inside the half-space: sign·(coord - a·z) ≥ 0; its plane's unit normal has length √(1 + a²).
        keep &= sign * (coord - a * z) >= -rho * math.sqrt(1.0 + a * a)
    return keep


def ray_blocks(
    cube_centres: npt.NDArray[np.float64], edge: float, origin: npt.ArrayLike, direction: npt.ArrayLike
) -> npt.NDArray[np.bool_]:
    """(B,) bool: cubes the ray enters in front of its origin (every voxel it enters lies in one)."""
    if cube_centres.shape[0] == 0:
        return np.zeros(0, bool)
    return np.isfinite(ray_box_entry(origin, direction, cube_centres, edge))


def mask_rect(mask: npt.NDArray[np.bool_]) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """Normalised corners of the bounding rectangle of a screen mask's True pixels (None when empty)."""
    cols = np.flatnonzero(mask.any(axis=0))
    rows = np.flatnonzero(mask.any(axis=1))
    if cols.size == 0:
        return None
    h, w = mask.shape
    return (cols[0] / w, rows[0] / h), ((cols[-1] + 1) / w, (rows[-1] + 1) / h)


def select_culled(  # noqa: PLR0913 (select_points' own keywords, plus the index and its cubes)
    index: LodIndex,
    cubes: Blocks,
    camera: PinholeCamera,
    mask: npt.NDArray[np.bool_],
    *,
    visible: npt.NDArray[np.bool_],
    eligible: npt.NDArray[np.bool_] | None = None,
    depth_mode: DepthMode = "front",
    distance: float = 0.5,
    splat_size: float = 0.2,
) -> npt.NDArray[np.int64]:
    """Rows (ascending) :func:`leap_core.selection.select_points` selects among the ``visible`` voxels, found
    without projecting the voxels of cubes that cannot matter.

    The candidates lie in the mask's bounding rectangle, so the cubes passing :func:`frustum_blocks` for it
    hold them all. In ``front`` mode the z-buffer also reads occluders in the candidates' cell box grown by
    one cell (:func:`leap_core.selection.front_surface`; cell = median on-screen size of the candidates), so
    the cubes of that wider window are added before the exact test runs on the union.

    Args:
        index: the grid's index; ``cubes`` one of its levels (the culling cubes).
        camera, mask: the tool's camera and (H, W) screen mask.
        visible: (V,) bool, the voxels shown (the only ones selectable or occluding).
        eligible: (V,) bool class filter applied after the depth test, or None.
        depth_mode, distance, splat_size: as :func:`~leap_core.selection.select_points`.
    """
    rect = mask_rect(mask)
    if rect is None:
        return np.zeros(0, np.int64)
    centres = index.centres

    def rows_in(lo: tuple[float, float], hi: tuple[float, float]) -> npt.NDArray[np.int64]:
        keep = frustum_blocks(cubes.cube_centres, cubes.edge, camera, lo, hi)
        rows = segment_rows(index.order, cubes.starts, np.flatnonzero(keep))
        return rows[visible[rows]]

    rows = rows_in(*rect)
    if depth_mode == "front" and rows.size:
        w, h = camera.width_px, camera.height_px
        cam = camera_coords(centres[rows], camera.position, camera.wxyz)
        uv, in_front = project_to_screen(
            centres[rows], camera.position, camera.wxyz, camera.fov_y, camera.aspect
        )
        col, row, on = pixel_of(uv, w, h)
        cand = in_front & on & mask[row, col]
        if cand.any():
            splat = splat_size * camera.focal_px / cam[cand, 2]
            cell = max(1.0, float(np.median(splat)))
            ccol, crow = (col[cand] / cell).astype(np.int64), (row[cand] / cell).astype(np.int64)
            # Occluder pixels: columns [(c0 - 1)·cell, (c1 + 2)·cell), one pixel of slack each side.
            u0 = ((ccol.min() - 1) * cell - 1) / w
            u1 = ((ccol.max() + 2) * cell + 1) / w
            v0 = ((crow.min() - 1) * cell - 1) / h
            v1 = ((crow.max() + 2) * cell + 1) / h
            rows = np.union1d(rows, rows_in((u0, v0), (u1, v1)))
    rows = np.sort(rows)
    picked = select_points(
        centres[rows],
        camera,
        mask,
        depth_mode=depth_mode,
        distance=distance,
        splat_size=splat_size,
        eligible=None if eligible is None else eligible[rows],
    )
    return rows[picked]


def ray_rows(
    index: LodIndex, cubes: Blocks, origin: npt.ArrayLike, direction: npt.ArrayLike
) -> npt.NDArray[np.int64]:
    """Rows (ascending) of the voxels in the cubes a click ray enters: every voxel the ray can hit."""
    hit = ray_blocks(cubes.cube_centres, cubes.edge, origin, direction)
    return np.sort(segment_rows(index.order, cubes.starts, np.flatnonzero(hit)))


def thin_rows(
    blocks: Blocks,
    full: npt.NDArray[np.int64],
    centres: npt.NDArray[np.float32],
    rows: npt.NDArray[np.int64],
) -> npt.NDArray[np.float32]:
    """Points marking ``rows``: the centres of those in the ``full`` (ascending) blocks, then the mean centre
    of each other block holding one of them (so a selection over the overview stays within the budget)."""
    b = blocks.of_row[rows].astype(np.int64)
    pos = np.minimum(np.searchsorted(full, b), max(full.shape[0] - 1, 0))
    inside = full[pos] == b if full.size else np.zeros(b.shape[0], bool)
    return np.concatenate([centres[rows[inside]], blocks.mean[np.unique(b[~inside])]]).astype(np.float32)


__all__ = ["frustum_blocks", "mask_rect", "ray_blocks", "ray_rows", "select_culled", "thin_rows"]
