"""The street grid and the ego vehicle's route through it (straight legs joined by turning arcs).

Streets form a Manhattan grid: streets along x at y = j·block_y, streets along y at x = i·block_x. Traffic
keeps right, so a vehicle heading ``h`` drives on the lane centre ``centreline + right(h)·lane_width / 2``
with ``right(h) = (h_y, −h_x)``. The ego starts on street y = 0 heading +x and reaches the intersection at
the origin after ``first_turn_distance`` metres, where it always turns; later intersections are crossed
or turned at random. A turn is the circular fillet tangent to the incoming and outgoing lane lines.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from leap_core.synth.raycast import rotation_xyz


@dataclass(frozen=True)
class EgoConfig:
    """How the ego vehicle drives."""

    cruise_speed: float = 8.0
    """Speed on straight road (m/s); 0.8 m per frame at 10 Hz."""
    turn_speed: float = 4.5
    """Speed through turns (m/s)."""
    accel: float = 1.6
    """Braking / acceleration before and after turns, and from ``start_speed`` (m/s²)."""
    start_speed: float | None = None
    """Speed at the first frame (m/s); None = the speed envelope's (cruise on a straight start). A lower
    speed (0 = from rest) rises at ``accel`` until it meets the envelope."""
    first_turn_distance: tuple[float, float] = (20.0, 28.0)
    """Range of the distance from the start to the first intersection's centre (m), drawn per seed."""
    left_turn_radius: float = 7.5
    """Radius of a left-turn arc between lane centres (m)."""
    right_turn_radius: float = 4.5
    """Radius of a right-turn arc between lane centres (m)."""
    sway: float = 0.12
    """Amplitude of the slow lateral weave within the lane (m)."""
    pitch_deg: float = 0.25
    """Amplitude of the body pitch oscillation (degrees)."""
    roll_per_accel_deg: float = 0.18
    """Body roll per m/s² of lateral acceleration in turns (degrees)."""

    def __post_init__(self) -> None:
        if self.start_speed is not None and not (0.0 <= self.start_speed < float("inf")):
            raise ValueError(
                f"EgoConfig.start_speed must be a speed >= 0 (m/s) or None, got {self.start_speed}"
            )


@dataclass(frozen=True)
class StreetGrid:
    """Street geometry shared by the route and the scene.

    Attributes:
        block_x: distance between streets along y (metres along x).
        block_y: distance between streets along x (metres along y).
        lane_width: width of one driving lane (one per direction).
        parking_width: width of the parking lane on each side, between the driving lane and the curb.
    """

    block_x: float
    block_y: float
    lane_width: float
    parking_width: float

    @property
    def half_road(self) -> float:
        """Distance from a street's centre line to its curbs."""
        return self.lane_width + self.parking_width


def right_of(h: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Right-hand normal (h_y, −h_x) of a 2D heading."""
    return np.array([h[1], -h[0]])


@dataclass(frozen=True)
class Leg:
    """A straight stretch of the route along one street.

    Attributes:
        s0, s1: route arc length where the leg starts and ends.
        start: (2,) lane-centre point at s0; heading: (2,) unit direction.
    """

    s0: float
    s1: float
    start: npt.NDArray[np.float64]
    heading: npt.NDArray[np.float64]


@dataclass(frozen=True)
class Route:
    """Densely sampled route with its per-frame arc lengths.

    Attributes:
        xy: (M, 2) lane-centre points every ``step`` metres; heading_angle: (M,) unwrapped yaw (rad);
        s: (M,) arc length; legs: the straight parts; turns: (K, 2) arc-length intervals of turning arcs;
        turn_sign: (K,) +1 left, −1 right; frame_s: (F,) ego arc length per frame; speed: (F,) m/s.
    """

    xy: npt.NDArray[np.float64]
    heading_angle: npt.NDArray[np.float64]
    s: npt.NDArray[np.float64]
    legs: tuple[Leg, ...]
    turns: npt.NDArray[np.float64]
    turn_sign: npt.NDArray[np.float64]
    frame_s: npt.NDArray[np.float64]
    speed: npt.NDArray[np.float64]
    poses: npt.NDArray[np.float64] = field(repr=False)
    """(F, 4, 4) vehicle → world; the vehicle frame has x forward, z up, origin on the road."""

    def at(
        self, s: float | npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Lane-centre position (…, 2) and yaw (…,) at arc length ``s`` (clamped to the route)."""
        s = np.clip(s, 0.0, self.s[-1])
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        return np.stack([x, y], axis=-1), np.interp(s, self.s, self.heading_angle)


def _rot90(h: npt.NDArray[np.float64], sign: int) -> npt.NDArray[np.float64]:
    """Heading turned left (sign = +1) or right (−1) by 90°."""
    return np.array([-h[1], h[0]]) if sign > 0 else np.array([h[1], -h[0]])


@dataclass(frozen=True)
class _Line:
    """A straight piece of the route from ``p0`` to ``p1``."""

    p0: npt.NDArray[np.float64]
    p1: npt.NDArray[np.float64]


@dataclass(frozen=True)
class _Arc:
    """A turning arc around ``centre``: points ``centre + radius·(cos a, sin a)`` for a from ``a0`` over
    ``sweep`` radians (positive = left turn)."""

    centre: npt.NDArray[np.float64]
    radius: float
    a0: float
    sweep: float


def plan_route(
    cfg: EgoConfig,
    grid: StreetGrid,
    frames: int,
    hz: float,
    rng: np.random.Generator,
    *,
    extra_length: float = 80.0,
    step: float = 0.05,
) -> Route:
    """Plan a route long enough for ``frames`` frames plus ``extra_length`` metres (room for a lead car).

    Turning at an intersection is a fillet of radius R between the lane lines: with corner C (where the
    lane lines cross), incoming heading a and outgoing heading b, the arc runs from C − R·a to C + R·b
    around C − R·a + R·b.
    """
    need = frames * cfg.cruise_speed / hz + extra_length
    pieces = _route_pieces(cfg, grid, rng, need)

    xs, hs, legs, turns, signs = [], [], [], [], []
    s_acc = 0.0
    for piece in pieces:
        if isinstance(piece, _Line):
            p0, p1 = piece.p0, piece.p1
            seg = float(np.linalg.norm(p1 - p0))
            n = max(int(np.ceil(seg / step)), 1)
            u = np.arange(n) / n
            h = (p1 - p0) / max(seg, 1e-9)
            xs.append(p0[None] + u[:, None] * (p1 - p0)[None])
            hs.append(np.full(n, np.arctan2(h[1], h[0])))
            legs.append(Leg(s0=s_acc, s1=s_acc + seg, start=np.asarray(p0, float), heading=h))
            s_acc += seg
        else:
            centre, radius, a0, sweep = piece.centre, piece.radius, piece.a0, piece.sweep
            seg = abs(sweep) * radius
            n = max(int(np.ceil(seg / step)), 1)
            ang = a0 + sweep * np.arange(n) / n
            xs.append(centre[None] + radius * np.stack([np.cos(ang), np.sin(ang)], axis=1))
            hs.append(ang + np.sign(sweep) * np.pi / 2)
            turns.append((s_acc, s_acc + seg))
            signs.append(np.sign(sweep))
            s_acc += seg
    xy = np.concatenate(xs)
    heading_angle = np.unwrap(np.concatenate(hs))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    turns_arr = np.array(turns, dtype=np.float64).reshape(-1, 2)

    frame_s = _drive(turns_arr, cfg, 0.0, frames, hz, cfg.cruise_speed, start_speed=cfg.start_speed)
    speed = np.array([_speed_limit(turns_arr, cfg, cfg.cruise_speed, sv) for sv in frame_s])
    if cfg.start_speed is not None:
        speed = np.minimum(speed, cfg.start_speed + cfg.accel * np.arange(frames) / hz)
    roll = _turn_roll(cfg, frame_s, speed, turns_arr, np.array(signs))
    poses = _ego_poses(cfg, s, xy, heading_angle, frame_s, roll=roll, rng=rng)
    return Route(
        xy=xy,
        heading_angle=heading_angle,
        s=s,
        legs=tuple(legs),
        turns=turns_arr,
        turn_sign=np.array(signs),
        frame_s=frame_s,
        speed=speed,
        poses=poses,
    )


def _route_pieces(
    cfg: EgoConfig, grid: StreetGrid, rng: np.random.Generator, need: float
) -> list[_Line | _Arc]:
    """The route as straight pieces and turning arcs, at least ``need`` metres long: the first
    intersection is always turned at, later ones are crossed (1/2) or turned left or right (1/4 each)."""
    lw = grid.lane_width
    d0 = float(rng.uniform(*cfg.first_turn_distance))
    heading = np.array([1.0, 0.0])
    inter = np.array([0.0, 0.0])
    start = np.array([-d0, 0.0]) + right_of(heading) * lw / 2
    pieces: list[_Line | _Arc] = []
    cur = start
    length = 0.0
    first = True
    sign_first = 1 if rng.random() < 0.5 else -1
    while length < need:
        if first:
            action = sign_first
            first = False
        else:
            r = rng.random()
            action = 0 if r < 0.5 else (1 if r < 0.75 else -1)
        if action == 0:
            nxt = inter + heading * (grid.block_x if abs(heading[0]) > 0.5 else grid.block_y)
            length += float(np.linalg.norm(nxt - inter))
            inter = nxt
            continue
        out = _rot90(heading, action)
        corner = inter + right_of(heading) * lw / 2 + right_of(out) * lw / 2
        radius = cfg.left_turn_radius if action > 0 else cfg.right_turn_radius
        t1 = corner - radius * heading
        t2 = corner + radius * out
        centre = t1 + radius * out
        pieces.append(_Line(cur, t1))
        a0 = np.arctan2(*(t1 - centre)[::-1])
        pieces.append(_Arc(centre, radius, a0, action * np.pi / 2))
        length += float(np.linalg.norm(t1 - cur)) + radius * np.pi / 2
        cur = t2
        heading = out
        inter = inter + heading * (grid.block_x if abs(heading[0]) > 0.5 else grid.block_y)
    pieces.append(_Line(cur, cur + heading * max(need - length, 0.0) + heading * 40.0))
    return pieces


def _turn_roll(
    cfg: EgoConfig,
    frame_s: npt.NDArray[np.float64],
    speed: npt.NDArray[np.float64],
    turns: npt.NDArray[np.float64],
    signs: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """(F,) body roll per frame (rad): the lateral acceleration v²/R of a turn rolls the body outward
    (towards the outside of the turn), zero on straight road."""
    roll = np.zeros_like(frame_s)
    for (a, b), sg in zip(turns, signs, strict=True):
        inside = (frame_s >= a) & (frame_s <= b)
        radius = (b - a) / (np.pi / 2)
        roll[inside] = sg * np.deg2rad(cfg.roll_per_accel_deg) * speed[inside] ** 2 / radius
    return roll


def _ego_poses(
    cfg: EgoConfig,
    s: npt.NDArray[np.float64],
    xy: npt.NDArray[np.float64],
    yaw: npt.NDArray[np.float64],
    frame_s: npt.NDArray[np.float64],
    *,
    roll: npt.NDArray[np.float64],
    rng: np.random.Generator,
) -> npt.NDArray[np.float64]:
    """Vehicle → world poses: lane centre + slow lateral weave, small pitch oscillation, ``roll`` (rad)."""
    phase = rng.uniform(0, 2 * np.pi, 3)
    px = np.interp(frame_s, s, xy[:, 0])
    py = np.interp(frame_s, s, xy[:, 1])
    ya = np.interp(frame_s, s, yaw)
    lateral = cfg.sway * np.sin(2 * np.pi * frame_s / 47.0 + phase[0])
    px = px + lateral * np.sin(ya)
    py = py - lateral * np.cos(ya)
    pitch = np.deg2rad(cfg.pitch_deg) * np.sin(2 * np.pi * frame_s / 9.0 + phase[1])
    poses = np.tile(np.eye(4), (len(frame_s), 1, 1))
    for i in range(len(frame_s)):
        poses[i, :3, :3] = rotation_xyz(roll[i], pitch[i], ya[i])
        poses[i, :3, 3] = [px[i], py[i], 0.0]
    return poses


def _speed_limit(turns: npt.NDArray[np.float64], cfg: EgoConfig, cruise: float, s: float) -> float:
    """Speed envelope at arc length s: min(cruise, √(v_turn² + 2·accel·d)), d = distance to the nearest
    turn interval (0 inside one), so a vehicle brakes before a turn and accelerates after it."""
    v = cruise
    for a, b in turns:
        dist = 0.0 if a <= s <= b else min(abs(s - a), abs(s - b))
        v = min(v, float(np.sqrt(cfg.turn_speed**2 + 2 * cfg.accel * dist)))
    return v


def _drive(
    turns: npt.NDArray[np.float64],
    cfg: EgoConfig,
    s_start: float,
    frames: int,
    hz: float,
    cruise: float,
    *,
    start_speed: float | None = None,
) -> npt.NDArray[np.float64]:
    """Arc length per frame when driving at the speed envelope from ``s_start`` (20 Euler steps per frame);
    with ``start_speed`` the speed is also at most ``start_speed + accel·t`` (t = time since the start)."""
    out = np.zeros(frames)
    sv, sub = s_start, 20
    for i in range(frames):
        out[i] = sv
        for k in range(sub):
            v = _speed_limit(turns, cfg, cruise, sv)
            if start_speed is not None:
                # At the sub-step's midpoint: exact for a constant acceleration from rest.
                v = min(v, start_speed + cfg.accel * (i * sub + k + 0.5) / hz / sub)
            sv += v / hz / sub
    return out


def drive_along(
    route: Route, cfg: EgoConfig, s_start: float, frames: int, hz: float, cruise_scale: float = 1.0
) -> npt.NDArray[np.float64]:
    """Arc length per frame of another vehicle that follows the route from ``s_start``, with the same
    speed envelope as the ego (slowing for turns) but a cruise speed scaled by ``cruise_scale``."""
    return _drive(route.turns, cfg, s_start, frames, hz, cfg.cruise_speed * cruise_scale)
