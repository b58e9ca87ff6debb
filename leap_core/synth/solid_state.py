"""A fixed-field-of-view solid-state LiDAR (Blickfeld-Cube-like) simulated by ray casting the scene.

Scan pattern. The sensor sweeps ``columns`` × ``lines`` rays over a ``h_fov`` × ``v_fov`` window around
its boresight. Rays lie on a virtual image plane one metre ahead of the sensor (the *grid frame*: x right,
y down, z along the boresight) at ``(u − c_u) / f_u``, ``(v − c_v) / f_v`` with column coordinate
``u = j + o_u`` and line coordinate ``v = i + o_v + (j / columns − ½)·slant``:

- ``f_u = (columns / 2) / tan(h_fov / 2)``, ``c_u = (columns − 1) / 2`` (and the same vertically), so the
  window's edges are at exactly ±h_fov / 2 and ±v_fov / 2;
- ``slant`` (0..1 line): the scan mirror keeps moving down while a line is swept, so each line descends by
  ``slant`` of the line spacing from its first to its last column (a raster scanner's sawtooth);
- ``(o_u, o_v)`` ∈ [−½, ½)² is a per-frame offset from the Halton sequence (bases 2 and 3) of the frame
  number (``interlace``): consecutive frames sample between the previous frames' rays, so the pattern does
  not repeat (the accumulated map fills in, as with a non-repeating scanner).

Every ray's grid coordinates stay within one cell of (j, i), so
``leap_core.synth.raycast.pinhole_tasks`` bounds primitives on this grid conservatively (it pads its
rectangles by a cell). Points are written in the *LiDAR frame*: the sensor head's frame (x along the
boresight, y left, z up) rotated back by the rig's fixed mount rotation, i.e. the drone body's axes at the
sensor (``leap_core.synth.agri``); calib.txt's Tr then carries the tilt. Returns beyond ``max_range`` or
without a hit are dropped, as are a material-dependent share of returns (glass, rubber); the range gets
Gaussian noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from leap_core.errors import ConfigError
from leap_core.synth.lidar import Scan
from leap_core.synth.materials import DROPOUT, REFLECTIVITY
from leap_core.synth.raycast import Primitives, cast_grid, pinhole_tasks, surface_hits

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

GRID_TO_HEAD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""(3, 3) grid frame (x right, y down, z boresight) → sensor-head frame (x boresight, y left, z up)."""


@dataclass(frozen=True)
class SolidStateLidarConfig:
    """Sensor model of the fixed-FOV solid-state LiDAR."""

    h_fov_deg: float = 70.0
    """Horizontal field of view (degrees), centred on the boresight."""
    v_fov_deg: float = 30.0
    """Vertical field of view (degrees), centred on the boresight."""
    columns: int = 320
    """Rays per scan line."""
    lines: int = 128
    """Scan lines per frame: 320 × 128 = 40,960 rays, about 40k returns over a farm."""
    slant: float = 1.0
    """How far (in line spacings) a line descends from its first column to its last (mirror motion)."""
    interlace: bool = True
    """Shift the pattern by a per-frame sub-ray offset (Halton sequence): a non-repeating scan."""
    max_range: float = 200.0
    """Returns farther than this are dropped (m)."""
    min_range: float = 1.0
    """Returns nearer than this are dropped (m)."""
    range_noise: float = 0.02
    """Standard deviation of the Gaussian range noise (m)."""
    remission_noise: float = 0.08
    """Relative standard deviation of the remission noise."""

    def __post_init__(self) -> None:
        for name in ("h_fov_deg", "v_fov_deg"):
            v = getattr(self, name)
            if not 0 < v < 170:
                raise ConfigError(f"must be in (0, 170) degrees, got {v}", field=(name,))
        if self.columns < 2 or self.lines < 2:
            raise ConfigError("columns and lines must be >= 2", field=("columns",))
        if not 0.0 <= self.slant <= 1.0:
            raise ConfigError(f"must be in [0, 1], got {self.slant}", field=("slant",))

    def K(self) -> F64:
        """(3, 3) intrinsics of the virtual ray grid (see the module docstring)."""
        fu = (self.columns / 2) / np.tan(np.deg2rad(self.h_fov_deg) / 2)
        fv = (self.lines / 2) / np.tan(np.deg2rad(self.v_fov_deg) / 2)
        return np.array([[fu, 0.0, (self.columns - 1) / 2], [0.0, fv, (self.lines - 1) / 2], [0.0, 0.0, 1.0]])


def halton(index: int, base: int) -> float:
    """The ``index``-th element (index ≥ 1) of the van der Corput sequence in ``base``, in [0, 1)."""
    out, f, i = 0.0, 1.0, index
    while i > 0:
        f /= base
        out += f * (i % base)
        i //= base
    return out


def frame_offset(cfg: SolidStateLidarConfig, frame: int) -> tuple[float, float]:
    """(o_u, o_v) in [−½, ½)² of frame ``frame`` (0, 0 without interlacing): Halton bases 2 and 3 of
    ``frame + 1``, shifted by −½."""
    if not cfg.interlace:
        return 0.0, 0.0
    return halton(frame + 1, 2) - 0.5, halton(frame + 1, 3) - 0.5


def scan_rays(cfg: SolidStateLidarConfig, frame: int) -> F32:
    """(3, lines, columns) unit ray directions of frame ``frame`` in the grid frame (x right, y down,
    z boresight); row i, column j is the ray of grid coordinates (u, v) of the module docstring."""
    k = cfg.K()
    o_u, o_v = frame_offset(cfg, frame)
    j = np.arange(cfg.columns, dtype=np.float64)
    i = np.arange(cfg.lines, dtype=np.float64)
    slant = (j / cfg.columns - 0.5) * cfg.slant
    u = (j + o_u - k[0, 2]) / k[0, 0]
    v = (i[:, None] + o_v + slant[None, :] - k[1, 2]) / k[1, 1]
    # Keep every ray inside the window: a shift never pushes the outermost rays past the FOV edges.
    u = np.clip(u, -(cfg.columns / 2) / k[0, 0], (cfg.columns / 2) / k[0, 0])
    v = np.clip(v, -(cfg.lines / 2) / k[1, 1], (cfg.lines / 2) / k[1, 1])
    d = np.stack([np.broadcast_to(u[None], v.shape), v, np.ones_like(v)])
    return np.asarray(d / np.linalg.norm(d, axis=0, keepdims=True), dtype=np.float32)


def solid_state_scan(
    prims: Primitives,
    head_to_world: F64,
    head_to_lidar: F64,
    cfg: SolidStateLidarConfig,
    frame: int,
    rng: np.random.Generator,
) -> Scan:
    """Cast one frame from the sensor head and turn the hits into a labelled point cloud.

    Args:
        prims: world primitives at this instant.
        head_to_world: (4, 4) pose of the sensor head (x boresight, y left, z up).
        head_to_lidar: (4, 4) sensor head → LiDAR frame (the frame points are written in).
        cfg: sensor model.
        frame: frame number (selects the interlace offset).
        rng: source of range noise, remission noise and dropouts.

    Returns:
        The scan in the LiDAR frame; points ordered by line, then by column (the firing order).
    """
    rays = scan_rays(cfg, frame)
    grid_to_world = np.eye(4)
    grid_to_world[:3, :3] = head_to_world[:3, :3] @ GRID_TO_HEAD
    grid_to_world[:3, 3] = head_to_world[:3, 3]
    rot, origin = grid_to_world[:3, :3], grid_to_world[:3, 3]
    dirs_w = np.einsum("ij,jhw->ihw", rot.astype(np.float32), rays)
    # Rays sit within one cell of their (j, i) on the unshifted grid, inside pinhole_tasks' padding.
    world_to_grid = np.asarray(np.linalg.inv(grid_to_world), dtype=np.float64)
    tasks = pinhole_tasks(prims, world_to_grid, cfg.K(), cfg.columns, cfg.lines, cfg.max_range)
    depth, pid = cast_grid(prims, origin, dirs_w, tasks, cfg.min_range, cfg.max_range)
    depth, pid = depth.reshape(-1), pid.reshape(-1)
    idx = np.flatnonzero(pid >= 0)
    p, t = pid[idx], depth[idx]
    d_world = dirs_w.reshape(3, -1).T[idx]
    hits = surface_hits(prims, origin, d_world, t, p)
    mat = prims.material[p]
    refl = REFLECTIVITY[mat]
    cos_inc = np.abs(np.einsum("ij,ij->i", hits.normal, d_world))
    u = rng.random(len(idx), dtype=np.float32)
    noise_r = rng.standard_normal(len(idx), dtype=np.float32)
    noise_i = rng.standard_normal(len(idx), dtype=np.float32)
    keep = u >= DROPOUT[mat]
    rng_noisy = t + cfg.range_noise * noise_r
    remission = refl * (0.35 + 0.65 * cos_inc) * (1.0 + cfg.remission_noise * noise_i)
    head = (GRID_TO_HEAD.astype(np.float32) @ rays.reshape(3, -1)).T[idx[keep]] * rng_noisy[keep, None]
    xyz = head @ head_to_lidar[:3, :3].T.astype(np.float32) + head_to_lidar[:3, 3].astype(np.float32)
    pts = np.empty((int(keep.sum()), 4), np.float32)
    pts[:, :3] = xyz
    pts[:, 3] = np.clip(remission[keep], 0.0, 1.0)
    return Scan(points=pts, semantic=prims.semantic[p[keep]], instance=prims.instance[p[keep]])
