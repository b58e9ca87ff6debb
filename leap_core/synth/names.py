"""Names in the demo world: the fine-grained vocabulary of the demo scene and its small lexicon.

Every object and stuff surface the demo generator builds carries a *name* from :data:`VOCABULARY` (a sedan,
a hedge, a curb, a traffic cone ...). The generator writes a per-pixel name-id image beside the 2D class and
instance masks (``gt2d/name/<frame>.png``, uint16, 0 = sky / nothing); the KITTI files are unchanged.
The simulated 2D labeler reads these names and decides, through the lexicon below, which of a class's text
prompts name which region (docs/METHOD.md, "The demo world" and stage A.7).

The lexicon is deliberately small and literal: a prompt names a region only if, after normalisation
(:func:`normalize`: lower case, ``-`` and ``_`` as spaces, single spaces, a plural ``s`` dropped when the
singular is listed), it equals one of the region name's phrases. Each phrase has a *strength*:

``exact``        the name itself ("sedan" for a sedan);
``synonym``      what people and detectors commonly call it ("car", "automobile" for a sedan);
``descriptive``  a concrete description ("four-door car", "metal post");
``hypernym``     a broader or looser category ("vehicle"; "car" for a van; "terrain" for a lawn).

There is no language model behind it: phrases the lexicon does not list name nothing.

Raw ground-truth ids. SemanticKITTI's raw ids stop at 259 (``moving-other-vehicle``). The demo scene also
holds objects that no SemanticKITTI class names well; their points and pixels carry the raw ids of
:data:`DEMO_EXTRA_RAW_IDS` in the demo's ``labels/*.label`` and ``gt2d/semantic`` files, so a class added in
the UI can be evaluated against them.

Datasets without a name image (2D ground truth from elsewhere, older demo folders) fall back to one generic
name per raw SemanticKITTI id (:data:`GENERIC_NAME_ID_BASE` + raw id: "car", "road", "other-ground" ...),
whose lexicon lists the SemanticKITTI class name and a few common synonyms.
"""

from __future__ import annotations

import functools
import hashlib
import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final, Literal

import numpy as np
import numpy.typing as npt

DEMO_EXTRA_RAW_IDS: Mapping[int, str] = MappingProxyType({300: "traffic-cone", 301: "bench", 302: "bollard"})
"""Raw id -> name of the demo-only objects (ids above SemanticKITTI's 0..259 range)."""

Strength = Literal["exact", "synonym", "descriptive", "hypernym"]
STRENGTHS: Final[tuple[Strength, ...]] = ("exact", "synonym", "descriptive", "hypernym")
"""Match strengths, strongest first."""

GENERIC_NAME_ID_BASE: Final = 1000
"""Name id of the generic name of raw id r is ``GENERIC_NAME_ID_BASE + r`` (the fallback vocabulary)."""


@dataclass(frozen=True)
class Name:
    """One entry of the vocabulary.

    Attributes:
        id: name id written to ``gt2d/name`` (1 .. 65535; 0 means no name).
        name: the fine-grained name ("sedan"); its normalised form is its ``exact`` phrase.
        raw_ids: raw ground-truth ids that surfaces with this name carry (a moving sedan has 252).
        synonyms, descriptions, hypernyms: the other phrases of the lexicon, by strength.
    """

    id: int
    name: str
    raw_ids: tuple[int, ...]
    synonyms: tuple[str, ...] = ()
    descriptions: tuple[str, ...] = ()
    hypernyms: tuple[str, ...] = ()

    def phrases(self) -> dict[str, Strength]:
        """Normalised phrase -> strength (a phrase listed twice keeps its strongest strength)."""
        out: dict[str, Strength] = {}
        groups: tuple[tuple[Strength, tuple[str, ...]], ...] = (
            ("hypernym", self.hypernyms),
            ("descriptive", self.descriptions),
            ("synonym", self.synonyms),
            ("exact", (self.name,)),
        )
        for strength, phrases in groups:  # weakest first, so stronger entries overwrite
            for p in phrases:
                out[normalize(p)] = strength
        return out


def normalize(phrase: str) -> str:
    """Lower case, ``-``/``_`` as spaces, runs of white space as one space, trimmed."""
    return re.sub(r"\s+", " ", re.sub(r"[-_]", " ", phrase.lower())).strip()


_CAR_RAW = (10, 252)
_TRUCK_RAW = (18, 258)
_PERSON_RAW = (30, 254)
_VEHICLE = ("vehicle", "motor vehicle")

# fmt: off
# Columns: id, name, raw ids, synonyms, descriptions, hypernyms (loose names: see the module docstring).
VOCABULARY: Final[tuple[Name, ...]] = (
    # ---------------------------------------------------------------- vehicles (SemanticKITTI car)
    Name(1, "sedan", _CAR_RAW, ("car", "automobile", "saloon"), ("four-door car",), _VEHICLE),
    Name(2, "hatchback", _CAR_RAW, ("car", "automobile"), ("small car", "compact car"), _VEHICLE),
    # Detectors call these "van" / "SUV", and loosely "car" or "truck"; SemanticKITTI's car includes them,
    # which is why the paper adds them to car as helper prompts.
    Name(3, "van", _CAR_RAW, ("minivan", "people carrier"), ("passenger van",), ("car", "truck", *_VEHICLE)),
    Name(4, "jeep", _CAR_RAW, ("suv", "sport utility vehicle", "off-roader"), ("four-wheel drive",),
         ("car", "truck", *_VEHICLE)),
    # ---------------------------------------------------------------- truck, other-vehicle
    Name(5, "box truck", _TRUCK_RAW, ("truck", "lorry", "delivery truck"), ("cargo truck",), _VEHICLE),
    Name(6, "bus", (13, 257), ("city bus", "coach"), ("public bus", "passenger bus"), _VEHICLE),
    # ---------------------------------------------------------------- two-wheelers, people
    Name(7, "city bike", (11,), ("bicycle", "bike", "pushbike"), ("parked bicycle",), ("vehicle",)),
    Name(8, "pedestrian", _PERSON_RAW, ("person", "walker"), ("man", "woman", "walking person"),
         ("human", "people")),
    Name(9, "child", _PERSON_RAW, ("kid",), ("small person",), ("person", "pedestrian", "human", "people")),
    # ---------------------------------------------------------------- flat
    Name(10, "asphalt", (40,), ("road", "street", "roadway"), ("asphalt road", "paved road"), ("ground",)),
    Name(11, "crosswalk", (40,), ("zebra crossing", "pedestrian crossing"), ("road marking",),
         ("road", "street")),
    Name(12, "parking lane", (44,), ("parking bay", "parking space", "parking spot"),
         ("parking area", "parking lot", "paved parking"), ("parking", "road", "street", "ground")),
    Name(13, "sidewalk", (48,), ("footpath", "pavement", "footway"), ("paved walkway",), ("ground",)),
    Name(14, "curb", (48,), ("kerb", "curbstone"), ("curb stone",), ("sidewalk", "road", "street")),
    Name(15, "gravel", (49,), ("gravel strip", "grit"), ("gravel path", "loose stones"),
         ("terrain", "ground")),
    # ---------------------------------------------------------------- construction
    Name(16, "house", (50,), ("building", "detached house", "home"), ("facade", "wall"), ("structure",)),
    Name(17, "apartment building", (50,), ("building", "apartment block", "row house"), ("facade", "wall"),
         ("house", "structure")),
    Name(18, "office building", (50,), ("building", "office block"), ("glass facade", "facade", "wall"),
         ("structure",)),
    Name(19, "roof", (50,), ("rooftop",), ("tiled roof",), ("building", "house")),
    Name(20, "wooden fence", (51,), ("fence", "picket fence"), ("wooden railing",), ("barrier",)),
    Name(21, "metal fence", (51,), ("fence", "railing"), ("metal railing", "guardrail"), ("barrier",)),
    # ---------------------------------------------------------------- nature
    Name(22, "tree", (70,), ("tree canopy", "treetop"), ("foliage", "leaves"), ("vegetation", "plant")),
    Name(23, "bush", (70,), ("shrub",), ("foliage",), ("vegetation", "plant", "terrain")),
    Name(24, "hedge", (70,), ("hedgerow",), ("shrub", "foliage"), ("vegetation", "plant", "fence")),
    Name(25, "trunk", (71,), ("tree trunk",), ("bark", "stem"), ("tree",)),
    Name(26, "lawn", (72,), ("grass", "turf"), ("grass field", "meadow"),
         ("terrain", "vegetation", "ground")),
    Name(27, "grass strip", (72,), ("grass", "grass verge", "verge"), ("lawn",),
         ("terrain", "vegetation", "ground")),
    # ---------------------------------------------------------------- objects
    Name(28, "lamp post", (80,), ("street lamp", "lamppost", "street light", "light pole"), (),
         ("pole", "post")),
    Name(29, "sign post", (80,), ("signpost",), ("metal post",), ("pole", "post")),
    Name(30, "traffic sign", (81,), ("road sign", "street sign", "signboard"),
         ("stop sign", "speed limit sign", "yield sign"), ("sign",)),
    # ---------------------------------------------------------------- demo-only objects (raw ids 300+)
    Name(31, "traffic cone", (300,), ("safety cone", "pylon"), ("orange cone",), ("cone",)),
    Name(32, "bench", (301,), ("park bench", "seat"), ("wooden bench",), ("street furniture",)),
    Name(33, "bollard", (302,), ("traffic bollard",), ("short post", "metal post"), ("post",)),
)
# fmt: on
"""The names the demo generator uses (ids 1..99)."""

AGRI_RAW_IDS: Mapping[int, str] = MappingProxyType(
    {1: "tree", 2: "pole", 3: "fence", 4: "wire", 5: "person", 6: "building", 7: "ground"}
)
"""Raw id -> class of the agri-uav domain (``leap synth --domain agri-uav``): the export / ground-truth ids
of ``projects/agri_uav.yaml``. They overlap SemanticKITTI's 0..259 range, so an agri-uav sequence is read
with the agri-uav schema only."""

_AGRI_TREE = ("vegetation", "plant")
# fmt: off
AGRI_VOCABULARY: Final[tuple[Name, ...]] = (
    Name(40, "orchard tree", (1,), ("tree", "fruit tree"), ("tree canopy", "treetop", "foliage"), _AGRI_TREE),
    Name(41, "field tree", (1,), ("tree", "oak tree"), ("tree canopy", "treetop", "foliage"), _AGRI_TREE),
    Name(42, "utility pole", (2,), ("telegraph pole", "power pole"), ("wooden pole",), ("pole", "post")),
    Name(43, "paddock fence", (3,), ("fence", "livestock fence", "farm fence"), ("wooden railing",),
         ("railing", "barrier")),
    Name(44, "power line", (4,), ("wire", "overhead cable", "overhead line", "electric cable"), ("cable",),
         ("line",)),
    Name(45, "farmer", (5,), ("person", "worker", "farm worker"), ("man", "woman"),
         ("human", "people", "pedestrian")),
    Name(46, "barn", (6,), ("farm building", "building"), ("wall",), ("structure", "house")),
    Name(47, "farmhouse", (6,), ("house", "building"), ("facade", "wall"), ("structure",)),
    Name(48, "shed", (6,), ("storage shed", "building"), ("wall",), ("structure", "house")),
    Name(49, "farm roof", (6,), ("roof", "rooftop"), ("tiled roof", "metal roof"), ("building", "house")),
    Name(50, "crop field", (7,), ("field", "cropland", "farmland"), ("crop rows", "crops"),
         ("ground", "terrain", "vegetation")),
    Name(51, "pasture", (7,), ("meadow", "grass", "grassland"), ("grass field",),
         ("ground", "terrain", "field")),
    Name(52, "bare soil", (7,), ("soil", "dirt", "ploughed field"), ("bare ground", "earth"),
         ("ground", "terrain", "field")),
    Name(53, "dirt track", (7,), ("farm track", "dirt road"), ("track",), ("ground", "road")),
)
# fmt: on
"""The names the agri-uav generator uses (ids 40..99; not part of the street demo's :data:`VOCABULARY`)."""

# Generic names of raw SemanticKITTI ids (and the demo extras), for 2D ground truth without a name image.
_GENERIC: Final[dict[int, tuple[str, tuple[str, ...], tuple[str, ...]]]] = {
    # raw id: (name, synonyms, hypernyms)
    10: ("car", ("automobile",), _VEHICLE),
    11: ("bicycle", ("bike",), ("vehicle",)),
    13: ("bus", (), _VEHICLE),
    15: ("motorcycle", ("motorbike",), _VEHICLE),
    16: ("on-rails", ("train", "tram"), _VEHICLE),
    18: ("truck", ("lorry",), _VEHICLE),
    20: ("other-vehicle", (), _VEHICLE),
    30: ("person", ("pedestrian",), ("human", "people")),
    31: ("bicyclist", ("cyclist",), ("person", "human", "people")),
    32: ("motorcyclist", ("biker",), ("person", "human", "people")),
    40: ("road", ("street",), ("ground",)),
    44: ("parking", ("parking lot", "parking space"), ("ground",)),
    48: ("sidewalk", ("footpath",), ("ground",)),
    49: ("other-ground", (), ("ground",)),
    50: ("building", ("house",), ("structure",)),
    51: ("fence", ("railing",), ("barrier",)),
    52: ("other-structure", (), ("structure",)),
    60: ("lane-marking", ("lane marking",), ("road",)),
    70: ("vegetation", ("tree", "bush"), ("plant",)),
    71: ("trunk", ("tree trunk",), ("tree",)),
    72: ("terrain", ("grass",), ("ground",)),
    80: ("pole", (), ("post",)),
    81: ("traffic-sign", ("traffic sign", "road sign"), ("sign",)),
    99: ("other-object", (), ()),
    **{raw: (name, (), ()) for raw, name in DEMO_EXTRA_RAW_IDS.items()},
}
_MOVING: Final = {252: 10, 253: 31, 254: 30, 255: 32, 256: 16, 257: 13, 258: 18, 259: 20}
"""SemanticKITTI moving-* raw id -> its static raw id (same generic name)."""

GENERIC_NAMES: Final[tuple[Name, ...]] = tuple(
    Name(
        GENERIC_NAME_ID_BASE + raw,
        name,
        (raw, *sorted(m for m, s in _MOVING.items() if s == raw)),
        synonyms,
        (),
        hypernyms,
    )
    for raw, (name, synonyms, hypernyms) in sorted(_GENERIC.items())
)
"""The fallback vocabulary: one generic name per raw id (name id = ``GENERIC_NAME_ID_BASE`` + raw id)."""

NAMES_BY_ID: Final[Mapping[int, Name]] = MappingProxyType(
    {n.id: n for n in VOCABULARY + AGRI_VOCABULARY + GENERIC_NAMES}
)
"""Every name (street demo, agri-uav and generic) by its id."""

NAME_IDS: Final[Mapping[str, int]] = MappingProxyType({n.name: n.id for n in VOCABULARY})
"""Demo name -> name id (what the generator writes)."""


AGRI_NAME_IDS: Final[Mapping[str, int]] = MappingProxyType({n.name: n.id for n in AGRI_VOCABULARY})
"""Agri-uav name -> name id."""


def name_id(name: str) -> int:
    """The id of a demo name (street or agri-uav); raises KeyError naming the unknown name."""
    try:
        return NAME_IDS[name] if name in NAME_IDS else AGRI_NAME_IDS[name]
    except KeyError:
        raise KeyError(f"unknown demo name {name!r} (see leap_core/synth/names.py)") from None


def generic_name_ids(raw_semantic: npt.NDArray[np.integer]) -> npt.NDArray[np.uint16]:
    """(H, W) generic name ids of a raw semantic id image; 0 where the raw id has no generic name."""
    lut = np.zeros(1 << 16, np.uint16)
    for n in GENERIC_NAMES:
        for raw in n.raw_ids:
            lut[raw] = n.id
    out: npt.NDArray[np.uint16] = lut[np.asarray(raw_semantic).astype(np.int64) & 0xFFFF]
    return out


def lexicon_digest() -> str:
    """Short hash of the whole vocabulary and lexicon (a labeler fingerprint includes it)."""
    blob = json.dumps(
        [[n.id, n.name, list(n.raw_ids), sorted(n.phrases().items())] for n in NAMES_BY_ID.values()],
        sort_keys=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


@functools.cache
def _phrases(name: Name) -> dict[str, Strength]:
    return name.phrases()


def match(prompt: str, name: Name) -> Strength | None:
    """How strongly ``prompt`` names a region called ``name`` (None: it does not name it)."""
    phrases = _phrases(name)
    q = normalize(prompt)
    if q in phrases:
        return phrases[q]
    if q.endswith("s") and q[:-1] in phrases:  # a plural prompt ("cars") names what its singular names
        return phrases[q[:-1]]
    return None


def _check() -> None:
    both = VOCABULARY + AGRI_VOCABULARY
    ids = [n.id for n in both]
    if len(set(ids)) != len(ids) or not all(0 < i < GENERIC_NAME_ID_BASE for i in ids):
        raise AssertionError("demo name ids must be unique and below GENERIC_NAME_ID_BASE")
    if len({n.name for n in both}) != len(both):
        raise AssertionError("demo names must be unique")


_check()

__all__ = [
    "AGRI_NAME_IDS",
    "AGRI_RAW_IDS",
    "AGRI_VOCABULARY",
    "DEMO_EXTRA_RAW_IDS",
    "GENERIC_NAMES",
    "GENERIC_NAME_ID_BASE",
    "NAMES_BY_ID",
    "NAME_IDS",
    "STRENGTHS",
    "VOCABULARY",
    "Name",
    "Strength",
    "generic_name_ids",
    "lexicon_digest",
    "match",
    "name_id",
    "normalize",
]
