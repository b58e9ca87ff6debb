"""The "simulated" 2D labeler: soft masks made from a dataset's 2D ground truth, steered by the class prompts
through a small lexicon, with a documented noise model.

It stands in for Grounding DINO + SAM (docs/METHOD.md stage A) on datasets that carry per-pixel 2D ground
truth (``gt2d/semantic``, ``gt2d/instance`` and, on the generated demo, ``gt2d/name``), so the 3D stages
can be run and measured without model weights, and so prompt expansion has a measurable effect. Users
always see it called "simulated".

Regions. Every pixel has a *name* (``leap_core.synth.names``): the demo's ``gt2d/name`` image gives
fine-grained names ("sedan", "hedge", "curb"); without that folder each pixel gets the generic name of its
raw semantic id ("car", "vegetation"). A *thing* region is one (name, instance id > 0) pair: one mask per
object, as a detector box + SAM would give. A *stuff* region is one 8-connected component of one name's
pixels that carry instance 0.

Prompts. Region r is offered to class c when one of c's prompts names r's name in the lexicon
(``names.match``), with the strongest matching strength k(r, c) among exact, synonym, descriptive and
hypernym; a negative prompt of c that names r more strongly than c's best prompt withdraws the offer (as
in docs/METHOD.md stage A.3). A region that no prompt names gets no mask, so a class whose prompts name
nothing finds nothing. When prompts of several classes name r, the classes compete: class c wins with
probability ∝ exp(match_confidence[k(r, c)] / match_temperature) (0: the strongest strength wins, ties
drawn uniformly), and the strongest loser takes the partner share of step 4. This is the joint-prompt
confusion of a real detector: a prompt like "vehicle" in two classes makes them split the vehicles.

Noise model, applied per image in this order (every parameter lives in :class:`SimulatedLabelerConfig`):

1. Calibration jitter. The whole label image is moved by one rigid 2D transform: a shift
   ``(dx, dy) ~ N(0, jitter_px²)`` and a rotation ``θ ~ N(0, jitter_deg²)`` about the image centre
   (nearest-neighbour resampling; pixels moved in from outside carry no label). This mimics a small
   camera↔LiDAR calibration or synchronisation error that shifts every mask against the points.
2. Missed regions. Region r won by class c is kept with probability
   ``recall(c) · (1 − Π_j (1 − match_detection[k(r, j)]))`` over the classes j whose prompts name r (each
   naming prompt is one more chance for the detector to box it; ``recall(c)`` = ``class_recall[c]`` if
   given, else ``recall``); regions smaller than ``min_region_px`` pixels are always missed.
3. Confusion. If c belongs to an ambiguous pair in ``confusion_pairs``, then with probability
   ``confusion_prob`` the mask's predicted class becomes its partner ĉ (one drawn uniformly when c has
   several partners); otherwise ĉ = c.
   Steps 2 and 3 and the competition draw are *persistent*: their draws belong to the object (thing: its
   name and instance id; stuff: its name and area rank in the image) and stay the same for
   ``persistence_frames`` consecutive frames, so a missed or confused object stays so for a while, as with
   a real detector. Independent per-frame errors would be averaged away by the voxel fusion far more
   easily than real ones.
4. Soft distribution. ``p(ĉ) = peak ~ U(peak_prob)``; of the remaining ``1 − peak``, the share
   ``partner_share`` goes to the class ĉ is confused with (c itself after a confusion, else the strongest
   competing class of the prompts, else one of c's partners), and the rest is spread over all other
   classes by a Dirichlet(``dirichlet_alpha``) draw. The mask's confidence is
   ``w ~ U(confidence) · match_confidence[k]``.
5. Boundary bleed. Each thing mask is dilated by a radius drawn uniformly from ``0..bleed_px`` pixels
   (stuff masks: ``0..stuff_bleed_px``), so it spills onto the background around it. Per-mask depth
   clustering in the projection stage is what removes the spill of foreground objects onto points behind.

Terms of the "paper" preset (:data:`SIMULATED_PRESETS`; off by default, and then nothing of them is drawn
or hashed, so the default masks and fingerprint stay byte for byte): per-class confusion
(``class_confusion``) and directed confusion (``confusion_targets``, :func:`confusion_targets`) in step 3,
size-dependent recall (``small_region_px``, :func:`size_recall`) in step 2, and in step 5 background leaks
(``box_leak_prob``, per class ``class_box_leak``: a thing mask of the winning class becomes its grown
bounding box, :func:`box_leak_crop`), one mask over two
adjacent objects (``pair_merge_prob``, :func:`adjacent_partner`), over-large stuff (``stuff_grow_prob``) and
tiled stuff confusion (``stuff_tile_px``, :func:`tile_split`; per tile of the world for the whole sequence
with ``stuff_world_tile``, :func:`world_tile_draws`), and stratified draws of the object errors
(``stratified_draws``, :func:`lattice_draws`; drifting from frame to frame with ``drift_draws``).
docs/METHOD.md A.7-A.8 give the details.

With every knob off (:meth:`SimulatedLabelerConfig.exact`) each named region is one mask with a one-hot
distribution and confidence 1, so where every region's name is named by exactly its own class's prompts,
the per-pixel argmax reproduces the mapped ground truth exactly.

Determinism: all draws come from ``SeedSequence([seed, frame.number, stream])`` (steps 1, 4, 5) or
``SeedSequence([seed, frame.number // persistence_frames, stream, object])`` (steps 2, 3; with
``stratified_draws``, four of them from a lattice in the object and ``frame.number // persistence_frames``
(``frame.number / persistence_frames`` with ``drift_draws``)
with phases from ``SeedSequence([seed, stream])``; world tiles from the tile and
``SeedSequence([seed, stream, name])``), so a frame's
output depends only on the seed, its frame number (its file number, ``Frame.number``) and its images,
never on which other frames are present, were labeled or in which order, and turning one knob does not
reshuffle the draws of the others.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import typing
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import read_png16
from leap_core.errors import ConfigError, LeapError
from leap_core.labelers.base import SoftMasks
from leap_core.synth.names import NAMES_BY_ID, STRENGTHS, generic_name_ids, lexicon_digest, match

if TYPE_CHECKING:
    from leap_core.datasets.kitti import Frame
    from leap_core.schema import Schema

# Independent random streams per noise step (see the module docstring, "Determinism").
(
    _STREAM_JITTER,
    _STREAM_OBJECT,
    _STREAM_PROBS,
    _STREAM_BLEED,
    _STREAM_SHAPE,
    _STREAM_TILE,
    _STREAM_LATTICE,
    _STREAM_WORLD,
) = range(8)

_DEFAULT_CLASS_RECALL: dict[str, float] = {
    # Small or thin objects are the ones open-vocabulary detectors miss most often.
    "bicycle": 0.7,
    "motorcycle": 0.7,
    "bicyclist": 0.7,
    "motorcyclist": 0.7,
    "person": 0.8,
    "other-vehicle": 0.8,
    "pole": 0.75,
    "traffic-sign": 0.75,
    "trunk": 0.75,
    "other-ground": 0.6,
}

_DEFAULT_MATCH_DETECTION: dict[str, float] = {
    "exact": 1.0,
    "synonym": 0.95,
    "descriptive": 0.85,
    "hypernym": 0.5,
}
_DEFAULT_MATCH_CONFIDENCE: dict[str, float] = {
    "exact": 1.0,
    "synonym": 0.85,
    "descriptive": 0.7,
    "hypernym": 0.45,
}

_DEFAULT_CONFUSION_PAIRS: tuple[tuple[str, str], ...] = (
    ("terrain", "vegetation"),
    ("road", "parking"),
    ("road", "sidewalk"),
    ("bicycle", "person"),
    ("car", "truck"),
)


def _check_strength_table(table: dict[str, float], name: str, *, positive: bool) -> None:
    """A per-strength table has exactly the four strengths as keys and values in [0, 1] ((0, 1] if
    ``positive``)."""
    if set(table) != set(STRENGTHS):
        got = ", ".join(map(str, table)) or "none"
        raise ConfigError(f"needs exactly the keys {', '.join(STRENGTHS)}, got {got}", field=(name,))
    for k, v in table.items():
        ok = 0.0 < float(v) <= 1.0 if positive else 0.0 <= float(v) <= 1.0
        if not ok:
            raise ConfigError(f"must be in {'(0, 1]' if positive else '[0, 1]'}, got {v}", field=(name, k))


def _check_confusion(pairs: tuple[tuple[str, str], ...], table: dict[str, dict[str, float]]) -> None:
    """``confusion_pairs``: two different names each; ``confusion_targets``: every weight >= 0 and of a
    class other than its row's."""
    for pair in pairs:
        if len(pair) != 2 or pair[0] == pair[1]:
            raise ConfigError(
                f"entries must be two different class names, got {list(pair)}", field=("confusion_pairs",)
            )
    for cname, targets in table.items():
        for tname, wt in targets.items():
            if not float(wt) >= 0.0 or tname == cname:
                raise ConfigError(
                    f"must be a weight >= 0 of another class, got {wt}",
                    field=("confusion_targets", cname, tname),
                )


@dataclass(frozen=True)
class SimulatedLabelerConfig:
    """Noise model of the simulated labeler (module docstring gives the exact procedure).

    The defaults aim at masks of roughly Grounding DINO + SAM quality on street scenes; they are not tuned
    to any result. :meth:`exact` turns every knob off.
    """

    seed: int = 0
    """Base seed; a frame's draws depend only on (seed, frame number)."""
    recall: float = 0.9
    """Probability that a region (object instance or connected stuff area) gets a mask at all."""
    class_recall: dict[str, float] = field(default_factory=lambda: dict(_DEFAULT_CLASS_RECALL))
    """Per-class recall overriding ``recall``, by class name; names not in the schema are ignored."""
    min_region_px: int = 16
    """Regions with fewer pixels than this are never detected (tiny fragments); 0 keeps every region."""
    confusion_prob: float = 0.1
    """Probability that a region of a class in ``confusion_pairs`` is labeled as its partner class."""
    persistence_frames: int = 5
    """Misses and confusions of one object are drawn once per block of this many consecutive frames
    (frame number // persistence_frames), as a detector's errors depend on an object's appearance, which
    changes slowly; 1 draws them independently in every frame (noise that fusion would average away too
    easily)."""
    confusion_pairs: tuple[tuple[str, str], ...] = _DEFAULT_CONFUSION_PAIRS
    """Ambiguous class pairs (symmetric), by class name; pairs with a name not in the schema are ignored."""
    peak_prob: tuple[float, float] = (0.5, 0.9)
    """Range (low, high) of the uniform draw of the predicted class's probability."""
    partner_share: float = 0.5
    """Share of the non-peak mass given to the confusable partner class (when the class has one)."""
    dirichlet_alpha: float = 1.0
    """Concentration of the Dirichlet draw that spreads the remaining mass over the other classes."""
    confidence: tuple[float, float] = (0.3, 0.9)
    """Range (low, high) of the uniform draw of a mask's confidence (its weight where masks overlap)."""
    bleed_px: int = 3
    """Largest dilation radius in pixels of thing (instance) masks onto their surroundings; 0 = no bleed."""
    stuff_bleed_px: int = 1
    """Largest dilation radius in pixels of stuff (region) masks."""
    jitter_px: float = 1.0
    """Standard deviation in pixels of the per-image shift of all masks (calibration error)."""
    jitter_deg: float = 0.1
    """Standard deviation in degrees of the per-image rotation of all masks about the image centre."""
    match_detection: dict[str, float] = field(default_factory=lambda: dict(_DEFAULT_MATCH_DETECTION))
    """Per match strength (exact, synonym, descriptive, hypernym): the chance that a prompt naming a region
    with that strength gets it detected (combined over the naming classes, times the class recall). A
    looser name finds its object less often."""
    match_confidence: dict[str, float] = field(default_factory=lambda: dict(_DEFAULT_MATCH_CONFIDENCE))
    """Per match strength: factor on the mask's confidence draw, and the similarity that decides which
    class wins a region that prompts of several classes name."""
    match_temperature: float = 0.1
    """Softness of that competition: class c wins with probability ∝ exp(match_confidence[k(c)] / T);
    0 = the strongest strength always wins (ties drawn uniformly)."""
    # The terms below are off by default (the default preset's masks and fingerprint do not see them); the
    # "paper" preset (:data:`SIMULATED_PRESETS`) turns them on to reach real Grounding DINO + SAM errors.
    class_confusion: dict[str, float] = field(default_factory=dict)
    """Per-class confusion probability overriding ``confusion_prob``, by class name (names not in the
    schema are ignored); a class still needs a partner in ``confusion_pairs`` to be confused."""
    confusion_targets: dict[str, dict[str, float]] = field(default_factory=dict)
    """Directed confusion, by class name: class → {class it is mistaken for: weight}. A confused region of a
    class listed here takes a target drawn with probability ∝ weight (instead of a partner of
    ``confusion_pairs`` drawn uniformly); the class's confusion probability is still ``class_confusion`` /
    ``confusion_prob``. Names not in the schema are ignored."""
    small_region_px: int = 0
    """Size-dependent recall: a region of a pixels is kept with its recall times ``min(1, a /
    small_region_px)`` (:func:`size_recall`), so small and far objects are missed more often; 0 = off."""
    box_leak_prob: float = 0.0
    """Probability that a thing mask becomes its whole bounding box grown by ``box_leak_margin``
    (:func:`box_leak_crop`): SAM segmenting the box rather than the object, the background inside the
    box leaks into the mask."""
    class_box_leak: dict[str, float] = field(default_factory=dict)
    """Per-class box-leak probability overriding ``box_leak_prob``, by class name (names not in the schema
    are ignored): a detector boxes some classes (thin or small objects, people) more loosely than others."""
    box_leak_margin: float = 0.0
    """Growth of the leaked box on each side, as a fraction of the box's height (top, bottom) and width
    (left, right)."""
    pair_merge_prob: float = 0.0
    """Probability that a thing mask also covers the nearest other thing region whose bounding box lies
    within ``pair_merge_gap_px`` of its own (:func:`adjacent_partner`): one mask over two adjacent objects
    (a rider and the bicycle, a person and the car behind), labeled as the first."""
    pair_merge_gap_px: int = 0
    """Largest gap in pixels between two bounding boxes for their objects to count as adjacent."""
    stuff_grow_prob: float = 0.0
    """Probability that a stuff mask is over-large: dilated by a radius drawn uniformly from
    ``1..stuff_grow_px`` (instead of its bleed when larger), so it covers the border of its neighbours."""
    stuff_grow_px: int = 0
    """Largest dilation radius in pixels of an over-large stuff mask."""
    stuff_tile_px: int = 0
    """When > 0, a stuff region's confusion is drawn per image tile of this many pixels (:func:`tile_split`)
    rather than once for the whole region: the confused tiles form a second mask labeled as the partner,
    as SAM splits a large surface into parts and the detector names some of them wrongly. The share of a
    surface confused then follows the confusion probability closely, where one draw per region flips whole
    roads at once."""
    stuff_world_tile: int = 0
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
        for name in (
            "recall",
            "confusion_prob",
            "partner_share",
            "box_leak_prob",
            "pair_merge_prob",
            "stuff_grow_prob",
        ):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"must be in [0, 1], got {v}", field=(name,))
        for table in ("class_recall", "class_confusion", "class_box_leak"):
            for cname, v in getattr(self, table).items():
                if not 0.0 <= float(v) <= 1.0:
                    raise ConfigError(f"must be in [0, 1], got {v}", field=(table, cname))
        for name in ("peak_prob", "confidence"):
            lo, hi = getattr(self, name)
            if not 0.0 < lo <= hi <= 1.0:
                raise ConfigError(f"must be a range 0 < low <= high <= 1, got ({lo}, {hi})", field=(name,))
        _check_confusion(self.confusion_pairs, self.confusion_targets)
        if not self.dirichlet_alpha > 0:
            raise ConfigError(f"must be > 0, got {self.dirichlet_alpha}", field=("dirichlet_alpha",))
        if self.persistence_frames < 1:
            raise ConfigError(f"must be >= 1, got {self.persistence_frames}", field=("persistence_frames",))
        for name in (
            "min_region_px",
            "bleed_px",
            "stuff_bleed_px",
            "jitter_px",
            "jitter_deg",
            "match_temperature",
            "small_region_px",
            "box_leak_margin",
            "pair_merge_gap_px",
            "stuff_grow_px",
            "stuff_tile_px",
            "stuff_world_tile",
        ):
            if getattr(self, name) < 0:
                raise ConfigError(f"must be >= 0, got {getattr(self, name)}", field=(name,))
        _check_needs(self)
        _check_strength_table(self.match_detection, "match_detection", positive=False)
        _check_strength_table(self.match_confidence, "match_confidence", positive=True)

    @classmethod
    def from_preset(cls, name: str) -> SimulatedLabelerConfig:
        """The config of a named preset (:data:`SIMULATED_PRESETS`); in a config dict, the key ``preset``
        of the ``simulated`` section (``leap_core.config.config_from_dict`` applies the section's other
        keys on top)."""
        return simulated_preset(name)

    @classmethod
    def exact(cls, seed: int = 0) -> SimulatedLabelerConfig:
        """Every noise knob off: one-hot masks of confidence 1 that reproduce the mapped 2D ground truth."""
        return cls(
            seed=seed,
            recall=1.0,
            class_recall={},
            min_region_px=0,
            confusion_prob=0.0,
            peak_prob=(1.0, 1.0),
            confidence=(1.0, 1.0),
            bleed_px=0,
            stuff_bleed_px=0,
            jitter_px=0.0,
            jitter_deg=0.0,
            match_detection=dict.fromkeys(STRENGTHS, 1.0),
            match_confidence=dict.fromkeys(STRENGTHS, 1.0),
            match_temperature=0.0,
        )


def _check_needs(cfg: SimulatedLabelerConfig) -> None:
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


_LATER_TERMS_OFF: dict[str, object] = {
    "class_confusion": {},
    "confusion_targets": {},
    "small_region_px": 0,
    "box_leak_prob": 0.0,
    "class_box_leak": {},
    "box_leak_margin": 0.0,
    "pair_merge_prob": 0.0,
    "pair_merge_gap_px": 0,
    "stuff_grow_prob": 0.0,
    "stuff_grow_px": 0,
    "stuff_tile_px": 0,
    "stratified_draws": False,
    "stuff_world_tile": 0,
    "drift_draws": False,
}
"""The noise terms added with the "paper" preset and their off values (the defaults)."""


def simulated_preset(name: str) -> SimulatedLabelerConfig:
    """The simulated labeler's config of preset ``name`` (:data:`SIMULATED_PRESETS`).

    Raises:
        ConfigError: ``field = ("preset",)`` for an unknown name.
    """
    if name not in SIMULATED_PRESETS:
        known = ", ".join(repr(n) for n in SIMULATED_PRESETS)
        raise ConfigError(f"unknown preset {name!r} (known: {known})", field=("preset",))
    return SIMULATED_PRESETS[name]()


def _paper_preset() -> SimulatedLabelerConfig:
    from leap_core.labelers.simulated_paper import PAPER_PRESET  # noqa: PLC0415  written by the fit script

    return SimulatedLabelerConfig(**PAPER_PRESET)


SIMULATED_PRESETS: dict[str, typing.Callable[[], SimulatedLabelerConfig]] = {
    "default": SimulatedLabelerConfig,
    "paper": _paper_preset,
}
"""Named simulated-labeler settings: ``default`` (the milder noise model, :class:`SimulatedLabelerConfig`'s
defaults) and ``paper`` (fitted so the demo's point row lands within ±5 IoU per class of the paper's Table 1
point row; ``leap_core/labelers/simulated_paper.py``, written by ``benchmarks/fit_labeler.py``). A project
file picks one with ``pipeline: {simulated: {preset: paper}}``, ``leap run`` with ``--labeler-preset``."""


@dataclass(frozen=True)
class _Region:
    """One ground-truth region: its name id, bounding box origin and the boolean crop inside the box."""

    name: int
    thing: bool
    ident: int
    """Identity of the object across frames: the instance id (things) or the area rank among the regions
    of its name, 0 = largest (stuff)."""
    y0: int
    x0: int
    crop: npt.NDArray[np.bool_]


def _rng(seed: int, index: int, stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, index, stream]))


def _jitter(
    names: npt.NDArray[np.uint16],
    inst: npt.NDArray[np.uint16],
    cfg: SimulatedLabelerConfig,
    rng: np.random.Generator,
    cells: npt.NDArray[np.uint16] | None = None,
) -> tuple[npt.NDArray[np.uint16], npt.NDArray[np.uint16], npt.NDArray[np.uint16] | None]:
    """Move the label images (and the world-cell image, if given) by one random rigid transform (shift +
    rotation about the centre)."""
    dx, dy = rng.normal(0.0, 1.0, size=2) * cfg.jitter_px
    theta = float(rng.normal(0.0, 1.0)) * cfg.jitter_deg
    if cfg.jitter_px == 0 and cfg.jitter_deg == 0:
        return names, inst, cells
    h, w = names.shape
    m = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), theta, 1.0)
    m[:, 2] += (dx, dy)

    def warp(img: npt.NDArray[np.uint16]) -> npt.NDArray[np.uint16]:
        warped = cv2.warpAffine(
            img, m, (w, h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        return np.asarray(warped, dtype=np.uint16)  # already uint16 (cv2 keeps the dtype): no copy

    return warp(names), warp(inst), None if cells is None else warp(cells)


def _regions(name_img: npt.NDArray[np.uint16], inst: npt.NDArray[np.uint16]) -> list[_Region]:
    """Thing regions (name, instance) first, sorted by key, then stuff components by name id and label."""
    _, w = name_img.shape
    regions: list[_Region] = []
    valid = name_img > 0
    thing = valid & (inst > 0)

    flat_idx = np.flatnonzero(thing)
    if flat_idx.size:
        key = name_img.ravel()[flat_idx].astype(np.int64) << 16 | inst.ravel()[flat_idx].astype(np.int64)
        order = np.argsort(key, kind="stable")
        key_sorted, idx_sorted = key[order], flat_idx[order]
        starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
        ends = np.r_[starts[1:], key_sorted.size]
        for s, e in zip(starts, ends, strict=True):
            pix = idx_sorted[s:e]
            ys, xs = pix // w, pix % w
            y0, x0 = int(ys.min()), int(xs.min())
            crop = np.zeros((int(ys.max()) - y0 + 1, int(xs.max()) - x0 + 1), dtype=bool)
            crop[ys - y0, xs - x0] = True
            key_s = int(key_sorted[s])
            regions.append(_Region(key_s >> 16, True, key_s & 0xFFFF, y0, x0, crop))

    stuff_name = np.where(valid & ~thing, name_img, np.uint16(0))
    for nid in (int(v) for v in np.unique(stuff_name) if v):
        ys = np.flatnonzero((stuff_name == nid).any(axis=1))
        # Label within the name's row band only: most stuff surfaces cover a fraction of the image height.
        by0, by1 = int(ys[0]), int(ys[-1]) + 1
        m = (stuff_name[by0:by1] == nid).astype(np.uint8)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8, ltype=cv2.CV_32S)
        # OpenCV's label numbering depends on its thread count (parallel labeling in stripes), so order the
        # components canonically by their first pixel in raster order; the noise draws follow this order.
        first = []
        for j in range(1, n):
            x0, y0, bw = (int(v) for v in stats[j, :3])
            first.append((y0, x0 + int(np.argmax(lab[y0, x0 : x0 + bw] == j)), j))
        first.sort()
        by_area = sorted((-int(stats[j, 4]), y, x, j) for y, x, j in first)
        rank = {j: r for r, (_, _, _, j) in enumerate(by_area)}
        for y0, _, j in first:
            x0, bw, bh = int(stats[j, 0]), int(stats[j, 2]), int(stats[j, 3])
            crop = lab[y0 : y0 + bh, x0 : x0 + bw] == j
            regions.append(_Region(nid, False, rank[j], by0 + y0, x0, crop))
    return regions


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


def _partners(schema_names: list[str], pairs: tuple[tuple[str, str], ...]) -> dict[int, list[int]]:
    """Class index → sorted partner indices, from the name pairs present in the schema."""
    index = {n: i for i, n in enumerate(schema_names)}
    out: dict[int, set[int]] = {}
    for a, b in pairs:
        if a in index and b in index:
            out.setdefault(index[a], set()).add(index[b])
            out.setdefault(index[b], set()).add(index[a])
    return {k: sorted(v) for k, v in out.items()}


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


def prompt_matches(schema: Schema) -> dict[int, list[tuple[int, int]]]:
    """Name id → [(class index, strength index)] of the classes whose prompts name it, strongest first.

    Strength index i is ``names.STRENGTHS[i]`` (0 = exact). A class's strength is the strongest over its
    prompts; a negative prompt of the class that names the region strictly more strongly rules the class
    out (docs/METHOD.md stage A.3 in discrete form). Names no prompt names are absent.
    """
    rank = {k: i for i, k in enumerate(STRENGTHS)}
    out: dict[int, list[tuple[int, int]]] = {}
    for nid, name in NAMES_BY_ID.items():
        found: list[tuple[int, int]] = []
        for c, cls in enumerate(schema.classes):
            pos = [rank[k] for p in cls.prompts if (k := match(p, name)) is not None]
            if not pos:
                continue
            neg = [rank[k] for p in cls.negative_prompts if (k := match(p, name)) is not None]
            if neg and min(neg) < min(pos):
                continue
            found.append((c, min(pos)))
        if found:
            out[nid] = sorted(found, key=lambda t: (t[1], t[0]))
    return out


def _compete(
    cands: list[tuple[int, int]], cfg: SimulatedLabelerConfig, u: float
) -> tuple[int, int, int | None]:
    """The winning class of a region named by ``cands`` [(class, strength index)], its strength index and
    the strongest other class (None when alone).

    ``P(c wins) = exp(s_c / T) / Σ_j exp(s_j / T)`` with ``s_c = match_confidence[k(r, c)]`` and
    ``T = match_temperature``; at T = 0 the classes of the strongest strength share the win equally.
    ``u`` ~ U(0, 1) picks from the cumulative distribution (classes in ``cands`` order).
    """
    if len(cands) == 1:
        return cands[0][0], cands[0][1], None
    if cfg.match_temperature == 0:
        best = cands[0][1]
        tied = [c for c in cands if c[1] == best]
        weights = np.ones(len(tied))
        pool = tied
    else:
        sim = np.array([cfg.match_confidence[STRENGTHS[k]] for _, k in cands])
        weights = np.exp((sim - sim.max()) / cfg.match_temperature)
        pool = cands
    cum = np.cumsum(weights / weights.sum())
    i = min(int(np.searchsorted(cum, u, side="right")), len(pool) - 1)
    win_c, win_k = pool[i]
    rival = next(c for c, _ in cands if c != win_c)
    return win_c, win_k, rival


def _distribution(
    true_c: int,
    pred_c: int,
    *,
    rival: int | None,
    partners: dict[int, list[int]],
    num_classes: int,
    cfg: SimulatedLabelerConfig,
    rng: np.random.Generator,
) -> npt.NDArray[np.float32]:
    """Step 4 of the noise model: peak on ``pred_c``, partner share, Dirichlet rest. Rows sum to 1."""
    # Draw every random number whatever the branch, so the stream stays aligned across regions.
    u_peak, u_partner = rng.random(2)
    spread = rng.dirichlet(np.full(max(num_classes, 1), cfg.dirichlet_alpha))
    lo, hi = cfg.peak_prob
    peak = lo + (hi - lo) * u_peak
    p = np.zeros(num_classes, dtype=np.float64)
    p[pred_c] = peak
    rest = 1.0 - peak
    if rest <= 0.0 or num_classes == 1:
        p[pred_c] = 1.0
        return p.astype(np.float32)
    second: int | None
    if pred_c != true_c:
        second = true_c
    elif rival is not None:
        second = rival
    else:
        cand = partners.get(true_c, [])
        second = cand[min(int(u_partner * len(cand)), len(cand) - 1)] if cand else None
    others = np.ones(num_classes, dtype=bool)
    others[pred_c] = False
    if second is not None:
        p[second] += rest * cfg.partner_share
        rest *= 1.0 - cfg.partner_share
        if num_classes > 2:
            others[second] = False
    w = spread * others
    total = w.sum()
    if total > 0:
        p += rest * w / total
    else:
        p[pred_c] += rest
    out: npt.NDArray[np.float32] = (p / p.sum()).astype(np.float32)
    return out


def _name_image(frame: Frame, semantic: npt.NDArray[np.uint16]) -> npt.NDArray[np.uint16]:
    """The frame's per-pixel name ids: ``gt2d/name/<frame>.png`` when the sequence has that folder, else
    the generic name of each pixel's raw semantic id."""
    folder = frame.seq.root / "gt2d" / "name"
    if not folder.is_dir():
        return generic_name_ids(semantic)
    names = read_png16(folder / f"{frame.frame_id}.png")
    if names.shape != semantic.shape:
        raise LeapError(
            f"{folder / (frame.frame_id + '.png')}: name image {names.shape} and semantic mask "
            f"{semantic.shape} differ in size"
        )
    unknown = np.setdiff1d(np.unique(names), [0, *NAMES_BY_ID])
    if unknown.size:
        raise LeapError(
            f"{folder / (frame.frame_id + '.png')}: unknown name ids {unknown[:5].tolist()} "
            "(see leap_core/synth/names.py)"
        )
    return names


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


def _per_class(names: list[str], default: float, table: dict[str, float]) -> npt.NDArray[np.float64]:
    """(C,) ``default`` per class, overridden by the by-name ``table`` (names not in ``names`` ignored)."""
    out = np.full(len(names), default, dtype=np.float64)
    for cname, v in table.items():
        if cname in names:
            out[names.index(cname)] = float(v)
    return out


def _object_draws(regions: list[_Region], seed: int, block: int, stream: int) -> npt.NDArray[np.float64]:
    """(R, 4) uniform draws per region that belong to the object (its name, kind and identity) and the
    block of frames, so they persist over ``persistence_frames``."""
    out = np.array(
        [
            np.random.default_rng(
                np.random.SeedSequence([seed, block, stream, r.name, int(r.thing), r.ident])
            ).random(4)
            for r in regions
        ]
    ).reshape(len(regions), 4)
    return out


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
    regions: list[_Region],
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
    regions: list[_Region], cfg: SimulatedLabelerConfig, seed: int, frame: int, *, shaped: bool
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(R, 4) object draws and (R, 4) shape draws of a frame's regions in frame number ``frame``'s block
    (:func:`_object_draws`; the shape draws only when a shape term is on, else ones), four of them
    replaced by lattice draws when ``stratified_draws`` is on (:func:`_stratify`)."""
    block = frame // cfg.persistence_frames
    u_obj = _object_draws(regions, seed, block, _STREAM_OBJECT)
    n = len(regions)
    u_shape = _object_draws(regions, seed, block, _STREAM_SHAPE) if shaped else np.ones((n, 4))
    if cfg.stratified_draws:
        _stratify(u_obj, u_shape, regions, seed, frame / cfg.persistence_frames if cfg.drift_draws else block)
    return u_obj, u_shape


def _merge_partners(regions: list[_Region], cfg: SimulatedLabelerConfig) -> npt.NDArray[np.int64]:
    """(R,) the thing region a pair merge of region i would add (:func:`adjacent_partner`); all -1 when the
    term is off."""
    if not (cfg.pair_merge_prob > 0 and regions):
        return np.full(len(regions), -1, np.int64)
    boxes = [(r.y0, r.x0, r.y0 + r.crop.shape[0], r.x0 + r.crop.shape[1]) for r in regions]
    return adjacent_partner(boxes, [r.thing for r in regions], cfg.pair_merge_gap_px)


@dataclass(frozen=True)
class _Draws:
    """One frame's per-region draws (row i = region i) and per-class tables, read by the mask shaping."""

    h: int
    w: int
    seed: int
    block: int
    u_obj: npt.NDArray[np.float64]
    """(R, 4) persistent: recall, confusion, partner choice, competition."""
    u_bleed: npt.NDArray[np.float64]
    """(R,) per frame: the bleed radius."""
    u_shape: npt.NDArray[np.float64]
    """(R, 4) persistent: box leak, pair merge, stuff growth, growth radius (ones when every term is off)."""
    cells: npt.NDArray[np.uint16] | None
    """(H, W) world cell per pixel (jittered with the label images) when world tiles are on, else None."""
    merge_with: npt.NDArray[np.int64]
    """(R,) the adjacent thing region a pair merge would add, -1 = none."""
    confusion_of: npt.NDArray[np.float64]
    """(C,) confusion probability per class."""
    leak_of: npt.NDArray[np.float64]
    """(C,) box-leak probability per class."""
    partners: dict[int, list[int]]
    targets: dict[int, tuple[list[int], npt.NDArray[np.float64]]]


class SimulatedLabeler:
    """Soft masks from 2D ground truth, steered by the prompts, with the noise model of
    :class:`SimulatedLabelerConfig`."""

    name = "simulated"

    def __init__(self, cfg: SimulatedLabelerConfig | None = None) -> None:
        self.cfg = cfg or SimulatedLabelerConfig()

    def fingerprint(self, schema: Schema) -> str:
        """Hash of the noise config, the lexicon and the schema parts the output depends on (class names,
        prompts and negative prompts: a prompt edit changes the masks, so it must re-run the 2D stage)."""
        cfg = asdict(self.cfg)
        cfg["confusion_pairs"] = [list(p) for p in self.cfg.confusion_pairs]
        # Terms added after version 3 enter the hash only when on, so the fingerprints (and 2D caches) of
        # configs that leave them off stay what they were.
        for name, off in _LATER_TERMS_OFF.items():
            if cfg[name] == off:
                del cfg[name]
        parts = {
            "labeler": self.name,
            "version": 3,
            "lexicon": lexicon_digest(),
            "config": cfg,
            "classes": [[c.name, list(c.prompts), list(c.negative_prompts)] for c in schema.classes],
        }
        return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]

    def label(self, frame: Frame, schema: Schema) -> SoftMasks:
        """Masks of one frame (reads ``gt2d/semantic``, ``gt2d/instance`` and ``gt2d/name`` if present)."""
        cfg = self.cfg
        sem, inst = frame.gt2d_semantic, frame.gt2d_instance
        if sem.shape != inst.shape:
            raise LeapError(
                f"{frame.seq.root / 'gt2d'}: frame {frame.frame_id} semantic {sem.shape} and instance "
                f"{inst.shape} masks differ in size"
            )
        seed, idx = cfg.seed, frame.number
        names_img, inst, cells = _jitter(
            _name_image(frame, sem),
            inst,
            cfg,
            _rng(seed, idx, _STREAM_JITTER),
            _cell_image(frame, sem) if cfg.stuff_world_tile > 0 else None,
        )
        h, w = names_img.shape
        names = list(schema.names)
        num_classes, regions, matches = len(names), _regions(names_img, inst), prompt_matches(schema)

        recall_of = _per_class(names, cfg.recall, cfg.class_recall)
        partners = _partners(names, cfg.confusion_pairs)

        n = len(regions)
        rng_probs, rng_bleed = (_rng(seed, idx, s) for s in (_STREAM_PROBS, _STREAM_BLEED))
        # Per object and block of frames: (recall draw, confusion draw, partner choice, competition draw).
        block = idx // cfg.persistence_frames
        u_bleed = rng_bleed.random(n)
        lo_c, hi_c = cfg.confidence
        conf = (lo_c + (hi_c - lo_c) * rng_probs.random(n)).astype(np.float32)
        # The shape terms (box leak, pair merge, over-large stuff) draw from their own persistent stream,
        # and only when on, so the default preset's draws and masks stay as they were.
        leak_of = _per_class(names, cfg.box_leak_prob, cfg.class_box_leak)
        shaped = bool(leak_of.any()) or cfg.pair_merge_prob > 0 or cfg.stuff_grow_prob > 0
        u_obj, u_shape = _persistent_draws(regions, cfg, seed, idx, shaped=shaped)
        draws = _Draws(
            h=h,
            w=w,
            seed=seed,
            block=block,
            u_obj=u_obj,
            u_bleed=u_bleed,
            u_shape=u_shape,
            cells=cells,
            merge_with=_merge_partners(regions, cfg),
            confusion_of=_per_class(names, cfg.confusion_prob, cfg.class_confusion),
            leak_of=leak_of,
            partners=partners,
            targets=confusion_targets(names, cfg.confusion_targets),
        )
        size_factor = size_recall([r.crop.sum() for r in regions], cfg.small_region_px)

        bits, probs, confs = [], [], []
        flat = np.zeros(h * w, dtype=bool)
        for i, reg in enumerate(regions):
            dist_rng = np.random.default_rng(rng_probs.integers(0, 2**63))
            cands = matches.get(reg.name)
            if not cands:
                continue  # no prompt names this region: the detector is never asked for it
            cls, k, rival = _compete(cands, cfg, float(u_obj[i, 3]))
            # Every class whose prompts name the region is one more chance for the detector to box it.
            missed = np.prod([1.0 - cfg.match_detection[STRENGTHS[kj]] for _, kj in cands])
            keep = recall_of[cls] * (1.0 - missed)
            if cfg.small_region_px:
                keep *= size_factor[i]
            if u_obj[i, 0] >= keep or reg.crop.sum() < cfg.min_region_px:
                continue
            parts, radius = self._parts(draws, i, reg, cls)
            rng_i = dist_rng
            for part, part_pred in parts:
                probs.append(
                    _distribution(
                        cls,
                        part_pred,
                        rival=rival,
                        partners=partners,
                        num_classes=num_classes,
                        cfg=cfg,
                        rng=rng_i,
                    )
                )
                rng_i = np.random.default_rng(dist_rng.integers(0, 2**63))
                confs.append(np.float32(conf[i] * cfg.match_confidence[STRENGTHS[k]]))
                mask = self._paint(flat, part, radius, h, w)
                j = int(draws.merge_with[i])
                if reg.thing and j >= 0 and draws.u_shape[i, 1] < cfg.pair_merge_prob:
                    other = regions[j]
                    img = mask.reshape(h, w)
                    rows = slice(other.y0, other.y0 + other.crop.shape[0])
                    img[rows, other.x0 : other.x0 + other.crop.shape[1]] |= other.crop
                bits.append(np.packbits(mask))
        if not bits:
            return SoftMasks.empty(h, w, num_classes)
        return SoftMasks(
            height=h,
            width=w,
            bits=np.stack(bits),
            probs=np.stack(probs),
            confidence=np.asarray(confs, dtype=np.float32),
        )

    def _parts(self, d: _Draws, i: int, reg: _Region, cls: int) -> tuple[list[tuple[_Region, int]], int]:
        """Region ``i`` (kept, won by class ``cls``) as masks to paint: [(shape, predicted class)] (two
        parts when its stuff tiles split it), and the dilation radius (steps 3 and 5 and the shape terms)."""
        cfg = self.cfg
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
            shape = _Region(reg.name, True, reg.ident, by0, bx0, box)
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
        d: _Draws,
        shape: _Region,
        cls: int,
        cand: list[int],
        target: tuple[list[int], npt.NDArray[np.float64]] | None,
    ) -> list[tuple[_Region, int]]:
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

    @staticmethod
    def _paint(
        flat: npt.NDArray[np.bool_], reg: _Region, radius: int, h: int, w: int
    ) -> npt.NDArray[np.bool_]:
        """Full-image flat mask of a region dilated by ``radius`` px (``flat`` is a reused zero buffer)."""
        crop, y0, x0 = reg.crop, reg.y0, reg.x0
        if radius > 0:
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
            padded = np.pad(crop, radius).astype(np.uint8)
            crop = cv2.dilate(padded, k).astype(bool)
            y0, x0 = y0 - radius, x0 - radius
            # Clip the dilated crop to the image.
            cy0, cx0 = max(0, -y0), max(0, -x0)
            cy1 = crop.shape[0] - max(0, y0 + crop.shape[0] - h)
            cx1 = crop.shape[1] - max(0, x0 + crop.shape[1] - w)
            crop = crop[cy0:cy1, cx0:cx1]
            y0, x0 = y0 + cy0, x0 + cx0
        img = flat.reshape(h, w)
        img[:] = False
        img[y0 : y0 + crop.shape[0], x0 : x0 + crop.shape[1]] = crop
        return flat


__all__ = [
    "SIMULATED_PRESETS",
    "SimulatedLabeler",
    "SimulatedLabelerConfig",
    "adjacent_partner",
    "box_gaps",
    "box_leak_crop",
    "confusion_targets",
    "lattice_draws",
    "prompt_matches",
    "simulated_preset",
    "size_recall",
    "tile_split",
    "world_tile_draws",
]
