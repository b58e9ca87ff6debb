"""A survey drone's flight: a lawnmower pattern of parallel lines at a fixed altitude band.

The drone flies line 0 along +x from the origin, turns left on a half circle of radius ``spacing / 2`` onto
line 1 (along −x at y = spacing), turns right onto line 2 (along +x at y = 2·spacing), and so on: the usual
photogrammetry / LiDAR survey pattern. Its body frame has x forward (the flight direction), y left and z up;
the survey altitude is drawn per seed and varies slowly (a real autopilot holds it to a metre or two), and
the body rolls and pitches a little (gusts, turns). The sensor rig (camera and LiDAR) is fixed to the body
and tilted down by the rig's mount pitch (``leap_core.synth.agri``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from leap_core.errors import ConfigError
from leap_core.synth.raycast import rotation_xyz

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SurveyConfig:
    """How the survey drone flies."""

    speed: float = 6.0
    """Ground speed along the lines and through the turns (m/s)."""
    altitude: tuple[float, float] = (15.0, 30.0)
    """Range of the survey altitude above the ground (m), drawn per seed; must lie within 10-40 m."""
    altitude_wave: float = 1.5
    """Amplitude of the slow altitude variation around the drawn altitude (m)."""
    line_length: float = 160.0
    """Length of one survey line (m)."""
    line_spacing: float = 40.0
    """Distance between neighbouring lines (m); the turns are half circles of half this radius."""
    wobble_deg: float = 1.2
    """Amplitude of the body's roll and pitch wobble (degrees)."""

    def __post_init__(self) -> None:
        lo, hi = self.altitude
        if not 10.0 <= lo <= hi <= 40.0:
            raise ConfigError(
                f"must satisfy 10 <= low <= high <= 40 m, got {self.altitude}", field=("altitude",)
            )
        if lo - self.altitude_wave < 10.0 or hi + self.altitude_wave > 40.0:
            raise ConfigError(
                f"altitude {self.altitude} ± {self.altitude_wave} leaves 10-40 m", field=("altitude_wave",)
            )
        if self.speed <= 0:
            raise ConfigError(f"must be > 0, got {self.speed}", field=("speed",))
        if self.line_length <= 0 or self.line_spacing <= 0:
            raise ConfigError("line_length and line_spacing must be > 0", field=("line_spacing",))


def lawnmower_path(line_length: float, spacing: float, lines: int, step: float = 0.1) -> tuple[F64, F64, F64]:
    """Densely sampled lawnmower path.

    Line k runs at y = k·spacing, along +x (k even, from x = 0 to ``line_length``) or −x (k odd); line k
    and k + 1 are joined by a half circle of radius r = spacing / 2 around ``(x_end, (k + ½)·spacing)``,
    to the left after an even line, to the right after an odd one.

    Args:
        line_length: L, metres per line.
        spacing: S, metres between lines.
        lines: number of lines (≥ 1).
        step: sampling distance (m).

    Returns:
        xy (M, 2) positions, yaw (M,) heading angles (rad, unwrapped), s (M,) arc length from the start.
    """
    r = spacing / 2
    xs: list[F64] = []
    yaws: list[F64] = []
    for k in range(lines):
        fwd = k % 2 == 0
        n = max(int(np.ceil(line_length / step)), 1)
        u = np.arange(n) / n
        x = u * line_length if fwd else line_length * (1 - u)
        xs.append(np.stack([x, np.full(n, k * spacing)], axis=1))
        yaws.append(np.full(n, 0.0 if fwd else np.pi))
        if k == lines - 1:
            end = np.array([[line_length if fwd else 0.0, k * spacing]])
            xs.append(end)
            yaws.append(np.array([0.0 if fwd else np.pi]))
            break
        m = max(int(np.ceil(np.pi * r / step)), 1)
        a = np.arange(m) / m * np.pi
        cx, cy = (line_length if fwd else 0.0), (k + 0.5) * spacing
        # Left turn (even k): angle −π/2 → +π/2 counter-clockwise; right turn (odd k): −π/2 → −3π/2.
        ang = -np.pi / 2 + a if fwd else -np.pi / 2 - a
        xs.append(np.stack([cx + r * np.cos(ang), cy + r * np.sin(ang)], axis=1))
        yaws.append(ang + (np.pi / 2 if fwd else -np.pi / 2))
    xy = np.concatenate(xs)
    yaw = np.unwrap(np.concatenate(yaws))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    return xy, yaw, s


def survey_poses(cfg: SurveyConfig, frames: int, hz: float, rng: np.random.Generator) -> tuple[F64, F64]:
    """Body → world pose per frame of a drone flying the lawnmower path at ``cfg.speed``.

    The altitude is ``h₀ + altitude_wave·sin(2π·s / 90 m + φ)`` with h₀ ~ U(altitude) drawn from ``rng``;
    roll and pitch are ``wobble·sin(2π·s / λ + φ)`` with wavelengths 23 m and 31 m.

    Returns:
        poses (F, 4, 4) body → world; altitude (F,) metres above the ground (z = 0).
    """
    s_frames = np.arange(frames) * cfg.speed / hz
    per_line = cfg.line_length + np.pi * cfg.line_spacing / 2
    lines = int(np.ceil((s_frames[-1] + 1.0) / per_line)) + 1
    xy, yaw, s = lawnmower_path(cfg.line_length, cfg.line_spacing, lines)
    h0 = float(rng.uniform(*cfg.altitude))
    phase = rng.uniform(0, 2 * np.pi, 3)
    alt = h0 + cfg.altitude_wave * np.sin(2 * np.pi * s_frames / 90.0 + phase[0])
    w = np.deg2rad(cfg.wobble_deg)
    roll = w * np.sin(2 * np.pi * s_frames / 23.0 + phase[1])
    pitch = w * np.sin(2 * np.pi * s_frames / 31.0 + phase[2])
    px = np.interp(s_frames, s, xy[:, 0])
    py = np.interp(s_frames, s, xy[:, 1])
    ya = np.interp(s_frames, s, yaw)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for i in range(frames):
        poses[i, :3, :3] = rotation_xyz(roll[i], pitch[i], ya[i])
        poses[i, :3, 3] = [px[i], py[i], alt[i]]
    return poses, alt
