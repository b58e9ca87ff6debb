"""A spinning 64-beam LiDAR (HDL-64E-like) simulated by ray casting the scene.

The beam elevations follow the HDL-64E layout: an upper block of lasers from +2° to about −8.3° (about
1/3° apart) and a lower block from about −8.8° to −24.9° (about 1/2° apart). One sweep fires every beam at
every azimuth step; all rays of a sweep start from the sensor centre at the same instant (no rolling
shutter / motion distortion). Returns beyond ``max_range`` or without a hit (sky) are dropped, as are a
material-dependent share of returns from glass and black rubber. The measured range gets Gaussian noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from leap_core.synth.materials import DROPOUT, REFLECTIVITY, Material
from leap_core.synth.raycast import Primitives, cast_grid, spherical_tasks, surface_hits
from leap_core.synth.textures import facade_uv, road_paint, window_mask


@dataclass(frozen=True)
class LidarConfig:
    """Sensor model of the spinning LiDAR."""

    height: float = 1.73
    """Mount height of the sensor centre above the road (m), as on the KITTI car."""
    beams: int = 64
    """Number of lasers; half in the upper block, half in the lower block."""
    upper_deg: tuple[float, float] = (2.0, -8.33)
    """Elevation of the first and last laser of the upper block (degrees)."""
    lower_deg: tuple[float, float] = (-8.83, -24.9)
    """Elevation of the first and last laser of the lower block (degrees)."""
    azimuth_step_deg: float = 0.2
    """Horizontal angle between consecutive firings (degrees): 1800 columns, about 105k returns per sweep
    in the demo street."""
    max_range: float = 80.0
    """Returns farther than this are dropped (m)."""
    min_range: float = 0.9
    """Returns nearer than this are dropped (m)."""
    range_noise: float = 0.02
    """Standard deviation of the Gaussian range noise (m)."""
    remission_noise: float = 0.08
    """Relative standard deviation of the remission noise."""


def beam_elevations(cfg: LidarConfig) -> npt.NDArray[np.float64]:
    """(B,) beam elevations in radians, strictly decreasing (row 0 = top beam)."""
    n_up = cfg.beams // 2
    up = np.linspace(cfg.upper_deg[0], cfg.upper_deg[1], n_up)
    low = np.linspace(cfg.lower_deg[0], cfg.lower_deg[1], cfg.beams - n_up)
    return np.asarray(np.deg2rad(np.concatenate([up, low])), dtype=np.float64)


def n_azimuth(cfg: LidarConfig) -> int:
    """Number of azimuth columns in one revolution."""
    return round(360.0 / cfg.azimuth_step_deg)


def ray_grid(cfg: LidarConfig) -> npt.NDArray[np.float32]:
    """(3, B, A) unit ray directions in the sensor frame; column j has azimuth −π + (j + ½)·2π/A."""
    elev = beam_elevations(cfg)
    a = n_azimuth(cfg)
    az = -np.pi + (np.arange(a) + 0.5) * 2 * np.pi / a
    ce, se = np.cos(elev)[:, None], np.sin(elev)[:, None]
    return np.stack(
        [ce * np.cos(az)[None], ce * np.sin(az)[None], np.broadcast_to(se, (len(elev), a))]
    ).astype(np.float32)


@dataclass(frozen=True)
class Scan:
    """One simulated sweep.

    Attributes:
        points: (N, 4) float32 x, y, z (sensor frame) and remission in [0, 1].
        semantic: (N,) uint16 raw class id per point; instance: (N,) uint16 instance id per point.
    """

    points: npt.NDArray[np.float32]
    semantic: npt.NDArray[np.uint16]
    instance: npt.NDArray[np.uint16]


def scan(
    prims: Primitives,
    sensor_to_world: npt.NDArray[np.float64],
    cfg: LidarConfig,
    rng: np.random.Generator,
    rays: npt.NDArray[np.float32] | None = None,
) -> Scan:
    """Cast one sweep from the sensor pose and turn the hits into a labelled point cloud.

    Args:
        prims: world primitives at this instant.
        sensor_to_world: (4, 4) pose of the sensor.
        cfg: sensor model.
        rng: source of range noise, remission noise and dropouts.
        rays: optional cached :func:`ray_grid` (sensor frame).

    Returns:
        The scan; points are ordered by azimuth column, then by beam (top to bottom).
    """
    rays = ray_grid(cfg) if rays is None else rays
    rot, origin = sensor_to_world[:3, :3], sensor_to_world[:3, 3]
    dirs_w = np.einsum("ij,jba->iba", rot.astype(np.float32), rays)
    world_to_sensor = np.asarray(np.linalg.inv(sensor_to_world), dtype=np.float64)
    tasks = spherical_tasks(prims, world_to_sensor, beam_elevations(cfg), rays.shape[2], cfg.max_range)
    depth, pid = cast_grid(prims, origin, dirs_w, tasks, cfg.min_range, cfg.max_range)
    # Column-major order: one azimuth after the other, like the sensor's firing sequence.
    depth, pid = depth.T.reshape(-1), pid.T.reshape(-1)
    dirs_s = rays.transpose(0, 2, 1).reshape(3, -1).T
    idx = np.flatnonzero(pid >= 0)
    p = pid[idx]
    t = depth[idx]
    d_world = dirs_w.transpose(0, 2, 1).reshape(3, -1).T[idx]
    hits = surface_hits(prims, origin, d_world, t, p)
    mat = prims.material[p]
    refl = lidar_reflectivity(prims, p, mat, hits.local, hits.face, t)
    cos_inc = np.abs(np.einsum("ij,ij->i", hits.normal, d_world))
    u = rng.random(len(idx), dtype=np.float32)
    noise_r = rng.standard_normal(len(idx), dtype=np.float32)
    noise_i = rng.standard_normal(len(idx), dtype=np.float32)
    # Dark, specular surfaces (glass, tyres, windows) lose returns more often.
    drop = np.maximum(DROPOUT[mat], np.where(refl < 0.1, np.float32(0.25), np.float32(0.0)))
    keep = u >= drop
    rng_noisy = t + cfg.range_noise * noise_r
    remission = refl * (0.35 + 0.65 * cos_inc) * (1.0 + cfg.remission_noise * noise_i)
    pts = np.empty((int(keep.sum()), 4), np.float32)
    pts[:, :3] = dirs_s[idx[keep]] * rng_noisy[keep, None]
    pts[:, 3] = np.clip(remission[keep], 0.0, 1.0)
    return Scan(points=pts, semantic=prims.semantic[p[keep]], instance=prims.instance[p[keep]])


def lidar_reflectivity(
    prims: Primitives,
    pid: npt.NDArray[np.int32],
    mat: npt.NDArray[np.uint8],
    local: npt.NDArray[np.float32],
    face: npt.NDArray[np.int8],
    dist: npt.NDArray[np.float32],
) -> npt.NDArray[np.float32]:
    """(n,) base remission before the incidence-angle falloff: the material's reflectivity, raised on lane
    paint, lowered on window glass, scaled by paint brightness on vehicles."""
    refl = REFLECTIVITY[mat]  # a new array: integer-array indexing copies
    footprint = dist * np.float32(np.deg2rad(0.2))
    road = np.flatnonzero((mat == Material.ASPHALT) & (face == 4))
    if road.size:
        paint = road_paint(local[road], prims.param[pid[road]], footprint[road])
        refl[road] += paint * np.float32(0.45)
    fac = np.flatnonzero((mat == Material.FACADE) & (face <= 3))
    if fac.size:
        q = pid[fac]
        half = prims.half[q].astype(np.float32)
        param = prims.param[q]
        u, h = facade_uv(local[fac], half, face[fac])
        width = np.where(face[fac] <= 1, 2 * half[:, 1], 2 * half[:, 0])
        win, _ = window_mask(u, h, width, param[:, 0], param[:, 1], footprint[fac])
        refl[fac] = refl[fac] * (1 - win) + np.float32(0.06) * win
    veh = np.flatnonzero(mat == Material.PAINT)
    if veh.size:
        lum = prims.color[pid[veh]] @ np.array([0.3, 0.5, 0.2], np.float32)
        refl[veh] = np.float32(0.08) + np.float32(0.3) * lum
    return refl
