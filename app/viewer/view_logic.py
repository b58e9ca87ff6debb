"""Pure view maths of the 3D review viewer: colours, visibility, corrections, focus dimming, undo/redo.

Everything here takes and returns numpy arrays (or small frozen records) and does no I/O, so the scene
facade (:mod:`app.viewer.scene`) only moves the results into viser handles. Shapes use V voxels, N points
and C classes; class index arrays are int16 with ``UNLABELED = -1``. The review queue's region maths lives
beside it in :mod:`app.viewer.region_logic`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, Literal, TypeVar

import numpy as np
import numpy.typing as npt

from leap_core.fusion import last_per_key
from leap_core.selection import project_to_screen, quat_to_matrix
from leap_core.types import UNLABELED

ColorMode = Literal["class", "confidence", "class_probability", "disagreement", "delta", "objects"]
"""How voxels are coloured: argmax class colour, max posterior on a colour scale, one class's posterior,
the camera-vs-final disagreement rate on the same scale (the share of a voxel's camera-labelled points
whose final label differs from the camera's), the change since the run before (``delta``: voxels whose
class changed in their class colour, the others pale), or ``objects``: the voxel map pale, the shown
scan's points in the colour of their object (:func:`app.viewer.nav_logic.object_colors`)."""

COLUMN_MODES: tuple[ColorMode, ...] = ("class_probability", "disagreement", "delta")
"""Modes coloured by a per-voxel column other than the confidence (passed as ``class_prob``)."""

UNLABELED_RGB: tuple[int, int, int] = (128, 128, 128)
"""Colour of unlabeled points (grey)."""

UNCHANGED_RGB: tuple[int, int, int] = (215, 215, 215)
"""Colour of a voxel whose class did not change since the run before, in the ``delta`` mode."""

SCALE_ANCHORS: tuple[tuple[int, int, int], ...] = (
    (68, 1, 84),
    (59, 82, 139),
    (33, 145, 140),
    (94, 201, 98),
    (253, 231, 37),
)
"""Evenly spaced anchor colours of the confidence scale (low → high): the viridis key colours, a
perceptually ordered scale that stays readable for colour-blind viewers."""


# ------------------------------------------------------------------------------------- colour scales
def make_lut(anchors: Sequence[Sequence[int]] = SCALE_ANCHORS, size: int = 256) -> npt.NDArray[np.uint8]:
    """Colour lookup table by piecewise-linear interpolation between evenly spaced anchors.

    Entry j (t = j / (size-1)) lies between anchors a_k, a_{k+1} with s = t·(K-1) - k:
    ``lut[j] = round((1-s)·a_k + s·a_{k+1})``.

    Args:
        anchors: (K, 3) RGB 0..255, K ≥ 2, low to high.
        size: number of entries (≥ 2).

    Returns:
        (size, 3) uint8.
    """
    a = np.asarray(anchors, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 2:
        raise ValueError(f"anchors must be (K >= 2, 3) RGB, got shape {a.shape}")
    if size < 2:
        raise ValueError(f"size must be >= 2, got {size}")
    t = np.linspace(0.0, 1.0, size) * (a.shape[0] - 1)
    k = np.minimum(np.floor(t).astype(np.int64), a.shape[0] - 2)
    s = (t - k)[:, None]
    lut: npt.NDArray[np.uint8] = np.rint((1.0 - s) * a[k] + s * a[k + 1]).astype(np.uint8)
    return lut


CONFIDENCE_LUT: npt.NDArray[np.uint8] = make_lut()
"""(256, 3) uint8 default confidence scale."""


def scalar_colors(
    values: npt.ArrayLike, lut: npt.NDArray[np.uint8] = CONFIDENCE_LUT, vmin: float = 0.0, vmax: float = 1.0
) -> npt.NDArray[np.uint8]:
    """Map scalars to colours: ``lut[round(clip((v - vmin) / (vmax - vmin), 0, 1) · (L-1))]``.

    Args:
        values: (N,) floats; NaN maps to the lowest colour.
        lut: (L, 3) uint8 table.
        vmin, vmax: the values mapped to the first and last entries (vmax > vmin).

    Returns:
        (N, 3) uint8.
    """
    if not vmax > vmin:
        raise ValueError(f"vmax must be > vmin, got vmin={vmin}, vmax={vmax}")
    v = np.asarray(values, dtype=np.float32)
    scale = np.float32((lut.shape[0] - 1) / (vmax - vmin))
    idx = (v - np.float32(vmin)) * scale + np.float32(0.5)
    np.clip(idx, 0, lut.shape[0] - 1, out=idx)
    idx = np.nan_to_num(idx, nan=0.0)
    colors: npt.NDArray[np.uint8] = lut[idx.astype(np.intp)]
    return colors


def class_colors(
    labels: npt.ArrayLike,
    palette: npt.ArrayLike,
    unlabeled: tuple[int, int, int] = UNLABELED_RGB,
) -> npt.NDArray[np.uint8]:
    """Colour of each class index: ``palette[label]``, ``unlabeled`` where label = -1.

    Args:
        labels: (N,) int class indices in [-1, C).
        palette: (C, 3) RGB 0..255.

    Returns:
        (N, 3) uint8.
    """
    lab = np.asarray(labels)
    pal = np.asarray(palette, dtype=np.uint8).reshape(-1, 3)
    if lab.size and (lab.max() >= pal.shape[0] or lab.min() < UNLABELED):
        raise ValueError(f"labels must lie in [-1, {pal.shape[0]}), got [{lab.min()}, {lab.max()}]")
    # Row C of the extended table is the unlabeled colour, so -1 indexes it directly (Python wraps -1).
    table = np.concatenate([pal, np.asarray(unlabeled, np.uint8).reshape(1, 3)])
    return table[lab.astype(np.intp)]


def blend(base: npt.NDArray[np.uint8], over: npt.ArrayLike, alpha: float) -> npt.NDArray[np.uint8]:
    """``round((1-α)·base + α·over)`` per channel, uint8 (used for highlight tints)."""
    out = (1.0 - alpha) * base.astype(np.float32) + alpha * np.asarray(over, np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------ the view
@dataclass(frozen=True)
class ViewState:
    """What the user asked to see; every view is a pure function of this and the grid."""

    mode: ColorMode = "class"
    """Colouring: ``class`` (argmax colours), ``confidence`` (max posterior) or ``class_probability``."""
    class_index: int = 0
    """Class whose posterior colours the voxels in ``class_probability`` mode."""
    threshold: float = 0.0
    """Voxels whose confidence is below this are hidden (in ``class_probability`` mode: whose
    probability of ``class_index`` is below it)."""
    enabled: tuple[bool, ...] = ()
    """Per-class visibility toggles by argmax class; empty means every class is shown."""
    max_points: int | None = None
    """Show at most this many voxels (decimation on request); None shows all."""


def visible_mask(
    label: npt.NDArray[np.int16],
    score: npt.NDArray[np.floating],
    threshold: float,
    enabled: Sequence[bool] = (),
) -> npt.NDArray[np.bool_]:
    """Voxels to draw: ``score ≥ threshold`` and the toggle of their class is on.

    Args:
        label: (V,) int16 argmax class per voxel (-1 = unlabeled, always drawn if above threshold).
        score: (V,) the value compared with the threshold.
        threshold: minimum score; ≤ 0 keeps every score.
        enabled: (C,) per-class toggles; empty keeps every class.

    Returns:
        (V,) bool.
    """
    mask = score >= np.float32(threshold) if threshold > 0 else np.ones(score.shape[0], bool)
    if len(enabled) and not all(enabled):
        table = np.append(np.asarray(enabled, bool), True)  # index -1 → "unlabeled", kept
        mask &= table[label.astype(np.intp)]
    return mask


def decimate_indices(indices: npt.NDArray[np.int64], max_points: int | None) -> npt.NDArray[np.int64]:
    """An evenly strided subset of ``indices`` of at most ``max_points`` (all of them if None or fewer).

    Keys are sorted by (x, y, z), so a stride thins space uniformly instead of cutting a region away.
    """
    n = indices.shape[0]
    if max_points is None or n <= max_points:
        return indices
    if max_points <= 0:
        return indices[:0]
    step = n / max_points
    kept: npt.NDArray[np.int64] = indices[(np.arange(max_points) * step).astype(np.int64)]
    return kept


def view_colors(
    state: ViewState,
    label: npt.NDArray[np.int16],
    conf: npt.NDArray[np.float32],
    class_prob: npt.NDArray[np.floating] | None,
    palette: npt.NDArray[np.uint8],
    rows: npt.NDArray[np.int64],
) -> npt.NDArray[np.uint8]:
    """Colours of the voxels ``rows`` for ``state.mode``.

    Args:
        label, conf: (V,) argmax class and its probability.
        class_prob: (V,) probability of ``state.class_index`` (``class_probability`` mode) or
            disagreement rate (``disagreement`` mode).
        palette: (C, 3) class colours.
        rows: (M,) voxel rows to colour.

    Returns:
        (M, 3) uint8.
    """
    if state.mode == "class":
        return class_colors(label[rows], palette)
    if state.mode == "confidence":
        return scalar_colors(conf[rows])
    if state.mode == "objects":
        return np.tile(np.asarray(UNCHANGED_RGB, np.uint8), (rows.shape[0], 1))
    if class_prob is None:
        raise ValueError(f"{state.mode} mode needs its per-voxel column")
    if state.mode == "delta":
        out = class_colors(label[rows], palette)
        out[class_prob[rows] < 0.5] = UNCHANGED_RGB
        return out
    return scalar_colors(class_prob[rows])


def view_score(
    state: ViewState, conf: npt.NDArray[np.float32], class_prob: npt.NDArray[np.floating] | None
) -> npt.NDArray[np.floating]:
    """The per-voxel value the threshold applies to in ``state.mode``: the mode's column in
    :data:`COLUMN_MODES` (``class_prob``: the class's probability, or the disagreement rate), else the
    confidence."""
    if state.mode in COLUMN_MODES:
        if class_prob is None:
            raise ValueError(f"{state.mode} mode needs its per-voxel column")
        return class_prob
    return conf


def render_view(
    state: ViewState,
    label: npt.NDArray[np.int16],
    conf: npt.NDArray[np.float32],
    palette: npt.NDArray[np.uint8],
    class_prob: npt.NDArray[np.floating] | None = None,
    corrected: npt.NDArray[np.bool_] | None = None,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
    """Rows of the voxels to draw and their colours: the whole view as one function of its inputs.

    In ``class_probability`` mode a corrected voxel counts as certain: P(c) = 1 when its assigned class
    is c, else 0.

    Args:
        state: the requested view.
        label, conf: (V,) argmax class and its probability (corrections already applied).
        palette: (C, 3) class colours.
        class_prob: (V,) probability of ``state.class_index`` (``class_probability`` mode only).
        corrected: (V,) bool, voxels overridden by a correction.

    Returns:
        ``(rows (M,) int64, colors (M, 3) uint8)``.
    """
    class_prob = corrected_class_prob(state, label, class_prob, corrected)
    score = view_score(state, conf, class_prob)
    mask = visible_mask(label, score, state.threshold, state.enabled)
    rows = decimate_indices(np.flatnonzero(mask), state.max_points)
    return rows, view_colors(state, label, conf, class_prob, palette, rows)


def corrected_class_prob(
    state: ViewState,
    label: npt.NDArray[np.int16],
    class_prob: npt.NDArray[np.floating] | None,
    corrected: npt.NDArray[np.bool_] | None,
) -> npt.NDArray[np.floating] | None:
    """``class_prob`` with corrected voxels certain (1 where their class is ``state.class_index``, else 0) in
    ``class_probability`` mode; unchanged otherwise (see :func:`render_view`)."""
    if (
        state.mode == "class_probability"
        and class_prob is not None
        and corrected is not None
        and corrected.any()
    ):
        return np.where(corrected, (label == state.class_index).astype(np.float32), class_prob)
    return class_prob


def visible_rows(
    state: ViewState,
    label: npt.NDArray[np.int16],
    score: npt.NDArray[np.floating],
    rows: npt.NDArray[np.int64],
) -> npt.NDArray[np.int64]:
    """The rows among ``rows`` that :func:`render_view` shows (before ``max_points``), in the given order;
    ``score`` is the (V,) per-voxel value of :func:`view_score` (corrections applied)."""
    return rows[visible_mask(label[rows], score[rows], state.threshold, state.enabled)]


def delta_column(
    keys: npt.NDArray[np.int64],
    label: npt.NDArray[np.int16],
    base_keys: npt.NDArray[np.int64],
    base_label: npt.NDArray[np.int16],
    base_to_current: npt.ArrayLike,
) -> npt.NDArray[np.float32]:
    """(V,) 1.0 where a voxel's class differs from the earlier run's class of the same voxel key, else 0.0
    (the ``delta`` colour mode's column).

    ``changed[v] = 1`` when key ``v`` is absent from ``base_keys`` or ``map[base_label[row(v)]] ≠ label[v]``
    with ``map = base_to_current`` (the earlier run's class indices in this run's numbering, by class name;
    -2 for a class this run lacks, so it always differs; unlabeled -1 stays -1).

    Args:
        keys, label: (V,) this run's sorted keys and classes (corrections applied).
        base_keys, base_label: (B,) the earlier run's sorted keys and classes.
        base_to_current: (C_base,) int, index map of the earlier run's classes.
    """
    keys = np.asarray(keys, dtype=np.int64)
    out = np.ones(keys.shape[0], np.float32)
    if base_keys.size == 0 or keys.size == 0:
        return out
    pos = np.minimum(np.searchsorted(base_keys, keys), base_keys.shape[0] - 1)
    hit = base_keys[pos] == keys
    table = np.append(np.asarray(base_to_current, dtype=np.int64), -1)  # index -1 (unlabeled) → -1
    before = table[base_label[pos[hit]].astype(np.intp)]
    out[np.flatnonzero(hit)[before == label[hit]]] = 0.0
    return out


# ------------------------------------------------------------------------------------- corrections
def apply_corrections(
    keys: npt.NDArray[np.int64],
    label: npt.NDArray[np.int16],
    conf: npt.NDArray[np.float32],
    corr_keys: npt.ArrayLike,
    corr_labels: npt.ArrayLike,
) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Overlay manual corrections on the grid's labels: a corrected voxel takes its class with confidence 1.

    Corrections are applied in order, so a later correction of the same voxel wins. Keys absent from the
    grid are ignored (the voxel was never observed in this run).

    Args:
        keys: (V,) int64 sorted unique grid keys.
        label, conf: (V,) argmax class and its probability.
        corr_keys: (K,) int64 corrected voxel keys, in the order the corrections were made.
        corr_labels: (K,) class index of each corrected key.

    Returns:
        ``(label', conf', corrected)``: new arrays (inputs untouched), ``corrected`` (V,) bool.
    """
    ck = np.asarray(corr_keys, dtype=np.int64).reshape(-1)
    cl = np.asarray(corr_labels, dtype=np.int16).reshape(-1)
    if ck.shape != cl.shape:
        raise ValueError(f"corr_keys {ck.shape} and corr_labels {cl.shape} must have the same length")
    label = label.copy()
    conf = conf.copy()
    corrected = np.zeros(keys.shape[0], bool)
    if ck.size == 0 or keys.size == 0:
        return label, conf, corrected
    pos = np.minimum(np.searchsorted(keys, ck), keys.shape[0] - 1)
    hit = keys[pos] == ck
    rows, cls = last_per_key(pos[hit], cl[hit])
    label[rows] = cls
    conf[rows] = 1.0
    corrected[rows] = True
    return label, conf, corrected


# ------------------------------------------------------------------------------ camera and selection
def select_in_rect(
    points: npt.ArrayLike,
    position: Sequence[float],
    wxyz: Sequence[float],
    fov_y: float,
    aspect: float,
    *,
    rect_min: Sequence[float],
    rect_max: Sequence[float],
) -> npt.NDArray[np.bool_]:
    """(N,) bool: the points in front of the camera whose screen position lies in the rectangle.

    ``rect_min`` / ``rect_max`` are normalised screen corners (see :func:`project_to_screen`); they are
    re-ordered if given swapped. Points hidden behind others are selected too (a box selects a volume).
    """
    uv, in_front = project_to_screen(points, position, wxyz, fov_y, aspect)
    lo = np.minimum(rect_min, rect_max)
    hi = np.maximum(rect_min, rect_max)
    inside = (uv[:, 0] >= lo[0]) & (uv[:, 0] <= hi[0]) & (uv[:, 1] >= lo[1]) & (uv[:, 1] <= hi[1])
    selected: npt.NDArray[np.bool_] = in_front & inside
    return selected


def orbit_view(
    target: npt.ArrayLike, distance: float, elevation_deg: float = 35.0, azimuth_deg: float = 225.0
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Camera ``(position, look_at)`` orbiting ``target`` (z up) at a distance, elevation and azimuth.

    ``position = target + d · (cos e · cos a, cos e · sin a, sin e)``.
    """
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    t = np.asarray(target, dtype=np.float64)
    offset = distance * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    return t + offset, t


# ------------------------------------------------------------------------------------------- focus
def dim_outside(
    colors: npt.NDArray[np.uint8],
    rows: npt.NDArray[np.int64],
    keep_rows: npt.NDArray[np.int64],
    toward: tuple[int, int, int] = (235, 235, 235),
    alpha: float = 0.75,
) -> npt.NDArray[np.uint8]:
    """Dim every drawn voxel but the focused ones: :func:`blend` ``(c, toward, α)`` where ``rows[m]`` is not
    in ``keep_rows``, the colour unchanged where it is.

    Args:
        colors: (M, 3) colours of the drawn voxels ``rows`` (M,).
        keep_rows: grid rows left at full colour (any order).

    Returns:
        (M, 3) uint8, a new array.
    """
    keep = np.isin(rows, keep_rows)
    out = blend(colors, toward, alpha)
    out[keep] = colors[keep]
    return out


# --------------------------------------------------------------------------------------- images
def draw_label_overlay(
    image: npt.NDArray[np.uint8],
    uv: npt.ArrayLike,
    labels: npt.ArrayLike,
    palette: npt.ArrayLike,
    *,
    radius: int = 1,
    alpha: float = 0.85,
    depth: npt.ArrayLike | None = None,
) -> npt.NDArray[np.uint8]:
    """Draw projected points as small squares in their class colour over a camera image.

    Each point paints the (2r+1)² pixels around ``round(uv)`` with ``(1-α)·image + α·colour``. Where
    squares overlap, the nearest point (smallest ``depth``) wins; unlabeled points (-1) are not drawn.

    Args:
        image: (H, W, 3) uint8 RGB (not modified).
        uv: (N, 2) pixel coordinates (column, row).
        labels: (N,) class index per point.
        palette: (C, 3) class colours.
        radius: half size r of each square in pixels.
        alpha: opacity of the colour.
        depth: (N,) distance used to resolve overlaps; None draws in the given order.

    Returns:
        (H, W, 3) uint8, a new image.
    """
    out: npt.NDArray[np.uint8] = image.copy()
    h, w = image.shape[:2]
    uv_arr = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    lab = np.asarray(labels).reshape(-1)
    keep = lab >= 0
    uv_arr, lab = uv_arr[keep], lab[keep]
    if depth is not None:
        # Paint far to near so the nearest point's colour is written last.
        order = np.argsort(-np.asarray(depth, dtype=np.float64).reshape(-1)[keep], kind="stable")
        uv_arr, lab = uv_arr[order], lab[order]
    if lab.size == 0:
        return out
    cols = class_colors(lab, palette)
    u0 = np.rint(uv_arr[:, 0]).astype(np.int64)
    v0 = np.rint(uv_arr[:, 1]).astype(np.int64)
    point = np.arange(lab.size)
    pix, who = [], []
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            u, v = u0 + du, v0 + dv
            ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
            pix.append(v[ok] * w + u[ok])
            who.append(point[ok])
    flat, src = np.concatenate(pix), np.concatenate(who)
    # Per pixel keep the point painted last (the nearest one when depth is given).
    order = np.argsort(src, kind="stable")
    flat, src = last_per_key(flat[order], src[order])
    colour = np.zeros((h * w, 3), np.uint8)
    painted = np.zeros(h * w, bool)
    colour[flat] = cols[src]
    painted[flat] = True
    base = out.reshape(-1, 3)
    base[painted] = blend(base[painted], colour[painted], alpha)
    return out


# ------------------------------------------------------------------------------------- undo / redo
T = TypeVar("T")


class EditHistory(Generic[T]):
    """Undo/redo stacks of applied edits (the caller knows how to apply and revert an edit).

    ``push`` records a newly applied edit and clears the redo stack; ``undo`` returns the edit to revert
    (moving it to the redo stack); ``redo`` returns the edit to re-apply (moving it back).
    """

    def __init__(self, limit: int = 1000) -> None:
        if limit < 1:
            raise ValueError(f"limit must be >= 1, got {limit}")
        self._done: list[T] = []
        self._undone: list[T] = []
        self._limit = limit

    def push(self, edit: T) -> None:
        self._done.append(edit)
        if len(self._done) > self._limit:
            del self._done[0]
        self._undone.clear()

    def undo(self) -> T | None:
        """The edit to revert, or None when there is nothing to undo."""
        if not self._done:
            return None
        edit = self._done.pop()
        self._undone.append(edit)
        return edit

    def redo(self) -> T | None:
        """The edit to re-apply, or None when there is nothing to redo."""
        if not self._undone:
            return None
        edit = self._undone.pop()
        self._done.append(edit)
        return edit

    @property
    def can_undo(self) -> bool:
        return bool(self._done)

    @property
    def can_redo(self) -> bool:
        return bool(self._undone)

    def __len__(self) -> int:
        return len(self._done)


__all__ = [
    "COLUMN_MODES",
    "CONFIDENCE_LUT",
    "ColorMode",
    "EditHistory",
    "ViewState",
    "apply_corrections",
    "blend",
    "class_colors",
    "corrected_class_prob",
    "decimate_indices",
    "delta_column",
    "dim_outside",
    "draw_label_overlay",
    "make_lut",
    "orbit_view",
    "project_to_screen",
    "quat_to_matrix",
    "render_view",
    "scalar_colors",
    "select_in_rect",
    "view_colors",
    "view_score",
    "visible_mask",
    "visible_rows",
]
