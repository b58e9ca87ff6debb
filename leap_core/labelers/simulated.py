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

Instances (docs/METHOD.md A.5a): the ground truth's thing instances (``gt2d/instance``, each id's class the
most frequent one its pixels carry in ``gt2d/semantic``), jittered with the masks, then missed, merged and
split (:func:`noisy_instances`). Their draws come from a stream of their own
(``SeedSequence([seed, frame.number, tag])``), so the masks are what they were without instances.

With every knob off (:meth:`SimulatedLabelerConfig.exact`) each named region is one mask with a one-hot
distribution and confidence 1, so where every region's name is named by exactly its own class's prompts,
the per-pixel argmax reproduces the mapped ground truth exactly.

Determinism: all draws come from ``SeedSequence([seed, frame.number, stream])`` (steps 1, 4, 5) or
``SeedSequence([seed, frame.number // persistence_frames, stream, object])`` (steps 2, 3), so a frame's
output depends only on the seed, its frame number (its file number, ``Frame.number``) and its images,
never on which other frames are present, were labeled or in which order, and turning one knob does not
reshuffle the draws of the others.

Extending it. A subclass adds noise terms through the labeler's steps, each a method it may override:
:meth:`SimulatedLabeler.extra_image` (one more per-pixel image, jittered with the label images),
:meth:`~SimulatedLabeler.frame_draws` (the frame's per-region draws, :class:`FrameDraws`),
:meth:`~SimulatedLabeler.keep_probability` (step 2), :meth:`~SimulatedLabeler.mask_parts` (steps 3 and 5:
the masks a kept region becomes) and :meth:`~SimulatedLabeler.paint_part`. Its streams are numbered from
:data:`FIRST_FREE_STREAM`, so the draws here stay what they are. The research lab's paper-calibrated
labeler (``simulated-paper``, beside leap_core; docs/METHOD.md A.7-A.8) is such a subclass.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import typing
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt
from scipy import ndimage

from leap_core.bounds import SEED_MAX, check_bounds, within
from leap_core.datasets.kitti import read_png16
from leap_core.errors import ConfigError, LeapError
from leap_core.labelers.base import Instances, SoftMasks
from leap_core.schema import MAX_RAW_ID
from leap_core.synth.names import NAMES_BY_ID, STRENGTHS, generic_name_ids, lexicon_digest, match

if TYPE_CHECKING:
    from leap_core.datasets.kitti import Frame
    from leap_core.schema import Schema

# Independent random streams per noise step (see the module docstring, "Determinism").
_STREAM_JITTER, _STREAM_OBJECT, _STREAM_PROBS, _STREAM_BLEED = range(4)

_INSTANCE_TAG = 0x494E5354
"""The instance noise's stream ("INST"): ``SeedSequence([seed, frame, tag])``, no stream number that the
steps above or a subclass's (from :data:`FIRST_FREE_STREAM`) use, so instances never move their draws."""

_INSTANCE_DEFAULTS = {"instance_miss": 0.1, "instance_merge": 0.1, "instance_split": 0.05}
"""The instance terms' defaults (checked against the config's in the tests): left out of fingerprints."""

FIRST_FREE_STREAM = 4
"""The first stream number this labeler does not draw from: a subclass's terms draw from streams numbered
from here, so they never share a draw with the steps above."""

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


def _check_strength_table(table: dict[str, float], name: str) -> None:
    """A per-strength table has exactly the four strengths as keys (its values' range is the field's
    bound)."""
    if set(table) != set(STRENGTHS):
        got = ", ".join(map(str, table)) or "none"
        raise ConfigError(f"needs exactly the keys {', '.join(STRENGTHS)}, got {got}", field=(name,))


def _check_pairs(pairs: tuple[tuple[str, str], ...]) -> None:
    """``confusion_pairs``: two different names each."""
    for pair in pairs:
        if len(pair) != 2 or pair[0] == pair[1]:
            raise ConfigError(
                f"entries must be two different class names, got {list(pair)}", field=("confusion_pairs",)
            )


@dataclass(frozen=True)
class SimulatedLabelerConfig:
    """Noise model of the simulated labeler (module docstring gives the exact procedure).

    The defaults aim at masks of roughly Grounding DINO + SAM quality on street scenes; they are not tuned
    to any result. :meth:`exact` turns every knob off.
    """

    seed: int = field(default=0, metadata=within(0, SEED_MAX))
    """Base seed; a frame's draws depend only on (seed, frame number)."""
    recall: float = field(default=0.9, metadata=within(0, 1))
    """Probability that a region (object instance or connected stuff area) gets a mask at all."""
    class_recall: dict[str, float] = field(
        default_factory=lambda: dict(_DEFAULT_CLASS_RECALL), metadata=within(0, 1)
    )
    """Per-class recall overriding ``recall``, by class name; names not in the schema are ignored."""
    min_region_px: int = field(default=16, metadata=within(0, 100_000_000, unit="px"))
    """Regions with fewer pixels than this are never detected (tiny fragments); 0 keeps every region."""
    confusion_prob: float = field(default=0.1, metadata=within(0, 1))
    """Probability that a region of a class in ``confusion_pairs`` is labeled as its partner class."""
    persistence_frames: int = field(default=5, metadata=within(1, 100_000))
    """Misses and confusions of one object are drawn once per block of this many consecutive frames
    (frame number // persistence_frames), as a detector's errors depend on an object's appearance, which
    changes slowly; 1 draws them independently in every frame (noise that fusion would average away too
    easily)."""
    confusion_pairs: tuple[tuple[str, str], ...] = _DEFAULT_CONFUSION_PAIRS
    """Ambiguous class pairs (symmetric), by class name; pairs with a name not in the schema are ignored."""
    peak_prob: tuple[float, float] = field(default=(0.5, 0.9), metadata=within(0, 1, low_open=True))
    """Range (low, high) of the uniform draw of the predicted class's probability."""
    partner_share: float = field(default=0.5, metadata=within(0, 1))
    """Share of the non-peak mass given to the confusable partner class (when the class has one)."""
    dirichlet_alpha: float = field(default=1.0, metadata=within(0, 1000, low_open=True))
    """Concentration of the Dirichlet draw that spreads the remaining mass over the other classes."""
    confidence: tuple[float, float] = field(default=(0.3, 0.9), metadata=within(0, 1, low_open=True))
    """Range (low, high) of the uniform draw of a mask's confidence (its weight where masks overlap)."""
    bleed_px: int = field(default=3, metadata=within(0, 100, unit="px"))
    """Largest dilation radius in pixels of thing (instance) masks onto their surroundings; 0 = no bleed."""
    stuff_bleed_px: int = field(default=1, metadata=within(0, 100, unit="px"))
    """Largest dilation radius in pixels of stuff (region) masks."""
    jitter_px: float = field(default=1.0, metadata=within(0, 100, unit="px"))
    """Standard deviation in pixels of the per-image shift of all masks (calibration error)."""
    jitter_deg: float = field(default=0.1, metadata=within(0, 180, unit="degrees"))
    """Standard deviation in degrees of the per-image rotation of all masks about the image centre."""
    match_detection: dict[str, float] = field(
        default_factory=lambda: dict(_DEFAULT_MATCH_DETECTION), metadata=within(0, 1)
    )
    """Per match strength (exact, synonym, descriptive, hypernym): the chance that a prompt naming a region
    with that strength gets it detected (combined over the naming classes, times the class recall). A
    looser name finds its object less often."""
    match_confidence: dict[str, float] = field(
        default_factory=lambda: dict(_DEFAULT_MATCH_CONFIDENCE), metadata=within(0, 1, low_open=True)
    )
    """Per match strength: factor on the mask's confidence draw, and the similarity that decides which
    class wins a region that prompts of several classes name."""
    match_temperature: float = field(default=0.1, metadata=within(0, 10))
    """Softness of that competition: class c wins with probability ∝ exp(match_confidence[k(c)] / T);
    0 = the strongest strength always wins (ties drawn uniformly)."""
    instance_miss: float = field(default=0.1, metadata=within(0, 1))
    """Probability that an object (a ground-truth instance of a thing class) gets no 2D instance: its
    box was missed (the same rate as ``recall``'s misses)."""
    instance_merge: float = field(default=0.1, metadata=within(0, 1))
    """Probability that two objects of one class whose image regions touch or whose boxes overlap become
    one instance (one box round a group of people or a row of parked cars)."""
    instance_split: float = field(default=0.05, metadata=within(0, 1))
    """Probability that an instance is cut in two across the middle of its longer image axis (an object
    seen in two parts round an occluder, or two boxes on one long vehicle)."""

    def __post_init__(self) -> None:
        check_bounds(self)
        for name in ("peak_prob", "confidence"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ConfigError(
                    f"must be a range (low, high) with low <= high, got ({lo}, {hi})", field=(name,)
                )
        _check_pairs(self.confusion_pairs)
        _check_strength_table(self.match_detection, "match_detection")
        _check_strength_table(self.match_confidence, "match_confidence")

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
            instance_miss=0.0,
            instance_merge=0.0,
            instance_split=0.0,
        )


MOVED_TERMS: dict[str, object] = {
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
    "stuff_world_tile": 0,
    "stratified_draws": False,
    "drift_draws": False,
}
"""Noise terms this labeler's config had, which only the paper-calibrated preset turned on, and the value
that left each off. They belong to the research lab's ``simulated-paper`` labeler now (beside leap_core;
docs/METHOD.md A.7 terms 6-14). Config dicts stored before they moved hold every one of them at this value:
``leap_core.config.config_from_dict`` reads such a dict as if they were absent and refuses any other
value, naming the field and that labeler."""

MOVED_TERMS_FIX = (
    "it is a noise term of the paper-calibrated labeler, which the research lab holds now: choose "
    "`labeler: simulated-paper` and set it in the `simulated_paper` section (run with `python -m lab`; "
    "docs/METHOD.md A.7), or remove it here"
)
"""What a config dict that sets a moved term (:data:`MOVED_TERMS`) to another value is told to do."""


MOVED_PRESETS: dict[str, str] = {
    "paper": "the paper preset belongs to the research lab's simulated-paper labeler now: choose "
    "`labeler: simulated-paper` with `simulated_paper: {preset: paper}` and run it with `python -m lab` "
    "(`python -m lab run SEQ --labeler simulated-paper --labeler-preset paper`)",
}
"""Presets this labeler had and a labeler beside leap_core has now: the name → how to get it."""


def simulated_preset(name: str) -> SimulatedLabelerConfig:
    """The simulated labeler's config of preset ``name`` (:data:`SIMULATED_PRESETS`).

    Raises:
        ConfigError: ``field = ("preset",)`` for an unknown name (naming where a moved preset lives).
    """
    if name not in SIMULATED_PRESETS:
        known = ", ".join(repr(n) for n in SIMULATED_PRESETS)
        moved = f"; {MOVED_PRESETS[name]}" if name in MOVED_PRESETS else ""
        raise ConfigError(f"unknown preset {name!r} (known: {known}){moved}", field=("preset",))
    return SIMULATED_PRESETS[name]()


SIMULATED_PRESETS: dict[str, typing.Callable[[], SimulatedLabelerConfig]] = {
    "default": SimulatedLabelerConfig,
}
"""Named simulated-labeler settings: ``default`` (the noise model of :class:`SimulatedLabelerConfig`'s
defaults). A project file picks one with ``pipeline: {simulated: {preset: default}}``, ``leap run`` with
``--labeler-preset default``."""


@dataclass(frozen=True)
class Region:
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
    extra: npt.NDArray[np.uint16] | None = None,
) -> tuple[npt.NDArray[np.uint16], npt.NDArray[np.uint16], npt.NDArray[np.uint16] | None]:
    """Move the label images (and ``extra``, a subclass's per-pixel image, if given) by one random rigid
    transform (shift + rotation about the centre)."""
    dx, dy = rng.normal(0.0, 1.0, size=2) * cfg.jitter_px
    theta = float(rng.normal(0.0, 1.0)) * cfg.jitter_deg
    if cfg.jitter_px == 0 and cfg.jitter_deg == 0:
        return names, inst, extra
    h, w = names.shape
    m = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), theta, 1.0)
    m[:, 2] += (dx, dy)

    def warp(img: npt.NDArray[np.uint16]) -> npt.NDArray[np.uint16]:
        warped = cv2.warpAffine(
            img, m, (w, h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        return np.asarray(warped, dtype=np.uint16)  # already uint16 (cv2 keeps the dtype): no copy

    return warp(names), warp(inst), None if extra is None else warp(extra)


def _regions(name_img: npt.NDArray[np.uint16], inst: npt.NDArray[np.uint16]) -> list[Region]:
    """Thing regions (name, instance) first, sorted by key, then stuff components by name id and label."""
    _, w = name_img.shape
    regions: list[Region] = []
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
            regions.append(Region(key_s >> 16, True, key_s & 0xFFFF, y0, x0, crop))

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
            regions.append(Region(nid, False, rank[j], by0 + y0, x0, crop))
    return regions


def _partners(schema_names: list[str], pairs: tuple[tuple[str, str], ...]) -> dict[int, list[int]]:
    """Class index → sorted partner indices, from the name pairs present in the schema."""
    index = {n: i for i, n in enumerate(schema_names)}
    out: dict[int, set[int]] = {}
    for a, b in pairs:
        if a in index and b in index:
            out.setdefault(index[a], set()).add(index[b])
            out.setdefault(index[b], set()).add(index[a])
    return {k: sorted(v) for k, v in out.items()}


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
    path = frame.gt2d_path("name")
    if not path.parent.is_dir():
        return generic_name_ids(semantic)
    names = read_png16(frame.seq.confined(path))
    if names.shape != semantic.shape:
        raise LeapError(f"{path}: name image {names.shape} and semantic mask {semantic.shape} differ in size")
    unknown = np.setdiff1d(np.unique(names), [0, *NAMES_BY_ID])
    if unknown.size:
        raise LeapError(f"{path}: unknown name ids {unknown[:5].tolist()} (see leap_core/synth/names.py)")
    return names


def per_class(names: list[str], default: float, table: dict[str, float]) -> npt.NDArray[np.float64]:
    """(C,) ``default`` per class, overridden by the by-name ``table`` (names not in ``names`` ignored)."""
    out = np.full(len(names), default, dtype=np.float64)
    for cname, v in table.items():
        if cname in names:
            out[names.index(cname)] = float(v)
    return out


def object_draws(regions: list[Region], seed: int, block: int, stream: int) -> npt.NDArray[np.float64]:
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


def _pick_partner(cand: list[int], u: float) -> int:
    """The partner of ``cand`` that a draw ``u`` ~ U(0, 1) picks, uniformly."""
    return cand[min(int(u * len(cand)), len(cand) - 1)]


@dataclass(frozen=True)
class FrameDraws:
    """One frame's regions, their draws (row i = region i) and per-class tables, read by the labeler's
    steps (:meth:`SimulatedLabeler.keep_probability`, :meth:`~SimulatedLabeler.mask_parts`,
    :meth:`~SimulatedLabeler.paint_part`). A subclass's :meth:`~SimulatedLabeler.frame_draws` may return
    a subclass of it carrying the draws of its own terms."""

    h: int
    w: int
    seed: int
    frame: int
    """The frame number (``Frame.number``)."""
    block: int
    """``frame // persistence_frames``: the block the persistent draws belong to."""
    regions: list[Region]
    names: list[str]
    """The schema's class names (column i of the distributions = class i)."""
    u_obj: npt.NDArray[np.float64]
    """(R, 4) persistent: recall, confusion, partner choice, competition."""
    u_bleed: npt.NDArray[np.float64]
    """(R,) per frame: the bleed radius."""
    partners: dict[int, list[int]]
    """Class index → its partner classes (``confusion_pairs``)."""
    confusion_of: npt.NDArray[np.float64]
    """(C,) confusion probability per class."""
    extra: npt.NDArray[np.uint16] | None
    """The subclass's per-pixel image (:meth:`SimulatedLabeler.extra_image`), jittered, or None."""


class SimulatedLabeler:
    """Soft masks from 2D ground truth, steered by the prompts, with the noise model of
    :class:`SimulatedLabelerConfig`."""

    name = "simulated"

    def __init__(self, cfg: SimulatedLabelerConfig | None = None) -> None:
        self.cfg = cfg or SimulatedLabelerConfig()

    def fingerprint(self, schema: Schema) -> str:
        """Hash of the noise config, the lexicon and the schema parts the output depends on (class names,
        prompts and negative prompts: a prompt edit changes the masks, so it must re-run the 2D stage)."""
        parts = {
            "labeler": self.name,
            "version": 3,
            "lexicon": lexicon_digest(),
            "config": self.fingerprint_config(),
            "classes": [[c.name, list(c.prompts), list(c.negative_prompts)] for c in schema.classes],
        }
        return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]

    def fingerprint_config(self) -> dict[str, object]:
        """The config as the fingerprint hashes it: every field, the pairs as lists."""
        cfg = asdict(self.cfg)
        cfg["confusion_pairs"] = [list(p) for p in self.cfg.confusion_pairs]
        # The instance terms only where they differ from their defaults: a run labeled before instances
        # existed keeps its fingerprint (its 2D cache entries, lacking instances, are recomputed).
        for name, default in _INSTANCE_DEFAULTS.items():
            if cfg[name] == default:
                del cfg[name]
        return cfg

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
        names_img, inst, extra = _jitter(
            _name_image(frame, sem), inst, cfg, _rng(seed, idx, _STREAM_JITTER), self.extra_image(frame, sem)
        )
        h, w = names_img.shape
        names = list(schema.names)
        num_classes, regions, matches = len(names), _regions(names_img, inst), prompt_matches(schema)

        recall_of = per_class(names, cfg.recall, cfg.class_recall)
        partners = _partners(names, cfg.confusion_pairs)

        n = len(regions)
        rng_probs, rng_bleed = (_rng(seed, idx, s) for s in (_STREAM_PROBS, _STREAM_BLEED))
        # Per object and block of frames: (recall draw, confusion draw, partner choice, competition draw).
        block = idx // cfg.persistence_frames
        u_bleed = rng_bleed.random(n)
        lo_c, hi_c = cfg.confidence
        conf = (lo_c + (hi_c - lo_c) * rng_probs.random(n)).astype(np.float32)
        draws = self.frame_draws(
            FrameDraws(
                h=h,
                w=w,
                seed=seed,
                frame=idx,
                block=block,
                regions=regions,
                names=names,
                u_obj=object_draws(regions, seed, block, _STREAM_OBJECT),
                u_bleed=u_bleed,
                partners=partners,
                confusion_of=per_class(names, cfg.confusion_prob, {}),
                extra=extra,
            )
        )

        bits, probs, confs = [], [], []
        flat = np.zeros(h * w, dtype=bool)
        for i, reg in enumerate(regions):
            dist_rng = np.random.default_rng(rng_probs.integers(0, 2**63))
            cands = matches.get(reg.name)
            if not cands:
                continue  # no prompt names this region: the detector is never asked for it
            cls, k, rival = _compete(cands, cfg, float(draws.u_obj[i, 3]))
            # Every class whose prompts name the region is one more chance for the detector to box it.
            missed = np.prod([1.0 - cfg.match_detection[STRENGTHS[kj]] for _, kj in cands])
            keep = self.keep_probability(draws, i, recall_of[cls] * (1.0 - missed))
            if draws.u_obj[i, 0] >= keep or reg.crop.sum() < cfg.min_region_px:
                continue
            parts, radius = self.mask_parts(draws, i, cls)
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
                # A region painted as several masks draws each one's distribution from a generator of
                # its own, so the first mask's draws are those of an unsplit region.
                rng_i = np.random.default_rng(dist_rng.integers(0, 2**63))
                confs.append(np.float32(conf[i] * cfg.match_confidence[STRENGTHS[k]]))
                bits.append(np.packbits(self.paint_part(flat, draws, i, part, radius)))
        instances = noisy_instances(
            inst,
            instance_classes(frame.gt2d_instance, sem, schema),
            cfg,
            np.random.SeedSequence([seed, idx, _INSTANCE_TAG]),
        )
        if not bits:
            return dataclasses.replace(SoftMasks.empty(h, w, num_classes), instances=instances)
        return SoftMasks(
            height=h,
            width=w,
            bits=np.stack(bits),
            probs=np.stack(probs),
            confidence=np.asarray(confs, dtype=np.float32),
            instances=instances,
        )

    # ------------------------------------------------------------------------- steps a subclass extends
    def extra_image(self, frame: Frame, semantic: npt.NDArray[np.uint16]) -> npt.NDArray[np.uint16] | None:
        """One more per-pixel image of ``frame`` that the jitter moves with the label images and
        :attr:`FrameDraws.extra` carries (``semantic``: the frame's semantic mask, for its size); none
        here."""
        del frame, semantic
        return None

    def frame_draws(self, draws: FrameDraws) -> FrameDraws:
        """The frame's draws: ``draws`` as the steps above drew them (a subclass adds its own)."""
        return draws

    def keep_probability(self, draws: FrameDraws, i: int, keep: float) -> float:
        """Step 2: the probability that region ``i`` is kept, given ``keep``, its recall times the chance
        that a naming prompt finds it."""
        del draws, i
        return keep

    def mask_parts(self, draws: FrameDraws, i: int, cls: int) -> tuple[list[tuple[Region, int]], int]:
        """Steps 3 and 5 for region ``i``, kept and won by class ``cls``: the masks to paint, [(shape,
        predicted class)] (here one: the region), and their dilation radius."""
        cfg = self.cfg
        reg = draws.regions[i]
        pred = cls
        cand = draws.partners.get(cls)
        if cand and draws.u_obj[i, 1] < draws.confusion_of[cls]:
            pred = _pick_partner(cand, float(draws.u_obj[i, 2]))
        max_r = cfg.bleed_px if reg.thing else cfg.stuff_bleed_px
        radius = min(int(draws.u_bleed[i] * (max_r + 1)), max_r)
        return [(reg, pred)], radius

    def paint_part(
        self, flat: npt.NDArray[np.bool_], draws: FrameDraws, i: int, part: Region, radius: int
    ) -> npt.NDArray[np.bool_]:
        """The flat full-image mask of ``part`` (a shape of region ``i``) dilated by ``radius`` pixels;
        ``flat`` is a reused zero buffer, returned."""
        del i
        return paint_region(flat, part, radius, draws.h, draws.w)


def instance_classes(
    inst: npt.NDArray[np.uint16], semantic: npt.NDArray[np.uint16], schema: Schema
) -> npt.NDArray[np.int16]:
    """(65536,) int16: the thing class of each ground-truth instance id of one image (-1: the id is absent
    or no thing), the schema class of the raw semantic ids most of its pixels carry (ties: lower class).

    Args:
        inst: (H, W) ground-truth instance ids (0 = none), before any jitter.
        semantic: (H, W) raw semantic ids of the same pixels.
    """
    out = np.full(MAX_RAW_ID + 1, -1, np.int16)
    if inst.shape != semantic.shape:
        raise LeapError(f"instance {inst.shape} and semantic {semantic.shape} masks differ in size")
    cls = schema.gt_lut()[semantic]
    things = schema.things()
    sel = (inst > 0) & (cls >= 0)
    sel[sel] = things[cls[sel]]
    if not sel.any():
        return out
    c = schema.num_classes
    key, count = np.unique(inst[sel].astype(np.int64) * c + cls[sel], return_counts=True)
    ids, classes = key // c, key % c
    # Per id the most frequent class: sorted by (id, -count, class), the first row of each id.
    order = np.lexsort((classes, -count, ids))
    first = np.r_[True, ids[order][1:] != ids[order][:-1]]
    out[ids[order][first]] = classes[order][first]
    return out


def touching_pairs(ids: npt.NDArray[np.integer]) -> set[tuple[int, int]]:
    """Pairs (a, b), a < b, of nonzero ids of an (H, W) image with 8-neighbouring pixels."""
    out: set[tuple[int, int]] = set()
    for x, y in (
        (ids[:, :-1], ids[:, 1:]),
        (ids[:-1, :], ids[1:, :]),
        (ids[:-1, :-1], ids[1:, 1:]),
        (ids[:-1, 1:], ids[1:, :-1]),
    ):
        sel = (x != y) & (x > 0) & (y > 0)
        if sel.any():
            a, b = x[sel].astype(np.int64), y[sel].astype(np.int64)
            pairs = np.unique(np.minimum(a, b) << 32 | np.maximum(a, b))
            out.update((int(p >> 32), int(p & 0xFFFFFFFF)) for p in pairs)
    return out


def noisy_instances(
    inst: npt.NDArray[np.uint16],
    classes: npt.NDArray[np.int16],
    cfg: SimulatedLabelerConfig,
    seed: np.random.SeedSequence,
) -> Instances:
    """The simulated labeler's instances of one image: its ground-truth thing instances with misses,
    merges and splits (docs/METHOD.md A.7, steps 6-8).

    Args:
        inst: (H, W) ground-truth instance ids (0 = none), jittered like the masks.
        classes: (65536,) the thing class per id (:func:`instance_classes`; -1 = no thing instance).
        cfg: ``instance_miss`` p_m, ``instance_merge`` p_g, ``instance_split`` p_s, ``min_region_px``, the
            ``confidence`` range of the scores.
        seed: the frame's instance stream. Draws are per ground-truth id (in id order) and per pair, from
            children of their own per step, so one term's setting never moves another's draws.

    1. Ids with a thing class and at least ``min_region_px`` pixels are the objects; each is missed with
       probability p_m.
    2. Two kept objects of one class whose pixels touch (8-neighbours) or whose boxes overlap are merged
       with probability p_g (a draw per pair; merges chain).
    3. Each instance (merged or not, drawn by its lowest id) is cut with probability p_s at the middle of
       its box's longer side (width when equal): pixels before it keep the instance, the others are a new
       one of the same class and score.
    4. Scores ``U(confidence)`` by the instance's lowest id; ids are numbered by descending score
       (:meth:`Instances.from_id_image`).
    """
    miss_seq, merge_seq, split_seq, score_seq = seed.spawn(4)
    gt = np.flatnonzero(classes >= 0)  # every thing id of the image, in id order: the draws' index
    u_miss = np.random.default_rng(miss_seq).random(gt.size)
    u_split = np.random.default_rng(split_seq).random(gt.size)
    u_score = np.random.default_rng(score_seq).random(gt.size)
    px = np.bincount(inst.ravel(), minlength=MAX_RAW_ID + 1)[gt]
    kept = gt[(px >= max(cfg.min_region_px, 1)) & (u_miss >= cfg.instance_miss)]
    groups = _merged(inst, kept, classes, cfg.instance_merge, merge_seq)
    lut = np.zeros(MAX_RAW_ID + 1, np.int32)
    lut[kept] = np.searchsorted([g[0] for g in groups], [_group_of(groups, int(g)) for g in kept]) + 1
    ids = lut[inst]
    lo, hi = cfg.confidence
    pos = np.searchsorted(gt, [g[0] for g in groups])
    label = [int(classes[g[0]]) for g in groups]
    score = [lo + (hi - lo) * float(u_score[p]) for p in pos]
    if cfg.instance_split > 0:
        for n, box in enumerate(ndimage.find_objects(ids)[: len(groups)], start=1):
            if (
                box is not None
                and u_split[pos[n - 1]] < cfg.instance_split
                and _split(ids, box, n, len(label) + 1)
            ):
                label.append(label[n - 1])
                score.append(score[n - 1])
    return Instances.from_id_image(ids, label, score)


def _group_of(groups: list[list[int]], g: int) -> int:
    """The lowest id of the group holding id ``g``."""
    return next(grp[0] for grp in groups if g in grp)


def _merged(
    inst: npt.NDArray[np.uint16],
    kept: npt.NDArray[np.int64],
    classes: npt.NDArray[np.int16],
    p_merge: float,
    seed: np.random.SeedSequence,
) -> list[list[int]]:
    """The kept ids in groups after step 2 of :func:`noisy_instances`, each group sorted, groups by their
    lowest id. A pair's draw comes from a child of ``seed`` keyed by the two ids, so it never depends on
    which other pairs exist (a miss elsewhere changes none)."""
    root = {int(g): int(g) for g in kept}

    def find(a: int) -> int:
        while root[a] != a:
            a = root[a]
        return a

    if p_merge > 0 and kept.size > 1:
        live = np.where(np.isin(inst, kept), inst, 0)
        boxes = ndimage.find_objects(live)
        pairs = touching_pairs(live)
        for i, a in enumerate(kept):
            for b in kept[i + 1 :]:
                sa, sb = boxes[a - 1], boxes[b - 1]
                if all(x.start < y.stop and y.start < x.stop for x, y in zip(sa, sb, strict=True)):
                    pairs.add((int(a), int(b)))
        for a, b in sorted(pairs):
            if classes[a] != classes[b]:
                continue
            child = np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, a, b))
            if np.random.default_rng(child).random() < p_merge:
                ra, rb = find(a), find(b)
                root[max(ra, rb)] = min(ra, rb)
    out: dict[int, list[int]] = {}
    for g in kept:
        out.setdefault(find(int(g)), []).append(int(g))
    return [out[r] for r in sorted(out)]


def _split(ids: npt.NDArray[np.int32], box: tuple[slice, ...], n: int, new: int) -> bool:
    """Step 3 of :func:`noisy_instances` in place: instance ``n`` (bounding ``box``) cut at the middle of
    its box's longer side, the far part numbered ``new``; False when that side is one pixel long."""
    axis = 1 if box[1].stop - box[1].start >= box[0].stop - box[0].start else 0
    span = box[axis]
    if span.stop - span.start < 2:
        return False
    coord = np.arange(span.start, span.stop) >= (span.start + span.stop) // 2
    window = ids[box]
    window[(window == n) & (coord[None, :] if axis else coord[:, None])] = new
    return True


def paint_region(
    flat: npt.NDArray[np.bool_], reg: Region, radius: int, h: int, w: int
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
    "FIRST_FREE_STREAM",
    "MOVED_PRESETS",
    "MOVED_TERMS",
    "MOVED_TERMS_FIX",
    "SIMULATED_PRESETS",
    "FrameDraws",
    "Region",
    "SimulatedLabeler",
    "SimulatedLabelerConfig",
    "object_draws",
    "paint_region",
    "per_class",
    "prompt_matches",
    "simulated_preset",
]
