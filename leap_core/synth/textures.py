"""Procedural texture helpers shared by the camera renderer and the LiDAR reflectivity model.

Textures are looked up from small tileable noise tiles with a pre-filtered mip chain: the level is
chosen from the pixel footprint (metres covered by one pixel at the hit), so far surfaces show the
average colour instead of aliasing. Regular patterns (lane markings, windows, bricks) are anti-aliased
the same way by fading to their mean coverage when a period shrinks below a few pixels.
"""

from __future__ import annotations

import functools

import numpy as np
import numpy.typing as npt

TILE = 256
"""Side of every noise tile in texels (power of two: coordinates wrap with a bit mask)."""
LEVELS = 7
"""Mip levels per tile (level l is blurred by ~2^l texels)."""

F32 = npt.NDArray[np.float32]


def _tile(beta: float, seed: int) -> npt.NDArray[np.float32]:
    """(LEVELS, TILE, TILE) tileable noise with power spectrum ∝ f^(−beta), zero mean, unit std per level 0,
    each level l low-passed by a Gaussian of σ = 0.6·2^l texels (σ = 0 at level 0)."""
    rng = np.random.default_rng(seed)
    spec = np.fft.fft2(rng.standard_normal((TILE, TILE)))
    f = np.fft.fftfreq(TILE)
    fr = np.hypot(f[:, None], f[None, :])
    fr[0, 0] = 1.0
    spec = spec * fr ** (-beta / 2)
    spec[0, 0] = 0.0
    base = np.fft.ifft2(spec).real
    base /= base.std()
    out = np.empty((LEVELS, TILE, TILE), np.float32)
    for lvl in range(LEVELS):
        sigma = 0.0 if lvl == 0 else 0.6 * 2.0**lvl
        lp = np.exp(-2 * (np.pi * sigma * fr) ** 2)
        lp[0, 0] = 1.0
        out[lvl] = np.fft.ifft2(np.fft.fft2(base) * lp).real
    return out


@functools.cache
def noise_bank() -> dict[str, npt.NDArray[np.float32]]:
    """The fixed noise tiles: ``smooth`` (β = 2.2, cloudy blotches) and ``grain`` (β = 0.7, fine grit)."""
    return {"smooth": _tile(2.2, 11), "grain": _tile(0.7, 12), "leaf": _tile(1.3, 13)}


def noise(
    name: str,
    u: F32,
    v: F32,
    texel: float,
    footprint: F32 | float,
) -> F32:
    """Sample tile ``name`` at surface coordinates (u, v) in metres, ``texel`` metres per texel.

    The mip level is round(log2(footprint / texel)), clipped to the chain. Returns values with roughly
    zero mean and unit standard deviation (less at coarse levels, as filtering removes detail).
    """
    tiles = noise_bank()[name]
    iu = np.floor(u * np.float32(1.0 / texel)).astype(np.int64) & (TILE - 1)
    iv = np.floor(v * np.float32(1.0 / texel)).astype(np.int64) & (TILE - 1)
    fp = np.maximum(np.asarray(footprint, np.float32) * np.float32(1.0 / texel), np.float32(1e-6))
    lvl = np.clip(np.rint(np.log2(fp)), 0, LEVELS - 1).astype(np.int64)
    if lvl.ndim == 0:
        lvl = np.broadcast_to(lvl, iu.shape)
    return np.asarray(tiles[lvl, iv, iu], dtype=np.float32)


def box_pattern(x: F32, period: float, duty: float, footprint: F32) -> F32:
    """Coverage of a periodic on/off pattern: 1 where frac(x / period) < duty, anti-aliased.

    When the footprint nears the period the value fades to the mean coverage ``duty``:
    w = clip(2·footprint / period − 0.5, 0, 1), value = (1 − w)·hard + w·duty.
    """
    hard = ((x * np.float32(1.0 / period)) % np.float32(1.0) < duty).astype(np.float32)
    w = np.clip(footprint * np.float32(2.0 / period) - np.float32(0.5), 0.0, 1.0)
    return np.asarray(hard * (1 - w) + np.float32(duty) * w, dtype=np.float32)


def band(x: F32, lo: float, hi: float, footprint: F32) -> F32:
    """Coverage of the band lo <= x < hi, fading to its share of one footprint when thinner than that."""
    hard = ((x >= lo) & (x < hi)).astype(np.float32)
    width = hi - lo
    w = np.clip(footprint / np.float32(width) - np.float32(0.5), 0.0, 1.0)
    near = (np.abs(x - np.float32((lo + hi) / 2)) < footprint).astype(np.float32)
    thin = w * near * np.minimum(np.float32(width) / np.maximum(footprint, 1e-6), 1.0)
    return np.asarray(hard * (1 - w) + thin, dtype=np.float32)


def road_paint(local: F32, param: F32, footprint: F32) -> F32:
    """White paint coverage in [0, 1] on the top face of a road tile.

    Args:
        local: (n, 3) hit points in the tile frame (x along the street, y across, y = 0 on the centre line).
        param: (n, 4) ``(s0, style, lane_width, -)``: street coordinate of x = 0, marking style
            (1 = dashed centre line, 3 m dash / 6 m gap, plus solid edge lines; 2 = zebra crossing with
            0.5 m stripes every 1 m across the street).
        footprint: (n,) metres per pixel at the hit.
    """
    s = local[:, 0] + param[:, 0]
    y = local[:, 1]
    style = param[:, 1]
    lane = param[:, 2]
    out = np.zeros(len(s), np.float32)
    st1 = style == 1
    if st1.any():
        fp = footprint[st1]
        centre = band(y[st1], -0.075, 0.075, fp) * box_pattern(s[st1], 9.0, 1 / 3, fp)
        edge = band(np.abs(y[st1]) - lane[st1], -0.18, -0.06, fp)
        out[st1] = np.maximum(centre, edge)
    st2 = style == 2
    if st2.any():
        fp = footprint[st2]
        inside = (np.abs(y[st2]) < lane[st2] - 0.3).astype(np.float32)
        out[st2] = box_pattern(y[st2] + 0.25, 1.0, 0.5, fp) * inside
    return out


def facade_uv(local: F32, half: F32, face: npt.NDArray[np.int8]) -> tuple[F32, F32]:
    """Facade coordinates of hits on a box's side faces: horizontal u (metres from the face's left edge)
    and height h above the box bottom. Faces ±x run along local y, faces ±y along local x."""
    along_y = face <= 1
    u = np.where(along_y, local[:, 1] + half[:, 1], local[:, 0] + half[:, 0])
    h = local[:, 2] + half[:, 2]
    return u.astype(np.float32), h.astype(np.float32)


def window_mask(
    u: F32,
    h: F32,
    width: F32,
    floor_h: F32,
    spacing: F32,
    footprint: F32,
) -> tuple[F32, F32]:
    """Window coverage on a facade and a frame coverage around it.

    Windows sit on every floor above the ground floor, one per ``spacing`` metres, 1.3 m wide (≤ 55 % of
    the spacing), from 0.9 m to 2.3 m above each floor (scaled with the floor height), at least 0.7 m from
    the facade's ends. Ground floors get shop windows (0.6..2.6 m high, 70 % of the spacing).
    """
    fz = h / floor_h
    floor_i = np.floor(fz)
    frac_z = fz - floor_i
    n_win = np.maximum(np.floor((width - 1.4) / spacing), 1.0)
    margin = (width - n_win * spacing) / 2
    uu = u - margin
    inside_u = (uu >= 0) & (uu < n_win * spacing)
    ww = np.minimum(np.float32(1.3), spacing * np.float32(0.55))
    shop = floor_i == 0
    duty = np.where(shop, np.float32(0.7), ww / spacing)
    fu = (uu / spacing) % np.float32(1.0)
    cu = np.abs(fu - 0.5)
    lo_z = np.where(shop, np.float32(0.6) / floor_h, np.float32(0.3))
    hi_z = np.where(shop, np.float32(0.87), np.float32(0.77))
    win_u = cu < duty / 2
    win_z = (frac_z > lo_z) & (frac_z < hi_z)
    hard = (win_u & win_z & inside_u).astype(np.float32)
    frame_u = cu < duty / 2 + 0.08 / spacing
    frame_z = (frac_z > lo_z - 0.05) & (frac_z < hi_z + 0.05)
    frame = (frame_u & frame_z & inside_u).astype(np.float32) - hard
    # Anti-aliasing: fade to the mean window coverage once a window is only a few pixels wide.
    w = np.clip(footprint / np.float32(0.35) - np.float32(0.5), 0.0, 1.0)
    mean_cov = duty * (hi_z - lo_z) * inside_u
    return hard * (1 - w) + w * mean_cov, frame * (1 - w)
