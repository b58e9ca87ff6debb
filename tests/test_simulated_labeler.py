"""The simulated labeler's noise knobs on hand-made 2D ground truth."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from leap_core.datasets.kitti import Calib, KittiSequence, write_calib, write_png16, write_poses, write_scan
from leap_core.errors import LeapError
from leap_core.labelers.simulated import SimulatedLabeler, SimulatedLabelerConfig
from leap_core.schema import ClassDef, Schema

H, W = 48, 64

# Raw ids: 40 road, 48 sidewalk, 72 terrain, 70 vegetation, 10 car, 18 truck, 99 (unmapped).
SCHEMA = Schema(
    name="mini",
    classes=(
        ClassDef("car", (100, 150, 245), ("car",), 10, (10,), "vehicle"),
        ClassDef("truck", (80, 30, 180), ("truck",), 18, (18,), "vehicle"),
        ClassDef("road", (255, 0, 255), ("road",), 40, (40,), "flat"),
        ClassDef("sidewalk", (75, 0, 75), ("sidewalk",), 48, (48,), "flat"),
        ClassDef("vegetation", (0, 175, 0), ("vegetation",), 70, (70,), "nature"),
        ClassDef("terrain", (150, 240, 80), ("terrain",), 72, (72,), "nature"),
    ),
)
CAR, TRUCK, ROAD, SIDEWALK, VEG, TERRAIN = range(6)


def _gt_images(k: int) -> tuple[np.ndarray, np.ndarray]:
    """A street-like label image: vegetation top, terrain strip, road bottom, two cars, one unmapped blob."""
    sem = np.zeros((H, W), np.uint16)
    inst = np.zeros((H, W), np.uint16)
    sem[:16] = 70
    sem[16:24] = 72
    sem[24:40] = 40
    sem[40:] = 48
    sem[30:38, 5 + k : 20 + k] = 10
    inst[30:38, 5 + k : 20 + k] = 1
    sem[26:36, 35:55] = 10
    inst[26:36, 35:55] = 2
    sem[2:6, 50:60] = 99  # unmapped id: must get no mask
    # A second, disconnected terrain region: a separate stuff mask.
    sem[44:47, 2:12] = 72
    return sem, inst


def make_sequence(root: Path, n_frames: int = 3) -> KittiSequence:
    """Smallest valid KITTI folder carrying 2D ground truth (the labeler reads only gt2d)."""
    root.mkdir(parents=True, exist_ok=True)
    p2 = np.array([[50.0, 0, W / 2, 0], [0, 50.0, H / 2, 0], [0, 0, 1, 0]])
    write_calib(root / "calib.txt", Calib(P2=p2, Tr=np.eye(4)))
    write_poses(root / "poses.txt", np.tile(np.eye(4), (n_frames, 1, 1)))
    for i in range(n_frames):
        fid = f"{i:06d}"
        write_scan(root / "velodyne" / f"{fid}.bin", np.zeros((4, 4), np.float32))
        sem, inst = _gt_images(i)
        write_png16(root / "gt2d" / "semantic" / f"{fid}.png", sem)
        write_png16(root / "gt2d" / "instance" / f"{fid}.png", inst)
    return KittiSequence(root)


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> KittiSequence:
    return make_sequence(tmp_path_factory.mktemp("sim_seq"))


def _argmax_image(masks) -> np.ndarray:
    probs = masks.pixel_probs()
    covered = probs.sum(axis=2) > 0
    out = np.where(covered, probs.argmax(axis=2), -1).astype(np.int16)
    return out


def _dilation_radius(got: np.ndarray, src: np.ndarray, radii: range) -> int | None:
    """The smallest radius r in ``radii`` whose elliptical dilation of mask ``src`` is mask ``got`` (None: no
    such r)."""
    for r in radii:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        if np.array_equal(got, cv2.dilate(src.astype(np.uint8), k).astype(bool)):
            return r
    return None


def _frame_regions(frame) -> list:
    """The simulated labeler's ground-truth regions of ``frame``, in its order (no jitter)."""
    from leap_core.labelers.simulated import _name_image, _regions

    return _regions(_name_image(frame, frame.gt2d_semantic), frame.gt2d_instance)


def test_zero_noise_reproduces_ground_truth(seq: KittiSequence) -> None:
    lab = SimulatedLabeler(SimulatedLabelerConfig.exact())
    for frame in seq:
        masks = lab.label(frame, SCHEMA)
        gt = SCHEMA.map_gt(frame.gt2d_semantic.ravel()).reshape(H, W)
        np.testing.assert_array_equal(_argmax_image(masks), gt)
        np.testing.assert_array_equal(masks.confidence, 1.0)
        assert set(np.unique(masks.probs)) <= {0.0, 1.0}
        # 2 cars + vegetation + 2 terrain regions + road + sidewalk; the unmapped blob has no mask.
        assert masks.num_masks == 7
        # Masks partition the mapped pixels: no pixel is covered twice.
        assert masks.dense().sum(axis=0).max() == 1


def test_recall_zero_gives_no_masks(seq: KittiSequence) -> None:
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), recall=0.0)
    masks = SimulatedLabeler(cfg).label(seq.frame(0), SCHEMA)
    assert masks.num_masks == 0
    assert masks.probs.shape == (0, SCHEMA.num_classes)


def test_class_recall_drops_only_that_class(seq: KittiSequence) -> None:
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), class_recall={"car": 0.0, "bus": 0.0})
    masks = SimulatedLabeler(cfg).label(seq.frame(0), SCHEMA)
    assert masks.num_masks == 5
    assert not (masks.probs.argmax(axis=1) == CAR).any()


def test_min_region_drops_small_regions(seq: KittiSequence) -> None:
    # The small terrain strip has 30 pixels, every other region more than 100.
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), min_region_px=31)
    masks = SimulatedLabeler(cfg).label(seq.frame(0), SCHEMA)
    assert masks.num_masks == 6


def test_confusion_moves_mass_to_partner(seq: KittiSequence) -> None:
    frame = seq.frame(0)
    exact = SimulatedLabeler(SimulatedLabelerConfig.exact()).label(frame, SCHEMA)
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), confusion_prob=1.0, peak_prob=(0.8, 0.8))
    confused = SimulatedLabeler(cfg).label(frame, SCHEMA)
    assert confused.num_masks == exact.num_masks
    true = exact.probs.argmax(axis=1)
    pred = confused.probs.argmax(axis=1)
    pairs = {CAR: {TRUCK}, ROAD: {SIDEWALK}, SIDEWALK: {ROAD}, TERRAIN: {VEG}, VEG: {TERRAIN}}
    for t, p, row in zip(true, pred, confused.probs, strict=True):
        assert p in pairs[int(t)]
        assert row[p] == pytest.approx(0.8, abs=1e-6)
        # Half of the remaining mass goes back to the true class (partner_share = 0.5).
        assert row[t] == pytest.approx(0.1, abs=1e-6)
        assert row.sum() == pytest.approx(1.0, abs=1e-6)
    # Same masks (pixels), only the distributions changed.
    np.testing.assert_array_equal(confused.bits, exact.bits)


def test_soft_probabilities_and_confidence_ranges(seq: KittiSequence) -> None:
    cfg = dataclasses.replace(
        SimulatedLabelerConfig.exact(), peak_prob=(0.5, 0.9), confidence=(0.3, 0.9), class_recall={}
    )
    masks = SimulatedLabeler(cfg).label(seq.frame(1), SCHEMA)
    peak = masks.probs.max(axis=1)
    assert ((peak >= 0.5 - 1e-6) & (peak <= 0.9 + 1e-6)).all()
    assert ((masks.confidence >= 0.3) & (masks.confidence <= 0.9)).all()
    np.testing.assert_allclose(masks.probs.sum(axis=1), 1.0, atol=1e-5)
    # No confusion: the peak stays on the true class, so the argmax image is still the ground truth.
    gt = SCHEMA.map_gt(seq.frame(1).gt2d_semantic.ravel()).reshape(H, W)
    np.testing.assert_array_equal(_argmax_image(masks), gt)


def test_bleed_dilates_thing_masks_onto_background(seq: KittiSequence) -> None:
    frame = seq.frame(0)
    exact = SimulatedLabeler(SimulatedLabelerConfig.exact()).label(frame, SCHEMA)
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), bleed_px=3)
    bled = SimulatedLabeler(cfg).label(frame, SCHEMA)
    grow = bled.dense().sum(axis=(1, 2)) - exact.dense().sum(axis=(1, 2))
    is_car = exact.probs.argmax(axis=1) == CAR
    assert (grow[~is_car] == 0).all()  # stuff_bleed_px = 0
    # Each thing mask is its exact mask dilated by an elliptical kernel of some radius 0..bleed_px (clipped
    # to the image), and at least one mask really grew.
    radii = []
    for m in np.flatnonzero(is_car):
        r = _dilation_radius(bled.dense()[m], exact.dense()[m], range(4))
        assert r is not None, f"mask {m} is no dilation of radius 0..3 of its exact mask"
        radii.append(r)
    assert max(radii) > 0 and (grow[is_car] > 0).any()


def test_jitter_shifts_all_masks_together(seq: KittiSequence) -> None:
    frame = seq.frame(0)
    exact = _argmax_image(SimulatedLabeler(SimulatedLabelerConfig.exact()).label(frame, SCHEMA))
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), jitter_px=3.0, seed=5)
    moved = _argmax_image(SimulatedLabeler(cfg).label(frame, SCHEMA))
    assert (moved != exact).any()
    # A pure rigid move: some integer shift of the ground truth matches most pixels again.
    best = max(
        (np.mean(np.roll(exact, (dy, dx), axis=(0, 1))[8:-8, 8:-8] == moved[8:-8, 8:-8]), dy, dx)
        for dy in range(-8, 9)
        for dx in range(-8, 9)
    )
    assert best[0] > 0.97


def test_deterministic_per_seed_and_frame(seq: KittiSequence) -> None:
    lab = SimulatedLabeler(SimulatedLabelerConfig(seed=3))
    forward = [lab.label(f, SCHEMA) for f in seq]
    fresh = SimulatedLabeler(SimulatedLabelerConfig(seed=3))
    backward = [fresh.label(f, SCHEMA) for f in reversed(list(seq))]
    for a, b in zip(forward, reversed(backward), strict=True):
        np.testing.assert_array_equal(a.bits, b.bits)
        np.testing.assert_array_equal(a.probs, b.probs)
        np.testing.assert_array_equal(a.confidence, b.confidence)
    other = SimulatedLabeler(SimulatedLabelerConfig(seed=4)).label(seq.frame(0), SCHEMA)
    same = np.array_equal(other.probs, forward[0].probs) and np.array_equal(other.bits, forward[0].bits)
    assert not same


def test_fingerprint_tracks_config_and_schema() -> None:
    a = SimulatedLabeler(SimulatedLabelerConfig()).fingerprint(SCHEMA)
    assert a == SimulatedLabeler(SimulatedLabelerConfig()).fingerprint(SCHEMA)
    assert a != SimulatedLabeler(SimulatedLabelerConfig(recall=0.5)).fingerprint(SCHEMA)
    renamed = SCHEMA.with_classes(
        [dataclasses.replace(SCHEMA.classes[0], name="automobile"), *SCHEMA.classes[1:]]
    )
    assert a != SimulatedLabeler(SimulatedLabelerConfig()).fingerprint(renamed)
    recolored = SCHEMA.with_classes(
        [dataclasses.replace(SCHEMA.classes[0], color=(1, 2, 3)), *SCHEMA.classes[1:]]
    )
    assert a == SimulatedLabeler(SimulatedLabelerConfig()).fingerprint(recolored)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"recall": 1.5}, ("recall",)),
        ({"peak_prob": (0.9, 0.5)}, ("peak_prob",)),
        ({"bleed_px": -1}, ("bleed_px",)),
        ({"jitter_deg": -1.0}, ("jitter_deg",)),
        ({"class_recall": {"car": 2.0}}, ("class_recall", "car")),
        ({"confusion_pairs": (("car", "car"),)}, ("confusion_pairs",)),
    ],
)
def test_config_validation_names_field(kwargs: dict, field: tuple[str, ...]) -> None:
    with pytest.raises(LeapError) as err:
        SimulatedLabelerConfig(**kwargs)
    assert err.value.field == field and str(err.value).startswith(".".join(field) + ": ")


def test_missing_gt2d_is_a_clear_error(tmp_path: Path) -> None:
    seq = make_sequence(tmp_path / "s", n_frames=1)
    (tmp_path / "s" / "gt2d" / "instance" / "000000.png").unlink()
    with pytest.raises(LeapError, match=r"000000\.png"):
        SimulatedLabeler().label(seq.frame(0), SCHEMA)


def test_misses_persist_within_a_block_of_frames(tmp_path: Path) -> None:
    seq = make_sequence(tmp_path / "s", n_frames=6)
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), recall=0.5, persistence_frames=3, seed=1)
    lab = SimulatedLabeler(cfg)

    def kept_cars(i: int) -> tuple[int, ...]:
        masks = lab.label(seq.frame(i), SCHEMA)
        # Car instances sit at fixed rows: instance 1 spans rows 30-37, instance 2 rows 26-35.
        dense = masks.dense()[masks.probs.argmax(axis=1) == CAR]
        return tuple(sorted(int(np.flatnonzero(m.any(axis=1))[0]) for m in dense))

    def kept_classes(i: int) -> list[int]:
        return sorted(lab.label(seq.frame(i), SCHEMA).probs.argmax(axis=1).tolist())

    for block in ((0, 1, 2), (3, 4, 5)):
        assert len({kept_cars(i) for i in block}) == 1
        assert len({tuple(kept_classes(i)) for i in block}) == 1
    # Over many seeds the kept share approaches the recall.
    cfg1 = dataclasses.replace(cfg, persistence_frames=1)
    counts = [
        SimulatedLabeler(dataclasses.replace(cfg1, seed=s)).label(seq.frame(0), SCHEMA).num_masks
        for s in range(40)
    ]
    assert 0.35 < np.mean(counts) / 7 < 0.65


# ------------------------------------------------------------------------------ prompts and names
def _named_sequence(root: Path, n_frames: int = 1) -> KittiSequence:
    """A sequence with a ``gt2d/name`` folder: 12 vans (instances 1..12) on asphalt, a lawn strip on top,
    a hedge at the left edge."""
    from leap_core.synth.names import name_id

    root.mkdir(parents=True, exist_ok=True)
    p2 = np.array([[50.0, 0, W / 2, 0], [0, 50.0, H / 2, 0], [0, 0, 1, 0]])
    write_calib(root / "calib.txt", Calib(P2=p2, Tr=np.eye(4)))
    write_poses(root / "poses.txt", np.tile(np.eye(4), (n_frames, 1, 1)))
    sem = np.full((H, W), 40, np.uint16)
    names = np.full((H, W), name_id("asphalt"), np.uint16)
    inst = np.zeros((H, W), np.uint16)
    sem[:10], names[:10] = 72, name_id("lawn")
    sem[10:, :4], names[10:, :4] = 70, name_id("hedge")
    for k in range(12):
        y, x = 12 + (k // 6) * 16, 6 + (k % 6) * 10
        sem[y : y + 10, x : x + 8], names[y : y + 10, x : x + 8], inst[y : y + 10, x : x + 8] = (
            10,
            name_id("van"),
            k + 1,
        )
    for i in range(n_frames):
        fid = f"{i:06d}"
        write_scan(root / "velodyne" / f"{fid}.bin", np.zeros((4, 4), np.float32))
        write_png16(root / "gt2d" / "semantic" / f"{fid}.png", sem)
        write_png16(root / "gt2d" / "instance" / f"{fid}.png", inst)
        write_png16(root / "gt2d" / "name" / f"{fid}.png", names)
    return KittiSequence(root)


def _schema(**prompts: tuple[str, ...]) -> Schema:
    """The mini schema with some classes' prompts replaced."""
    return SCHEMA.with_classes(
        [dataclasses.replace(c, prompts=prompts.get(c.name, c.prompts)) for c in SCHEMA.classes]
    )


def test_a_region_gets_a_mask_only_when_a_prompt_names_it(tmp_path: Path) -> None:
    seq = _named_sequence(tmp_path / "s")
    frame = seq.frame(0)
    exact = SimulatedLabeler(SimulatedLabelerConfig.exact())
    # "car" names a van only loosely, but alone it names it (and "truck" too: the two compete).
    masks = exact.label(frame, SCHEMA)
    classes = masks.probs.argmax(axis=1)
    assert (classes == CAR).sum() + (classes == TRUCK).sum() == 12
    # Prompts that name nothing find nothing.
    useless = _schema(
        car=("spaceship",),
        truck=("zeppelin",),
        road=("ocean",),
        sidewalk=("glacier",),
        vegetation=("cloud",),
        terrain=("moon",),
    )
    assert exact.label(frame, useless).num_masks == 0
    # Without a name image, every pixel is named by its raw id's generic name ("car" for raw id 10).
    generic = exact.label(make_sequence(tmp_path / "g", 1).frame(0), _schema(car=("van",)))
    assert not (generic.probs.argmax(axis=1) == CAR).any()


def test_prompts_of_two_classes_that_name_a_region_compete(tmp_path: Path) -> None:
    """A van is loosely both "car" and "truck": with only those prompts the two classes split the vans; the
    helper prompt "van" names them strongly and car wins nearly every one (the paper's prompt expansion)."""
    seq = _named_sequence(tmp_path / "s")
    frame = seq.frame(0)

    def car_share(schema: Schema) -> float:
        wins = []
        for seed in range(8):
            cfg = dataclasses.replace(SimulatedLabelerConfig.exact(seed=seed), match_temperature=0.1)
            cfg = dataclasses.replace(cfg, match_confidence=SimulatedLabelerConfig().match_confidence)
            masks = SimulatedLabeler(cfg).label(frame, schema)
            cls = masks.probs.argmax(axis=1)
            vehicles = cls[(cls == CAR) | (cls == TRUCK)]
            assert vehicles.size == 12
            wins.append(float(np.mean(vehicles == CAR)))
        return float(np.mean(wins))

    assert 0.3 < car_share(SCHEMA) < 0.7
    assert car_share(_schema(car=("car", "van"))) > 0.95  # exact beats hypernym e^5.5 : 1 at T = 0.1
    # The loser of a competition takes the partner share of the winner's distribution.
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), peak_prob=(0.8, 0.8))
    masks = SimulatedLabeler(cfg).label(frame, SCHEMA)
    vans = masks.probs[(masks.probs.argmax(axis=1) == CAR) | (masks.probs.argmax(axis=1) == TRUCK)]
    np.testing.assert_allclose(np.sort(vans[:, [CAR, TRUCK]], axis=1), [[0.1, 0.8]] * 12, atol=1e-6)


def test_match_strength_sets_detection_and_confidence(tmp_path: Path) -> None:
    seq = _named_sequence(tmp_path / "s")
    frame = seq.frame(0)
    base = SimulatedLabelerConfig.exact()
    cfg = dataclasses.replace(
        base,
        match_detection={"exact": 1.0, "synonym": 1.0, "descriptive": 1.0, "hypernym": 0.0},
        match_confidence={"exact": 1.0, "synonym": 0.8, "descriptive": 0.6, "hypernym": 0.4},
    )
    lab = SimulatedLabeler(cfg)
    # "vegetation" names the hedge only as a hypernym: never detected at detection 0.
    assert not (lab.label(frame, SCHEMA).probs.argmax(axis=1) == VEG).any()
    masks = lab.label(frame, _schema(vegetation=("hedge",), terrain=("grass",), car=("minivan",)))
    cls = masks.probs.argmax(axis=1)
    assert masks.confidence[cls == VEG].tolist() == [1.0]  # exact
    assert masks.confidence[cls == TERRAIN].tolist() == pytest.approx([0.8])  # synonym
    assert masks.confidence[cls == CAR].tolist() == pytest.approx([0.8] * 12)


def test_negative_prompt_that_names_a_region_more_strongly_rules_the_class_out(tmp_path: Path) -> None:
    seq = _named_sequence(tmp_path / "s")
    lab = SimulatedLabeler(SimulatedLabelerConfig.exact())
    schema = SCHEMA.with_classes(
        [
            dataclasses.replace(c, negative_prompts=("minivan",)) if c.name == "car" else c
            for c in SCHEMA.classes
        ]
    )
    cls = lab.label(seq.frame(0), schema).probs.argmax(axis=1)
    assert (cls == TRUCK).sum() == 12 and not (cls == CAR).any()


def test_editing_prompts_changes_the_fingerprint() -> None:
    lab = SimulatedLabeler(SimulatedLabelerConfig())
    a = lab.fingerprint(SCHEMA)
    assert a != lab.fingerprint(_schema(car=("car", "van")))
    negative = SCHEMA.with_classes(
        [
            dataclasses.replace(c, negative_prompts=("minivan",)) if c.name == "car" else c
            for c in SCHEMA.classes
        ]
    )
    assert a != lab.fingerprint(negative)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"match_detection": {"exact": 1.0}}, ("match_detection",)),
        (
            {"match_confidence": {"exact": 1.0, "synonym": 1.0, "descriptive": 1.0, "hypernym": 0.0}},
            ("match_confidence", "hypernym"),
        ),
        ({"match_temperature": -0.1}, ("match_temperature",)),
    ],
)
def test_match_config_validation_names_field(kwargs: dict, field: tuple[str, ...]) -> None:
    with pytest.raises(LeapError) as err:
        SimulatedLabelerConfig(**kwargs)
    assert err.value.field == field


def test_unknown_name_ids_are_a_clear_error(tmp_path: Path) -> None:
    seq = _named_sequence(tmp_path / "s")
    write_png16(tmp_path / "s" / "gt2d" / "name" / "000000.png", np.full((H, W), 999, np.uint16))
    with pytest.raises(LeapError, match=r"name.000000\.png: unknown name ids \[999\]"):
        SimulatedLabeler().label(seq.frame(0), SCHEMA)


_PROBS = ("recall", "confusion_prob", "partner_share")
_NON_NEGATIVE = (
    "min_region_px",
    "bleed_px",
    "stuff_bleed_px",
    "jitter_px",
    "jitter_deg",
    "match_temperature",
)
_ONES = {"exact": 1.0, "synonym": 1.0, "descriptive": 1.0, "hypernym": 1.0}


def _accepted(**kwargs: object) -> None:
    SimulatedLabelerConfig(**kwargs)  # raises if refused


def _refused(field: tuple[str, ...], **kwargs: object) -> str:
    with pytest.raises(LeapError) as err:
        SimulatedLabelerConfig(**kwargs)
    assert err.value.field == field, (kwargs, err.value.field)
    return str(err.value)


def test_config_validation_edges_of_every_range() -> None:
    """Each range's ends are accepted and the values just outside are refused, field by field (a check
    with ``<`` for ``<=``, or the wrong field, fails here)."""
    for name in _PROBS:
        _accepted(**{name: 0.0})
        _accepted(**{name: 1.0})
        _refused((name,), **{name: -0.01})
        _refused((name,), **{name: 1.01})
    _accepted(class_recall={"car": 0.0, "road": 1.0})
    _refused(("class_recall", "car"), class_recall={"road": 0.5, "car": -0.01})
    _refused(("class_recall", "car"), class_recall={"car": 1.01})
    for name in ("peak_prob", "confidence"):
        for ok in ((1.0, 1.0), (0.5, 0.5), (1e-9, 1.0)):
            _accepted(**{name: ok})
        for bad in ((0.0, 0.5), (0.6, 0.5), (0.5, 1.01)):
            _refused((name,), **{name: bad})
    _accepted(dirichlet_alpha=1e-9)
    _refused(("dirichlet_alpha",), dirichlet_alpha=0.0)
    _refused(("dirichlet_alpha",), dirichlet_alpha=float("nan"))
    _accepted(persistence_frames=1)
    _refused(("persistence_frames",), persistence_frames=0)
    for name in _NON_NEGATIVE:
        _accepted(**{name: 0})
        _refused((name,), **{name: -1})


def test_strength_tables_need_the_four_strengths_in_range() -> None:
    """``match_detection`` takes [0, 1], ``match_confidence`` (0, 1]; both need exactly the four strengths,
    and the message lists the keys given ("none" for an empty table)."""
    _accepted(match_detection={**_ONES, "hypernym": 0.0}, match_confidence=_ONES)
    _refused(("match_detection", "hypernym"), match_detection={**_ONES, "hypernym": -0.01})
    _refused(("match_detection", "exact"), match_detection={**_ONES, "exact": 1.01})
    _refused(("match_confidence", "hypernym"), match_confidence={**_ONES, "hypernym": 0.0})
    _refused(("match_confidence", "exact"), match_confidence={**_ONES, "exact": 1.01})
    _accepted(match_confidence={**_ONES, "exact": 1e-9})
    assert _refused(("match_detection",), match_detection={}).endswith("got none")
    msg = _refused(("match_confidence",), match_confidence={**_ONES, "fuzzy": 1.0})
    assert msg.endswith("got exact, synonym, descriptive, hypernym, fuzzy")


def test_confusion_pairs_need_two_different_names() -> None:
    _accepted(confusion_pairs=(("car", "truck"),))
    _refused(("confusion_pairs",), confusion_pairs=(("car", "truck", "road"),))
    _refused(("confusion_pairs",), confusion_pairs=(("car", "truck"), ("road",)))
    _refused(("confusion_pairs",), confusion_pairs=(("car", "truck"), ("road", "road")))


def _exact(**kw: object) -> SimulatedLabeler:
    """The labeler with every noise knob off but those given."""
    return SimulatedLabeler(dataclasses.replace(SimulatedLabelerConfig.exact(), **kw))


def test_regions_no_prompt_names_are_skipped_and_the_rest_labeled(seq: KittiSequence) -> None:
    # The car regions come first (thing regions precede stuff); with no prompt naming them, the regions after
    # them still get their masks.
    frame = seq.frame(0)
    full = _argmax_image(_exact().label(frame, SCHEMA))
    got = _argmax_image(_exact().label(frame, _schema(car=("zebra",))))
    assert (full == CAR).any() and not (got == CAR).any()
    np.testing.assert_array_equal(got[full != CAR], full[full != CAR])


def test_min_region_px_keeps_a_region_of_exactly_that_size(seq: KittiSequence) -> None:
    # The smallest region of frame 0 is the second terrain strip, 3 x 10 pixels.
    frame = seq.frame(0)
    n = _exact().label(frame, SCHEMA).num_masks
    assert _exact(min_region_px=30).label(frame, SCHEMA).num_masks == n
    assert _exact(min_region_px=31).label(frame, SCHEMA).num_masks == n - 1


def test_unnamed_pixels_of_a_name_image_are_no_region(tmp_path: Path) -> None:
    # Name id 0 (no name, e.g. sky) is allowed in gt2d/name and gets no mask; the named pixels are labeled.
    from leap_core.datasets.kitti import read_png16

    seq = _named_sequence(tmp_path / "s")
    path = tmp_path / "s" / "gt2d" / "name" / "000000.png"
    names = read_png16(path)
    names[:4] = 0
    write_png16(path, names)
    got = _argmax_image(_exact().label(seq.frame(0), _schema(terrain=("lawn",), road=("asphalt",))))
    assert (got[:4] == -1).all() and (got[4:10] == TERRAIN).all() and (got[10:, 4:] >= 0).all()


def test_the_rival_class_takes_the_second_share(tmp_path: Path) -> None:
    # Every van is named loosely by "car" and by "truck": the class that loses the competition gets the
    # partner share (0.5 of the 0.4 left by a 0.6 peak), also with no confusion pairs at all.
    frame = _named_sequence(tmp_path / "s").frame(0)
    lab = _exact(confusion_pairs=(), peak_prob=(0.6, 0.6), partner_share=0.5)
    probs = lab.label(frame, SCHEMA).probs
    vans = probs[np.isin(probs.argmax(axis=1), [CAR, TRUCK])]
    assert len(vans) == 12
    rival = np.where(vans.argmax(axis=1) == CAR, vans[:, TRUCK], vans[:, CAR])
    assert (rival >= 0.2 - 1e-6).all(), rival


def _one_frame(root: Path, sem: np.ndarray, inst: np.ndarray) -> KittiSequence:
    make_sequence(root, n_frames=1)
    write_png16(root / "gt2d" / "semantic" / "000000.png", sem)
    write_png16(root / "gt2d" / "instance" / "000000.png", inst)
    return KittiSequence(root)


# ================================================================================== instances
def _instance_frame(root: Path, n_frames: int = 1) -> KittiSequence:
    """Two touching cars (ids 1, 2), a truck touching car 2 (id 3), a lone car (id 4), a road pixel block
    with an instance id (a stuff class: no instance), in each of ``n_frames`` frames."""
    sem, inst = np.full((H, W), 40, np.uint16), np.zeros((H, W), np.uint16)
    for ident, raw, rows, cols in (
        (1, 10, (10, 20), (2, 12)),
        (2, 10, (10, 20), (12, 22)),
        (3, 18, (10, 20), (22, 40)),
        (4, 10, (30, 40), (44, 60)),
        (5, 40, (42, 46), (2, 8)),
    ):
        sem[rows[0] : rows[1], cols[0] : cols[1]] = raw
        inst[rows[0] : rows[1], cols[0] : cols[1]] = ident
    make_sequence(root, n_frames=n_frames)
    for i in range(n_frames):
        write_png16(root / "gt2d" / "semantic" / f"{i:06d}.png", sem)
        write_png16(root / "gt2d" / "instance" / f"{i:06d}.png", inst)
    return KittiSequence(root)


def _instances(seq: KittiSequence, **kw: object):
    cfg = dataclasses.replace(SimulatedLabelerConfig.exact(), **kw)
    ins = SimulatedLabeler(cfg).label(seq.frame(0), SCHEMA).instances
    assert ins is not None
    return ins


def _parts(ins) -> list[tuple[int, tuple[int, int, int, int]]]:
    """(class, box rows0, rows1, cols0, cols1) of each instance, sorted."""
    out = []
    for k in range(1, ins.num_instances + 1):
        ys, xs = np.nonzero(ins.ids == k)
        out.append(
            (int(ins.label[k - 1]), (int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1))
        )
    return sorted(out)


def test_exact_instances_are_the_thing_instances_of_the_ground_truth(tmp_path: Path) -> None:
    ins = _instances(_instance_frame(tmp_path / "s"))
    assert _parts(ins) == [
        (CAR, (10, 20, 2, 12)),
        (CAR, (10, 20, 12, 22)),
        (CAR, (30, 40, 44, 60)),
        (TRUCK, (10, 20, 22, 40)),
    ]  # the road block's id is stuff: no instance
    np.testing.assert_array_equal(ins.score, 1.0)
    assert ins.ids.dtype == np.int32 and ins.ids.shape == (H, W)


def test_instance_misses_merges_and_splits(tmp_path: Path) -> None:
    seq = _instance_frame(tmp_path / "s")
    assert _instances(seq, instance_miss=1.0).num_instances == 0
    # Touching cars merge; the truck touches car 2 but is another class; the lone car stays alone.
    assert _parts(_instances(seq, instance_merge=1.0)) == [
        (CAR, (10, 20, 2, 22)),
        (CAR, (30, 40, 44, 60)),
        (TRUCK, (10, 20, 22, 40)),
    ]
    # Each cut at the middle of its longer side: the 10 × 16 lone car at column 52, the 10 × 18 truck at 31.
    split = _parts(_instances(seq, instance_split=1.0))
    assert (CAR, (30, 40, 44, 52)) in split and (CAR, (30, 40, 52, 60)) in split
    assert (TRUCK, (10, 20, 22, 31)) in split and (TRUCK, (10, 20, 31, 40)) in split
    assert len(split) == 8
    # A tall instance is cut across its rows.
    sem, inst = np.full((H, W), 40, np.uint16), np.zeros((H, W), np.uint16)
    sem[4:44, 30:34], inst[4:44, 30:34] = 10, 7
    tall = _one_frame(tmp_path / "t", sem, inst)
    assert _parts(_instances(tall, instance_split=1.0)) == [(CAR, (4, 24, 30, 34)), (CAR, (24, 44, 30, 34))]


def test_instance_noise_draws_per_frame_and_apart_from_each_other(tmp_path: Path) -> None:
    """Half rates over many frames: each term acts on some frames only, and setting one term leaves the
    outcome of another unchanged (their draws are their own)."""
    frames = list(_instance_frame(tmp_path / "s", n_frames=12))

    def counts(**kw: object) -> list[int]:
        lab = SimulatedLabeler(dataclasses.replace(SimulatedLabelerConfig.exact(), **kw))
        return [lab.label(f, SCHEMA).instances.num_instances for f in frames]

    missed = counts(instance_miss=0.5)
    assert len(set(missed)) > 1 and max(missed) <= 4
    assert counts(instance_miss=0.5) == missed  # seeded by (seed, frame number)
    merged = counts(instance_merge=0.5)
    assert set(merged) <= {3, 4} and len(set(merged)) == 2
    both = counts(instance_miss=0.5, instance_split=1.0)
    assert both == [2 * m for m in missed]  # the same objects missed, each kept one cut in two
    # Split draws of their own: kept objects (miss draw ≥ 0.5) are cut on some frames (with the miss
    # draws reused, none would be).
    half = counts(instance_miss=0.5, instance_split=0.5)
    assert all(m <= h <= 2 * m for h, m in zip(half, missed, strict=True)) and half != missed


def test_instances_leave_the_semantic_masks_as_they_were(seq: KittiSequence) -> None:
    """The default labeler's masks, probabilities and confidences of the module's frames are those recorded
    before instances existed (their noise has its own stream), whatever the instance terms."""
    import hashlib

    for cfg in (
        SimulatedLabelerConfig(),
        SimulatedLabelerConfig(instance_miss=0.7, instance_merge=1.0, instance_split=1.0),
    ):
        h = hashlib.sha256()
        for f in seq:
            sm = SimulatedLabeler(cfg).label(f, SCHEMA)
            for a in (sm.bits, sm.probs, sm.confidence):
                h.update(a.tobytes())
        assert h.hexdigest()[:16] == "f1c89981a9f11029"


def test_instance_terms_enter_the_fingerprint_only_off_their_defaults() -> None:
    from leap_core.labelers.simulated import _INSTANCE_DEFAULTS

    default = SimulatedLabelerConfig()
    assert {k: getattr(default, k) for k in _INSTANCE_DEFAULTS} == _INSTANCE_DEFAULTS
    fp = SimulatedLabeler().fingerprint(SCHEMA)
    assert "instance_miss" not in SimulatedLabeler().fingerprint_config()
    for name in _INSTANCE_DEFAULTS:
        other = SimulatedLabeler(dataclasses.replace(default, **{name: 0.5}))
        assert other.fingerprint(SCHEMA) != fp
