"""Picking: which voxel a click ray hits first.

A viewer click gives a ray (origin o, direction d) in world coordinates. Each voxel is the axis-aligned cube
of edge ``s`` around its centre c. The slab method intersects the ray with the cube: along axis k the ray is
inside the slab ``|o_k + t·d_k - c_k| ≤ s/2`` for ``t`` between

    t1_k = (c_k - s/2 - o_k) / d_k   and   t2_k = (c_k + s/2 - o_k) / d_k,

so it is inside the cube for ``t ∈ [t_in, t_out]`` with ``t_in = max_k min(t1_k, t2_k)`` and
``t_out = min_k max(t1_k, t2_k)``. An axis with ``d_k = 0`` constrains nothing when ``|o_k - c_k| ≤ s/2``
and excludes the cube otherwise. The cube is hit when ``t_out ≥ max(t_in, 0)`` (in front of the origin);
its distance is ``max(t_in, 0)`` (0 when the origin lies inside it). With ``d`` normalised, ``t`` is in
metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class Pick:
    """The voxel a ray hits first."""

    index: int
    """Row of the hit voxel in the centres given to :func:`pick_voxel`."""
    distance: float
    """Distance (metres) from the ray origin to where the ray enters the voxel (0 from inside it)."""


def ray_box_entry(
    origin: npt.ArrayLike, direction: npt.ArrayLike, centres: npt.ArrayLike, edge: float
) -> npt.NDArray[np.float64]:
    """Distance along the ray at which it enters each cube, ``inf`` where it misses (see the module doc).

    Args:
        origin: (3,) ray origin o.
        direction: (3,) ray direction d, any non-zero length (normalised here, so distances are metres).
        centres: (N, 3) cube centres c.
        edge: cube edge s > 0.

    Returns:
        (N,) float64 ``max(t_in, 0)`` for the cubes the ray meets in front of its origin, else ``inf``.

    Raises:
        ValueError: zero or non-finite direction, non-positive edge, or wrong shapes.
    """
    o = np.asarray(origin, dtype=np.float64).reshape(-1)
    d = np.asarray(direction, dtype=np.float64).reshape(-1)
    c = np.asarray(centres, dtype=np.float64)
    if o.shape != (3,) or d.shape != (3,):
        raise ValueError(f"origin and direction must be 3-vectors, got {o.shape} and {d.shape}")
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centres must be (N, 3), got {c.shape}")
    norm = float(np.linalg.norm(d))
    if not np.isfinite(norm) or norm == 0.0 or not np.all(np.isfinite(o)):
        raise ValueError(f"the ray needs a finite origin and a non-zero direction, got {o} and {d}")
    if not edge > 0:
        raise ValueError(f"edge must be > 0, got {edge}")
    d = d / norm
    half = 0.5 * float(edge)
    rel = c - o  # (N, 3) c - o
    t_in = np.zeros(c.shape[0])
    t_out = np.full(c.shape[0], np.inf)
    # t_in starts at 0 rather than -inf: only what lies in front of the origin counts.
    for k in range(3):
        if d[k] == 0.0:
            outside = np.abs(rel[:, k]) > half
            t_out[outside] = -np.inf
            continue
        t1 = (rel[:, k] - half) / d[k]
        t2 = (rel[:, k] + half) / d[k]
        np.maximum(t_in, np.minimum(t1, t2), out=t_in)
        np.minimum(t_out, np.maximum(t1, t2), out=t_out)
    return np.where(t_out >= t_in, t_in, np.inf)


def pick_voxel(
    origin: npt.ArrayLike,
    direction: npt.ArrayLike,
    centres: npt.ArrayLike,
    voxel_size: float,
    *,
    max_distance: float = np.inf,
) -> Pick | None:
    """The first voxel (cube of edge ``voxel_size`` around each centre) the ray enters, or None.

    Ties (the ray enters two cubes at the same distance, e.g. along a shared face) go to the lower row.

    Args:
        origin, direction: the ray (see :func:`ray_box_entry`).
        centres: (N, 3) voxel centres.
        voxel_size: voxel edge in metres.
        max_distance: voxels entered farther than this are ignored.
    """
    t = ray_box_entry(origin, direction, centres, voxel_size)
    if t.size == 0:
        return None
    i = int(np.argmin(t))
    if not (np.isfinite(t[i]) and t[i] <= max_distance):
        return None
    return Pick(index=i, distance=float(t[i]))


__all__ = ["Pick", "pick_voxel", "ray_box_entry"]
