"""Procedural farm for the agri-uav domain: fields, tracks, tree rows and single trees, power lines (poles
and sagging wires), paddock fences, farm buildings and people, built from analytic primitives.

Classes are the seven of ``projects/agri_uav.yaml`` (raw ids :data:`leap_core.synth.names.AGRI_RAW_IDS`);
every primitive carries a name of :data:`leap_core.synth.names.AGRI_VOCABULARY`, as the street demo's do.
Everything is deterministic from the seed. The ground is a patchwork of rectangular fields (crops, pasture,
bare soil) separated by dirt tracks, built ``margin`` metres around the survey path. Hero objects are placed
relative to the start of the survey so that every class is in view within the first frames: a power line
crossing the first survey line, a farmstead (barn, shed, farmhouse) beside it, a fenced paddock, a tree row,
people working; the rest is random and avoids the farmstead.

World frame: x, y on the ground, z up, the ground's surface at z = 0 (field tops a little above it).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Final

import numpy as np
import numpy.typing as npt

from leap_core.errors import ConfigError
from leap_core.synth.materials import Material as M
from leap_core.synth.names import AGRI_NAME_IDS
from leap_core.synth.raycast import Primitives, rotation_xyz
from leap_core.synth.scene import Actor, _Ids, _Parts, person_look
from leap_core.synth.survey import SurveyConfig, survey_poses

F64 = npt.NDArray[np.float64]

TREE, POLE, FENCE, WIRE, PERSON, BUILDING, GROUND = 1, 2, 3, 4, 5, 6, 7
"""Raw ids of the agri-uav classes (``projects/agri_uav.yaml``'s gt_ids)."""
AGRI_CLASS_IDS: Final = frozenset({TREE, POLE, FENCE, WIRE, PERSON, BUILDING, GROUND})
"""Every class a farm holds."""


@dataclass(frozen=True)
class FarmConfig:
    """Layout and density of the procedural farm."""

    margin: float = 150.0
    """Fields are built this far around the survey path (m): must cover the camera's view."""
    field_size: tuple[float, float] = (35.0, 70.0)
    """Range of a field's side length (m)."""
    track_width: float = 4.0
    """Width of the dirt tracks between fields (m)."""
    crop_share: float = 0.5
    """Share of the fields under crops (the rest: pasture and bare soil, half each)."""
    crop_height: tuple[float, float] = (0.15, 0.6)
    """Range of the crop height (m), drawn per field."""
    tile: float = 16.0
    """Longest side of a ground tile (m): smaller tiles give tighter bounds when ray casting."""
    tree_row_rate: float = 0.3
    """Chance that a field edge carries a row of trees."""
    trees_per_pasture: float = 1.5
    """Mean number of single trees in a pasture."""
    fence_rate: float = 0.35
    """Chance that a pasture is fenced (a paddock)."""
    extra_buildings: tuple[int, int] = (2, 5)
    """Range of the number of farm buildings besides the hero farmstead."""
    persons: tuple[int, int] = (4, 8)
    """Range of the number of people besides the two hero farmers."""
    walk_speed: float = 1.2
    """Speed of walking people (m/s)."""
    pole_spacing: tuple[float, float] = (40.0, 55.0)
    """Range of the distance between utility poles (m)."""
    wire_thickness: float = 0.06
    """Side of a wire's square section (m): power lines with insulation, thick enough to be drawn by a
    pixel at 30 m (real conductors are 1-3 cm; thinner wires vanish from the images' 2D ground truth)."""

    def __post_init__(self) -> None:
        if self.margin < 50:
            raise ConfigError(f"must be >= 50 m, got {self.margin}", field=("margin",))
        lo, hi = self.field_size
        if not 10 <= lo <= hi:
            raise ConfigError(f"must satisfy 10 <= low <= high, got {self.field_size}", field=("field_size",))
        if not 0 <= self.crop_share <= 1:
            raise ConfigError(f"must be in [0, 1], got {self.crop_share}", field=("crop_share",))


_CROP_GREENS: Final = np.array([[0.22, 0.42, 0.12], [0.3, 0.48, 0.14], [0.5, 0.55, 0.2], [0.62, 0.56, 0.25]])
_SOILS: Final = np.array([[0.42, 0.32, 0.22], [0.36, 0.27, 0.19], [0.5, 0.4, 0.28]])
_GRASS: Final = np.array([0.27, 0.42, 0.15])
_TRACK: Final = np.array([0.56, 0.48, 0.36])


@dataclass(frozen=True)
class FarmScene:
    """Static primitives, walking people, the drone's flight and the lighting.

    Attributes:
        static: every primitive that does not move.
        actors: walking and standing people.
        poses: (F, 4, 4) drone body → world per frame (x forward, y left, z up).
        altitude: (F,) drone height above the ground (m).
        sun: (3,) unit vector towards the sun.
        hz: frame rate.
    """

    static: Primitives
    actors: tuple[Actor, ...]
    poses: F64
    altitude: F64
    sun: F64
    hz: float

    @property
    def num_frames(self) -> int:
        return len(self.poses)

    def primitives_at(self, frame: int) -> Primitives:
        """All primitives (static first, then people) at ``frame``; people carry the name "farmer"."""
        parts = [self.static]
        for a in self.actors:
            prims = a.primitives(frame)
            parts.append(replace(prims, name=np.full(len(prims), AGRI_NAME_IDS["farmer"], np.uint16)))
        return Primitives.concat(parts)

    def semantic_ids(self) -> set[int]:
        """Raw class ids present in the scene."""
        return {int(v) for v in np.unique(self.static.semantic)} | {a.semantic for a in self.actors}


class _Free:
    """Discs on the ground already taken (farmstead, trees, buildings): a plain list, the farm is sparse."""

    def __init__(self) -> None:
        self.discs: list[tuple[float, float, float]] = []

    def free(self, x: float, y: float, r: float) -> bool:
        return all((x - ox) ** 2 + (y - oy) ** 2 >= (r + orad) ** 2 for ox, oy, orad in self.discs)

    def add(self, x: float, y: float, r: float) -> None:
        self.discs.append((x, y, r))


Rect = tuple[float, float, float, float]
"""An axis-aligned rectangle on the ground: (x0, x1, y0, y1)."""


def _tiles(x0: float, x1: float, y0: float, y1: float, tile: float) -> list[Rect]:
    """Pieces of a rectangle, none longer than ``tile`` on either side."""
    nx, ny = max(int(np.ceil((x1 - x0) / tile)), 1), max(int(np.ceil((y1 - y0) / tile)), 1)
    ex, ey = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    return [(ex[i], ex[i + 1], ey[j], ey[j + 1]) for i in range(nx) for j in range(ny)]


@dataclass(frozen=True)
class _Surface:
    """How a ground slab looks: material, colour, name and texture parameters."""

    mat: int
    color: F64
    name: str
    param: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


def _slab(p: _Parts, rect: Rect, top: float, look: _Surface) -> None:
    """A ground box (class ground) from z = −0.5 to ``top`` over the rectangle."""
    x0, x1, y0, y1 = rect
    p.box(
        ((x0 + x1) / 2, (y0 + y1) / 2, (top - 0.5) / 2),
        ((x1 - x0) / 2, (y1 - y0) / 2, (top + 0.5) / 2),
        GROUND,
        look.mat,
        look.color,
        name=look.name,
        param=look.param,
    )


def _edges(lo: float, hi: float, size: tuple[float, float], rng: np.random.Generator) -> F64:
    """Field boundaries from ``lo`` to past ``hi``: steps drawn uniformly in ``size``."""
    out = [lo]
    while out[-1] < hi:
        out.append(out[-1] + float(rng.uniform(*size)))
    return np.array(out)


def _fields(cfg: FarmConfig, p: _Parts, rng: np.random.Generator, lo: F64, hi: F64) -> list[tuple[str, F64]]:
    """Fields and tracks over [lo, hi]; returns each field's kind and (x0, x1, y0, y1) inner rectangle."""
    ex = _edges(lo[0], hi[0], cfg.field_size, rng)
    ey = _edges(lo[1], hi[1], cfg.field_size, rng)
    hw = cfg.track_width / 2
    out: list[tuple[str, F64]] = []
    for i in range(len(ex) - 1):
        for j in range(len(ey) - 1):
            r = np.array([ex[i] + hw, ex[i + 1] - hw, ey[j] + hw, ey[j + 1] - hw])
            u = rng.random()
            kind = "crop" if u < cfg.crop_share else ("pasture" if u < (1 + cfg.crop_share) / 2 else "soil")
            along = 0.0 if (r[1] - r[0]) >= (r[3] - r[2]) else np.pi / 2
            if kind == "crop":
                top = float(rng.uniform(*cfg.crop_height))
                look = _Surface(
                    M.CROP,
                    _CROP_GREENS[rng.integers(len(_CROP_GREENS))] * rng.uniform(0.9, 1.1),
                    "crop field",
                    (float(rng.uniform(0.5, 0.9)), along, float(rng.uniform(0.2, 0.9)), 0),
                )
            elif kind == "pasture":
                top = 0.06
                look = _Surface(M.GRASS, _GRASS * rng.uniform(0.85, 1.15), "pasture")
            else:
                top = 0.03
                furrows = float(rng.uniform(0.5, 0.9)) if rng.random() < 0.7 else 0.0
                look = _Surface(
                    M.SOIL, _SOILS[rng.integers(len(_SOILS))], "bare soil", (furrows, along, 0, 0)
                )
            for t in _tiles(float(r[0]), float(r[1]), float(r[2]), float(r[3]), cfg.tile):
                _slab(p, t, top, look)
            out.append((kind, r))
    # Tracks: strips along every boundary (crossings overlap, which is harmless).
    track = _Surface(M.SOIL, _TRACK, "dirt track")
    for x in ex:
        for t in _tiles(x - hw, x + hw, ey[0] - hw, ey[-1] + hw, cfg.tile):
            _slab(p, t, 0.0, track)
    for y in ey:
        for t in _tiles(ex[0] - hw, ex[-1] + hw, y - hw, y + hw, cfg.tile):
            _slab(p, t, 0.0, track)
    return out


def _tree(p: _Parts, rng: np.random.Generator, x: float, y: float, inst: int, *, orchard: bool) -> None:
    """Trunk and crown (one core ellipsoid and lobes), all class tree with one instance id."""
    scale = rng.uniform(0.5, 0.7) if orchard else rng.uniform(0.9, 1.5)
    name = "orchard tree" if orchard else "field tree"
    trunk_h = rng.uniform(1.2, 2.0) * scale * (1.0 if orchard else 1.6)
    p.cylinder(
        (x, y, trunk_h / 2),
        rng.uniform(0.15, 0.25) * scale,
        trunk_h / 2,
        TREE,
        M.BARK,
        (0.33, 0.26, 0.2) * rng.uniform(0.8, 1.1, 3),
        inst=inst,
        name=name,
    )
    rx, rz = rng.uniform(2.0, 3.2) * scale, rng.uniform(2.0, 3.0) * scale
    green = np.array([0.2, 0.36, 0.12]) * rng.uniform(0.75, 1.15, 3)
    centre = np.array([x, y, trunk_h + rz * 0.8])
    p.ellipsoid(
        centre,
        (rx, rx * rng.uniform(0.8, 1.0), rz),
        TREE,
        M.LEAVES,
        green,
        yaw=rng.uniform(0, np.pi),
        param=(rng.uniform(0, 100), 0, 0, 0),
        inst=inst,
        name=name,
    )
    for k in range(int(rng.integers(2, 5))):
        ang = 2 * np.pi * (k + rng.uniform(-0.3, 0.3)) / 4
        off = np.array([np.cos(ang) * rx * 0.5, np.sin(ang) * rx * 0.5, rng.uniform(-0.2, 0.5) * rz])
        s = rng.uniform(0.5, 0.7)
        p.ellipsoid(
            centre + off,
            (rx * s, rx * s, rz * s),
            TREE,
            M.LEAVES,
            green * rng.uniform(0.85, 1.12),
            yaw=rng.uniform(0, np.pi),
            param=(rng.uniform(0, 100), 0, 0, 0),
            inst=inst,
            name=name,
        )


def _building(  # noqa: PLR0913  one parameter per dimension of the building
    p: _Parts,
    rng: np.random.Generator,
    centre: tuple[float, float],
    *,
    yaw: float,
    length: float,
    width: float,
    wall_h: float,
    inst: int,
    name: str,
) -> None:
    """Walls (a box) and a gable roof with its ridge along the building's length (local x)."""
    rot = rotation_xyz(0.0, 0.0, yaw)
    c = np.array([centre[0], centre[1], 0.0])
    style = 1 if name == "barn" else 0
    wall = np.array([0.78, 0.74, 0.66]) if style == 0 else np.array([0.55, 0.3, 0.22])
    p.box(
        c + np.array([0, 0, wall_h / 2]),
        (length / 2, width / 2, wall_h / 2),
        BUILDING,
        M.FACADE,
        wall * rng.uniform(0.9, 1.1),
        yaw=yaw,
        param=(3.0, float(rng.uniform(3.0, 5.0)), style, float(rng.uniform(0, 100))),
        inst=inst,
        name=name,
    )
    pitch = np.deg2rad(rng.uniform(20, 35))
    ridge = width / 2 * np.tan(pitch)
    color = np.array([0.55, 0.22, 0.15]) if rng.random() < 0.5 else np.array([0.42, 0.44, 0.46])
    slope = width / 2 / np.cos(pitch)
    for sign in (1.0, -1.0):
        r = rot @ rotation_xyz(-sign * pitch, 0.0, 0.0)
        centre_s = c + rot @ np.array([0.0, sign * width / 4, wall_h + ridge / 2 + 0.05])
        p.box(
            centre_s,
            (length / 2 + 0.3, slope / 2 + 0.3, 0.08),
            BUILDING,
            M.ROOF,
            color,
            rot=r,
            inst=inst,
            name="farm roof",
        )
    p.box(
        c + np.array([0, 0, wall_h + ridge / 4]),
        (length / 2 - 0.05, width / 4, ridge / 4),
        BUILDING,
        M.ROOF,
        color * 0.8,
        yaw=yaw,
        inst=inst,
        name="farm roof",
    )


def _fence(p: _Parts, rng: np.random.Generator, x0: float, x1: float, y0: float, y1: float) -> None:
    """A paddock fence (1.2 m panels, wooden slats) around [x0, x1] × [y0, y1], with a gate gap."""
    color = np.array([0.5, 0.38, 0.26]) * rng.uniform(0.85, 1.1)
    gate = int(rng.integers(4))
    sides = [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
    for k, (a, b) in enumerate(sides):
        a_, b_ = np.array(a), np.array(b)
        length = float(np.linalg.norm(b_ - a_))
        d = (b_ - a_) / length
        n = max(int(np.ceil(length / 8.0)), 1)
        for m in range(n):
            s0, s1 = m * length / n, (m + 1) * length / n
            if k == gate and m == n // 2:
                s1 = s0 + (s1 - s0) * 0.4  # the gate: a gap in the middle panel
            q = a_ + d * (s0 + s1) / 2
            p.box(
                (q[0], q[1], 0.6),
                ((s1 - s0) / 2, 0.04, 0.6),
                FENCE,
                M.FENCE,
                color,
                yaw=float(np.arctan2(d[1], d[0])),
                param=(0, 0, 0, 0),
                name="paddock fence",
            )


def _power_line(p: _Parts, rng: np.random.Generator, cfg: FarmConfig, a: F64, b: F64, first: float) -> None:
    """Utility poles from ``a`` towards ``b`` (the first ``first`` metres from a, then every
    ``pole_spacing``), a crossarm on each, and three wires per span sagging as a parabola
    ``z(u) = z₀ − 4·sag·u·(1 − u)`` drawn as eight straight pieces."""
    d = (b - a) / np.linalg.norm(b - a)
    across = np.array([-d[1], d[0]])
    total = float(np.linalg.norm(b - a))
    stations = [first]
    while stations[-1] < total:
        stations.append(stations[-1] + float(rng.uniform(*cfg.pole_spacing)))
    h = float(rng.uniform(8.0, 10.0))
    wood = np.array([0.4, 0.33, 0.26])
    tops = []
    for s in stations:
        q = a + d * s
        p.cylinder(
            (q[0], q[1], h / 2), 0.13, h / 2, POLE, M.BARK, wood * rng.uniform(0.85, 1.1), name="utility pole"
        )
        p.box(
            (q[0], q[1], h - 0.3),
            (0.06, 1.25, 0.06),
            POLE,
            M.BARK,
            wood * 0.9,
            yaw=float(np.arctan2(d[1], d[0])),
            name="utility pole",
        )
        tops.append(
            [np.r_[q + across * off, h - 0.2 + (0.5 if off == 0 else 0.0)] for off in (-1.1, 0.0, 1.1)]
        )
    for k in range(len(tops) - 1):
        sag = float(rng.uniform(0.6, 1.2))
        for w in range(3):
            p0, p1 = tops[k][w], tops[k + 1][w]
            u = np.linspace(0.0, 1.0, 9)
            pts = p0[None] + u[:, None] * (p1 - p0)[None]
            pts[:, 2] -= 4 * sag * u * (1 - u)
            for m in range(8):
                p.rod(
                    pts[m],
                    pts[m + 1],
                    cfg.wire_thickness,
                    WIRE,
                    M.METAL,
                    (0.12, 0.12, 0.13),
                    name="power line",
                )


def _walker(
    inst: int, rng: np.random.Generator, start: F64, *, heading: float, speed: float, frames: int, hz: float
) -> Actor:
    """A person walking from ``start`` along ``heading`` at ``speed`` (0 = standing, turning slowly)."""
    t = np.arange(frames) / hz
    dirv = np.array([np.cos(heading), np.sin(heading)])
    xy = start[None] + (speed * t)[:, None] * dirv[None]
    yaw = np.full(frames, heading) if speed > 0 else heading + 0.3 * np.sin(t * 0.5)
    phase = 2 * np.pi * speed * t / 1.4 + rng.uniform(0, 2 * np.pi)
    return Actor(inst, PERSON, Primitives.empty(), person_look(rng), xy, yaw, phase, 0.0)


@dataclass(frozen=True)
class _Build:
    """What the steps of one farm build share."""

    cfg: FarmConfig
    p: _Parts
    ids: _Ids
    free: _Free
    actors: list[Actor]
    frames: int
    hz: float
    lo: F64
    """(2,) south-west corner of the built area."""
    hi: F64
    """(2,) north-east corner."""


def _heroes(b: _Build, rng: np.random.Generator) -> None:
    """Objects in the view of the first frames: the drone starts at the origin flying +x with the rig
    looking ahead and down, its LiDAR seeing the ground about 10-60 m ahead (a power line across the first
    line, a farmstead, a fenced paddock, a tree row, two farmers)."""
    p, ids, free = b.p, b.ids, b.free
    x_line = float(rng.uniform(24.0, 32.0))
    _power_line(
        p,
        rng,
        b.cfg,
        np.array([x_line, b.lo[1]]),
        np.array([x_line, b.hi[1]]),
        first=float(-b.lo[1] - 15.0 + rng.uniform(-4, 4)),
    )
    free.add(x_line, -15.0, 2.0)
    farmstead = [
        ((44.0, 14.0), 0.0, 16.0, 10.0, 5.5, "barn"),
        ((38.0, -9.0), np.pi / 2, 6.0, 4.0, 2.8, "shed"),
        ((62.0, -14.0), 0.2, 11.0, 8.0, 5.5, "farmhouse"),
    ]
    for (cx, cy), yaw, length, width, wall_h, name in farmstead:
        _building(p, rng, (cx, cy), yaw=yaw, length=length, width=width, wall_h=wall_h, inst=ids(), name=name)
        free.add(cx, cy, np.hypot(length, width) / 2 + 1.5)
    _fence(p, rng, 6.0, 22.0, 5.0, 20.0)
    free.add(14.0, 12.5, 11.0)
    for k in range(8):
        x = 4.0 + 6.5 * k + rng.uniform(-0.5, 0.5)
        if free.free(x, -24.0, 1.5):
            _tree(p, rng, x, -24.0, ids(), orchard=False)
            free.add(x, -24.0, 3.0)
    for start, heading, speed in (((16.0, -4.0), 0.4, b.cfg.walk_speed), ((34.0, 4.0), 2.5, 0.0)):
        b.actors.append(
            _walker(ids(), rng, np.array(start), heading=heading, speed=speed, frames=b.frames, hz=b.hz)
        )
        free.add(start[0], start[1], 1.0)


def _field_objects(b: _Build, rng: np.random.Generator, fields: list[tuple[str, F64]]) -> None:
    """Tree rows along field edges, single trees and paddock fences in pastures, orchards in crop fields."""
    p, ids, free, cfg = b.p, b.ids, b.free, b.cfg
    for kind, (x0, x1, y0, y1) in fields:
        if rng.random() < cfg.tree_row_rate:
            y = y0 - 1.0 if rng.random() < 0.5 else y1 + 1.0
            x = x0 + rng.uniform(2.0, 6.0)
            while x < x1 - 2.0:
                if free.free(x, y, 2.5):
                    _tree(p, rng, x, y, ids(), orchard=False)
                    free.add(x, y, 2.5)
                x += rng.uniform(6.0, 9.0)
        if kind == "pasture":
            for _ in range(int(rng.poisson(cfg.trees_per_pasture))):
                x, y = rng.uniform(x0 + 3, x1 - 3), rng.uniform(y0 + 3, y1 - 3)
                if free.free(x, y, 4.0):
                    _tree(p, rng, x, y, ids(), orchard=False)
                    free.add(x, y, 4.0)
            if rng.random() < cfg.fence_rate and free.free((x0 + x1) / 2, (y0 + y1) / 2, 3.0):
                _fence(p, rng, x0 + 1.0, x1 - 1.0, y0 + 1.0, y1 - 1.0)
        elif kind == "crop" and rng.random() < 0.15:
            # An orchard: rows of small trees over the field.
            for y in np.arange(y0 + 3.0, y1 - 2.0, 5.0):
                for x in np.arange(x0 + 3.0, x1 - 2.0, 4.5):
                    if free.free(x, y, 1.8):
                        _tree(p, rng, x, y, ids(), orchard=True)


def _scattered(b: _Build, rng: np.random.Generator, path: F64) -> None:
    """More farm buildings anywhere, a second power line along x, and people near the flight path."""
    p, ids, free, cfg, lo, hi = b.p, b.ids, b.free, b.cfg, b.lo, b.hi
    for _ in range(int(rng.integers(cfg.extra_buildings[0], cfg.extra_buildings[1] + 1))):
        for _try in range(20):
            cx, cy = rng.uniform(lo[0] + 20, hi[0] - 20), rng.uniform(lo[1] + 20, hi[1] - 20)
            length, width = rng.uniform(8, 24), rng.uniform(6, 12)
            if free.free(cx, cy, np.hypot(length, width) / 2 + 3):
                name = ("barn", "shed", "farmhouse")[int(rng.integers(3))]
                _building(
                    p,
                    rng,
                    (cx, cy),
                    yaw=rng.uniform(0, np.pi),
                    length=length,
                    width=width,
                    wall_h=rng.uniform(3.0, 7.0),
                    inst=ids(),
                    name=name,
                )
                free.add(cx, cy, np.hypot(length, width) / 2 + 3)
                break
    y_line = float(rng.uniform(lo[1] + 60, hi[1] - 60))
    _power_line(
        p, rng, cfg, np.array([lo[0], y_line]), np.array([hi[0], y_line]), first=float(rng.uniform(5, 30))
    )
    for _ in range(int(rng.integers(cfg.persons[0], cfg.persons[1] + 1))):
        for _try in range(20):
            q = path[int(rng.integers(len(path)))] + rng.uniform(-30, 30, 2)
            if free.free(q[0], q[1], 1.0):
                speed = cfg.walk_speed if rng.random() < 0.5 else 0.0
                b.actors.append(
                    _walker(
                        ids(),
                        rng,
                        q,
                        heading=rng.uniform(0, 2 * np.pi),
                        speed=speed,
                        frames=b.frames,
                        hz=b.hz,
                    )
                )
                free.add(q[0], q[1], 1.0)
                break


def build_farm(cfg: FarmConfig, survey: SurveyConfig, frames: int, hz: float, seed: int) -> FarmScene:
    """Build the farm and the drone's flight for ``frames`` frames at ``hz`` from ``seed`` (deterministic)."""
    ss = np.random.SeedSequence([int(seed), 0xA6F1])
    rng_route, rng_hero, rng_farm, rng_light = (np.random.default_rng(s) for s in ss.spawn(4))
    poses, altitude = survey_poses(survey, frames, hz, rng_route)
    path = poses[:, :2, 3]
    # The farm must cover what the camera sees from the first frame on, wherever the path goes.
    lo = np.minimum(path.min(axis=0), [0.0, 0.0]) - cfg.margin
    hi = np.maximum(path.max(axis=0), [survey.line_length, 0.0]) + cfg.margin
    b = _Build(cfg, _Parts(), _Ids(), _Free(), [], frames, hz, lo, hi)
    fields = _fields(cfg, b.p, rng_farm, lo, hi)
    _heroes(b, rng_hero)
    _field_objects(b, rng_farm, fields)
    _scattered(b, rng_farm, path)
    az = rng_light.uniform(0, 2 * np.pi)
    el = np.deg2rad(rng_light.uniform(35, 60))
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return FarmScene(
        static=b.p.build(), actors=tuple(b.actors), poses=poses, altitude=altitude, sun=sun, hz=hz
    )
