"""Class colours: a new class gets the candidate colour farthest from every colour already in use.

Distances are CIE 1976 ΔE (Euclidean distance in CIELAB, D65 white), a perceptual-ish space where equal
distances look roughly equally different, unlike RGB where two greens 60 units apart look alike and two
blues 60 units apart do not.
"""

from __future__ import annotations

import colorsys
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

RGB = tuple[int, int, int]

UNLABELED_RGB: RGB = (128, 128, 128)
"""The colour of unlabeled points in the viewer (grey); a class colour must stay far from it."""

_HUES = tuple(range(0, 360, 10))
_SAT_VAL = ((0.85, 0.95), (0.65, 0.80), (0.95, 0.65), (0.45, 0.95))


def _candidates() -> npt.NDArray[np.int64]:
    """(36 · 4, 3) saturated RGB colours: every 10° of hue at four (saturation, value) pairs, none grey."""
    out = []
    for s, v in _SAT_VAL:
        for hue in _HUES:
            r, g, b = colorsys.hsv_to_rgb(hue / 360.0, s, v)
            out.append((round(r * 255), round(g * 255), round(b * 255)))
    return np.asarray(out, dtype=np.int64)


CANDIDATES: npt.NDArray[np.int64] = _candidates()
"""The colours :func:`distinct_color` chooses from, in preference order for ties."""


def srgb_to_lab(rgb: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """(..., 3) sRGB 0..255 → (..., 3) CIELAB (L* 0..100), D65 white.

    Linearise ``c ≤ 0.04045 ? c/12.92 : ((c+0.055)/1.055)^2.4``, XYZ = M·rgb (sRGB matrix), then
    ``f(t) = t^(1/3)`` above (6/29)³ else ``t/(3(6/29)²) + 4/29``; L = 116 f(Y) − 16,
    a = 500 (f(X/Xn) − f(Y)), b = 200 (f(Y) − f(Z/Zn)).
    """
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array(
        [
            [0.4124564, 0.3575761, 0.1804375],
            [0.2126729, 0.7151522, 0.0721750],
            [0.0193339, 0.1191920, 0.9503041],
        ]
    )
    xyz = lin @ m.T / np.array([0.95047, 1.0, 1.08883])
    d = 6.0 / 29.0
    f = np.where(xyz > d**3, np.cbrt(xyz), xyz / (3 * d * d) + 4.0 / 29.0)
    return np.stack(
        [116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], axis=-1
    )


def distinct_color(used: Sequence[Sequence[int]], avoid: Sequence[Sequence[int]] = (UNLABELED_RGB,)) -> RGB:
    """The candidate colour (:data:`CANDIDATES`) maximising the minimum ΔE to ``used`` and ``avoid``.

    Args:
        used: RGB 0..255 colours of the existing classes (any number, duplicates allowed).
        avoid: further colours to stay away from; by default the viewer's unlabeled grey.

    Returns:
        ``argmax_c min_{u in used + avoid} ‖lab(c) − lab(u)‖`` (the first such candidate on ties), so the
        result is never a colour already used and never grey.
    """
    taken = [tuple(int(v) for v in u) for u in (*used, *avoid)]
    if not taken:
        return (int(CANDIDATES[0, 0]), int(CANDIDATES[0, 1]), int(CANDIDATES[0, 2]))
    cand = srgb_to_lab(CANDIDATES)
    ref = srgb_to_lab(np.asarray(taken, dtype=np.float64))
    dist = np.linalg.norm(cand[:, None, :] - ref[None, :, :], axis=-1).min(axis=1)
    best = CANDIDATES[int(np.argmax(dist))]
    return (int(best[0]), int(best[1]), int(best[2]))


__all__ = ["CANDIDATES", "RGB", "UNLABELED_RGB", "distinct_color", "srgb_to_lab"]
