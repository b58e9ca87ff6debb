"""The forward colour camera: KITTI-like calibration, ray-cast rendering with textures, sun light and
shadows, and per-pixel 2D ground truth.

Projection model (as in KITTI): a LiDAR point X maps to ``P2 · Tr · [X 1]ᵀ``; with ``P2 = K [I | t₂]`` the
camera centre sits at −t₂ in the rectified camera-0 frame. Pixel centres are at integer (u, v), so the
pixel of a projected point is ``round(u), round(v)``. Each pixel is rendered from the ray through its
centre; the 2D ground truth is the class / instance / name of the surface that ray hits (0 for sky).

Shading: albedo from procedural textures per material, Lambert with the sun (shadowed with a lazily
built sun-view depth map of the static scene plus exact shadow rays against moving objects) plus a
hemispheric ambient term, Blinn-Phong highlights on paint and glass, aerial haze, a sky gradient with
clouds, then a light blur and sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Final

import cv2
import numpy as np
import numpy.typing as npt

from leap_core.synth.materials import Material as M
from leap_core.synth.raycast import (
    OrthoGrid,
    Primitives,
    SurfaceHits,
    cast_grid,
    cast_parallel,
    occluded_towards,
    ortho_bounds,
    ortho_tasks,
    pinhole_tasks,
    rotation_xyz,
    surface_hits,
)
from leap_core.synth.textures import box_pattern, facade_uv, noise, road_paint, window_mask

F32 = npt.NDArray[np.float32]

_HORIZON: Final = np.array([0.8, 0.85, 0.9], np.float32)
"""Sky colour at the horizon (linear RGB)."""
_HAZE: Final = _HORIZON * np.float32(0.92)
"""Colour that aerial haze fades distant surfaces (and the ground beyond the blocks) towards."""


@dataclass(frozen=True)
class CameraConfig:
    """Intrinsics, mounting and rendering of the left colour camera (defaults: KITTI odometry 00-02)."""

    width: int = 1242
    """Image width (pixels)."""
    height: int = 375
    """Image height (pixels)."""
    fx: float = 721.5377
    """Focal length along u (pixels)."""
    fy: float = 721.5377
    """Focal length along v (pixels)."""
    cx: float = 609.5593
    """Principal point u (pixels)."""
    cy: float = 172.854
    """Principal point v (pixels)."""
    p2_offset: tuple[float, float, float] = (44.85728, 0.2163791, 0.002745884)
    """Fourth column of P2 (camera 2's offset from the rectified camera 0, times K), as in KITTI."""
    tr_translation: tuple[float, float, float] = (-0.004069766, -0.07631618, -0.2717806)
    """Translation of Tr (LiDAR → camera 0, in camera coordinates): the camera sits 0.27 m ahead of
    and 0.08 m below the LiDAR, as on the KITTI car."""
    tr_rotation_deg: tuple[float, float, float] = (0.35, -0.25, 0.15)
    """Small mounting rotation (roll, pitch, yaw in degrees, about the LiDAR axes) added to the axis swap
    LiDAR (x fwd, y left, z up) → camera (x right, y down, z fwd)."""
    max_range: float = 170.0
    """Primitives entirely beyond this distance are not rendered (m)."""
    shadow_range: float = 90.0
    """Sun shadows are computed for surfaces up to this distance (m)."""
    shadow_res: float = 0.08
    """Cell size of the sun-view shadow map (m)."""
    noise_std: float = 1.6
    """Standard deviation of the sensor noise added to the 8-bit image."""

    def scaled(self, factor: float) -> CameraConfig:
        """The same camera at ``factor`` × the resolution (same field of view; a coarser shadow map when
        smaller). Used for fast previews and tests."""
        w, h = max(round(self.width * factor), 8), max(round(self.height * factor), 8)
        fu, fv = w / self.width, h / self.height
        out = replace(
            self,
            width=w,
            height=h,
            fx=self.fx * fu,
            fy=self.fy * fv,
            cx=(self.cx + 0.5) * fu - 0.5,
            cy=(self.cy + 0.5) * fv - 0.5,
            shadow_res=self.shadow_res / min(factor, 1.0),
        )
        # Keep camera 2's physical offset: P2[:, 3] = K · t₂.
        p2x, p2y, p2z = (float(v) for v in out.K() @ self.cam2_offset())
        return replace(out, p2_offset=(p2x, p2y, p2z))

    def K(self) -> npt.NDArray[np.float64]:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def P2(self) -> npt.NDArray[np.float64]:
        """(3, 4) projection ``K [I | t₂]`` of the colour camera in the rectified camera-0 frame."""
        return np.concatenate([self.K(), np.array(self.p2_offset)[:, None]], axis=1)

    def Tr(self) -> npt.NDArray[np.float64]:
        """(4, 4) LiDAR → camera-0 transform."""
        axes = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
        r = axes @ rotation_xyz(*np.deg2rad(self.tr_rotation_deg))
        tr = np.eye(4)
        tr[:3, :3] = r
        tr[:3, 3] = self.tr_translation
        return tr

    def cam2_offset(self) -> npt.NDArray[np.float64]:
        """t₂ = K⁻¹ · P2[:, 3]: camera-2 coordinates are camera-0 coordinates plus t₂."""
        return np.linalg.solve(self.K(), np.array(self.p2_offset))


@dataclass(frozen=True)
class CameraFrame:
    """One rendered image and its 2D ground truth.

    Attributes:
        rgb: (H, W, 3) uint8 image. semantic: (H, W) uint16 raw class id (0 = sky / nothing).
        instance: (H, W) uint16 instance id (0 = stuff). name: (H, W) uint16 name id of the surface
        (``leap_core.synth.names``; 0 = sky). depth: (H, W) float32 z-depth (inf = sky). cell: (H, W)
        uint16 world cell of the surface seen (:func:`world_cells`; 0 for sky, like cell (0, 0)).
    """

    rgb: npt.NDArray[np.uint8]
    semantic: npt.NDArray[np.uint16]
    instance: npt.NDArray[np.uint16]
    name: npt.NDArray[np.uint16]
    depth: npt.NDArray[np.float32]
    cell: npt.NDArray[np.uint16]


WORLD_CELL_M = 2.0
"""Edge of the square world cells of :func:`world_cells`, in metres."""


def world_cells(world: npt.ArrayLike) -> npt.NDArray[np.uint16]:
    """(N,) uint16 id of the ``WORLD_CELL_M`` × ``WORLD_CELL_M`` world cell under each of the points
    ``world`` (N, >= 2): ``(ix mod 256) · 256 + (iy mod 256)`` with ``ix = floor(x / WORLD_CELL_M)`` (iy
    likewise), so ids repeat every 512 m along each axis. The simulated labeler keys persistent stuff
    errors by it (docs/METHOD.md A.7, term 13): a surface patch looks the same from every frame that sees it.
    """
    xy = np.asarray(world, dtype=np.float64).reshape(-1, np.shape(world)[-1])[:, :2]
    ij = np.floor(xy / WORLD_CELL_M).astype(np.int64) & 255
    out: npt.NDArray[np.uint16] = ((ij[:, 0] << 8) | ij[:, 1]).astype(np.uint16)
    return out


def pixel_rays(cfg: CameraConfig) -> F32:
    """(3, H, W) camera-frame rays through the pixel centres, scaled so z = 1 (t = depth)."""
    u = (np.arange(cfg.width, dtype=np.float64) - cfg.cx) / cfg.fx
    v = (np.arange(cfg.height, dtype=np.float64) - cfg.cy) / cfg.fy
    return np.stack(
        [
            np.broadcast_to(u[None], (cfg.height, cfg.width)),
            np.broadcast_to(v[:, None], (cfg.height, cfg.width)),
            np.ones((cfg.height, cfg.width)),
        ]
    ).astype(np.float32)


def camera_to_world(cfg: CameraConfig, lidar_to_world: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(4, 4) pose of camera 2 (its optical centre, axes of the rectified frame) in the world."""
    cam2_to_cam0 = np.eye(4)
    cam2_to_cam0[:3, 3] = -cfg.cam2_offset()
    return lidar_to_world @ np.linalg.inv(cfg.Tr()) @ cam2_to_cam0


# ------------------------------------------------------------------------------------------ shadows
class SunShadows:
    """Sun visibility of static geometry from a sun-view depth map built tile by tile on demand.

    The map is an orthographic ray grid looking down the sun direction (``OrthoGrid`` with e3 = sun).
    A point is lit when the map's first hit above it is its own primitive (convex primitives never shadow
    themselves on their sunlit side) or lies no higher along the sun ray than the point plus a slope bias.
    Tiles of ``2**tile_bits`` × ``2**tile_bits`` cells live in one growing atlas, so consecutive frames
    reuse them and a lookup is a single gather.
    """

    def __init__(
        self, static: Primitives, sun: npt.NDArray[np.float64], res: float, tile_bits: int = 7
    ) -> None:
        e3 = np.asarray(sun, np.float64) / np.linalg.norm(sun)
        e1 = np.cross(np.array([0.0, 0.0, 1.0]), e3)
        e1 /= np.linalg.norm(e1)
        self.basis = np.stack([e1, np.cross(e3, e1), e3], axis=1)
        # Thin casters (poles, sign posts, rods) are thickened to two cells so their shadows stay solid lines.
        self.static = Primitives(**{**static.__dict__, "half": np.maximum(static.half, res)})
        self.res = res
        self.bits = tile_bits
        self.cells = 1 << tile_bits
        self.bounds = ortho_bounds(self.static, self.basis)
        self.top = float((self.static.corners() @ e3).max()) + 1.0 if len(static) else 1.0
        self.slots: dict[tuple[int, int], int] = {}
        self.t_atlas = np.empty((16, self.cells, self.cells), np.float32)
        self.p_atlas = np.empty((16, self.cells, self.cells), np.int32)

    def _slot(self, key: tuple[int, int]) -> int:
        """Atlas slot of tile ``key`` (cast on first use)."""
        slot = self.slots.get(key)
        if slot is None:
            slot = len(self.slots)
            if slot == len(self.t_atlas):
                self.t_atlas = np.concatenate([self.t_atlas, np.empty_like(self.t_atlas)])
                self.p_atlas = np.concatenate([self.p_atlas, np.empty_like(self.p_atlas)])
            tile_m = self.res * self.cells
            grid = OrthoGrid(
                self.basis, key[0] * tile_m, key[1] * tile_m, self.res, self.cells, self.cells, self.top
            )
            self.t_atlas[slot], self.p_atlas[slot] = cast_parallel(
                self.static, grid, ortho_tasks(self.bounds, grid)
            )
            self.slots[key] = slot
        return slot

    def lit(self, points: F32, pid: npt.NDArray[np.int32], cos_sun: F32) -> F32:
        """(n,) sun visibility in [0, 1] of world points on primitives ``pid`` (static indices; −1 for
        moving ones), with ``cos_sun`` = n·sun of their surface. Percentage-closer filtering over the four
        nearest map cells (bilinear weights) softens the edges of shadows by one cell."""
        b = self.basis.astype(np.float32)
        pu = points @ b[:, 0] * np.float32(1.0 / self.res) - np.float32(0.5)
        pw = points @ b[:, 1] * np.float32(1.0 / self.res) - np.float32(0.5)
        t_pt = np.float32(self.top) - points @ b[:, 2]
        tan = np.sqrt(np.maximum(1 - cos_sun**2, 0)) / np.maximum(cos_sun, 0.05)
        bias = np.float32(0.03) + np.float32(self.res) * np.minimum(tan, 4.0)
        cu0, cw0 = np.floor(pu), np.floor(pw)
        fu, fw = pu - cu0, pw - cw0
        cu0, cw0 = cu0.astype(np.int64), cw0.astype(np.int64)
        # Dense lookup table tile → atlas slot over every tile the four taps can touch.
        ti0, tj0 = cu0 >> self.bits, cw0 >> self.bits
        i0, j0 = int(ti0.min()), int(tj0.min())
        ni, nj = int(ti0.max()) - i0 + 2, int(tj0.max()) - j0 + 2
        used = np.zeros((ni, nj), bool)
        used.reshape(-1)[np.unique((ti0 - i0) * nj + (tj0 - j0))] = True
        used[1:, :] |= used[:-1, :]
        used[:, 1:] |= used[:, :-1]
        lut = np.full(ni * nj, -1, np.int64)
        for k in np.flatnonzero(used.reshape(-1)).tolist():
            lut[k] = self._slot((k // nj + i0, k % nj + j0))
        t_flat, p_flat = self.t_atlas.reshape(-1), self.p_atlas.reshape(-1)
        mask = self.cells - 1
        out = np.zeros(len(points), np.float32)
        for du, dw in ((0, 0), (1, 0), (0, 1), (1, 1)):
            cu, cw = cu0 + du, cw0 + dw
            slot = lut[((cu >> self.bits) - i0) * nj + ((cw >> self.bits) - j0)]
            flat = (((slot << self.bits) + (cw & mask)) << self.bits) + (cu & mask)
            weight = (fu if du else 1 - fu) * (fw if dw else 1 - fw)
            out += weight * ((p_flat[flat] == pid) | (t_pt <= t_flat[flat] + bias))
        return out


# ------------------------------------------------------------------------------------------ render
def render(
    prims: Primitives,
    n_static: int,
    cam_to_world: npt.NDArray[np.float64],
    cfg: CameraConfig,
    *,
    sun: npt.NDArray[np.float64],
    shadows: SunShadows | None,
    rng: np.random.Generator,
    rays: F32 | None = None,
) -> CameraFrame:
    """Render one image and its ground truth.

    Args:
        prims: world primitives; the first ``n_static`` are the static scene (indexed as in ``shadows``),
            the rest are moving objects.
        cam_to_world: (4, 4) pose of camera 2.
        cfg: camera model.
        sun: (3,) unit vector towards the sun.
        shadows: sun-visibility cache of the static scene, or None for no shadows.
        rng: source of sensor noise.
        rays: optional cached :func:`pixel_rays`.
    """
    rays = pixel_rays(cfg) if rays is None else rays
    h, w = cfg.height, cfg.width
    rot, origin = cam_to_world[:3, :3], cam_to_world[:3, 3]
    dirs = np.einsum("ij,jhw->ihw", rot.astype(np.float32), rays)
    world_to_cam = np.asarray(np.linalg.inv(cam_to_world), dtype=np.float64)
    tasks = pinhole_tasks(prims, world_to_cam, cfg.K(), w, h, cfg.max_range)
    depth, pid = cast_grid(prims, origin, dirs, tasks, 0.05, 1e4)
    flat_pid = pid.reshape(-1)
    idx = np.flatnonzero(flat_pid >= 0)
    d = np.stack([dirs[k].reshape(-1)[idx] for k in range(3)], axis=1)
    t = depth.reshape(-1)[idx]
    p = flat_pid[idx]
    hits = surface_hits(prims, origin, d, t, p)
    norm_d = np.sqrt(np.einsum("ij,ij->i", d, d))
    dist = t * norm_d
    view = d / norm_d[:, None]
    cos_v = np.abs(np.einsum("ij,ij->i", hits.normal, view))
    footprint = dist / np.float32(cfg.fx) / np.maximum(cos_v, np.float32(0.2))
    world = origin.astype(np.float32)[None] + t[:, None] * d

    albedo = _albedo(prims, p, hits, world, footprint, view)
    sun32 = np.asarray(sun, np.float32)
    cos_sun = hits.normal @ sun32
    sun_vis = (cos_sun > 0).astype(np.float32)
    if shadows is not None:
        cand = np.flatnonzero((cos_sun > 0) & (dist < cfg.shadow_range))
        if cand.size:
            pts = world[cand] + hits.normal[cand] * np.float32(0.02)
            pid_static = np.where(p[cand] < n_static, p[cand], -1)
            vis = shadows.lit(pts, pid_static, cos_sun[cand])
            if len(prims) > n_static:
                moving = prims.subset(np.arange(n_static, len(prims)))
                vis *= ~occluded_towards(moving, pts, sun, t_min=1e-3, groups=moving.instance)
            sun_vis[cand] = vis
    sun_term = sun_vis * np.maximum(cos_sun, 0)
    hemi = np.float32(0.62) + np.float32(0.38) * hits.normal[:, 2]
    light = (np.float32(0.42) * hemi)[:, None] * np.array([0.93, 0.97, 1.06], np.float32) + (
        np.float32(0.78) * sun_term
    )[:, None] * np.array([1.0, 0.96, 0.88], np.float32)
    color = albedo * light
    color += _specular(prims, p, hits, view, sun32, sun_vis > 0.5)
    haze = np.exp(-dist / np.float32(420.0))[:, None]
    linear = np.empty((h * w, 3), np.float32)
    linear[idx] = color * haze + _HAZE * (1 - haze)
    miss = np.flatnonzero(flat_pid < 0)
    linear[miss] = _sky(np.stack([dirs[k].reshape(-1)[miss] for k in range(3)], axis=1), sun32)
    rgb = _sensor_image(linear.reshape(h, w, 3), cfg.noise_std, rng)

    def gt(column: npt.NDArray[np.uint16]) -> npt.NDArray[np.uint16]:
        return _scatter(column[p], idx, h, w)

    depth_out = np.where(pid >= 0, depth, np.float32(np.inf)).astype(np.float32)
    return CameraFrame(
        rgb=rgb,
        semantic=gt(prims.semantic),
        instance=gt(prims.instance),
        name=gt(prims.name),
        depth=depth_out,
        cell=_scatter(world_cells(world), idx, h, w),
    )


def _scatter(
    values: npt.NDArray[np.uint16], idx: npt.NDArray[np.int64], h: int, w: int
) -> npt.NDArray[np.uint16]:
    """(H, W) image holding ``values`` at the flat pixel indices ``idx`` and 0 elsewhere."""
    img = np.zeros(h * w, np.uint16)
    img[idx] = values
    return img.reshape(h, w)


def _sensor_image(linear: F32, noise_std: float, rng: np.random.Generator) -> npt.NDArray[np.uint8]:
    """(H, W, 3) uint8 image of (H, W, 3) linear colour in [0, 1]: a light optical blur, then Gaussian
    sensor noise of ``noise_std`` (8-bit units) and rounding."""
    img = np.asarray(cv2.GaussianBlur(linear, (3, 3), 0.55), dtype=np.float32)
    img *= np.float32(255.0)
    img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_std) + np.float32(0.5)
    return np.clip(img, 0, 255).astype(np.uint8)


def _sky(d: F32, sun: F32) -> F32:
    """(n, 3) colour of rays that hit nothing: horizon-to-zenith gradient, sun glow and soft clouds above
    the horizon, hazy distant ground below it (beyond the built blocks)."""
    n = d / np.linalg.norm(d, axis=1, keepdims=True)
    e = np.clip(n[:, 2], -1, 1)
    k = np.clip(e * 2.5, 0, 1)[:, None] ** 0.6
    zenith = np.array([0.33, 0.52, 0.82], np.float32)
    col = _HORIZON * (1 - k) + zenith * k
    glow = np.maximum(n @ sun, 0) ** 24
    col += glow[:, None] * np.array([0.35, 0.3, 0.2], np.float32)
    up = np.flatnonzero(e > 0.01)
    if up.size:
        s = np.float32(60.0) / (e[up] + np.float32(0.08))
        cu, cv = n[up, 0] * s, n[up, 1] * s
        cl = noise("smooth", cu, cv, 0.5, s * np.float32(0.004)) * np.float32(0.5) + noise(
            "smooth", cu * 3, cv * 3, 0.5, 0.5
        ) * np.float32(0.2)
        cover = np.clip(cl - np.float32(0.15), 0, 1)[:, None]
        col[up] = col[up] * (1 - cover * 0.8) + np.float32(0.96) * cover * 0.8
    down = np.flatnonzero(e < 0)
    if down.size:
        g = np.clip(-e[down] * 40, 0, 1)[:, None]
        col[down] = _HAZE * (1 - g * 0.25) + np.array([0.36, 0.4, 0.3], np.float32) * g * 0.25
    return np.asarray(col, dtype=np.float32)


def _specular(
    prims: Primitives,
    p: npt.NDArray[np.int32],
    hits: SurfaceHits,
    view: F32,
    sun: F32,
    lit: npt.NDArray[np.bool_],
) -> F32:
    """Blinn-Phong highlights and sky reflections on car paint and glass."""
    out = np.zeros((len(p), 3), np.float32)
    mat = prims.material[p]
    sel = np.flatnonzero((mat == M.PAINT) | (mat == M.GLASS) | (mat == M.METAL))
    if sel.size == 0:
        return out
    nrm = hits.normal[sel]
    v = -view[sel]
    half = v + sun
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    spec = np.maximum(np.einsum("ij,ij->i", nrm, half), 0) ** 60 * lit[sel]
    fres = (1 - np.abs(np.einsum("ij,ij->i", nrm, v))) ** 3
    out[sel] = (np.float32(0.55) * spec + np.float32(0.18) * fres)[:, None] * np.array(
        [1.0, 1.0, 1.0], np.float32
    )
    return out


def _hash01(*ints: npt.NDArray[np.int64]) -> F32:
    """Deterministic pseudo-random value in [0, 1) per integer tuple (cell / window / slab index)."""
    h = np.zeros_like(ints[0], dtype=np.uint64)
    for k, v in enumerate(ints):
        h ^= v.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15 * (k + 1) & 0xFFFFFFFFFFFFFFFF)
        h = (h ^ (h >> np.uint64(31))) * np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(29)
    return np.asarray((h >> np.uint64(40)).astype(np.float64) / float(1 << 24), dtype=np.float32)


def _albedo(  # noqa: PLR0912, PLR0915  one short branch per material, read as a table
    prims: Primitives, p: npt.NDArray[np.int32], hits: SurfaceHits, world: F32, fp: F32, view: F32
) -> F32:
    """(n, 3) textured surface colour per hit, by material."""
    mat = prims.material[p]
    base = prims.color[p].copy()
    out = base.copy()
    loc, face = hits.local, hits.face
    half = prims.half[p].astype(np.float32)
    param = prims.param[p]
    x, y, z = world[:, 0], world[:, 1], world[:, 2]

    def sel(m: int) -> npt.NDArray[np.int64]:
        return np.flatnonzero(mat == m)

    i = sel(M.ASPHALT)
    if i.size:
        g = noise("grain", x[i], y[i], 0.018, fp[i])
        s1 = noise("smooth", x[i], y[i], 0.35, fp[i])
        s2 = noise("smooth", x[i] * 0.7, y[i] * 0.7, 2.5, fp[i])
        tone = 1 + 0.07 * g + 0.06 * s1 + 0.07 * s2
        col = base[i] * tone[:, None]
        top = face[i] == 4
        paint = np.where(top, road_paint(loc[i], param[i], fp[i]), 0)
        out[i] = col * (1 - paint[:, None]) + np.float32(0.86) * paint[:, None]
    i = sel(M.PAVERS)
    if i.size:
        seam = np.maximum(box_pattern(x[i], 0.22, 0.1, fp[i]), box_pattern(y[i] + 0.05, 0.22, 0.1, fp[i]))
        cell = _hash01(np.floor(x[i] / 0.22).astype(np.int64), np.floor(y[i] / 0.22).astype(np.int64))
        g = noise("grain", x[i], y[i], 0.02, fp[i])
        tone = (0.9 + 0.18 * cell * (1 - np.clip(fp[i] / 0.1, 0, 1)) + 0.05 * g) * (1 - 0.35 * seam)
        out[i] = base[i] * tone[:, None]
    i = sel(M.SLABS)
    if i.size:
        top = face[i] == 4
        seam = np.maximum(
            box_pattern(x[i] + 0.02, 0.5, 0.05, fp[i]), box_pattern(y[i] + 0.02, 0.5, 0.05, fp[i])
        )
        cell = _hash01(np.floor(x[i] / 0.5).astype(np.int64), np.floor(y[i] / 0.5).astype(np.int64))
        g = noise("grain", x[i], y[i], 0.02, fp[i])
        s = noise("smooth", x[i], y[i], 0.6, fp[i])
        tone_top = (0.94 + 0.1 * cell * (1 - np.clip(fp[i] / 0.2, 0, 1)) + 0.04 * g + 0.05 * s) * (
            1 - 0.25 * seam
        )
        tone_side = 1.12 + 0.05 * g
        out[i] = base[i] * np.where(top, tone_top, tone_side)[:, None]
    i = sel(M.GRASS)
    if i.size:
        g = noise("grain", x[i], y[i], 0.025, fp[i])
        s = noise("smooth", x[i], y[i], 0.4, fp[i])
        s2 = noise("smooth", y[i] * 0.9, x[i] * 0.9, 2.0, fp[i])
        dry = np.clip(0.5 + 0.35 * s2, 0, 1)[:, None]
        col = base[i] * (1 - 0.35 * dry) + np.array([0.46, 0.45, 0.24], np.float32) * 0.35 * dry
        out[i] = col * (0.85 + 0.17 * g + 0.1 * s)[:, None]
    i = sel(M.LEAVES)
    if i.size:
        # Triplanar leaf noise: three planar projections blended by the normal, so curved crowns show no
        # stretched streaks.
        seed = param[i, 0]
        nrm = np.abs(hits.normal[i]) ** 4
        nrm /= nrm.sum(axis=1, keepdims=True)
        xi, yi, zi = x[i] + seed, y[i] - seed, z[i]
        lf = (
            nrm[:, 0] * noise("leaf", yi, zi, 0.045, fp[i])
            + nrm[:, 1] * noise("leaf", xi, zi, 0.045, fp[i])
            + nrm[:, 2] * noise("leaf", xi, yi, 0.045, fp[i])
        )
        lf2 = (
            nrm[:, 0] * noise("smooth", yi, zi, 0.25, fp[i])
            + nrm[:, 1] * noise("smooth", xi, zi, 0.25, fp[i])
            + nrm[:, 2] * noise("smooth", xi, yi, 0.25, fp[i])
        )
        val = np.clip(0.66 + 0.3 * lf + 0.22 * lf2, 0.12, 1.25)
        gaps = np.clip(-lf - 1.0, 0, 1) * 0.65
        hue = np.clip(0.5 + 0.45 * lf2, 0, 1)[:, None]
        col = base[i] * (1 - 0.3 * hue) + np.array([0.36, 0.44, 0.13], np.float32) * 0.3 * hue
        out[i] = col * (val * (1 - gaps))[:, None]
    i = sel(M.BARK)
    if i.size:
        ang = np.arctan2(loc[i, 1], loc[i, 0]) * half[i, 0]
        g = noise("grain", ang * 4, z[i] * 0.35, 0.02, fp[i])
        out[i] = base[i] * (0.78 + 0.22 * g)[:, None]
    i = sel(M.FACADE)
    if i.size:
        out[i] = _facade(base[i], loc[i], half[i], face[i], param[i], fp[i])
    i = sel(M.ROOF)
    if i.size:
        rows = box_pattern(loc[i, 1], 0.34, 0.12, fp[i])
        cell = _hash01(
            np.floor(loc[i, 1] / 0.34).astype(np.int64), np.floor(loc[i, 0] / 0.25).astype(np.int64)
        )
        g = noise("grain", loc[i, 0], loc[i, 1], 0.02, fp[i])
        out[i] = (
            base[i]
            * ((0.9 + 0.15 * cell * (1 - np.clip(fp[i] / 0.1, 0, 1)) + 0.05 * g) * (1 - 0.4 * rows))[:, None]
        )
    i = sel(M.METAL)
    if i.size:
        g = noise("grain", x[i] + y[i], z[i], 0.03, fp[i])
        out[i] = base[i] * (0.9 + 0.1 * g)[:, None]
    i = sel(M.SIGN)
    if i.size:
        out[i] = _sign(loc[i], half[i], face[i], param[i], prims.kind[p[i]])
    i = sel(M.PAINT)
    if i.size:
        out[i] = _car_body(base[i], loc[i], half[i], face[i], param[i])
    i = sel(M.GLASS)
    if i.size:
        # Cabin boxes: glass sides between pillars, painted roof. Screen wedges (param 1): glass on the
        # sloped top face between the A-pillars, paint elsewhere.
        wedge = param[i, 0] > 0.5
        side = face[i] <= 3
        along = np.where(face[i] <= 1, np.abs(loc[i, 1]) / half[i, 1], np.abs(loc[i, 0]) / half[i, 0])
        pillar = side & ((along > 0.9) | ((face[i] >= 2) & (np.abs(loc[i, 0]) / half[i, 0] < 0.05)))
        lowz = (loc[i, 2] / half[i, 2]) < -0.88
        cabin_glass = ~wedge & side & ~pillar & ~lowz
        wedge_glass = (
            wedge
            & (face[i] == 4)
            & (np.abs(loc[i, 1]) / half[i, 1] < 0.88)
            & (np.abs(loc[i, 0]) / half[i, 0] < 0.93)
        )
        sky_ref = np.clip(0.5 - 0.5 * view[i, 2], 0, 1)
        glass = np.array([0.07, 0.085, 0.1], np.float32) + np.float32(0.12) * sky_ref[:, None]
        out[i] = np.where((cabin_glass | wedge_glass)[:, None], glass, base[i])
    i = sel(M.RUBBER)
    if i.size:
        cap = face[i] <= 5
        rad = np.hypot(loc[i, 0], loc[i, 1]) / half[i, 0]
        rim = cap & (rad < 0.62)
        out[i] = np.where(rim[:, None], np.array([0.55, 0.56, 0.58], np.float32), base[i])
    i = sel(M.CLOTH)
    if i.size:
        g = noise("grain", x[i] + y[i], z[i], 0.015, fp[i])
        out[i] = base[i] * (0.88 + 0.12 * g)[:, None]
    i = sel(M.SKIN)
    if i.size:
        hair = (loc[i, 2] / half[i, 2] > 0.35) | (
            (loc[i, 0] / half[i, 0] < -0.3) & (loc[i, 2] / half[i, 2] > -0.2)
        )
        out[i] = np.where(hair[:, None], np.array([0.12, 0.08, 0.05], np.float32), base[i])
    i = sel(M.FENCE)
    if i.size:
        along = np.where(half[i, 0] > half[i, 1], loc[i, 0], loc[i, 1])
        style = param[i, 0]
        hgt = loc[i, 2] + half[i, 2]
        slats = box_pattern(along, 0.13, 0.78, fp[i])
        bars = box_pattern(along, 0.12, 0.3, fp[i])
        rail = ((hgt > 2 * half[i, 2] - 0.08) | ((hgt > 0.2) & (hgt < 0.28))).astype(np.float32)
        g = noise("grain", along, hgt, 0.02, fp[i])
        wood = base[i] * ((0.55 + 0.45 * slats) * (0.9 + 0.1 * g))[:, None]
        metal = (
            base[i] * (0.45 + 0.55 * np.maximum(bars, rail))[:, None]
            + np.array([0.16, 0.2, 0.12], np.float32) * (1 - np.maximum(bars, rail))[:, None]
        )
        out[i] = np.where((style == 0)[:, None], wood, metal)
    i = sel(M.TARP)
    if i.size:
        along = loc[i, 0]
        panel = box_pattern(along + 0.02, 1.2, 0.03, fp[i])
        g = noise("smooth", along, loc[i, 2], 0.3, fp[i])
        out[i] = base[i] * ((0.92 + 0.06 * g) * (1 - 0.3 * panel))[:, None]
    i = sel(M.SOIL)
    if i.size:
        g = noise("grain", x[i], y[i], 0.03, fp[i])
        s = noise("smooth", x[i] * 0.8, y[i] * 0.8, 1.5, fp[i])
        ang = param[i, 1]
        across = -x[i] * np.sin(ang) + y[i] * np.cos(ang)
        spacing = np.maximum(param[i, 0], np.float32(0.1))
        furrow = np.where(param[i, 0] > 0, box_pattern(across / spacing, 1.0, 0.4, fp[i] / spacing), 0)
        out[i] = base[i] * ((0.88 + 0.1 * g + 0.1 * s) * (1 - 0.25 * furrow))[:, None]
    i = sel(M.CROP)
    if i.size:
        ang = param[i, 1]
        across = -x[i] * np.sin(ang) + y[i] * np.cos(ang)
        spacing = np.maximum(param[i, 0], np.float32(0.1))
        rows = box_pattern(across / spacing, 1.0, 0.35 + 0.5 * param[i, 2], fp[i] / spacing)
        rows = np.where(face[i] == 4, rows, np.float32(0.8))
        g = noise("leaf", x[i], y[i], 0.04, fp[i])
        s = noise("smooth", x[i], y[i], 3.0, fp[i])
        soil = np.array([0.36, 0.27, 0.18], np.float32)
        leaf = base[i] * (0.85 + 0.15 * g + 0.12 * s)[:, None]
        out[i] = leaf * rows[:, None] + soil * (1 - rows)[:, None]
    return np.asarray(np.clip(out, 0, 1.2), dtype=np.float32)


def _facade(base: F32, loc: F32, half: F32, face: npt.NDArray[np.int8], param: F32, fp: F32) -> F32:
    """Walls with windows (plaster, brick or glass bands), plinth and flat roof."""
    out = base.copy()
    side = face <= 3
    floor_h, spacing, style, seed = param[:, 0], param[:, 1], param[:, 2], param[:, 3]
    u, hgt = facade_uv(loc, half, face)
    width = np.where(face <= 1, 2 * half[:, 1], 2 * half[:, 0])
    g = noise("grain", u + seed, hgt, 0.02, fp)
    s = noise("smooth", u + seed, hgt, 0.5, fp)
    wall = base * (0.93 + 0.04 * g + 0.06 * s)[:, None]
    brick = style == 1
    if brick.any():
        row = np.floor(hgt / 0.075)
        mortar = np.maximum(
            box_pattern(hgt, 0.075, 0.16, fp), box_pattern(u + 0.125 * (row % 2), 0.25, 0.06, fp)
        )
        wall[brick] *= (
            1
            - 0.18 * mortar[brick]
            + 0.12
            * _hash01(row.astype(np.int64), np.floor(u / 0.25).astype(np.int64))[brick]
            * (1 - np.clip(fp[brick] / 0.05, 0, 1))
        )[:, None]
    win, frame = window_mask(u, hgt, width, floor_h, spacing, fp)
    office = style == 2
    if office.any():
        fz = (hgt / floor_h) % 1.0
        band = ((fz > 0.28) & (fz < 0.95) & (hgt > floor_h)).astype(np.float32)
        mull = box_pattern(u, 1.5, 0.04, fp)
        win = np.where(office, band * (1 - mull), win)
        frame = np.where(office, band * mull, frame)
    wi = np.floor(u / spacing).astype(np.int64)
    fl = np.floor(hgt / floor_h).astype(np.int64)
    hv = _hash01(wi, fl, np.floor(seed).astype(np.int64))
    sky_ref = np.clip(0.35 + 0.6 * ((hgt / floor_h) % 1.0), 0, 1) * 0.18
    glass = np.stack([0.09 + sky_ref, 0.11 + sky_ref * 1.1, 0.14 + sky_ref * 1.3], axis=1).astype(np.float32)
    curtain = (hv > 0.7) & (((hgt / floor_h) % 1.0) > 0.55)
    glass = np.where(curtain[:, None], np.array([0.55, 0.52, 0.45], np.float32), glass)
    glass *= (0.8 + 0.4 * hv)[:, None]
    frame_col = np.array([0.86, 0.86, 0.84], np.float32)
    col = wall * (1 - win - frame)[:, None] + glass * win[:, None] + frame_col * frame[:, None]
    plinth = (hgt < 0.45).astype(np.float32)[:, None]
    col = col * (1 - plinth * 0.35)
    out = np.where(side[:, None], col, out)
    roof = face == 4
    out[roof] = np.array([0.36, 0.35, 0.34], np.float32) * (0.9 + 0.1 * g[roof])[:, None]
    return np.asarray(out, dtype=np.float32)


def _sign(loc: F32, half: F32, face: npt.NDArray[np.int8], param: F32, kind: npt.NDArray[np.int8]) -> F32:
    """Sign plates: a coloured, bordered front face, grey metal elsewhere."""
    style = param[:, 0]
    disc = kind == 1
    front = np.where(disc, face == 4, face == 0)
    # Normalised plate coordinates (a across, b up) and the distance to the edge in metres.
    a = np.where(disc, loc[:, 0], loc[:, 1])
    b = np.where(disc, loc[:, 1], loc[:, 2])
    ha = np.where(disc, half[:, 0], half[:, 1])
    hb = np.where(disc, half[:, 0], half[:, 2])
    rad = np.hypot(a, b)
    edge = np.where(disc, half[:, 0] - rad, np.minimum(ha - np.abs(a), hb - np.abs(b)))
    white = np.array([0.92, 0.92, 0.9], np.float32)
    red = np.array([0.78, 0.08, 0.07], np.float32)
    blue = np.array([0.05, 0.22, 0.6], np.float32)
    yellow = np.array([0.95, 0.76, 0.08], np.float32)
    black = np.array([0.06, 0.06, 0.06], np.float32)
    out = np.tile(np.array([0.55, 0.56, 0.58], np.float32), (len(loc), 1))
    c = np.tile(white, (len(loc), 1))
    border = edge < 0.045
    symbol = (np.abs(a) < 0.3 * ha) & (np.abs(b) < 0.55 * hb)
    s0, s1, s2, s3 = style == 0, style == 1, style == 2, style == 3
    c[s0] = np.where((border | symbol)[s0, None], white, blue)
    ring = np.where(disc, edge < 0.22 * half[:, 0], edge < 0.07)
    bar = (np.abs(b) < 0.12 * hb) & (np.abs(a) < 0.6 * ha)
    c[s1] = np.where(ring[s1, None], red, np.where(bar[s1, None], black, white))
    text = (np.abs(a) < 0.75 * ha) & ((np.abs(b) * 4 / hb) % 1.0 < 0.35) & (np.abs(b) < 0.6 * hb)
    c[s2] = np.where(border[s2, None], black, np.where(text[s2, None], black, yellow))
    c[s3] = np.where((edge < 0.035)[s3, None], red, np.where(text[s3, None], black, white))
    return np.where(front[:, None], c, out)


def _car_body(base: F32, loc: F32, half: F32, face: npt.NDArray[np.int8], param: F32) -> F32:
    """Car paint with head lamps and grille at the front (+x), tail lamps and plate at the back, dark
    sills and a door seam on the sides."""
    out = base.copy()
    yn = loc[:, 1] / half[:, 1]
    zn = loc[:, 2] / half[:, 2]
    front, back, side = face == 0, face == 1, (face == 2) | (face == 3)
    lamp = (np.abs(yn) > 0.6) & (np.abs(yn) < 0.92) & (zn > 0.25) & (zn < 0.75)
    grille = (np.abs(yn) < 0.45) & (zn > 0.1) & (zn < 0.6)
    plate = (np.abs(loc[:, 1]) < 0.26) & (np.abs(loc[:, 2] + 0.25 * half[:, 2]) < 0.065)
    bumper = zn < -0.45
    truck = param[:, 0] > 0.5
    out = np.where((front & lamp)[:, None], np.array([0.95, 0.95, 0.9], np.float32), out)
    out = np.where((front & grille & ~truck)[:, None], np.array([0.08, 0.08, 0.09], np.float32), out)
    out = np.where((front & truck & (zn > 0.15))[:, None], np.array([0.08, 0.1, 0.12], np.float32), out)
    out = np.where((back & lamp)[:, None], np.array([0.7, 0.05, 0.04], np.float32), out)
    out = np.where(((front | back) & plate)[:, None], np.array([0.92, 0.92, 0.88], np.float32), out)
    out = np.where(((front | back) & bumper & ~plate)[:, None], np.array([0.1, 0.1, 0.1], np.float32), out)
    sill = side & (zn < -0.7)
    seam = side & (np.abs(loc[:, 0] - 0.05 * half[:, 0]) < 0.012) & (zn > -0.7)
    out = np.where((sill | seam)[:, None], out * 0.45, out)
    return out
