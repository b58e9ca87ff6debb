"""Procedural street scene: a grid of blocks with buildings, sidewalks, yards, trees, poles, signs, parked
and moving vehicles, pedestrians and bicycles, all built from analytic primitives.

Everything is deterministic from the seed. The scene covers every block within ``margin`` metres of the
ego route. Objects that matter for the demo (a walking person, a lead car and oncoming cars, trucks,
bicycles, people at the corner, a sign facing the ego) are placed relative to the route first, so they
are always in the camera's view; the rest of the street furniture is random and avoids them.

Block sides are addressed in side coordinates: ``a`` along the curb (direction ``t``), ``c`` across it
(``c = 0`` on the curb line, ``c > 0`` into the block, ``c < 0`` into the street), world = o + a·t + c·n.
Traffic keeps right, so the lane next to a side flows along −t.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Final, NamedTuple

import numpy as np
import numpy.typing as npt

from leap_core.synth.materials import Material as M
from leap_core.synth.materials import SemanticId as S
from leap_core.synth.names import name_id
from leap_core.synth.raycast import BOX, CYLINDER, ELLIPSOID, Primitives, rotation_xyz, rotation_z
from leap_core.synth.route import EgoConfig, Route, StreetGrid, drive_along, plan_route, right_of

F64 = npt.NDArray[np.float64]

_Row = tuple[int, F64, F64, F64, int, int, int, F64, tuple[float, ...], int]
"""One primitive before packing: kind, center, rot, half, semantic, instance, material, color, param, name."""

_DEFAULT_NAME: Final[dict[int, str]] = {
    S.CAR: "sedan",
    S.MOVING_CAR: "sedan",
    S.BICYCLE: "city bike",
    S.TRUCK: "box truck",
    S.MOVING_BUS: "bus",
    S.PERSON: "pedestrian",
    S.MOVING_PERSON: "pedestrian",
    S.ROAD: "asphalt",
    S.PARKING: "parking lane",
    S.SIDEWALK: "sidewalk",
    S.OTHER_GROUND: "gravel",
    S.BUILDING: "apartment building",
    S.FENCE: "wooden fence",
    S.VEGETATION: "tree",
    S.TRUNK: "trunk",
    S.TERRAIN: "lawn",
    S.POLE: "lamp post",
    S.TRAFFIC_SIGN: "traffic sign",
    S.TRAFFIC_CONE: "traffic cone",
    S.BENCH: "bench",
    S.BOLLARD: "bollard",
}
"""Name of a primitive whose builder gives none: the most common name of its class in the scene."""


@dataclass(frozen=True)
class SceneConfig:
    """Layout and density of the procedural street scene."""

    block_x: tuple[float, float] = (72.0, 96.0)
    """Range of the spacing of streets along x (m), drawn per seed."""
    block_y: tuple[float, float] = (72.0, 96.0)
    """Range of the spacing of streets along y (m), drawn per seed."""
    lane_width: float = 3.5
    """Width of one driving lane (one lane per direction)."""
    parking_width: float = 2.3
    """Width of the parking lane along each curb."""
    sidewalk_width: float = 3.4
    """Width of the sidewalk (curb to lot line)."""
    curb_height: float = 0.14
    """Height of sidewalks above the road."""
    lawn_height: float = 0.10
    """Height of lawns and yards above the road."""
    margin: float = 160.0
    """Blocks within this distance of the route are built (must cover the camera's range)."""
    tile: float = 10.0
    """Longest side of a ground tile (m): shorter tiles give tighter screen bounds when ray casting."""
    parked_car_rate: float = 0.72
    """Share of parking slots holding a car."""
    truck_rate: float = 0.06
    """Chance that a parking slot holds a truck instead of a car."""
    tree_row_rate: float = 0.65
    """Chance that a block side has a row of street trees."""
    yard_rate: float = 0.5
    """Chance that a block side has detached houses with front yards (else closed row buildings)."""
    grass_strip_rate: float = 0.35
    """Chance that a sidewalk has a grass strip along the curb."""
    gravel_strip_rate: float = 0.4
    """Chance that such a strip is gravel (other-ground) instead of grass."""
    cone_rate: float = 0.25
    """Chance that a block side has a few traffic cones along its parking lane."""
    jeep_rate: float = 0.2
    """Share of the parked cars (vans aside) that are jeeps (SUVs)."""
    bench_rate: float = 0.35
    """Mean number of benches per sidewalk."""
    bollard_rate: float = 0.3
    """Chance that a sidewalk has a row of bollards near a corner."""
    lamp_spacing: tuple[float, float] = (24.0, 34.0)
    """Range of the spacing of street lamps (m)."""
    bicycles_per_side: float = 0.6
    """Mean number of parked bicycles per block side."""
    persons_per_side: float = 0.5
    """Mean number of standing pedestrians per block side."""
    walk_speed: float = 1.35
    """Speed of walking pedestrians (m/s)."""
    oncoming_speed: float = 7.0
    """Speed of oncoming cars (m/s)."""


# --------------------------------------------------------------------------------------------- palettes
_CAR_COLORS: Final = np.array(
    [
        [0.85, 0.85, 0.86],
        [0.62, 0.63, 0.65],
        [0.09, 0.09, 0.1],
        [0.12, 0.18, 0.38],
        [0.55, 0.08, 0.07],
        [0.35, 0.36, 0.38],
        [0.8, 0.8, 0.78],
        [0.2, 0.3, 0.22],
        [0.5, 0.52, 0.55],
        [0.15, 0.2, 0.28],
    ]
)
_PLASTER: Final = np.array(
    [
        [0.86, 0.81, 0.69],
        [0.88, 0.83, 0.62],
        [0.82, 0.82, 0.79],
        [0.86, 0.73, 0.67],
        [0.71, 0.76, 0.8],
        [0.79, 0.64, 0.45],
        [0.9, 0.88, 0.82],
        [0.74, 0.7, 0.62],
    ]
)
_BRICK: Final = np.array([[0.58, 0.29, 0.21], [0.52, 0.33, 0.26], [0.66, 0.42, 0.33], [0.45, 0.26, 0.2]])
_SHIRTS: Final = np.array(
    [
        [0.75, 0.12, 0.1],
        [0.12, 0.25, 0.55],
        [0.9, 0.9, 0.88],
        [0.15, 0.15, 0.16],
        [0.3, 0.5, 0.25],
        [0.85, 0.65, 0.15],
        [0.45, 0.3, 0.5],
        [0.55, 0.55, 0.58],
    ]
)
_PANTS: Final = np.array(
    [[0.1, 0.12, 0.2], [0.12, 0.12, 0.12], [0.6, 0.55, 0.45], [0.3, 0.32, 0.35], [0.2, 0.25, 0.4]]
)
_SKIN: Final = np.array([[0.87, 0.7, 0.6], [0.75, 0.56, 0.44], [0.52, 0.36, 0.27], [0.93, 0.78, 0.68]])


class _Parts:
    """Accumulates primitives row by row, then packs them into a :class:`Primitives` table."""

    def __init__(self) -> None:
        self.rows: list[_Row] = []

    def add(  # noqa: PLR0913  one parameter per column of a Primitives row
        self,
        kind: int,
        center: npt.ArrayLike,
        half: npt.ArrayLike,
        sem: int,
        mat: int,
        color: npt.ArrayLike,
        *,
        rot: F64 | None = None,
        yaw: float = 0.0,
        param: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0),
        inst: int = 0,
        name: str | None = None,
    ) -> None:
        r = rotation_z(yaw) if rot is None else rot
        nid = name_id(name if name is not None else _DEFAULT_NAME[sem])
        half = np.asarray(half, np.float64)
        if kind == CYLINDER:
            half = np.array([half[0], half[0], half[2]])
        self.rows.append(
            (kind, np.asarray(center, float), r, half, sem, inst, mat, np.asarray(color, float), param, nid)
        )

    def box(
        self, center: npt.ArrayLike, half: npt.ArrayLike, sem: int, mat: int, color: npt.ArrayLike, **kw: Any
    ) -> None:
        self.add(BOX, center, half, sem, mat, color, **kw)

    def cylinder(
        self,
        center: npt.ArrayLike,
        radius: float,
        half_height: float,
        sem: int,
        mat: int,
        color: npt.ArrayLike,
        **kw: Any,
    ) -> None:
        self.add(CYLINDER, center, (radius, radius, half_height), sem, mat, color, **kw)

    def ellipsoid(
        self, center: npt.ArrayLike, radii: npt.ArrayLike, sem: int, mat: int, color: npt.ArrayLike, **kw: Any
    ) -> None:
        self.add(ELLIPSOID, center, radii, sem, mat, color, **kw)

    def rod(
        self,
        p0: npt.ArrayLike,
        p1: npt.ArrayLike,
        thick: float,
        sem: int,
        mat: int,
        color: npt.ArrayLike,
        *,
        inst: int = 0,
        name: str | None = None,
    ) -> None:
        """A thin box from p0 to p1 (square section ``thick``), local x along the rod."""
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        self.add(
            BOX,
            (p0 + p1) / 2,
            (np.linalg.norm(p1 - p0) / 2, thick / 2, thick / 2),
            sem,
            mat,
            color,
            rot=_frame_x(p1 - p0),
            inst=inst,
            name=name,
        )

    def build(self) -> Primitives:
        if not self.rows:
            return Primitives.empty()
        cols = list(zip(*self.rows, strict=True))
        return Primitives(
            kind=np.array(cols[0], np.int8),
            center=np.array(cols[1], np.float64),
            rot=np.array(cols[2], np.float64),
            half=np.array(cols[3], np.float64),
            semantic=np.array(cols[4], np.uint16),
            instance=np.array(cols[5], np.uint16),
            material=np.array(cols[6], np.uint8),
            color=np.clip(np.array(cols[7], np.float32), 0, 1),
            param=np.array(cols[8], np.float32).reshape(-1, 4),
            name=np.array(cols[9], np.uint16),
        )


def _cross(a: F64, b: F64) -> F64:
    """3-vector cross product (np.cross is slow for single vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _frame_x(direction: npt.ArrayLike) -> F64:
    """Rotation whose local x is ``direction`` and local y is horizontal (local z as upright as possible)."""
    x = np.asarray(direction, float)
    x = x / np.linalg.norm(x)
    up = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.95 else np.array([0.0, 1.0, 0.0])
    y = _cross(up, x)
    y /= np.linalg.norm(y)
    return np.stack([x, y, _cross(x, y)], axis=1)


def _frame_z(direction: npt.ArrayLike) -> F64:
    """Rotation whose local z is ``direction`` (for discs: wheels, round signs)."""
    z = np.asarray(direction, float)
    z = z / np.linalg.norm(z)
    ref = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    x = _cross(ref, z)
    x /= np.linalg.norm(x)
    return np.stack([x, _cross(z, x), z], axis=1)


def _yaw_of(v: F64) -> float:
    return float(np.arctan2(v[1], v[0]))


# ---------------------------------------------------------------------------------------- object shapes
# Shapes are built in the object's frame: x forward, y left, z up, origin on the ground at the centre.
def car_shape(
    rng: np.random.Generator, sem: int, inst: int, van: bool = False, jeep: bool = False
) -> Primitives:
    """Lower body, cabin (glass sides), four wheels. Sedans 3.9 to 4.8 m long (named "hatchback" below
    4.3 m); vans taller and boxier; jeeps (SUVs) sit higher with a longer, taller cabin."""
    p = _Parts()
    color = _CAR_COLORS[rng.integers(len(_CAR_COLORS))] * rng.uniform(0.92, 1.05)
    length = rng.uniform(4.6, 5.1) if van else rng.uniform(3.9, 4.8)
    width = rng.uniform(1.75, 1.95) if van else rng.uniform(1.7, 1.85)
    body_top = rng.uniform(0.9, 1.0)
    clear = 0.28
    if jeep and not van:
        # The same draws as a sedan, raised and lengthened, so choosing a jeep shifts no other draw.
        length, body_top, clear = max(length, 4.35), body_top + 0.22, 0.42
    name = "van" if van else "jeep" if jeep else ("hatchback" if length < 4.3 else "sedan")
    p.box(
        (0, 0, (clear + body_top) / 2),
        (length / 2, width / 2, (body_top - clear) / 2),
        sem,
        M.PAINT,
        color,
        param=(0.0, 0, 0, 0),
        inst=inst,
        name=name,
    )
    if van:
        cab_len, cab_h, cab_x = length * 0.36, rng.uniform(0.75, 0.95), -0.1 * length
    else:
        cab_len, cab_h, cab_x = length * rng.uniform(0.2, 0.24), rng.uniform(0.42, 0.5), -0.07 * length
        if jeep:
            cab_len, cab_h = cab_len * 1.3, cab_h + 0.2
    cab_w = width / 2 - 0.08
    p.box(
        (cab_x, 0, body_top + cab_h / 2),
        (cab_len, cab_w, cab_h / 2),
        sem,
        M.GLASS,
        color,
        inst=inst,
        name=name,
    )
    # Sloped wind screen and rear window: thick boxes whose top face is the slope; the rest of each box
    # lies inside the body and cabin, so no gap opens under the slope.
    for side, run in (
        (1.0, rng.uniform(0.55, 0.8) if not van else 0.3),
        (-1.0, rng.uniform(0.35, 0.6) if not van else 0.12),
    ):
        a = np.array([cab_x + side * (cab_len + run), 0.0, body_top])
        b = np.array([cab_x + side * cab_len, 0.0, body_top + cab_h])
        axis = (b - a) / np.linalg.norm(b - a)
        normal = np.array([axis[2] * side, 0.0, -axis[0] * side])
        thick = 0.3
        centre = (a + b) / 2 - normal * thick / 2
        rot = np.stack([axis * side, np.array([0.0, 1.0, 0.0]) * side, normal], axis=1)
        if np.linalg.det(rot) < 0:
            rot[:, 1] *= -1
        p.box(
            centre,
            (np.linalg.norm(b - a) / 2, cab_w, thick / 2),
            sem,
            M.GLASS,
            color,
            rot=rot,
            param=(1.0, 0, 0, 0),
            inst=inst,
            name=name,
        )
    r = rng.uniform(0.3, 0.34)
    axle = length / 2 - rng.uniform(0.7, 0.85)
    for sx in (-1, 1):
        for sy in (-1, 1):
            p.cylinder(
                (sx * axle, sy * (width / 2 - 0.12), r),
                r,
                0.11,
                sem,
                M.RUBBER,
                (0.05, 0.05, 0.05),
                rot=_frame_z((0, sy, 0)),
                inst=inst,
                name=name,
            )
    return p.build()


def _wheels(p: _Parts, xs: tuple[float, ...], half_track: float, sem: int, inst: int) -> None:
    """A pair of 0.5 m rubber wheels (left, right) at each axle position ``xs`` of a vehicle's frame."""
    r = 0.5
    for x in xs:
        for sy in (-1, 1):
            p.cylinder(
                (x, sy * half_track, r),
                r,
                0.16,
                sem,
                M.RUBBER,
                (0.05, 0.05, 0.05),
                rot=_frame_z((0, sy, 0)),
                inst=inst,
            )


def truck_shape(rng: np.random.Generator, sem: int, inst: int) -> Primitives:
    """Cab, cargo box, chassis and six wheels; about 8 m long and 3.5 m tall."""
    p = _Parts()
    cab_color = _CAR_COLORS[rng.integers(len(_CAR_COLORS))]
    box_color = np.array([0.9, 0.9, 0.88]) if rng.random() < 0.6 else np.array([0.25, 0.4, 0.6])
    cargo_len = rng.uniform(5.2, 6.4)
    cab_len = 1.9
    total = cargo_len + cab_len + 0.2
    front = total / 2
    p.box(
        (front - cab_len / 2, 0, 0.55 + 1.3),
        (cab_len / 2, 1.2, 1.3),
        sem,
        M.PAINT,
        cab_color,
        param=(1, 0, 0, 0),
        inst=inst,
    )
    p.box(
        (front - cab_len / 2 - 0.05, 0, 0.55 + 2.35),
        (cab_len / 2 - 0.1, 1.15, 0.25),
        sem,
        M.GLASS,
        cab_color,
        inst=inst,
    )
    cx = front - cab_len - 0.2 - cargo_len / 2
    p.box((cx, 0, 1.05 + 1.45), (cargo_len / 2, 1.25, 1.45), sem, M.TARP, box_color, inst=inst)
    p.box((cx + 0.3, 0, 0.78), (total / 2 - 0.4, 0.9, 0.25), sem, M.METAL, (0.12, 0.12, 0.13), inst=inst)
    _wheels(p, (front - 1.0, cx - cargo_len / 2 + 1.0, cx - cargo_len / 2 + 2.1), 1.0, sem, inst)
    return p.build()


@dataclass(frozen=True)
class PersonLook:
    """Size and colours of a pedestrian."""

    height: float
    shirt: tuple[float, float, float]
    pants: tuple[float, float, float]
    skin: tuple[float, float, float]


_CHILD_HEIGHT: Final = 1.45
"""People shorter than this are named "child"."""


def person_look(rng: np.random.Generator, child: bool = False) -> PersonLook:
    return PersonLook(
        height=float(rng.uniform(1.05, 1.4) if child else rng.uniform(1.58, 1.92)),
        shirt=tuple(_SHIRTS[rng.integers(len(_SHIRTS))] * rng.uniform(0.85, 1.05)),
        pants=tuple(_PANTS[rng.integers(len(_PANTS))]),
        skin=tuple(_SKIN[rng.integers(len(_SKIN))]),
    )


def person_shape(look: PersonLook, sem: int, inst: int, phase: float, swing: float) -> Primitives:
    """Legs, torso, arms and head; legs and arms swing by ``swing·sin(phase)`` radians about the hips
    and shoulders (opposite sides in counter-phase)."""
    p = _Parts()
    h = look.height
    name = "child" if h < _CHILD_HEIGHT else "pedestrian"
    leg, torso = 0.47 * h, 0.3 * h
    hip, shoulder = leg, leg + torso
    for side in (-1, 1):
        a = side * swing * np.sin(phase)
        r_leg = rotation_xyz(0.0, a, 0.0)
        p.box(
            np.array([0, side * 0.1, hip]) + r_leg @ np.array([0, 0, -leg / 2]),
            (0.075, 0.075, leg / 2),
            sem,
            M.CLOTH,
            look.pants,
            rot=r_leg,
            inst=inst,
            name=name,
        )
        r_arm = rotation_xyz(0.0, -a * 0.8, 0.0)
        arm = 0.36 * h
        p.box(
            np.array([0, side * 0.245, shoulder - 0.04]) + r_arm @ np.array([0, 0, -arm / 2]),
            (0.05, 0.05, arm / 2),
            sem,
            M.CLOTH,
            look.shirt,
            rot=r_arm,
            inst=inst,
            name=name,
        )
    p.box((0, 0, hip + torso / 2), (0.12, 0.19, torso / 2), sem, M.CLOTH, look.shirt, inst=inst, name=name)
    p.ellipsoid(
        (0.0, 0, shoulder + 0.14 * h * 0.75), (0.1, 0.085, 0.12), sem, M.SKIN, look.skin, inst=inst, name=name
    )
    return p.build()


def bicycle_shape(rng: np.random.Generator, sem: int, inst: int) -> Primitives:
    """Two thin wheels and a tube frame (about 1.7 m long)."""
    p = _Parts()
    color = _SHIRTS[rng.integers(len(_SHIRTS))] * 0.9
    r, wb = 0.34, 1.04
    for x in (-wb / 2, wb / 2):
        p.cylinder((x, 0, r), r, 0.02, sem, M.RUBBER, (0.06, 0.06, 0.06), rot=_frame_z((0, 1, 0)), inst=inst)
    bb = np.array([0.0, 0, 0.3])
    head = np.array([0.38, 0, 0.78])
    seat = np.array([-0.2, 0, 0.86])
    rear = np.array([-wb / 2, 0, r])
    front = np.array([wb / 2, 0, r])
    for a, b in (
        (bb, head),
        (bb, seat),
        (seat + np.array([0.02, 0, -0.06]), head),
        (bb, rear),
        (seat, rear),
        (head, front),
    ):
        p.rod(a, b, 0.035, sem, M.METAL, color, inst=inst)
    handlebar = head + np.array([0.02, 0, 0.2])
    p.box(seat + np.array([0, 0, 0.03]), (0.12, 0.06, 0.03), sem, M.CLOTH, (0.08, 0.08, 0.08), inst=inst)
    p.box(handlebar, (0.025, 0.28, 0.02), sem, M.METAL, (0.15, 0.15, 0.15), inst=inst)
    p.rod(head, handlebar, 0.03, sem, M.METAL, color, inst=inst)
    return p.build()


def bus_shape(rng: np.random.Generator, sem: int, inst: int) -> Primitives:
    """A city bus: a 12 m painted body with a dark windscreen, a glazed upper band and six wheels."""
    p = _Parts()
    color = np.array([0.85, 0.72, 0.12]) if rng.random() < 0.5 else np.array([0.2, 0.42, 0.7])
    length, width, clear = rng.uniform(11.0, 12.5), 2.5, 0.35
    p.box(
        (0, 0, clear + 0.9), (length / 2, width / 2, 0.9), sem, M.PAINT, color, param=(1, 0, 0, 0), inst=inst
    )
    p.box(
        (0, 0, clear + 1.8 + 0.55),
        (length / 2 - 0.05, width / 2 - 0.03, 0.55),
        sem,
        M.GLASS,
        color,
        inst=inst,
    )
    _wheels(p, (length / 2 - 2.4, -length / 2 + 3.0, -length / 2 + 1.9), width / 2 - 0.2, sem, inst)
    return p.build()


def cone_shape(inst: int) -> Primitives:
    """A 0.6 m traffic cone: a square black foot and three stacked orange / white cylinders."""
    p = _Parts()
    sem = S.TRAFFIC_CONE
    p.box((0, 0, 0.02), (0.19, 0.19, 0.02), sem, M.RUBBER, (0.05, 0.05, 0.05), inst=inst)
    orange, white = (0.95, 0.35, 0.05), (0.92, 0.92, 0.9)
    for k, (radius, color) in enumerate(((0.15, orange), (0.11, white), (0.075, orange))):
        p.cylinder((0, 0, 0.04 + 0.09 + 0.18 * k), radius, 0.09, sem, M.CLOTH, color, inst=inst)
    return p.build()


def bench_shape(rng: np.random.Generator, inst: int) -> Primitives:
    """A 1.8 m wooden park bench (seat and back slats on two metal frames), facing +x."""
    p = _Parts()
    sem = S.BENCH
    wood = np.array([0.5, 0.34, 0.2]) * rng.uniform(0.85, 1.1)
    half_len = 0.9
    p.box((0, 0, 0.45), (0.22, half_len, 0.03), sem, M.FENCE, wood, param=(0, 0, 0, 0), inst=inst)
    p.box((-0.24, 0, 0.75), (0.03, half_len, 0.2), sem, M.FENCE, wood, param=(0, 0, 0, 0), inst=inst)
    for sy in (-1, 1):
        p.box(
            (-0.05, sy * (half_len - 0.1), 0.22),
            (0.22, 0.03, 0.22),
            sem,
            M.METAL,
            (0.15, 0.15, 0.16),
            inst=inst,
        )
    return p.build()


def bollard_shape(inst: int) -> Primitives:
    """A 0.9 m metal bollard with a reflective band."""
    p = _Parts()
    p.cylinder((0, 0, 0.45), 0.09, 0.45, S.BOLLARD, M.METAL, (0.22, 0.23, 0.25), inst=inst)
    p.cylinder((0, 0, 0.78), 0.095, 0.04, S.BOLLARD, M.SIGN, (0.9, 0.9, 0.9), inst=inst)
    return p.build()


def _place(shape: Primitives, x: float, y: float, yaw: float, z: float = 0.0) -> Primitives:
    return shape.transformed(rotation_z(yaw), np.array([x, y, z]))


def _tree(p: _Parts, rng: np.random.Generator, x: float, y: float, z0: float, scale: float = 1.0) -> None:
    """Trunk cylinder and one to three crown ellipsoids."""
    trunk_h = rng.uniform(2.2, 3.6) * scale
    tr = rng.uniform(0.12, 0.24) * scale
    p.cylinder(
        (x, y, z0 + trunk_h / 2 + 0.4),
        tr,
        trunk_h / 2 + 0.4,
        S.TRUNK,
        M.BARK,
        (0.33, 0.26, 0.2) * rng.uniform(0.8, 1.1, 3),
    )
    rx, rz = rng.uniform(1.7, 3.1) * scale, rng.uniform(1.9, 3.3) * scale
    green = np.array([0.2, 0.36, 0.12]) * rng.uniform(0.75, 1.15, 3)
    top = z0 + trunk_h + 0.4
    centre = np.array([x, y, top + rz * 0.6])
    p.ellipsoid(
        centre,
        (rx * 0.85, rx * rng.uniform(0.75, 0.95), rz * 0.9),
        S.VEGETATION,
        M.LEAVES,
        green,
        yaw=rng.uniform(0, np.pi),
        param=(rng.uniform(0, 100), 0, 0, 0),
    )
    # Lobes around the core make the crown irregular.
    n_lobes = int(rng.integers(3, 7))
    for k in range(n_lobes):
        ang = 2 * np.pi * (k + rng.uniform(-0.3, 0.3)) / n_lobes
        elev = rng.uniform(-0.3, 0.8)
        off = np.array(
            [
                np.cos(ang) * np.cos(elev) * rx * 0.55,
                np.sin(ang) * np.cos(elev) * rx * 0.55,
                np.sin(elev) * rz * 0.5,
            ]
        )
        s = rng.uniform(0.45, 0.65)
        p.ellipsoid(
            centre + off,
            (rx * s, rx * s * rng.uniform(0.8, 1.2), rz * s * rng.uniform(0.8, 1.1)),
            S.VEGETATION,
            M.LEAVES,
            green * rng.uniform(0.85, 1.12),
            yaw=rng.uniform(0, np.pi),
            param=(rng.uniform(0, 100), 0, 0, 0),
        )


def _lamp(p: _Parts, rng: np.random.Generator, x: float, y: float, z0: float, toward: F64) -> None:
    """Street lamp: pole, arm reaching over the road, lamp head (all class pole)."""
    h = rng.uniform(6.0, 8.0)
    grey = np.array([0.42, 0.43, 0.45]) * rng.uniform(0.8, 1.2)
    p.cylinder((x, y, z0 + h / 2), 0.075, h / 2, S.POLE, M.METAL, grey)
    tip = np.array([x, y, z0 + h]) + np.r_[toward * 1.6, 0.25]
    p.rod((x, y, z0 + h - 0.1), tip, 0.07, S.POLE, M.METAL, grey)
    p.box(tip + np.array([0, 0, -0.08]), (0.35, 0.16, 0.07), S.POLE, M.METAL, grey * 0.8, yaw=_yaw_of(toward))


def _sign(
    p: _Parts,
    rng: np.random.Generator,
    x: float,
    y: float,
    z0: float,
    facing: F64,
    *,
    style: int | None = None,
) -> None:
    """Sign post (pole) with one or two plates (traffic-sign) whose front faces ``facing``."""
    h = rng.uniform(2.4, 3.0)
    p.cylinder((x, y, z0 + h / 2), 0.04, h / 2, S.POLE, M.METAL, (0.55, 0.56, 0.58), name="sign post")
    style = int(rng.integers(0, 4)) if style is None else style
    plate_z = z0 + h - 0.35
    front = np.array([x, y, 0]) + np.r_[facing, 0] * 0.06
    if style == 1 and rng.random() < 0.6:
        p.cylinder(
            (front[0], front[1], plate_z),
            0.32,
            0.015,
            S.TRAFFIC_SIGN,
            M.SIGN,
            (0.9, 0.9, 0.9),
            rot=_frame_z(np.r_[facing, 0]),
            param=(1, 0, 0, 0),
        )
    else:
        hw, hh = (0.32, 0.32) if style != 2 else (0.5, 0.22)
        p.box(
            (front[0], front[1], plate_z),
            (0.015, hw, hh),
            S.TRAFFIC_SIGN,
            M.SIGN,
            (0.9, 0.9, 0.9),
            yaw=_yaw_of(facing),
            param=(style, 0, 0, 0),
        )
    if rng.random() < 0.35:
        p.box(
            (front[0], front[1], plate_z - 0.55),
            (0.015, 0.3, 0.14),
            S.TRAFFIC_SIGN,
            M.SIGN,
            (0.9, 0.9, 0.9),
            yaw=_yaw_of(facing),
            param=(3, 0, 0, 0),
        )


# ----------------------------------------------------------------------------------------- occupancy
class _Occupancy:
    """Discs on the ground plane already taken by objects (a 4 m hash grid)."""

    def __init__(self) -> None:
        self.cells: dict[tuple[int, int], list[tuple[float, float, float]]] = {}

    def free(self, x: float, y: float, r: float) -> bool:
        cx, cy = int(np.floor(x / 4)), int(np.floor(y / 4))
        for i in range(cx - 2, cx + 3):
            for j in range(cy - 2, cy + 3):
                for ox, oy, orad in self.cells.get((i, j), ()):
                    if (ox - x) ** 2 + (oy - y) ** 2 < (orad + r) ** 2:
                        return False
        return True

    def add(self, x: float, y: float, r: float) -> None:
        self.cells.setdefault((int(np.floor(x / 4)), int(np.floor(y / 4))), []).append((x, y, r))

    def add_segment(self, p0: F64, p1: F64, r: float) -> None:
        n = max(int(np.ceil(np.linalg.norm(p1 - p0) / max(r, 0.3))), 1)
        for u in np.linspace(0, 1, n + 1):
            q = p0 + u * (p1 - p0)
            self.add(float(q[0]), float(q[1]), r)

    def free_segment(self, p0: F64, p1: F64, r: float) -> bool:
        n = max(int(np.ceil(np.linalg.norm(p1 - p0) / max(r, 0.3))), 1)
        points = (p0 + u * (p1 - p0) for u in np.linspace(0, 1, n + 1))
        return all(self.free(q[0], q[1], r) for q in points)


# -------------------------------------------------------------------------------------------- actors
@dataclass(frozen=True)
class Actor:
    """A moving object with a pose per frame.

    Attributes:
        instance: instance id; semantic: raw class id (moving car 252 / moving person 254).
        shape: rigid shape in the object frame (cars); empty for walking persons (rebuilt per frame).
        look: appearance of a person, or None.
        xy: (F, 2) ground position per frame; yaw: (F,) heading; phase: (F,) gait phase (persons).
        z: height of the ground it moves on (the curb height for pedestrians on sidewalks).
    """

    instance: int
    semantic: int
    shape: Primitives
    look: PersonLook | None
    xy: F64
    yaw: F64
    phase: F64
    z: float = 0.0

    def primitives(self, frame: int) -> Primitives:
        """World primitives of this actor at ``frame``."""
        if self.look is not None:
            local = person_shape(self.look, self.semantic, self.instance, float(self.phase[frame]), 0.38)
        else:
            local = self.shape
        return _place(
            local, float(self.xy[frame, 0]), float(self.xy[frame, 1]), float(self.yaw[frame]), self.z
        )


@dataclass(frozen=True)
class Scene:
    """Static primitives, moving actors, the ego route and the lighting.

    Attributes:
        static: every primitive that does not move.
        actors: moving objects.
        route: ego route with per-frame vehicle poses.
        grid: street grid geometry.
        sun: (3,) unit vector pointing towards the sun.
        hz: frame rate.
    """

    static: Primitives
    actors: tuple[Actor, ...]
    route: Route
    grid: StreetGrid
    sun: F64
    hz: float

    @property
    def num_frames(self) -> int:
        return len(self.route.frame_s)

    def primitives_at(self, frame: int) -> Primitives:
        """All primitives (static first, then actors) at ``frame``."""
        return Primitives.concat([self.static] + [a.primitives(frame) for a in self.actors])

    def semantic_ids(self) -> set[int]:
        """Raw class ids present in the scene (static and moving)."""
        return {int(v) for v in np.unique(self.static.semantic)} | {a.semantic for a in self.actors}


# --------------------------------------------------------------------------------------------- build
class _Ids:
    def __init__(self) -> None:
        self.next = 1

    def __call__(self) -> int:
        self.next += 1
        return self.next - 1


@dataclass(frozen=True)
class _Build:
    """What the steps of one scene build share: the layout, the ground already taken, the instance id
    counter and the static objects built so far (their order is the order of the scene's primitives)."""

    cfg: SceneConfig
    grid: StreetGrid
    occ: _Occupancy
    ids: _Ids
    statics: list[Primitives]
    extra: np.random.Generator
    """Draws added with the demo's names (jeeps, gravel, cones, benches, bollards, the bus, children):
    a stream of its own, so they shift none of the older layout draws."""


class _Side(NamedTuple):
    """A block side (or lot side) in side coordinates: world (x, y) = o + a·t + c·n (module docstring)."""

    o: F64
    """(2,) origin: a = c = 0."""
    t: F64
    """(2,) unit direction along the curb (a)."""
    n: F64
    """(2,) unit direction across it, into the block (c)."""
    length: float
    """Length of the side along t (m)."""

    def at(self, a: float, c: float) -> F64:
        """World (x, y) of side coordinates (a, c)."""
        return self.o + a * self.t + c * self.n

    def boxes(
        self, a: tuple[float, float], c: tuple[float, float], z: tuple[float, float], tile: float
    ) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
        """(centre, half extents) of the axis-aligned boxes that cover [a0, a1] × [c0, c1] × [z0, z1] in
        side coordinates, split into tiles no longer than ``tile`` along a."""
        (a0, a1), (c0, c1), (z0, z1) = a, c, z
        n_tiles = max(int(np.ceil((a1 - a0) / tile)), 1)
        edges = np.linspace(a0, a1, n_tiles + 1)
        out = []
        for ta, tb in itertools.pairwise(edges):
            q0 = self.o + ta * self.t + c0 * self.n
            q1 = self.o + tb * self.t + c1 * self.n
            lo, hi = np.minimum(q0, q1), np.maximum(q0, q1)
            out.append(
                (
                    ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (z0 + z1) / 2),
                    ((hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2, (z1 - z0) / 2),
                )
            )
        return out


def build_scene(cfg: SceneConfig, ego: EgoConfig, frames: int, hz: float, seed: int) -> Scene:
    """Build the scene for ``frames`` frames at ``hz`` from ``seed`` (deterministic)."""
    ss = np.random.SeedSequence([int(seed), 0x5EED])
    # spawn(5)'s first four children equal spawn(4)'s: the fifth stream was added without moving the others.
    rng_route, rng_hero, rng_city, rng_light, rng_extra = (np.random.default_rng(s) for s in ss.spawn(5))
    grid = StreetGrid(
        block_x=float(rng_city.uniform(*cfg.block_x)),
        block_y=float(rng_city.uniform(*cfg.block_y)),
        lane_width=cfg.lane_width,
        parking_width=cfg.parking_width,
    )
    route = plan_route(ego, grid, frames, hz, rng_route)
    statics: list[Primitives] = []
    build = _Build(cfg, grid, _Occupancy(), _Ids(), statics, rng_extra)
    actors: list[Actor] = []
    _heroes(build, ego, route, hz, rng_hero, actors)

    pts = route.xy[:: max(len(route.xy) // 200, 1)]
    lo = pts.min(axis=0) - cfg.margin
    hi = pts.max(axis=0) + cfg.margin
    blocks = []
    for i in range(int(np.floor(lo[0] / grid.block_x)), int(np.floor(hi[0] / grid.block_x)) + 1):
        for j in range(int(np.floor(lo[1] / grid.block_y)), int(np.floor(hi[1] / grid.block_y)) + 1):
            bx0, by0 = i * grid.block_x, j * grid.block_y
            dx = np.maximum(np.maximum(bx0 - pts[:, 0], pts[:, 0] - bx0 - grid.block_x), 0)
            dy = np.maximum(np.maximum(by0 - pts[:, 1], pts[:, 1] - by0 - grid.block_y), 0)
            if np.hypot(dx, dy).min() <= cfg.margin:
                blocks.append((i, j))
    p = _Parts()
    yard_hint = _yard_hints(grid, route, rng_city)
    for i, j in blocks:
        _block(build, i, j, rng_city, p, yard_hint)
    _named_extras(build, route, hz, actors)
    for i, j in blocks:
        for side in _side_frames(grid, i, j):
            _street_objects(build, side)
    _streets(cfg, grid, set(blocks), rng_city, p)
    statics.insert(0, p.build())
    az = rng_light.uniform(0, 2 * np.pi)
    el = np.deg2rad(rng_light.uniform(32, 55))
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return Scene(
        static=Primitives.concat(statics), actors=tuple(actors), route=route, grid=grid, sun=sun, hz=hz
    )


def _yard_hints(grid: StreetGrid, route: Route, rng: np.random.Generator) -> dict[tuple[int, int, int], bool]:
    """Force front yards on one side of the first street (y = 0, along +x) so fences, lawns and bushes are
    in view from the first frame. Keys are (block i, block j, side): block (i, 0) faces the street with
    its side 0, block (i, −1) with its side 2."""
    leg = route.legs[0]
    yard_on_left = rng.random() < 0.5
    hints: dict[tuple[int, int, int], bool] = {}
    x_lo, x_hi = leg.start[0] - grid.block_x, leg.start[0] + leg.s1 + grid.block_x
    for i in range(int(np.floor(x_lo / grid.block_x)), int(np.floor(x_hi / grid.block_x)) + 1):
        hints[(i, 0, 0)] = yard_on_left
        hints[(i, -1, 2)] = not yard_on_left
    return hints


def _oncoming(inst: int, sem: int, shape: Primitives, xy: F64, heading: F64) -> Actor:
    """A vehicle on the oncoming lane: driving against ``heading`` along ``xy`` (T, 2), never turning."""
    frames = len(xy)
    return Actor(inst, sem, shape, None, xy, np.full(frames, _yaw_of(-heading)), np.zeros(frames))


def _heroes(  # noqa: PLR0915  a scene recipe: one placement after the other, read top to bottom
    build: _Build, ego: EgoConfig, route: Route, hz: float, rng: np.random.Generator, actors: list[Actor]
) -> None:
    """Objects placed relative to the route so every class shows up in the camera."""
    cfg, grid, occ, ids, statics = build.cfg, build.grid, build.occ, build.ids, build.statics
    frames = len(route.frame_s)
    t = np.arange(frames) / hz
    lw, hr, sw = grid.lane_width, grid.half_road, cfg.sidewalk_width
    leg1 = route.legs[0]
    h1 = leg1.heading
    centre1 = leg1.start - right_of(h1) * lw / 2  # a point on the first street's centre line
    inter1 = np.array([0.0, 0.0])

    def street_point(centre: F64, h: F64, along: float, lateral: float) -> F64:
        """Point ``along`` metres from ``centre`` along the street, ``lateral`` right of its centre line."""
        return centre + h * along + right_of(h) * lateral

    # Lead car: drives the route ahead of the ego, slowing for the turns like the ego does. It is a jeep
    # (an SUV: SemanticKITTI's car, a detector's "SUV"), so the prompt expansion car -> jeep matters in view.
    lead_s = drive_along(route, ego, float(rng.uniform(13, 18)), frames, hz, cruise_scale=1.05)
    lead_xy, lead_yaw = route.at(lead_s)
    inst = ids()
    lead = car_shape(rng, S.MOVING_CAR, inst, jeep=True)
    actors.append(Actor(inst, S.MOVING_CAR, lead, None, lead_xy, lead_yaw, np.zeros(frames)))

    # Oncoming car on the first street, passing the ego before it reaches the intersection.
    d0 = float(np.dot(inter1 - leg1.start, h1))
    start = street_point(
        centre1, h1, float(np.dot(leg1.start - centre1, h1)) + max(d0 - 2.0, 12.0) + 14.0, -lw / 2
    )
    xy = start[None] - cfg.oncoming_speed * t[:, None] * h1[None]
    inst = ids()
    actors.append(_oncoming(inst, S.MOVING_CAR, car_shape(rng, S.MOVING_CAR, inst), xy, h1))

    # After the first turn: an oncoming car on the new street that reaches the intersection well after the
    # ego has left it.
    if len(route.legs) > 1:
        leg2 = route.legs[1]
        h2 = leg2.heading
        centre2 = leg2.start - right_of(h2) * lw / 2
        t_exit = leg2.s0 / ego.cruise_speed + 2.5
        dist = cfg.oncoming_speed * (t_exit + 3.0) + hr
        start2 = centre2 + h2 * (float(np.dot(inter1 - centre2, h2)) + dist) - right_of(h2) * lw / 2
        xy = start2[None] - cfg.oncoming_speed * t[:, None] * h2[None]
        inst = ids()
        actors.append(
            Actor(
                inst,
                S.MOVING_CAR,
                car_shape(rng, S.MOVING_CAR, inst),
                None,
                xy,
                np.full(frames, _yaw_of(-h2)),
                np.zeros(frames),
            )
        )
    else:
        leg2, h2, centre2 = leg1, h1, centre1

    # Walking persons: towards the ego on the first street's right sidewalk (starting near the corner),
    # and away from it on the second street.
    c_walk = hr + sw - 0.8
    along_corner = float(np.dot(inter1 - centre1, h1)) - hr - 1.5
    for centre, h, along, direction in (
        (centre1, h1, along_corner - rng.uniform(0, 3), -1.0),
        (centre2, h2, float(np.dot(inter1 - centre2, h2)) + hr + rng.uniform(9, 14), 1.0),
    ):
        look = person_look(rng)
        p0 = street_point(centre, h, along, c_walk)
        xy = p0[None] + direction * cfg.walk_speed * t[:, None] * h[None]
        occ.add_segment(xy[0], xy[-1], 0.45)
        phase = 2 * np.pi * cfg.walk_speed / 1.45 * t + rng.uniform(0, 2 * np.pi)
        inst = ids()
        actors.append(
            Actor(
                inst,
                S.MOVING_PERSON,
                Primitives.empty(),
                look,
                xy,
                np.full(frames, _yaw_of(direction * h)),
                phase,
                cfg.curb_height,
            )
        )

    # People waiting at the corners of the first intersection, and a sign facing the ego.
    p = _Parts()
    for lateral in (hr + 1.1, -(hr + 1.3)):
        q = street_point(centre1, h1, along_corner + rng.uniform(-1.0, 1.0), lateral)
        look = person_look(rng)
        inst = ids()
        statics.append(
            _place(
                person_shape(look, S.PERSON, inst, 0.0, 0.0),
                q[0],
                q[1],
                _yaw_of(-np.sign(lateral) * right_of(h1)),
                cfg.curb_height,
            )
        )
        occ.add(q[0], q[1], 0.5)
    q = street_point(centre1, h1, along_corner - 1.5, hr + 0.35)
    _sign(p, rng, q[0], q[1], cfg.curb_height, -h1, style=int(rng.integers(0, 4)))
    occ.add(q[0], q[1], 0.5)

    # More pedestrians standing on both sidewalks of the first two streets, ahead of the ego.
    for centre, h, lo, hi in (
        (centre1, h1, 4.0, along_corner - 3.0),
        (
            centre2,
            h2,
            float(np.dot(inter1 - centre2, h2)) + hr + 4.0,
            float(np.dot(inter1 - centre2, h2)) + hr + 40.0,
        ),
    ):
        for _ in range(3):
            if hi <= lo:
                break
            side = 1.0 if rng.random() < 0.6 else -1.0
            q = street_point(centre, h, rng.uniform(lo, hi), side * (hr + rng.uniform(1.2, 1.9)))
            if occ.free(q[0], q[1], 0.6):
                inst = ids()
                statics.append(
                    _place(
                        person_shape(person_look(rng), S.PERSON, inst, 0.0, 0.0),
                        q[0],
                        q[1],
                        rng.uniform(-np.pi, np.pi),
                        cfg.curb_height,
                    )
                )
                occ.add(q[0], q[1], 0.6)

    # Parked bicycles near the road on both streets.
    for centre, h, along0 in (
        (centre1, h1, along_corner - 8.0),
        (centre2, h2, float(np.dot(inter1 - centre2, h2)) + hr + 6.0),
    ):
        for k, lateral in enumerate((hr + 1.7, -(hr + 1.7))):
            along = along0 + (-1) ** k * rng.uniform(0, 4) - (2.5 if k else 0.0)
            q = street_point(centre, h, along, lateral)
            if occ.free(q[0], q[1], 0.9):
                inst = ids()
                statics.append(
                    _place(
                        bicycle_shape(rng, S.BICYCLE, inst),
                        q[0],
                        q[1],
                        _yaw_of(h) + rng.uniform(-0.15, 0.15),
                        cfg.curb_height,
                    )
                )
                occ.add(q[0], q[1], 0.9)

    # Trucks: one parked beyond the first intersection (visible from the start), one on the second street.
    for centre, h, along in (
        (centre1, h1, float(np.dot(inter1 - centre1, h1)) + hr + rng.uniform(11, 18)),
        (centre2, h2, float(np.dot(inter1 - centre2, h2)) + hr + rng.uniform(18, 26)),
    ):
        side = 1.0 if rng.random() < 0.5 else -1.0
        q = street_point(centre, h, along, side * (lw + grid.parking_width / 2))
        yaw = _yaw_of(h if side > 0 else -h)
        inst = ids()
        statics.append(_place(truck_shape(rng, S.TRUCK, inst), q[0], q[1], yaw))
        occ.add_segment(q - h * 4.2, q + h * 4.2, 1.4)
    statics.append(p.build())


def _named_extras(build: _Build, route: Route, hz: float, actors: list[Actor]) -> None:
    """Objects added with the demo's names, placed on the first street so the camera sees them early: an
    oncoming bus, a row of traffic cones on the ego lane's edge, a bench, bollards at the corner and two
    children. Their draws come from ``build.extra`` only."""
    cfg, grid, occ, ids, statics, rng = (
        build.cfg,
        build.grid,
        build.occ,
        build.ids,
        build.statics,
        build.extra,
    )
    frames = len(route.frame_s)
    t = np.arange(frames) / hz
    lw, hr, sw, ch = grid.lane_width, grid.half_road, cfg.sidewalk_width, cfg.curb_height
    leg1 = route.legs[0]
    h1 = leg1.heading
    centre1 = leg1.start - right_of(h1) * lw / 2
    start_along = float(np.dot(leg1.start - centre1, h1))
    along_corner = float(np.dot(np.zeros(2) - centre1, h1)) - hr - 1.5

    def point(along: float, lateral: float) -> F64:
        return centre1 + h1 * along + right_of(h1) * lateral

    # The bus comes towards the ego in the oncoming lane, behind the (faster) oncoming car of _heroes.
    d0 = float(np.dot(np.zeros(2) - leg1.start, h1))
    bus_start = point(start_along + max(d0 - 2.0, 12.0) + 14.0 + rng.uniform(22.0, 30.0), -lw / 2)
    xy = bus_start[None] - cfg.oncoming_speed * 0.85 * t[:, None] * h1[None]
    inst = ids()
    actors.append(_oncoming(inst, S.MOVING_BUS, bus_shape(rng, S.MOVING_BUS, inst), xy, h1))

    # Cones on the right edge of the ego lane, ahead of the start.
    a0 = start_along + rng.uniform(14.0, 20.0)
    for k in range(5):
        q = point(a0 + 2.2 * k, lw - 0.35)
        if occ.free(q[0], q[1], 0.25):
            statics.append(_place(cone_shape(ids()), q[0], q[1], rng.uniform(0, np.pi)))
            occ.add(q[0], q[1], 0.25)

    # A bench on the right sidewalk, back to the lots; bollards at the corner; two children nearby.
    for along in np.linspace(start_along + 8.0, along_corner - 6.0, 12):
        q = point(float(along), hr + sw - 0.5)
        if occ.free(q[0], q[1], 1.0):
            statics.append(_place(bench_shape(rng, ids()), q[0], q[1], _yaw_of(-right_of(h1)), ch))
            occ.add(q[0], q[1], 1.0)
            break
    for side in (1.0, -1.0):
        for k in range(4):
            q = point(along_corner - 4.0 - 1.4 * k, side * (hr + 0.3))
            if occ.free(q[0], q[1], 0.2):
                statics.append(_place(bollard_shape(ids()), q[0], q[1], 0.0, ch))
                occ.add(q[0], q[1], 0.2)
    for _ in range(2):
        q = point(float(rng.uniform(start_along + 10.0, along_corner - 3.0)), -(hr + rng.uniform(1.2, 2.2)))
        if occ.free(q[0], q[1], 0.45):
            look = person_look(rng, child=True)
            statics.append(
                _place(
                    person_shape(look, S.PERSON, ids(), 0.0, 0.0), q[0], q[1], rng.uniform(-np.pi, np.pi), ch
                )
            )
            occ.add(q[0], q[1], 0.45)


def _street_objects(build: _Build, side: _Side) -> None:
    """Cones in the parking lane, benches and a bollard row on one block side (``build.extra`` draws)."""
    cfg, occ, ids, statics, rng = build.cfg, build.occ, build.ids, build.statics, build.extra
    ch, sw = cfg.curb_height, cfg.sidewalk_width
    if rng.random() < cfg.cone_rate:
        a = rng.uniform(8.0, max(side.length - 16.0, 9.0))
        for k in range(int(rng.integers(2, 5))):
            q = side.at(a + 1.8 * k, -build.grid.parking_width + 0.4)
            if occ.free(q[0], q[1], 0.25):
                statics.append(_place(cone_shape(ids()), q[0], q[1], rng.uniform(0, np.pi)))
                occ.add(q[0], q[1], 0.25)
    for _ in range(rng.poisson(cfg.bench_rate)):
        q = side.at(rng.uniform(6.0, side.length - 6.0), sw - 0.5)
        if occ.free(q[0], q[1], 1.0):
            statics.append(_place(bench_shape(rng, ids()), q[0], q[1], _yaw_of(-side.n), ch))
            occ.add(q[0], q[1], 1.0)
    if rng.random() < cfg.bollard_rate:
        a = rng.uniform(4.0, 7.0)
        for k in range(int(rng.integers(3, 6))):
            q = side.at(a + 1.4 * k, 0.3)
            if occ.free(q[0], q[1], 0.2):
                statics.append(_place(bollard_shape(ids()), q[0], q[1], 0.0, ch))
                occ.add(q[0], q[1], 0.2)


def _side_frames(grid: StreetGrid, i: int, j: int) -> list[_Side]:
    """The four curb lines of block (i, j), counter-clockwise from the south."""
    hr = grid.half_road
    x0, x1 = i * grid.block_x + hr, (i + 1) * grid.block_x - hr
    y0, y1 = j * grid.block_y + hr, (j + 1) * grid.block_y - hr
    return [
        _Side(np.array([x0, y0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), x1 - x0),
        _Side(np.array([x1, y0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), y1 - y0),
        _Side(np.array([x1, y1]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), x1 - x0),
        _Side(np.array([x0, y1]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), y1 - y0),
    ]


def _block(
    build: _Build,
    i: int,
    j: int,
    rng: np.random.Generator,
    p: _Parts,
    yard_hint: dict[tuple[int, int, int], bool],
) -> None:
    """One block: sidewalk ring, lot ground, buildings (row or detached with yards), street furniture,
    parked cars in the parking lanes along its four curbs."""
    cfg, grid = build.cfg, build.grid
    sw, lh = cfg.sidewalk_width, cfg.lawn_height
    sides = _side_frames(grid, i, j)
    yard = [yard_hint.get((i, j, k), bool(rng.random() < cfg.yard_rate)) for k in range(4)]
    setback = [rng.uniform(3.5, 6.0) if y else rng.uniform(0.0, 0.6) for y in yard]
    depth_max = 14.0
    footprints: list[tuple[F64, F64]] = []
    for side in sides:
        strip = rng.random() < cfg.grass_strip_rate
        gravel = strip and build.extra.random() < cfg.gravel_strip_rate
        _sidewalk(cfg, grid, p, side, strip, gravel)
        _furniture(build, rng, p, side, strip)
        _parked(build, rng, side)

    # Buildings on the lot sides. Sides 1 and 3 leave the corners to sides 0 and 2.
    for k, side in enumerate(sides):
        lot = _Side(side.at(sw, sw), side.t, side.n, side.length - 2 * sw)
        reserve = 0.0 if k % 2 == 0 else max(setback[0], setback[2]) + depth_max + 0.5
        _buildings(cfg, rng, p, lot, reserve=reserve, yard=yard[k], setback=setback[k], footprints=footprints)

    # Lot ground (lawns, yards, backyards) in tiles; tiles fully under one building are skipped.
    o, t, n, _ = sides[0]
    x0, y0 = o + sw * (t + n)
    x1 = x0 + sides[0].length - 2 * sw
    y1 = y0 + sides[1].length - 2 * sw
    nx, ny = max(int(np.ceil((x1 - x0) / 12)), 1), max(int(np.ceil((y1 - y0) / 12)), 1)
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    for a in range(nx):
        for b in range(ny):
            lo, hi = np.array([xs[a], ys[b]]), np.array([xs[a + 1], ys[b + 1]])
            if any((flo <= lo + 0.01).all() and (fhi >= hi - 0.01).all() for flo, fhi in footprints):
                continue
            p.box(
                ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lh - 0.3) / 2),
                ((hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2, (lh + 0.3) / 2),
                S.TERRAIN,
                M.GRASS,
                (0.31, 0.43, 0.19),
            )


def _sidewalk(
    cfg: SceneConfig, grid: StreetGrid, p: _Parts, side: _Side, strip: bool, gravel: bool = False
) -> None:
    """The sidewalk along one curb (a concrete curb, then slabs; with a grass strip, or a gravel strip when
    ``gravel``, behind the curb when ``strip``) and the parking lane in front of it."""
    sw, ch, length = cfg.sidewalk_width, cfg.curb_height, side.length
    slabs = (0.6, 0.59, 0.57)
    for centre, half in side.boxes((0, length), (0.0, 0.18), (-0.3, ch + 0.01), cfg.tile):
        p.box(centre, half, S.SIDEWALK, M.SLABS, (0.62, 0.61, 0.58), name="curb")
    if strip:
        for centre, half in side.boxes((sw, length - sw), (0.18, 1.5), (-0.3, ch - 0.03), cfg.tile):
            if gravel:
                # Plain (style 0) asphalt shading with a light stone colour reads as fine gravel.
                p.box(centre, half, S.OTHER_GROUND, M.ASPHALT, (0.56, 0.53, 0.47), name="gravel")
            else:
                p.box(centre, half, S.TERRAIN, M.GRASS, (0.33, 0.45, 0.2), name="grass strip")
        for centre, half in side.boxes((0, length), (1.5, sw), (-0.3, ch), cfg.tile):
            p.box(centre, half, S.SIDEWALK, M.SLABS, slabs)
        for centre, half in side.boxes((0, sw), (0.0, sw), (-0.3, ch), cfg.tile):
            p.box(centre, half, S.SIDEWALK, M.SLABS, slabs)
        for centre, half in side.boxes((length - sw, length), (0.0, sw), (-0.3, ch), cfg.tile):
            p.box(centre, half, S.SIDEWALK, M.SLABS, slabs)
    else:
        for centre, half in side.boxes((0, length), (0.18, sw), (-0.3, ch), cfg.tile):
            p.box(centre, half, S.SIDEWALK, M.SLABS, slabs)
    for centre, half in side.boxes((6.0, length - 6.0), (-grid.parking_width, 0.0), (-0.3, 0.006), cfg.tile):
        p.box(centre, half, S.PARKING, M.PAVERS, (0.4, 0.39, 0.38), param=(0.0, 0.0, 0.0, 0.0))


def _buildings(  # noqa: PLR0912, PLR0915  a scene recipe: one building after the other, read top to bottom
    cfg: SceneConfig,
    rng: np.random.Generator,
    p: _Parts,
    lot: _Side,
    *,
    reserve: float,
    yard: bool,
    setback: float,
    footprints: list[tuple[F64, F64]],
) -> None:
    """Buildings along one lot side (side coordinates from the lot line), plus fences/hedges, bushes and
    yard trees for detached houses."""
    o, t, n, length = lot
    lh = cfg.lawn_height
    a = reserve + (rng.uniform(0.0, 2.0) if yard else 0.0)
    end = length - reserve
    fence_style = int(rng.integers(0, 2))
    hedge = rng.random() < 0.3
    fence_color = np.array([0.45, 0.33, 0.22]) if fence_style == 0 else np.array([0.3, 0.32, 0.3])
    while a < end - 5.0:
        if yard:
            width = min(rng.uniform(9.0, 14.0), end - a - 1.0)
            depth = rng.uniform(9.0, 12.0)
            floors = int(rng.integers(1, 4))
            gap = rng.uniform(3.0, 8.0)
        else:
            width = min(rng.uniform(8.0, 20.0), end - a)
            depth = rng.uniform(10.0, 14.0)
            floors = int(rng.integers(3, 7))
            gap = 0.0 if rng.random() < 0.8 else rng.uniform(2.0, 5.0)
        if width < 5.0:
            break
        floor_h = rng.uniform(2.9, 3.4)
        height = floors * floor_h + rng.uniform(0.3, 0.9)
        r = rng.random()
        style = 1 if r < 0.3 else (2 if (r > 0.9 and not yard and floors >= 4) else 0)
        color = (
            _BRICK[rng.integers(len(_BRICK))]
            if style == 1
            else (np.array([0.55, 0.58, 0.6]) if style == 2 else _PLASTER[rng.integers(len(_PLASTER))])
        )
        color = color * rng.uniform(0.9, 1.05)
        bname = "house" if yard else ("office building" if style == 2 else "apartment building")
        q0 = o + a * t + setback * n
        q1 = o + (a + width) * t + (setback + depth) * n
        lo, hi = np.minimum(q0, q1), np.maximum(q0, q1)
        footprints.append((lo, hi))
        spacing = rng.uniform(2.4, 3.4)
        p.box(
            ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, height / 2),
            ((hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2, height / 2),
            S.BUILDING,
            M.FACADE,
            color,
            param=(floor_h, spacing, style, rng.uniform(0, 1000)),
            name=bname,
        )
        mid = a + width / 2
        if yard and rng.random() < 0.75:
            _gable(p, rng, lot, mid=mid, width=width, setback=setback, depth=depth, height=height)
        elif not yard and rng.random() < 0.3:
            # A set-back top storey on some row buildings.
            q0 = o + (a + 1.0) * t + (setback + 2.0) * n
            q1 = o + (a + width - 1.0) * t + (setback + depth - 1.0) * n
            lo2, hi2 = np.minimum(q0, q1), np.maximum(q0, q1)
            p.box(
                ((lo2[0] + hi2[0]) / 2, (lo2[1] + hi2[1]) / 2, height + floor_h / 2),
                ((hi2[0] - lo2[0]) / 2, (hi2[1] - lo2[1]) / 2, floor_h / 2),
                S.BUILDING,
                M.FACADE,
                color * 0.95,
                param=(floor_h, spacing, style, rng.uniform(0, 1000)),
                name=bname,
            )
        if yard:
            lot0, lot1 = a - gap / 2 if a > reserve + 0.5 else a - 1.0, a + width + gap / 2
            lot0, lot1 = max(lot0, reserve), min(lot1, end)
            gate = mid
            for s0, s1 in ((lot0, gate - 0.7), (gate + 0.7, lot1)):
                if s1 - s0 < 0.5:
                    continue
                if hedge:
                    boxes = lot.boxes((s0, s1), (0.15, 0.75), (lh, lh + rng.uniform(0.8, 1.3)), 12.0)
                    green = np.array([0.17, 0.32, 0.1]) * rng.uniform(0.85, 1.15)
                    leaf_seed = (rng.uniform(0, 100), 0, 0, 0)
                    for centre, half in boxes:
                        p.box(centre, half, S.VEGETATION, M.LEAVES, green, param=leaf_seed, name="hedge")
                else:
                    fh = rng.uniform(0.9, 1.3)
                    for centre, half in lot.boxes((s0, s1), (0.12, 0.17), (lh, lh + fh), 12.0):
                        p.box(
                            centre,
                            half,
                            S.FENCE,
                            M.FENCE,
                            fence_color,
                            param=(fence_style, 0, 0, 0),
                            name="wooden fence" if fence_style == 0 else "metal fence",
                        )
            for _ in range(rng.integers(1, 4)):
                s = rng.uniform(a + 0.8, a + width - 0.8)
                if abs(s - gate) < 1.3:
                    continue
                c = setback - rng.uniform(0.6, 1.2)
                q = o + s * t + c * n
                r = rng.uniform(0.5, 1.1)
                p.ellipsoid(
                    (q[0], q[1], lh + r * 0.7),
                    (r, r * rng.uniform(0.8, 1.2), r * rng.uniform(0.7, 1.0)),
                    S.VEGETATION,
                    M.LEAVES,
                    np.array([0.2, 0.38, 0.13]) * rng.uniform(0.8, 1.2, 3),
                    param=(rng.uniform(0, 100), 0, 0, 0),
                    name="bush",
                )
            if rng.random() < 0.4 and setback > 4.0:
                s = rng.uniform(a, a + width)
                if abs(s - gate) > 2.5:
                    q = o + s * t + setback * 0.45 * n
                    _tree(p, rng, q[0], q[1], lh, scale=0.8)
        a += width + gap


def _gable(
    p: _Parts,
    rng: np.random.Generator,
    lot: _Side,
    *,
    mid: float,
    width: float,
    setback: float,
    depth: float,
    height: float,
) -> None:
    """Two pitched roof slabs meeting at a ridge parallel to the street, with the attic volume filled."""
    o, t, n = lot.o, lot.t, lot.n
    pitch = np.deg2rad(rng.uniform(28, 42))
    ridge_h = depth / 2 * np.tan(pitch)
    t3, n3, z3 = np.r_[t, 0.0], np.r_[n, 0.0], np.array([0.0, 0.0, 1.0])
    color = np.array([0.55, 0.22, 0.15]) if rng.random() < 0.7 else np.array([0.25, 0.25, 0.27])
    base = np.r_[o + mid * t, height]
    slope_len = depth / 2 / np.cos(pitch)
    for sign, c_mid in ((1.0, setback + depth / 4), (-1.0, setback + 3 * depth / 4)):
        y_axis = n3 * np.cos(pitch) * sign + z3 * np.sin(pitch)
        y_axis = y_axis * sign
        x_axis = t3
        z_axis = _cross(x_axis, y_axis)
        if z_axis[2] < 0:
            x_axis, z_axis = -x_axis, -z_axis
        rot = np.stack([x_axis, y_axis, z_axis], axis=1)
        centre = base + n3 * c_mid + z3 * (ridge_h / 2) + z3 * 0.05
        p.box(
            centre,
            (width / 2 + 0.3, slope_len / 2 + 0.3, 0.08),
            S.BUILDING,
            M.ROOF,
            color * rng.uniform(0.9, 1.1),
            rot=rot,
            name="roof",
        )
    attic = base + n3 * (setback + depth / 2) + z3 * (ridge_h / 4)
    half_along, half_across = width / 2 - 0.05, depth / 4
    hx = abs(t[0]) * half_along + abs(n[0]) * half_across
    hy = abs(t[1]) * half_along + abs(n[1]) * half_across
    p.box(attic, (hx, hy, ridge_h / 4), S.BUILDING, M.ROOF, color * 0.8, name="roof")


def _tree_row(build: _Build, rng: np.random.Generator, p: _Parts, side: _Side, strip: bool) -> None:
    """Street trees along the curb of one sidewalk (in the grass strip when it has one), on
    ``tree_row_rate`` of the sides."""
    cfg, occ = build.cfg, build.occ
    if rng.random() < cfg.tree_row_rate:
        a = rng.uniform(6.0, 12.0)
        while a < side.length - 8.0:
            q = side.at(a + rng.uniform(-0.5, 0.5), 0.85 if strip else 1.0)
            if occ.free(q[0], q[1], 1.2):
                _tree(p, rng, q[0], q[1], cfg.curb_height - (0.03 if strip else 0.0))
                occ.add(q[0], q[1], 1.2)
            a += rng.uniform(8.0, 13.0)


def _furniture(build: _Build, rng: np.random.Generator, p: _Parts, side: _Side, strip: bool) -> None:
    """Street trees, lamps, signs, parked bicycles and standing people on one sidewalk."""
    cfg, occ, ids, statics = build.cfg, build.occ, build.ids, build.statics
    at, t, n, length = side.at, side.t, side.n, side.length
    ch = cfg.curb_height

    _tree_row(build, rng, p, side, strip)
    a = rng.uniform(5.0, 15.0)
    while a < length - 5.0:
        q = at(a, 0.4)
        if occ.free(q[0], q[1], 0.5):
            _lamp(p, rng, q[0], q[1], ch, -n)
            occ.add(q[0], q[1], 0.5)
        a += rng.uniform(*cfg.lamp_spacing)
    # Sign before the intersection at a = 0 (traffic next to this side flows along −t), facing it.
    if rng.random() < 0.65:
        q = at(rng.uniform(2.5, 4.5), 0.35)
        if occ.free(q[0], q[1], 0.4):
            _sign(p, rng, q[0], q[1], ch, t)
            occ.add(q[0], q[1], 0.4)
    if rng.random() < 0.35:
        q = at(rng.uniform(10, max(length - 10, 11)), 0.35)
        if occ.free(q[0], q[1], 0.4):
            _sign(p, rng, q[0], q[1], ch, t if rng.random() < 0.5 else -t)
            occ.add(q[0], q[1], 0.4)
    for _ in range(rng.poisson(cfg.bicycles_per_side)):
        q = at(rng.uniform(6, length - 6), 1.75)
        if occ.free(q[0], q[1], 0.9):
            inst = ids()
            yaw = _yaw_of(t) + (np.pi if rng.random() < 0.5 else 0.0) + rng.uniform(-0.1, 0.1)
            statics.append(_place(bicycle_shape(rng, S.BICYCLE, inst), q[0], q[1], yaw, ch))
            occ.add(q[0], q[1], 0.9)
    for _ in range(rng.poisson(cfg.persons_per_side)):
        q = at(rng.uniform(4, length - 4), rng.uniform(1.3, 2.0))
        if occ.free(q[0], q[1], 0.45):
            inst = ids()
            statics.append(
                _place(
                    person_shape(person_look(rng), S.PERSON, inst, 0.0, 0.0),
                    q[0],
                    q[1],
                    rng.uniform(-np.pi, np.pi),
                    ch,
                )
            )
            occ.add(q[0], q[1], 0.45)


def _parked(build: _Build, rng: np.random.Generator, side: _Side) -> None:
    """Parallel-parked cars (and the odd truck) in the parking lane along one curb, facing traffic (−t)."""
    cfg, grid, occ, ids, statics = build.cfg, build.grid, build.occ, build.ids, build.statics
    o, t, n, length = side
    c = -grid.parking_width / 2
    a = 7.0 + rng.uniform(0, 2.0)
    while a < length - 7.0:
        truck = rng.random() < cfg.truck_rate
        size = 8.2 if truck else 4.8
        if a + size > length - 7.0:
            break
        q = o + (a + size / 2) * t + c * n
        if rng.random() < cfg.parked_car_rate and occ.free_segment(
            q - t * (size / 2 - 1), q + t * (size / 2 - 1), 1.0
        ):
            inst = ids()
            yaw = _yaw_of(-t) + rng.uniform(-0.03, 0.03)
            off = n * rng.uniform(-0.12, 0.12)
            if truck:
                shape = truck_shape(rng, S.TRUCK, inst)
            else:
                van = bool(rng.random() < 0.15)
                jeep = not van and bool(build.extra.random() < cfg.jeep_rate)
                shape = car_shape(rng, S.CAR, inst, van=van, jeep=jeep)
            statics.append(_place(shape, q[0] + off[0], q[1] + off[1], yaw))
            occ.add_segment(q - t * (size / 2 - 1), q + t * (size / 2 - 1), 1.0)
            a += size + rng.uniform(0.6, 2.2)
        else:
            a += rng.uniform(2.0, 6.0)


def _streets(
    cfg: SceneConfig, grid: StreetGrid, blocks: set[tuple[int, int]], rng: np.random.Generator, p: _Parts
) -> None:
    """Road tiles of every street segment and intersection next to a built block: marked lanes, zebra
    crossings at some segment ends, plain asphalt in intersections."""
    hr, lw = grid.half_road, grid.lane_width
    asphalt = (0.3, 0.3, 0.31)
    inters: set[tuple[int, int]] = set()
    for i, j in blocks:
        inters.update({(i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1)})
    for i, j in sorted(inters):
        cx, cy = i * grid.block_x, j * grid.block_y
        p.box((cx, cy, -0.25), (hr, hr, 0.25), S.ROAD, M.ASPHALT, asphalt, param=(0, 0, lw, 0))
        for axis, blen in ((0, grid.block_x), (1, grid.block_y)):
            nb = (i + 1, j) if axis == 0 else (i, j + 1)
            if nb not in inters:
                continue
            adjacent = ({(i, j - 1), (i, j)} if axis == 0 else {(i - 1, j), (i, j)}) & blocks
            if not adjacent:
                continue
            yaw = 0.0 if axis == 0 else np.pi / 2
            d = np.array([1.0, 0.0]) if axis == 0 else np.array([0.0, 1.0])
            s_lo, s_hi = hr, blen - hr
            zebra_lo, zebra_hi = rng.random() < 0.6, rng.random() < 0.6
            pieces: list[tuple[float, float, int]] = []
            a = s_lo
            if zebra_lo:
                pieces.append((a, a + 4.0, 2))
                a += 4.0
            end = s_hi - (4.0 if zebra_hi else 0.0)
            n_t = max(int(np.ceil((end - a) / cfg.tile)), 1)
            edges = np.linspace(a, end, n_t + 1)
            pieces += [(e0, e1, 1) for e0, e1 in itertools.pairwise(edges)]
            if zebra_hi:
                pieces.append((end, s_hi, 2))
            for s0, s1, style in pieces:
                mid = (s0 + s1) / 2
                q = np.array([cx, cy]) + d * mid
                p.box(
                    (q[0], q[1], -0.25),
                    ((s1 - s0) / 2, hr, 0.25),
                    S.ROAD,
                    M.ASPHALT,
                    asphalt,
                    yaw=yaw,
                    param=(mid, style, lw, 0),
                    name="crosswalk" if style == 2 else "asphalt",
                )
