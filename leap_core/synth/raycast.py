"""Vectorised ray casting of analytic primitives onto regular ray grids (camera pixels, LiDAR beams).

Every sensor here shoots all of its rays from ONE origin, laid out on a 2D grid whose ray direction is
monotonic in both grid indices (image rows/columns, LiDAR beams/azimuth columns). That allows the cheap
"splatting" form of ray casting used here: for each primitive, bound its projection onto the grid by a
rectangle of grid cells (a *task*), and intersect only those rays with it, keeping the nearest hit per ray
in a depth buffer. The work is the summed rectangle area, not rays × primitives.

Primitives live in their own local frame: ``world = center + rot @ local``.

- box: ``|local_k| <= half_k`` for k = x, y, z;
- cylinder: ``local_x² + local_y² <= half_x²`` and ``|local_z| <= half_z`` (axis = local z);
- ellipsoid: ``Σ_k (local_k / half_k)² <= 1``.

Faces of a hit are numbered ``2k`` for the +k face of a box (or the +z cap of a cylinder), ``2k + 1`` for
the −k face, :data:`FACE_SIDE` for the curved side of a cylinder and :data:`FACE_CURVED` for an ellipsoid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

BOX: Final = 0
"""``Primitives.kind`` of an oriented box."""
CYLINDER: Final = 1
"""``Primitives.kind`` of a capped cylinder along its local z axis."""
ELLIPSOID: Final = 2
"""``Primitives.kind`` of an ellipsoid with semi-axes ``half``."""

FACE_SIDE: Final = 6
"""Face id of a hit on a cylinder's curved side."""
FACE_CURVED: Final = 7
"""Face id of a hit on an ellipsoid."""

_ROT_IDENTITY, _ROT_YAW, _ROT_GENERAL = 0, 1, 2

# Corner sign pattern of a box and its 12 edges (pairs of corner indices differing in one sign).
_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
_EDGES = np.array(
    [
        (a, b)
        for a in range(8)
        for b in range(a + 1, 8)
        if np.abs(_CORNER_SIGNS[a] - _CORNER_SIGNS[b]).sum() == 2
    ]
)


@dataclass(frozen=True)
class Primitives:
    """A flat table of P analytic primitives with their labels and appearance.

    Attributes:
        kind: (P,) int8, :data:`BOX`, :data:`CYLINDER` or :data:`ELLIPSOID`.
        center: (P, 3) float64 world position of the local origin.
        rot: (P, 3, 3) float64 rotation local → world (columns are the local axes in world coordinates).
        half: (P, 3) float64 half extents (box), (radius, radius, half height) (cylinder) or semi-axes.
        semantic: (P,) uint16 raw SemanticKITTI class id.
        instance: (P,) uint16 instance id (0 for stuff).
        name: (P,) uint16 fine-grained name id (``leap_core.synth.names``; 0 = no name).
        material: (P,) uint8 material id (``leap_core.synth.materials.Material``).
        color: (P, 3) float32 base albedo in [0, 1] (linear RGB).
        param: (P, 4) float32 material-specific texture parameters (see ``materials``).
    """

    kind: npt.NDArray[np.int8]
    center: npt.NDArray[np.float64]
    rot: npt.NDArray[np.float64]
    half: npt.NDArray[np.float64]
    semantic: npt.NDArray[np.uint16]
    instance: npt.NDArray[np.uint16]
    name: npt.NDArray[np.uint16]
    material: npt.NDArray[np.uint8]
    color: npt.NDArray[np.float32]
    param: npt.NDArray[np.float32]

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    @staticmethod
    def empty() -> Primitives:
        return Primitives(
            kind=np.zeros(0, np.int8),
            center=np.zeros((0, 3)),
            rot=np.zeros((0, 3, 3)),
            half=np.zeros((0, 3)),
            semantic=np.zeros(0, np.uint16),
            instance=np.zeros(0, np.uint16),
            name=np.zeros(0, np.uint16),
            material=np.zeros(0, np.uint8),
            color=np.zeros((0, 3), np.float32),
            param=np.zeros((0, 4), np.float32),
        )

    @staticmethod
    def concat(parts: Sequence[Primitives]) -> Primitives:
        """Concatenate primitive tables in order."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return Primitives.empty()
        return Primitives(
            **{f: np.concatenate([getattr(p, f) for p in parts]) for f in Primitives.__dataclass_fields__}
        )

    def subset(self, index: npt.NDArray[np.integer] | npt.NDArray[np.bool_]) -> Primitives:
        """Rows ``index`` of every field."""
        return Primitives(**{f: getattr(self, f)[index] for f in Primitives.__dataclass_fields__})

    def transformed(self, rot: npt.NDArray[np.float64], trans: npt.NDArray[np.float64]) -> Primitives:
        """Apply the rigid transform ``x ↦ rot @ x + trans`` to every primitive (object parts → world)."""
        return Primitives(
            kind=self.kind,
            center=self.center @ rot.T + trans,
            rot=np.einsum("ij,pjk->pik", rot, self.rot),
            half=self.half,
            semantic=self.semantic,
            instance=self.instance,
            name=self.name,
            material=self.material,
            color=self.color,
            param=self.param,
        )

    def bounding_radius(self) -> npt.NDArray[np.float64]:
        """(P,) radius of a sphere around ``center`` that contains each primitive."""
        r = np.asarray(np.linalg.norm(self.half, axis=1), dtype=np.float64)
        cyl = self.kind == CYLINDER
        r[cyl] = np.hypot(self.half[cyl, 0] * np.sqrt(2), self.half[cyl, 2])
        ell = self.kind == ELLIPSOID
        r[ell] = self.half[ell].max(axis=1)
        return r

    def corners(self) -> npt.NDArray[np.float64]:
        """(P, 8, 3) world corners of each primitive's oriented bounding box.

        ``corners[p, i] = center_p + rot_p @ (signs_i * half_p)`` with signs_i in {-1, 1}³.
        """
        half = self.half.copy()
        cyl = self.kind == CYLINDER
        half[cyl, 1] = half[cyl, 0]  # a cylinder's radius is half[0]
        local = _CORNER_SIGNS[None] * half[:, None, :]
        return np.asarray(self.center[:, None, :] + np.einsum("pij,pkj->pki", self.rot, local), np.float64)


def rotation_z(yaw: float) -> npt.NDArray[np.float64]:
    """3×3 rotation by ``yaw`` radians about +z (counter-clockwise seen from above)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_xyz(roll: float, pitch: float, yaw: float) -> npt.NDArray[np.float64]:
    """3×3 rotation ``Rz(yaw) · Ry(pitch) · Rx(roll)`` (angles in radians)."""
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return np.asarray(rotation_z(yaw) @ ry @ rx, dtype=np.float64)


# ------------------------------------------------------------------------------------ intersections
# Each function takes the ray origin (ox, oy, oz) and direction (dx, dy, dz) in the primitive's LOCAL
# frame; each component is a Python float or a float32 array, all broadcastable to one shape (a shared
# origin with many directions, or many origins with one direction). It returns the entry distance t
# (float32, t in units of |d|), or +inf where the ray misses or enters at t <= t_min.
Arr = npt.NDArray[np.float32] | float


def _halves(half: npt.NDArray[np.float64] | npt.NDArray[np.float32]) -> tuple[Arr, Arr, Arr]:
    """Half extents as three Python floats (one primitive) or three float32 columns (one per ray)."""
    if half.ndim == 1:
        return float(half[0]), float(half[1]), float(half[2])
    h = half.astype(np.float32, copy=False)
    return h[:, 0], h[:, 1], h[:, 2]


def intersect_box(
    ox: Arr, oy: Arr, oz: Arr, dx: Arr, dy: Arr, dz: Arr, *, half: npt.NDArray[np.float64], t_min: float
) -> npt.NDArray[np.float32]:
    """Slab test: t = max_k min(t_k⁻, t_k⁺), hit iff t <= min_k max(t_k⁻, t_k⁺) and t > t_min,
    with t_k^± = (±half_k − o_k) / d_k."""
    with np.errstate(all="ignore"):
        return _box(ox, oy, oz, dx, dy, dz, half=half, t_min=t_min)


def _slab(o: Arr, d: Arr, h: Arr) -> tuple[Arr, Arr]:
    """Entry and exit distance ``(min(t⁻, t⁺), max(t⁻, t⁺))`` of the slab ``|o + t·d| <= h`` on one axis."""
    inv = np.float32(1.0) / d if isinstance(d, np.ndarray) else 1.0 / d if d != 0 else np.inf
    ta = (-h - o) * inv
    tb = (h - o) * inv
    return np.minimum(ta, tb), np.maximum(ta, tb)


def _box(
    ox: Arr,
    oy: Arr,
    oz: Arr,
    dx: Arr,
    dy: Arr,
    dz: Arr,
    *,
    half: npt.NDArray[np.float64],
    t_min: float,
) -> npt.NDArray[np.float32]:
    hx, hy, hz = _halves(half)
    tnear, tfar = _slab(ox, dx, hx)
    for ok, dk, hk in ((oy, dy, hy), (oz, dz, hz)):
        lo, hi = _slab(ok, dk, hk)
        tnear = np.maximum(tnear, lo)
        tfar = np.minimum(tfar, hi)
    hit = (tnear <= tfar) & (tnear > t_min)
    return np.where(hit, tnear, np.float32(np.inf)).astype(np.float32, copy=False)


def intersect_cylinder(
    ox: Arr, oy: Arr, oz: Arr, dx: Arr, dy: Arr, dz: Arr, *, half: npt.NDArray[np.float64], t_min: float
) -> npt.NDArray[np.float32]:
    """Side: smallest root of (ox + t dx)² + (oy + t dy)² = r² with |oz + t dz| <= h; cap: the plane
    z = ±h on the origin's side (when |oz| > h), inside the disc. Returns the nearer valid one."""
    with np.errstate(all="ignore"):
        return _cylinder(ox, oy, oz, dx, dy, dz, half=half, t_min=t_min)


def _cylinder(
    ox: Arr,
    oy: Arr,
    oz: Arr,
    dx: Arr,
    dy: Arr,
    dz: Arr,
    *,
    half: npt.NDArray[np.float64],
    t_min: float,
) -> npt.NDArray[np.float32]:
    r, _, h = _halves(half)
    a = dx * dx + dy * dy
    b = dx * ox + dy * oy
    c = ox * ox + oy * oy - r * r
    disc = b * b - a * c
    t_side = (-b - np.sqrt(disc)) / a
    z = oz + t_side * dz
    t = np.where((disc >= 0) & (np.abs(z) <= h) & (t_side > t_min), t_side, np.float32(np.inf))
    zc = np.where(oz > 0, h, -h)
    t_cap = (zc - oz) / dz
    px = ox + t_cap * dx
    py = oy + t_cap * dy
    ok = (np.abs(oz) > h) & (px * px + py * py <= r * r) & (t_cap > t_min) & (t_cap < t)
    t = np.where(ok, t_cap, t)
    return np.asarray(t, np.float32)


def intersect_ellipsoid(
    ox: Arr, oy: Arr, oz: Arr, dx: Arr, dy: Arr, dz: Arr, *, half: npt.NDArray[np.float64], t_min: float
) -> npt.NDArray[np.float32]:
    """Scale to the unit sphere (o' = o / s, d' = d / s) and take the smaller root of |o' + t d'|² = 1."""
    with np.errstate(all="ignore"):
        return _ellipsoid(ox, oy, oz, dx, dy, dz, half=half, t_min=t_min)


def _ellipsoid(
    ox: Arr,
    oy: Arr,
    oz: Arr,
    dx: Arr,
    dy: Arr,
    dz: Arr,
    *,
    half: npt.NDArray[np.float64],
    t_min: float,
) -> npt.NDArray[np.float32]:
    hx, hy, hz = _halves(half)
    sx, sy, sz = 1.0 / hx, 1.0 / hy, 1.0 / hz
    ox, oy, oz = ox * sx, oy * sy, oz * sz
    ex, ey, ez = dx * sx, dy * sy, dz * sz
    a = ex * ex + ey * ey + ez * ez
    b = ex * ox + ey * oy + ez * oz
    c = ox * ox + oy * oy + oz * oz - 1.0
    disc = b * b - a * c
    t = (-b - np.sqrt(disc)) / a
    return np.asarray(np.where((disc >= 0) & (t > t_min), t, np.float32(np.inf)), np.float32)


_INTERSECT = {BOX: _box, CYLINDER: _cylinder, ELLIPSOID: _ellipsoid}
"""Raw intersection per kind (callers silence floating-point warnings once around their loop)."""


# ----------------------------------------------------------------------------------- grid bounding
def pinhole_tasks(
    prims: Primitives,
    world_to_cam: npt.NDArray[np.float64],
    K: npt.NDArray[np.float64],
    width: int,
    height: int,
    max_range: float,
    *,
    near: float = 0.05,
) -> npt.NDArray[np.int64]:
    """Pixel rectangles that bound each primitive's image in a pinhole camera.

    Args:
        prims: P primitives in world coordinates.
        world_to_cam: (4, 4) world → camera (x right, y down, z forward; origin at the optical centre).
        K: (3, 3) intrinsics; pixel centres are at integer (u, v) = (K @ x)[:2] / z.
        width, height: image size.
        max_range: primitives whose bounding sphere lies entirely farther than this are culled.
        near: near clipping distance; the bounding box is clipped to z >= near before projection.

    Returns:
        (T, 5) int64 rows ``(p, v0, v1, u0, u1)``: rays in rows v0:v1 and columns u0:u1 may hit primitive p.
    """
    centers_cam = prims.center @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    keep = np.linalg.norm(centers_cam, axis=1) - prims.bounding_radius() <= max_range
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return np.zeros((0, 5), np.int64)
    corners = prims.subset(idx).corners() @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]  # (n, 8, 3)
    z = corners[..., 2]
    ok_c = z >= near
    a, b = corners[:, _EDGES[:, 0]], corners[:, _EDGES[:, 1]]
    za, zb = a[..., 2], b[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (near - za) / (zb - za)
    ok_e = (za - near) * (zb - near) < 0
    e = a + np.clip(s, 0, 1)[..., None] * (b - a)
    pts = np.concatenate([corners, e], axis=1)  # (n, 20, 3)
    ok = np.concatenate([ok_c, ok_e], axis=1)
    zz = np.where(ok, pts[..., 2], 1.0)
    u = K[0, 0] * pts[..., 0] / zz + K[0, 1] * pts[..., 1] / zz + K[0, 2]
    v = K[1, 1] * pts[..., 1] / zz + K[1, 2]
    big = 1e9
    u0 = np.where(ok, u, big).min(axis=1)
    u1 = np.where(ok, u, -big).max(axis=1)
    v0 = np.where(ok, v, big).min(axis=1)
    v1 = np.where(ok, v, -big).max(axis=1)
    any_ok = ok.any(axis=1)
    c0 = np.clip(np.ceil(u0) - 1, 0, width).astype(np.int64)
    c1 = np.clip(np.floor(u1) + 2, 0, width).astype(np.int64)
    r0 = np.clip(np.ceil(v0) - 1, 0, height).astype(np.int64)
    r1 = np.clip(np.floor(v1) + 2, 0, height).astype(np.int64)
    good = any_ok & (c1 > c0) & (r1 > r0)
    return np.asarray(np.stack([idx, r0, r1, c0, c1], axis=1)[good], dtype=np.int64)


def spherical_tasks(
    prims: Primitives,
    world_to_sensor: npt.NDArray[np.float64],
    elevations: npt.NDArray[np.float64],
    n_azimuth: int,
    max_range: float,
) -> npt.NDArray[np.int64]:
    """Cell rectangles that bound each primitive on a spinning LiDAR's (beam, azimuth) grid.

    Grid convention: row i has elevation ``elevations[i]`` (radians, strictly decreasing: row 0 is the top
    beam); column j has azimuth ``-π + (j + 0.5)·2π / n_azimuth`` (atan2(y, x) in the sensor frame).

    Bounds (conservative): with the box's xy footprint within ``ρ`` of its centre at horizontal distance
    ``d``, every point has horizontal distance in [d − ρ, d + ρ], so elevations lie in
    [atan2(z_min, ·), atan2(z_max, ·)] with the distance chosen per sign of z. The azimuth interval spans
    the corners' azimuths relative to the centre's, or the full circle when d <= ρ. Wrapping intervals are
    split into two tasks.

    Returns:
        (T, 5) int64 rows ``(p, r0, r1, c0, c1)``.
    """
    rot, trans = world_to_sensor[:3, :3], world_to_sensor[:3, 3]
    centers = prims.center @ rot.T + trans
    keep = np.linalg.norm(centers, axis=1) - prims.bounding_radius() <= max_range
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return np.zeros((0, 5), np.int64)
    corners = prims.subset(idx).corners() @ rot.T + trans  # (n, 8, 3)
    cxy = corners[..., :2].mean(axis=1)
    d = np.linalg.norm(cxy, axis=1)
    rho = np.linalg.norm(corners[..., :2] - cxy[:, None], axis=2).max(axis=1)
    zmin, zmax = corners[..., 2].min(axis=1), corners[..., 2].max(axis=1)
    dmin, dmax = np.maximum(d - rho, 1e-6), d + rho
    e_hi = np.arctan2(zmax, np.where(zmax > 0, dmin, dmax))
    e_lo = np.arctan2(zmin, np.where(zmin < 0, dmin, dmax))
    # Rows: beams with e_lo <= elevation <= e_hi (elevations decreasing), one beam of slack each side.
    neg = -elevations
    r0 = np.clip(np.searchsorted(neg, -e_hi, side="left") - 1, 0, len(elevations))
    r1 = np.clip(np.searchsorted(neg, -e_lo, side="right") + 1, 0, len(elevations))
    step = 2 * np.pi / n_azimuth
    az_c = np.arctan2(cxy[:, 1], cxy[:, 0])
    rel = np.arctan2(corners[..., 1], corners[..., 0]) - az_c[:, None]
    rel = (rel + np.pi) % (2 * np.pi) - np.pi
    full = d <= rho * 1.0001 + 1e-6
    a_lo, a_hi = az_c + rel.min(axis=1), az_c + rel.max(axis=1)
    j0 = np.floor((a_lo + np.pi) / step - 0.5).astype(np.int64) - 1
    j1 = np.ceil((a_hi + np.pi) / step - 0.5).astype(np.int64) + 2
    j0 = np.where(full, 0, j0)
    j1 = np.where(full | (j1 - j0 >= n_azimuth), j0 + n_azimuth, j1)
    rows = []
    for shift in (-n_azimuth, 0, n_azimuth):
        a, b = np.clip(j0 + shift, 0, n_azimuth), np.clip(j1 + shift, 0, n_azimuth)
        good = (b > a) & (r1 > r0)
        rows.append(np.stack([idx, r0, r1, a, b], axis=1)[good])
    return np.concatenate(rows)


# ----------------------------------------------------------------------------------------- casting
def _rot_types(rot: npt.NDArray[np.float64]) -> npt.NDArray[np.int8]:
    eye = np.abs(rot - np.eye(3)).max(axis=(1, 2)) < 1e-12
    yaw = (np.abs(rot[:, 2, :2]).max(axis=1) < 1e-12) & (np.abs(rot[:, :2, 2]).max(axis=1) < 1e-12)
    return np.where(eye, _ROT_IDENTITY, np.where(yaw, _ROT_YAW, _ROT_GENERAL)).astype(np.int8)


def cast_grid(
    prims: Primitives,
    origin: npt.NDArray[np.float64],
    dirs: npt.NDArray[np.float32],
    tasks: npt.NDArray[np.int64],
    t_min: float,
    t_max: float,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32]]:
    """Nearest hit per ray of a grid, shared origin.

    Tasks run front to back (by the nearest possible distance of their primitive), and a task is skipped
    when every ray of its rectangle already hit something nearer than that distance (occlusion culling:
    parked cars behind a building cost one slice and a max). The result does not depend on the order
    except for exact ties in t.

    Args:
        prims: primitives in world coordinates.
        origin: (3,) world position all rays start from.
        dirs: (3, R, C) float32 world ray directions, one plane per component (not necessarily unit).
        tasks: (T, 5) rows ``(p, r0, r1, c0, c1)`` from :func:`pinhole_tasks` / :func:`spherical_tasks`.
        t_min, t_max: only hits with t_min < t < t_max count (t in units of |d|).

    Returns:
        depth (R, C) float32 (t_max where nothing was hit) and pid (R, C) int32 primitive index (-1 = none).
    """
    _, n_rows, n_cols = dirs.shape
    depth = np.full((n_rows, n_cols), t_max, np.float32)
    pid = np.full((n_rows, n_cols), -1, np.int32)
    if len(tasks) == 0:
        return depth, pid
    rot_type = _rot_types(prims.rot)
    o_local = np.einsum("pji,pj->pi", prims.rot, origin[None] - prims.center).tolist()
    kind, rot, half = prims.kind, prims.rot, prims.half
    # Nearest possible hit of each task's primitive in units of t: (|c − o| − radius) / max |d|.
    d_max = float(np.sqrt((dirs[0] ** 2 + dirs[1] ** 2 + dirs[2] ** 2).max())) * 1.001
    p_all = tasks[:, 0]
    near = (np.linalg.norm(prims.center[p_all] - origin, axis=1) - prims.bounding_radius()[p_all]) / d_max
    order = np.argsort(near, kind="stable")
    with np.errstate(all="ignore"):
        # The per-primitive loop: the rays of each rectangle, depth test in place.
        for (p, r0, r1, c0, c1), t_near in zip(tasks[order].tolist(), near[order].tolist(), strict=True):
            if t_near > 0 and depth[r0:r1, c0:c1].max() <= t_near:
                continue  # fully hidden behind what is already in the depth buffer
            wx, wy, wz = dirs[0, r0:r1, c0:c1], dirs[1, r0:r1, c0:c1], dirs[2, r0:r1, c0:c1]
            rt = rot_type[p]
            if rt == _ROT_IDENTITY:
                dx, dy, dz = wx, wy, wz
            else:
                m = rot[p].astype(np.float32)
                dx = wx * m[0, 0] + wy * m[1, 0]
                dy = wx * m[0, 1] + wy * m[1, 1]
                if rt == _ROT_YAW:
                    dz = wz
                else:
                    dx += wz * m[2, 0]
                    dy += wz * m[2, 1]
                    dz = wx * m[0, 2] + wy * m[1, 2] + wz * m[2, 2]
            ox, oy, oz = o_local[p]
            t = _INTERSECT[int(kind[p])](ox, oy, oz, dx, dy, dz, half=half[p], t_min=t_min)
            zb = depth[r0:r1, c0:c1]
            closer = t < zb
            np.copyto(zb, t, where=closer)
            np.copyto(pid[r0:r1, c0:c1], p, where=closer)
    return depth, pid


@dataclass(frozen=True)
class SurfaceHits:
    """Surface attributes at n ray hits (deferred: computed once per ray after the depth test).

    Attributes:
        local: (n, 3) float32 hit point in the primitive's local frame.
        normal: (n, 3) float32 unit outward normal in world coordinates.
        face: (n,) int8 face id (see module docstring).
    """

    local: npt.NDArray[np.float32]
    normal: npt.NDArray[np.float32]
    face: npt.NDArray[np.int8]


def surface_hits(
    prims: Primitives,
    origin: npt.NDArray[np.float64],
    dirs: npt.NDArray[np.float32],
    t: npt.NDArray[np.float32],
    pid: npt.NDArray[np.int32],
) -> SurfaceHits:
    """Local hit point, world normal and face of n hits.

    Args:
        prims: the primitives cast against.
        origin: (3,) ray origin.
        dirs: (n, 3) ray directions (as cast).
        t: (n,) hit distances; pid: (n,) primitive index (all >= 0).
    """
    rot32 = prims.rot.astype(np.float32)
    o_local = np.einsum("pji,pj->pi", prims.rot, origin[None] - prims.center).astype(np.float32)
    rot = rot32[pid]  # (n, 3, 3)
    local = o_local[pid] + t[:, None] * np.einsum("nji,nj->ni", rot, dirs)
    half = prims.half[pid].astype(np.float32)
    kind = prims.kind[pid]
    n_local = np.zeros_like(local)
    face = np.zeros(len(pid), np.int8)
    q = np.abs(local) / np.maximum(half, 1e-6)
    box = kind == BOX
    if box.any():
        axis = q[box].argmax(axis=1)
        sign = np.sign(local[box, axis]).astype(np.float32)
        sign[sign == 0] = 1
        nb = np.zeros((int(box.sum()), 3), np.float32)
        nb[np.arange(len(axis)), axis] = sign
        n_local[box] = nb
        face[box] = (2 * axis + (sign < 0)).astype(np.int8)
    cyl = kind == CYLINDER
    if cyl.any():
        lc = local[cyl]
        rad = np.hypot(lc[:, 0], lc[:, 1])
        radial_q = rad / np.maximum(half[cyl, 0], 1e-6)
        side = np.abs(radial_q - 1) <= np.abs(q[cyl, 2] - 1)
        nc = np.zeros_like(lc)
        nc[:, 0] = np.where(side, lc[:, 0] / np.maximum(rad, 1e-9), 0)
        nc[:, 1] = np.where(side, lc[:, 1] / np.maximum(rad, 1e-9), 0)
        nc[:, 2] = np.where(side, 0, np.sign(lc[:, 2]) + (lc[:, 2] == 0))
        n_local[cyl] = nc
        face[cyl] = np.where(side, FACE_SIDE, np.where(lc[:, 2] >= 0, 4, 5))
    ell = kind == ELLIPSOID
    if ell.any():
        n_local[ell] = local[ell] / np.maximum(half[ell], 1e-6) ** 2
        face[ell] = FACE_CURVED
    normal = np.einsum("nij,nj->ni", rot, n_local)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    return SurfaceHits(local=local, normal=normal.astype(np.float32), face=face)


# ------------------------------------------------------------------------------- parallel (shadow) rays
@dataclass(frozen=True)
class OrthoGrid:
    """A grid of parallel rays (an orthographic view, e.g. from the sun).

    Attributes:
        basis: (3, 3) columns e1, e2, e3: the grid spans e1 (columns) and e2 (rows); rays travel along −e3.
        u0, w0: plane coordinates (along e1, e2) of the grid's corner; res: cell size (m).
        rows, cols: grid size; top: e3-coordinate of the ray origins (above everything).

    Cell (r, c) shoots from ``(u0 + (c + ½)·res)·e1 + (w0 + (r + ½)·res)·e2 + top·e3`` along −e3, so a
    hit at distance t has e3-coordinate ``top − t``.
    """

    basis: npt.NDArray[np.float64]
    u0: float
    w0: float
    res: float
    rows: int
    cols: int
    top: float


def ortho_tasks(bounds: npt.NDArray[np.float64], grid: OrthoGrid) -> npt.NDArray[np.int64]:
    """Cell rectangles of primitives from their projected bounds.

    Args:
        bounds: (P, 4) ``(u_min, u_max, w_min, w_max)`` of each primitive's bounding-box corners projected
            on e1 and e2 (see :func:`ortho_bounds`).
        grid: the ray grid.

    Returns:
        (T, 5) int64 rows ``(p, r0, r1, c0, c1)`` of primitives overlapping the grid.
    """
    c0 = np.floor((bounds[:, 0] - grid.u0) / grid.res - 0.5).astype(np.int64)
    c1 = np.ceil((bounds[:, 1] - grid.u0) / grid.res - 0.5).astype(np.int64) + 1
    r0 = np.floor((bounds[:, 2] - grid.w0) / grid.res - 0.5).astype(np.int64)
    r1 = np.ceil((bounds[:, 3] - grid.w0) / grid.res - 0.5).astype(np.int64) + 1
    c0, c1 = np.clip(c0, 0, grid.cols), np.clip(c1, 0, grid.cols)
    r0, r1 = np.clip(r0, 0, grid.rows), np.clip(r1, 0, grid.rows)
    good = (c1 > c0) & (r1 > r0)
    return np.stack([np.flatnonzero(good), r0[good], r1[good], c0[good], c1[good]], axis=1)


def ortho_bounds(prims: Primitives, basis: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(P, 4) ``(u_min, u_max, w_min, w_max)``: bounding-box corners projected on basis columns e1, e2."""
    corners = prims.corners()
    u = corners @ basis[:, 0]
    w = corners @ basis[:, 1]
    return np.stack([u.min(axis=1), u.max(axis=1), w.min(axis=1), w.max(axis=1)], axis=1)


def cast_parallel(
    prims: Primitives,
    grid: OrthoGrid,
    tasks: npt.NDArray[np.int64],
    t_min: float = 0.0,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32]]:
    """Nearest hit per cell of an :class:`OrthoGrid` (depth buffer over parallel rays).

    Returns:
        t (rows, cols) float32 distance from the origin plane (inf = nothing hit) and pid int32 (-1 = none).
    """
    depth = np.full((grid.rows, grid.cols), np.inf, np.float32)
    pid = np.full((grid.rows, grid.cols), -1, np.int32)
    e1, e2, e3 = grid.basis[:, 0], grid.basis[:, 1], grid.basis[:, 2]
    with np.errstate(all="ignore"):
        for p, r0, r1, c0, c1 in tasks.tolist():
            rot = prims.rot[p]
            a = e1 @ rot  # (3,) local-axis components of e1
            b = e2 @ rot
            const = (grid.top * e3 - prims.center[p]) @ rot
            d = -(e3 @ rot)
            u = (grid.u0 + (np.arange(c0, c1, dtype=np.float32) + 0.5) * grid.res).astype(np.float32)[None, :]
            w = (grid.w0 + (np.arange(r0, r1, dtype=np.float32) + 0.5) * grid.res).astype(np.float32)[:, None]
            ox, oy, oz = (
                np.asarray(float(a[k]) * u + float(b[k]) * w + float(const[k]), dtype=np.float32)
                for k in range(3)
            )
            t = _INTERSECT[int(prims.kind[p])](
                ox, oy, oz, float(d[0]), float(d[1]), float(d[2]), half=prims.half[p], t_min=t_min
            )
            t = np.broadcast_to(t, (r1 - r0, c1 - c0))
            zb = depth[r0:r1, c0:c1]
            closer = t < zb
            np.copyto(zb, t, where=closer)
            np.copyto(pid[r0:r1, c0:c1], p, where=closer)
    return depth, pid


def occluded_towards(
    prims: Primitives,
    points: npt.NDArray[np.float32],
    direction: npt.NDArray[np.float64],
    t_min: float = 1e-3,
    groups: npt.NDArray[np.integer] | None = None,
) -> npt.NDArray[np.bool_]:
    """(n,) True where the ray from each point along ``direction`` hits any of ``prims``.

    For few primitives (moving objects): the points are projected on a plane across ``direction``; each
    group of primitives (``groups``, e.g. the instance id of each part; one group if None) first selects
    the points inside its parts' joint projected bounds, then each part tests only the points inside its
    own bounds.
    """
    out = np.zeros(len(points), bool)
    if len(prims) == 0 or len(points) == 0:
        return out
    e3 = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    ref = np.array([0.0, 0.0, 1.0]) if abs(e3[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(ref, e3)
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(e3, e1), e3], axis=1)
    bounds = ortho_bounds(prims, basis)
    top = (prims.corners() @ e3).max(axis=1)
    b32 = basis.astype(np.float32)
    pu, pw, pe = points @ b32[:, 0], points @ b32[:, 1], points @ b32[:, 2]
    groups = np.zeros(len(prims), np.int64) if groups is None else np.asarray(groups)
    with np.errstate(all="ignore"):
        for g in np.unique(groups):
            members = np.flatnonzero(groups == g)
            gb = bounds[members]
            cand = np.flatnonzero(
                (pu >= gb[:, 0].min())
                & (pu <= gb[:, 1].max())
                & (pw >= gb[:, 2].min())
                & (pw <= gb[:, 3].max())
                & (pe < top[members].max())
                & ~out
            )
            if cand.size == 0:
                continue
            cu, cw, cpts = pu[cand], pw[cand], points[cand]
            hit = np.zeros(len(cand), bool)
            for p in members.tolist():
                u0, u1, w0, w1 = bounds[p]
                sel = np.flatnonzero((cu >= u0) & (cu <= u1) & (cw >= w0) & (cw <= w1) & ~hit)
                if sel.size == 0:
                    continue
                rot = prims.rot[p]
                rel = (cpts[sel].astype(np.float64) - prims.center[p]) @ rot
                d = e3 @ rot
                t = _INTERSECT[int(prims.kind[p])](
                    rel[:, 0].astype(np.float32),
                    rel[:, 1].astype(np.float32),
                    rel[:, 2].astype(np.float32),
                    float(d[0]),
                    float(d[1]),
                    float(d[2]),
                    half=prims.half[p],
                    t_min=t_min,
                )
                hit[sel[np.isfinite(t)]] = True
            out[cand] = hit
    return out
