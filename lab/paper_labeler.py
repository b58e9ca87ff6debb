"""The simulated labeler with the noise terms fitted to the paper: the lab's ``simulated-paper`` labeler.

:class:`SimulatedPaperLabeler` is the product's simulated labeler (``leap_core.labelers.simulated``: regions,
prompts and its five noise steps, drawn exactly as there) with the terms that make its 2D labels as wrong
as the paper's Grounding DINO + SAM (docs/METHOD.md A.7 terms 6-14, fitted in A.8). Its config,
:class:`SimulatedPaperConfig`, is the product's config plus these terms; with every term off (their
defaults) it draws nothing more than the product's labeler, so its masks are the product's, byte for byte.

- Per-class and directed confusion (step 3): ``class_confusion`` overrides ``confusion_prob`` per class;
  ``confusion_targets`` (:func:`confusion_targets`) makes a confused region take a target drawn by weight.
- Size-dependent recall (step 2): ``small_region_px`` (:func:`size_recall`).
- Background leaks (step 5): with ``box_leak_prob`` (per class ``class_box_leak``) a thing mask becomes its
  grown bounding box (:func:`box_leak_crop`).
- One mask over two adjacent objects: ``pair_merge_prob`` (:func:`adjacent_partner`).
- Over-large stuff: ``stuff_grow_prob``.
- Tiled stuff confusion: ``stuff_tile_px`` (:func:`tile_split`); per tile of the world for the whole
  sequence with ``stuff_world_tile`` (:func:`world_tile_draws`, reads ``gt2d/cell``).
- Stratified draws of the object errors: ``stratified_draws`` (:func:`lattice_draws`), drifting from frame
  to frame with ``drift_draws``.

Determinism: the product's streams, plus persistent shape draws from ``SeedSequence([seed, frame.number //
persistence_frames, stream, object])`` (drawn only when a shape term is on), four of the object draws from
a lattice in the object and ``frame.number // persistence_frames`` (``frame.number / persistence_frames``
with ``drift_draws``) with phases from ``SeedSequence([seed, stream])`` when ``stratified_draws`` is on,
image tiles from ``SeedSequence([seed, block, stream, name, object])`` and world tiles from the tile and
``SeedSequence([seed, stream, name])``. The streams are numbered after the product's
(``FIRST_FREE_STREAM``), so turning a term on reshuffles no other draw.

Presets (:data:`PAPER_LABELER_PRESETS`): ``default`` (every term off: the product's default noise) and
``paper`` (``lab/paper_preset.py``, written by ``python -m lab.fit_labeler --write``). In a config dict:
``pipeline: {labeler: simulated-paper, simulated_paper: {preset: paper}}``; on the command line:
``python -m lab run SEQ --labeler simulated-paper --labeler-preset paper``.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from leap_core.bounds import within
from leap_core.errors import ConfigError, LeapError
from leap_core.labelers import LabelerSpec
from leap_core.labelers.base import Labeler
from leap_core.labelers.simulated import (
    FIRST_FREE_STREAM,
    FrameDraws,
    Region,
    SimulatedLabeler,
    SimulatedLabelerConfig,
    object_draws,
    per_class,
)
from leap_core.runtime import Runtime

if TYPE_CHECKING:
    from leap_core.datasets.kitti import Frame

# Random streams of the terms here, after the product labeler's (module docstring, "Determinism").
_STREAM_SHAPE, _STREAM_TILE, _STREAM_LATTICE, _STREAM_WORLD = range(FIRST_FREE_STREAM, FIRST_FREE_STREAM + 4)


@dataclass(frozen=True)
class SimulatedPaperConfig(SimulatedLabelerConfig):
    """The simulated labeler's noise model plus the terms of docs/METHOD.md A.7 6-14, all off by default
    (then its masks are those of :class:`~leap_core.labelers.simulated.SimulatedLabelerConfig`'s)."""

    class_confusion: dict[str, float] = field(default_factory=dict, metadata=within(0, 1))
    """Per-class confusion probability overriding ``confusion_prob``, by class name (names not in the
    schema are ignored); a class still needs a partner in ``confusion_pairs`` to be confused."""
    confusion_targets: dict[str, dict[str, float]] = field(
        default_factory=dict, metadata=within(0, 1_000_000)
    )
    """Directed confusion, by class name: class → {class it is mistaken for: weight}. A confused region of a
    class listed here takes a target drawn with probability ∝ weight (instead of a partner of
    ``confusion_pairs`` drawn uniformly); the class's confusion probability is still ``class_confusion`` /
    ``confusion_prob``. Names not in the schema are ignored."""
    small_region_px: int = field(default=0, metadata=within(0, 100_000_000, unit="px"))
    """Size-dependent recall: a region of a pixels is kept with its recall times ``min(1, a /
    small_region_px)`` (:func:`size_recall`), so small and far objects are missed more often; 0 = off."""
    box_leak_prob: float = field(default=0.0, metadata=within(0, 1))
    """Probability that a thing mask becomes its whole bounding box grown by ``box_leak_margin``
    (:func:`box_leak_crop`): SAM segmenting the box rather than the object, the background inside the
    box leaks into the mask."""
    class_box_leak: dict[str, float] = field(default_factory=dict, metadata=within(0, 1))
    """Per-class box-leak probability overriding ``box_leak_prob``, by class name (names not in the schema
    are ignored): a detector boxes some classes (thin or small objects, people) more loosely than others."""
    box_leak_margin: float = field(default=0.0, metadata=within(0, 10))
    """Growth of the leaked box on each side, as a fraction of the box's height (top, bottom) and width
    (left, right)."""
    pair_merge_prob: float = field(default=0.0, metadata=within(0, 1))
    """Probability that a thing mask also covers the nearest other thing region whose bounding box lies
    within ``pair_merge_gap_px`` of its own (:func:`adjacent_partner`): one mask over two adjacent objects
    (a rider and the bicycle, a person and the car behind), labeled as the first."""
    pair_merge_gap_px: int = field(default=0, metadata=within(0, 10_000, unit="px"))
    """Largest gap in pixels between two bounding boxes for their objects to count as adjacent."""
    stuff_grow_prob: float = field(default=0.0, metadata=within(0, 1))
    """Probability that a stuff mask is over-large: dilated by a radius drawn uniformly from
    ``1..stuff_grow_px`` (instead of its bleed when larger), so it covers the border of its neighbours."""
    stuff_grow_px: int = field(default=0, metadata=within(0, 100, unit="px"))
    """Largest dilation radius in pixels of an over-large stuff mask."""
    stuff_tile_px: int = field(default=0, metadata=within(0, 100_000, unit="px"))
    """When > 0, a stuff region's confusion is drawn per image tile of this many pixels (:func:`tile_split`)
    rather than once for the whole region: the confused tiles form a second mask labeled as the partner,
    as SAM splits a large surface into parts and the detector names some of them wrongly. The share of a
    surface confused then follows the confusion probability closely, where one draw per region flips whole
    roads at once."""
    stuff_world_tile: int = field(default=0, metadata=within(0, 100_000))
    """When > 0, the tiled stuff confusion (``stuff_tile_px``, which must then be > 0 too) is drawn per
    world tile of this many world cells a side (``gt2d/cell``: 2 m cells of generated data, so 2 = 4 m
    tiles) instead of per image tile, and once for the whole sequence instead of per block of frames
    (:func:`world_tile_draws`): a patch of pavement or hedge taken for another class is taken so in every
    frame that sees it, as a detector's errors on a surface follow its appearance. Image tiles move over
    the world as the camera does, so their errors average out in the voxel fusion where a real detector's
    do not (docs/METHOD.md A.7, term 13). Needs the ``gt2d/cell`` images of ``leap synth``."""
    stratified_draws: bool = False
    """When on, the persistent draws that decide an object's confusion (and its target), box leak and pair
    merge come from a 2D lattice over (object, block of frames) (:func:`lattice_draws`) instead of
    independent uniforms, so the share of a class's object-blocks hit by an error follows its probability
    closely in every sequence and for every seed (on the demo with the "paper" preset, person's point-row
    IoU over labeler seeds 0-7 has a standard deviation of 6.2 with them, 11.1 without). Each error still
    lasts its block, but an object's errors are spread evenly over its blocks, so the voxel fusion's
    majority recovers them more easily (docs/METHOD.md A.7, term 12)."""
    drift_draws: bool = False
    """With ``stratified_draws``: the lattice's time coordinate is ``frame.number / persistence_frames``
    instead of its block ``frame.number // persistence_frames``, so an object's lattice draw drifts by
    ``a2 / persistence_frames`` a frame (0.15 for the confusion) instead of jumping once a block. Its
    wrong frames then come in runs (about ``q · persistence_frames / a2`` frames at confusion probability q)
    and their share of the object's frames follows q for any lifetime, where block-wise decisions move a
    short-lived object's share a whole block at a time (the demo's one bicycle, six blocks: point-row IoU
    15.0 or 42.6 and nothing between as q moves; docs/METHOD.md A.7, term 14)."""

    def __post_init__(self) -> None:
        super().__post_init__()  # checks every field's range, these terms' too
        _check_targets(self.confusion_targets)
        _check_needs(self)

    @classmethod
    def from_preset(cls, name: str) -> SimulatedPaperConfig:
        """The config of a named preset (:data:`PAPER_LABELER_PRESETS`); in a config dict, the key
        ``preset`` of the ``simulated_paper`` section."""
        if name not in PAPER_LABELER_PRESETS:
            known = ", ".join(repr(n) for n in PAPER_LABELER_PRESETS)
            raise ConfigError(f"unknown preset {name!r} (known: {known})", field=("preset",))
        return PAPER_LABELER_PRESETS[name]()

    @classmethod
    def exact(cls, seed: int = 0) -> SimulatedPaperConfig:
        """Every noise knob off (the terms here are off by default)."""
        out = super().exact(seed)
        assert isinstance(out, SimulatedPaperConfig)
        return out

    @classmethod
    def from_simulated(cls, cfg: SimulatedLabelerConfig) -> SimulatedPaperConfig:
        """The product labeler's settings ``cfg`` with every term here off: the same masks."""
        return cls(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(SimulatedLabelerConfig)})


def _check_targets(table: dict[str, dict[str, float]]) -> None:
    """``confusion_targets``: every weight is of a class other than its row's (its range is the field's
    bound)."""
    for cname, targets in table.items():
        for tname, wt in targets.items():
            if tname == cname:
                raise ConfigError(
                    f"must be a weight of another class, got {wt} for {cname} itself",
                    field=("confusion_targets", cname, tname),
                )


def _check_needs(cfg: SimulatedPaperConfig) -> None:
    """Refuse a term that is on while the term it works through is off, naming the first."""
    for name, needs, why in (
        (
            "stuff_world_tile",
            "stuff_tile_px",
            "world tiles replace the image tiles of the tiled stuff confusion: set stuff_tile_px > 0 too",
        ),
        (
            "drift_draws",
            "stratified_draws",
            "drifting draws move the stratified lattice over time: set stratified_draws too",
        ),
    ):
        if getattr(cfg, name) and not getattr(cfg, needs):
            raise ConfigError(why, field=(name,))


def _paper_preset() -> SimulatedPaperConfig:
    from lab.paper_preset import PAPER_PRESET

    return SimulatedPaperConfig(**PAPER_PRESET)


PAPER_LABELER_PRESETS: dict[str, typing.Callable[[], SimulatedPaperConfig]] = {
    "default": SimulatedPaperConfig,
    "paper": _paper_preset,
}
"""Named settings of the ``simulated-paper`` labeler: ``default`` (every term off: the product's default
noise) and ``paper`` (fitted so the demo's point row lands within ±5 IoU per class of the paper's Table 1
point row; ``lab/paper_preset.py``, written by ``python -m lab.fit_labeler --write``)."""


def size_recall(area: npt.ArrayLike, small_px: int) -> npt.NDArray[np.float64]:
    """(R,) factor on the recall of regions of ``area`` (R,) pixels: ``min(1, a / small_px)``; all ones
    when ``small_px`` is 0 (the term is off)."""
    a = np.asarray(area, dtype=np.float64)
    if small_px <= 0:
        return np.ones_like(a)
    out: npt.NDArray[np.float64] = np.minimum(1.0, a / float(small_px))
    return out


def box_leak_crop(
    box_h: int, box_w: int, y0: int, x0: int, margin: float, size: tuple[int, int]
) -> tuple[npt.NDArray[np.bool_], int, int]:
    """A leaked mask: the full bounding box (rows ``y0..y0+box_h-1``, columns ``x0..x0+box_w-1``) grown by
    ``round(margin·box_h)`` rows above and below and ``round(margin·box_w)`` columns left and right,
    clipped to the image of ``size`` = (h, w). Returns the all-True crop and its origin ``(y0', x0')``."""
    h, w = size
    my, mx = round(margin * box_h), round(margin * box_w)
    ny0, nx0 = max(0, y0 - my), max(0, x0 - mx)
    ny1, nx1 = min(h, y0 + box_h + my), min(w, x0 + box_w + mx)
    return np.ones((max(0, ny1 - ny0), max(0, nx1 - nx0)), dtype=bool), ny0, nx0


def tile_split(
    crop: npt.NDArray[np.bool_], y0: int, x0: int, tile_px: int, u_tiles: npt.NDArray[np.float64], prob: float
) -> npt.NDArray[np.bool_]:
    """The pixels of a region's ``crop`` (origin ``(y0, x0)`` in the image) whose image tile is confused:
    pixel (y, x) lies in tile ``(y // tile_px, x // tile_px)``, which is confused when its draw
    ``u_tiles[ty, tx]`` (uniform in [0, 1), one per tile of the image) is below ``prob``."""
    ty = (y0 + np.arange(crop.shape[0])) // tile_px
    tx = (x0 + np.arange(crop.shape[1])) // tile_px
    out: npt.NDArray[np.bool_] = crop & (u_tiles[np.ix_(ty, tx)] < prob)
    return out


def world_tile_draws(
    cells: npt.ArrayLike,
    tile: int,
    phases: tuple[float, float],
    stratified: bool = True,
    seed_key: tuple[int, ...] = (),
) -> npt.NDArray[np.float64]:
    """(2, ...) two draws in [0, 1) per pixel of ``cells`` (any shape; uint16 world cell ids
    ``ix · 256 + iy``, ``leap_core.synth.camera.world_cells``), equal for every pixel of one world tile
    ``(tx, ty) = (ix // tile, iy // tile)`` in every frame: draw 0 decides the confusion, draw 1 its target.

    Stratified: :func:`lattice_draws` with key tx and block ty, ``u_d = frac(phases[d] + tx · a1 + ty ·
    a2)`` with the lattice steps of decisions 0 and 1, so the confused share of any sizeable patch of tiles
    is close to the probability. Otherwise independent uniforms per tile, seeded by ``seed_key`` and
    the tile (``phases`` unused).
    """
    c = np.asarray(cells, dtype=np.int64)
    tx, ty = (c >> 8) // tile, (c & 255) // tile
    if stratified:
        return np.stack(
            [lattice_draws(tx, ty, phases[d], _LATTICE_STEPS[d]).reshape(c.shape) for d in range(2)]
        )
    key = tx * 256 + ty
    uniq, inv = np.unique(key, return_inverse=True)
    table = np.array(
        [np.random.default_rng(np.random.SeedSequence([*seed_key, int(k)])).random(2) for k in uniq]
    ).reshape(-1, 2)
    return np.moveaxis(table[inv.reshape(c.shape)], -1, 0)


def box_gaps(boxes: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """(R, R) gap in pixels between bounding boxes ``boxes`` (R, 4) = (y0, x0, y1, x1), ends exclusive:
    ``max(gap_y, gap_x)`` with ``gap_y = max(0, y0_j − y1_i, y0_i − y1_j)`` (0 where the boxes touch or
    overlap on that axis), so boxes within g pixels of each other in both directions have gap ≤ g."""
    b = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    y0, x0, y1, x1 = (b[:, k] for k in range(4))
    gy = np.maximum(0, np.maximum(y0[None, :] - y1[:, None], y0[:, None] - y1[None, :]))
    gx = np.maximum(0, np.maximum(x0[None, :] - x1[:, None], x0[:, None] - x1[None, :]))
    out: npt.NDArray[np.int64] = np.maximum(gy, gx)
    return out


def adjacent_partner(boxes: npt.ArrayLike, eligible: npt.ArrayLike, max_gap: int) -> npt.NDArray[np.int64]:
    """(R,) for each region i, the eligible region j ≠ i whose box is nearest to i's (:func:`box_gaps`),
    if that gap is ≤ ``max_gap``, else -1; equal gaps go to the lower index."""
    gaps = box_gaps(boxes).astype(np.float64)
    ok = np.asarray(eligible, dtype=bool).reshape(-1)
    n = ok.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    gaps[:, ~ok] = np.inf
    np.fill_diagonal(gaps, np.inf)
    best = gaps.argmin(axis=1)  # the first minimum: the lower index on ties
    out: npt.NDArray[np.int64] = np.where(gaps[np.arange(n), best] <= max_gap, best, -1).astype(np.int64)
    return out


def confusion_targets(
    schema_names: list[str], table: dict[str, dict[str, float]]
) -> dict[int, tuple[list[int], npt.NDArray[np.float64]]]:
    """Class index → (target class indices, their cumulative normalised weights) of the directed confusion
    ``table`` (class name → {target name: weight}); entries naming a class not in the schema, and classes
    left with no positive weight, are dropped."""
    index = {n: i for i, n in enumerate(schema_names)}
    out: dict[int, tuple[list[int], npt.NDArray[np.float64]]] = {}
    for cname, row in table.items():
        pairs = [(index[t], float(wt)) for t, wt in row.items() if t in index and float(wt) > 0]
        if cname in index and pairs:
            wts = np.array([wt for _, wt in pairs])
            out[index[cname]] = ([t for t, _ in pairs], np.cumsum(wts / wts.sum()))
    return out


def _pick_many(
    cand: list[int], target: tuple[list[int], npt.NDArray[np.float64]] | None, u: npt.ArrayLike
) -> npt.NDArray[np.int64]:
    """The confused class for each draw of ``u`` ~ U(0, 1) (any shape): from the cumulative weights of a
    directed target row, else uniform over the pair partners ``cand``."""
    v = np.asarray(u, dtype=np.float64)
    if target is not None:
        at = np.minimum(np.searchsorted(target[1], v, side="right"), len(target[0]) - 1)
        return np.asarray(target[0], dtype=np.int64)[at]
    return np.asarray(cand, dtype=np.int64)[np.minimum((v * len(cand)).astype(np.int64), len(cand) - 1)]


def _pick(cand: list[int], target: tuple[list[int], npt.NDArray[np.float64]] | None, u: float) -> int:
    """:func:`_pick_many` for one draw."""
    return int(_pick_many(cand, target, u))


def _cell_image(frame: Frame, semantic: npt.NDArray[np.uint16]) -> npt.NDArray[np.uint16]:
    """The frame's per-pixel world cells (``gt2d/cell/<frame>.png``), which world tiles need."""
    cells = frame.gt2d_cell
    folder = frame.seq.root / "gt2d" / "cell"
    if cells is None:
        raise LeapError(
            f"{folder}: missing; stuff_world_tile needs the world-cell images that `leap synth` "
            "writes (regenerate the sequence, or set stuff_world_tile: 0)"
        )
    if cells.shape != semantic.shape:
        raise LeapError(
            f"{folder / (frame.frame_id + '.png')}: cell image {cells.shape} and semantic mask "
            f"{semantic.shape} differ in size"
        )
    return cells


_LATTICE_PRIMES: tuple[tuple[int, int], ...] = ((2, 3), (5, 7), (11, 13), (17, 19))
"""Per stratified decision (confusion, its target, box leak, pair merge): the primes p, q whose square roots
give its lattice steps (frac √p, frac √q). Square roots of distinct primes are linearly independent over
the rationals, so the four decisions of one object are jointly equidistributed (asymptotically
independent) where one lattice with four phases would make them shifts of each other."""

_LATTICE_STEPS: tuple[tuple[float, float], ...] = tuple(
    (math.sqrt(p) % 1.0, math.sqrt(q) % 1.0) for p, q in _LATTICE_PRIMES
)
"""The steps (a1, a2) of :func:`lattice_draws` per stratified decision, from :data:`_LATTICE_PRIMES`."""


def lattice_draws(
    keys: npt.ArrayLike, block: float | npt.ArrayLike, phase: float, steps: tuple[float, float]
) -> npt.NDArray[np.float64]:
    """(R,) draws in [0, 1) of objects ``keys`` (R,) integers in the block of frames ``block`` (one, or
    (R,) of them; a fraction with ``drift_draws``): ``u = frac(phase + key · a1 + block · a2)`` with
    ``(a1, a2) = steps``, irrational and independent over the rationals.

    For a fixed key the values over consecutive blocks, and for a fixed block the values over consecutive
    keys, are spread evenly over [0, 1) (a Kronecker sequence), so the share of (key, block) pairs with
    ``u < q`` is close to q in any sizeable set of them, where independent uniforms make it binomial.
    ``phase`` ~ U(0, 1) (one per seed and decision) shifts the whole lattice.
    """
    k = np.asarray(keys, dtype=np.float64).reshape(-1)
    b = np.asarray(block, dtype=np.float64).reshape(-1)
    a1, a2 = steps
    out: npt.NDArray[np.float64] = np.mod(phase + k * a1 + b * a2, 1.0)
    return out


def _stratify(
    u_obj: npt.NDArray[np.float64],
    u_shape: npt.NDArray[np.float64],
    regions: list[Region],
    seed: int,
    when: float,
) -> None:
    """Replace, in place, the confusion and target draws (``u_obj[:, 1:3]``) and the box-leak and
    pair-merge draws (``u_shape[:, 0:2]``) by :func:`lattice_draws` keyed by the object (a thing's instance
    id; a stuff region's name and area rank), one lattice per decision (:data:`_LATTICE_PRIMES`), at time
    ``when``: the block of frames, or with ``drift_draws`` the frame number over ``persistence_frames``."""
    keys = [r.ident if r.thing else (r.name << 8) + r.ident for r in regions]
    phases = np.random.default_rng(np.random.SeedSequence([seed, _STREAM_LATTICE])).random(4)
    cols = ((u_obj, 1), (u_obj, 2), (u_shape, 0), (u_shape, 1))
    for (arr, col), steps, phase in zip(cols, _LATTICE_STEPS, phases, strict=True):
        arr[:, col] = lattice_draws(keys, when, float(phase), steps)


def _persistent_draws(
    draws: FrameDraws, cfg: SimulatedPaperConfig, *, shaped: bool
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(R, 4) object draws (the product labeler's, ``draws.u_obj``) and (R, 4) shape draws of a frame's
    regions in its block (the shape draws only when a shape term is on, else ones), four of them replaced
    by lattice draws when ``stratified_draws`` is on (:func:`_stratify`)."""
    u_obj = draws.u_obj.copy()
    n = len(draws.regions)
    u_shape = (
        object_draws(draws.regions, draws.seed, draws.block, _STREAM_SHAPE) if shaped else np.ones((n, 4))
    )
    if cfg.stratified_draws:
        when = draws.frame / cfg.persistence_frames if cfg.drift_draws else draws.block
        _stratify(u_obj, u_shape, draws.regions, draws.seed, when)
    return u_obj, u_shape


def _merge_partners(regions: list[Region], cfg: SimulatedPaperConfig) -> npt.NDArray[np.int64]:
    """(R,) the thing region a pair merge of region i would add (:func:`adjacent_partner`); all -1 when the
    term is off."""
    if not (cfg.pair_merge_prob > 0 and regions):
        return np.full(len(regions), -1, np.int64)
    boxes = [(r.y0, r.x0, r.y0 + r.crop.shape[0], r.x0 + r.crop.shape[1]) for r in regions]
    return adjacent_partner(boxes, [r.thing for r in regions], cfg.pair_merge_gap_px)


@dataclass(frozen=True)
class PaperDraws(FrameDraws):
    """:class:`~leap_core.labelers.simulated.FrameDraws` plus the draws and tables of the terms here."""

    u_shape: npt.NDArray[np.float64]
    """(R, 4) persistent: box leak, pair merge, stuff growth, growth radius (ones when every term is off)."""
    cells: npt.NDArray[np.uint16] | None
    """(H, W) world cell per pixel (jittered with the label images) when world tiles are on, else None."""
    merge_with: npt.NDArray[np.int64]
    """(R,) the adjacent thing region a pair merge would add, -1 = none."""
    leak_of: npt.NDArray[np.float64]
    """(C,) box-leak probability per class."""
    targets: dict[int, tuple[list[int], npt.NDArray[np.float64]]]
    """Class index → its directed confusion targets (:func:`confusion_targets`)."""
    size_factor: npt.NDArray[np.float64]
    """(R,) factor on each region's recall (:func:`size_recall`)."""


class SimulatedPaperLabeler(SimulatedLabeler):
    """The simulated labeler with the terms of :class:`SimulatedPaperConfig` (module docstring)."""

    name = "simulated-paper"
    cfg: SimulatedPaperConfig

    def __init__(self, cfg: SimulatedPaperConfig | None = None) -> None:
        super().__init__(cfg or SimulatedPaperConfig())

    def extra_image(self, frame: Frame, semantic: npt.NDArray[np.uint16]) -> npt.NDArray[np.uint16] | None:
        """The world cells of each pixel (``gt2d/cell``) when world tiles are on."""
        return _cell_image(frame, semantic) if self.cfg.stuff_world_tile > 0 else None

    def frame_draws(self, draws: FrameDraws) -> PaperDraws:
        """The product's draws, four of the object draws stratified when ``stratified_draws`` is on, and
        the terms' own: shape draws, merge partners, per-class confusion and leak, targets, size factors."""
        cfg = self.cfg
        regions, names = draws.regions, draws.names
        # The shape terms (box leak, pair merge, over-large stuff) draw from their own persistent stream,
        # and only when on, so that with them off the draws and masks are the product labeler's.
        leak_of = per_class(names, cfg.box_leak_prob, cfg.class_box_leak)
        shaped = bool(leak_of.any()) or cfg.pair_merge_prob > 0 or cfg.stuff_grow_prob > 0
        u_obj, u_shape = _persistent_draws(draws, cfg, shaped=shaped)
        base = {f.name: getattr(draws, f.name) for f in dataclasses.fields(FrameDraws)}
        base.update(u_obj=u_obj, confusion_of=per_class(names, cfg.confusion_prob, cfg.class_confusion))
        return PaperDraws(
            **base,
            u_shape=u_shape,
            cells=draws.extra,
            merge_with=_merge_partners(regions, cfg),
            leak_of=leak_of,
            targets=confusion_targets(names, cfg.confusion_targets),
            size_factor=size_recall([r.crop.sum() for r in regions], cfg.small_region_px),
        )

    def keep_probability(self, draws: FrameDraws, i: int, keep: float) -> float:
        """Step 2 with size-dependent recall: ``keep`` times the region's size factor."""
        assert isinstance(draws, PaperDraws)
        if self.cfg.small_region_px:
            keep *= draws.size_factor[i]
        return keep

    def mask_parts(self, draws: FrameDraws, i: int, cls: int) -> tuple[list[tuple[Region, int]], int]:
        """Region ``i`` (kept, won by class ``cls``) as masks to paint: [(shape, predicted class)] (two or
        more parts when its stuff tiles split it), and the dilation radius (steps 3 and 5 and the shape
        terms)."""
        d = draws
        assert isinstance(d, PaperDraws)
        cfg = self.cfg
        reg = d.regions[i]
        pred = cls
        target = d.targets.get(cls)
        cand = target[0] if target is not None else d.partners.get(cls)
        # Tiled stuff: the confusion is drawn per image tile instead of for the whole region.
        tiled = bool(cand) and not reg.thing and cfg.stuff_tile_px > 0
        if cand and not tiled and d.u_obj[i, 1] < d.confusion_of[cls]:
            pred = _pick(cand, target, float(d.u_obj[i, 2]))
        max_r = cfg.bleed_px if reg.thing else cfg.stuff_bleed_px
        radius = min(int(d.u_bleed[i] * (max_r + 1)), max_r)
        shape = reg
        if reg.thing and d.u_shape[i, 0] < d.leak_of[cls]:
            bh, bw = reg.crop.shape
            box, by0, bx0 = box_leak_crop(bh, bw, reg.y0, reg.x0, cfg.box_leak_margin, (d.h, d.w))
            shape = Region(reg.name, True, reg.ident, by0, bx0, box)
        if not reg.thing and d.u_shape[i, 2] < cfg.stuff_grow_prob and cfg.stuff_grow_px > 0:
            grow = 1 + min(int(d.u_shape[i, 3] * cfg.stuff_grow_px), cfg.stuff_grow_px - 1)
            radius = max(radius, grow)
        if not (tiled and cand):
            return [(shape, pred)], radius
        if d.cells is not None:
            return self._world_parts(d, shape, cls, cand, target), radius
        t = cfg.stuff_tile_px
        u_tiles = np.random.default_rng(
            np.random.SeedSequence([d.seed, d.block, _STREAM_TILE, reg.name, reg.ident])
        ).random((-(-d.h // t), -(-d.w // t)))
        moved = tile_split(shape.crop, shape.y0, shape.x0, t, u_tiles, float(d.confusion_of[cls]))
        partner = _pick(cand, target, float(d.u_obj[i, 2]))
        parts = [
            (dataclasses.replace(shape, crop=shape.crop & ~moved), cls),
            (dataclasses.replace(shape, crop=moved), partner),
        ]
        return [(part, c) for part, c in parts if part.crop.any()], radius

    def _world_parts(
        self,
        d: PaperDraws,
        shape: Region,
        cls: int,
        cand: list[int],
        target: tuple[list[int], npt.NDArray[np.float64]] | None,
    ) -> list[tuple[Region, int]]:
        """Stuff region ``shape`` split by world tiles (term 13): the pixels whose tile is confused, one
        part per target they take (:func:`world_tile_draws`, keyed by the region's name and the seed, not
        the frame), and the rest, labeled ``cls``."""
        assert d.cells is not None
        cfg = self.cfg
        ch, cw = shape.crop.shape
        cells = d.cells[shape.y0 : shape.y0 + ch, shape.x0 : shape.x0 + cw]
        phases = np.random.default_rng(np.random.SeedSequence([d.seed, _STREAM_WORLD, shape.name])).random(2)
        u = world_tile_draws(
            cells,
            cfg.stuff_world_tile,
            (float(phases[0]), float(phases[1])),
            cfg.stratified_draws,
            (d.seed, _STREAM_WORLD, shape.name),
        )
        moved = shape.crop & (u[0] < d.confusion_of[cls])
        parts = [(dataclasses.replace(shape, crop=shape.crop & ~moved), cls)]
        if moved.any():
            picks = _pick_many(cand, target, u[1][moved])
            for c in np.unique(picks):
                part = np.zeros_like(moved)
                part[moved] = picks == c
                parts.append((dataclasses.replace(shape, crop=part), int(c)))
        return [(part, c) for part, c in parts if part.crop.any()]

    def paint_part(
        self, flat: npt.NDArray[np.bool_], draws: FrameDraws, i: int, part: Region, radius: int
    ) -> npt.NDArray[np.bool_]:
        """The product's painted mask, plus the whole adjacent object when region ``i`` (a thing) merges
        with it (term 9)."""
        d = draws
        assert isinstance(d, PaperDraws)
        mask = super().paint_part(flat, d, i, part, radius)
        reg, j = d.regions[i], int(d.merge_with[i])
        if reg.thing and j >= 0 and d.u_shape[i, 1] < self.cfg.pair_merge_prob:
            other = d.regions[j]
            img = mask.reshape(d.h, d.w)
            rows = slice(other.y0, other.y0 + other.crop.shape[0])
            img[rows, other.x0 : other.x0 + other.crop.shape[1]] |= other.crop
        return mask


def _labeler(config: SimulatedPaperConfig, runtime: Runtime) -> Labeler:  # noqa: ARG001 - no deployment values
    return SimulatedPaperLabeler(config)


LABELER: LabelerSpec[SimulatedPaperConfig] = LabelerSpec(
    name="simulated-paper",
    label="simulated, paper-calibrated (lab)",
    description="the simulated labeler with the research lab's noise terms, fitted to the paper's point "
    "row with --labeler-preset paper (demo data, no models)",
    section="simulated_paper",
    config_type=SimulatedPaperConfig,
    factory=_labeler,
    needs="gt2d",
    missing="the simulated-paper labeler needs 2D ground truth (gt2d/semantic, gt2d/instance)",
    presets=tuple(PAPER_LABELER_PRESETS),
)
"""The lab's labeler record, registered into ``leap_core.labelers.LABELERS`` when ``lab`` is imported."""


__all__ = [
    "LABELER",
    "PAPER_LABELER_PRESETS",
    "PaperDraws",
    "SimulatedPaperConfig",
    "SimulatedPaperLabeler",
    "adjacent_partner",
    "box_gaps",
    "box_leak_crop",
    "confusion_targets",
    "lattice_draws",
    "size_recall",
    "tile_split",
    "world_tile_draws",
]
