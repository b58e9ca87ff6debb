"""The lab's ``simulated-paper`` labeler (lab/paper_labeler.py): its noise terms (hand-computed cases and
their effect on the masks), its presets, its registration and config section, and that with the same
settings it gives the masks of the simulated labeler's former ``paper`` preset, byte for byte."""

from __future__ import annotations

import dataclasses
import math
from fractions import Fraction
from pathlib import Path

import labfixtures
import numpy as np
import pytest

from lab.paper_labeler import (
    LABELER,
    SimulatedPaperConfig,
    SimulatedPaperLabeler,
    _pick,
    adjacent_partner,
    box_gaps,
    box_leak_crop,
    confusion_targets,
    lattice_draws,
    size_recall,
    tile_split,
    world_tile_draws,
)
from leap_core.config import config_from_dict, config_to_dict
from leap_core.datasets.kitti import KittiSequence, write_png16
from leap_core.errors import ConfigError, LeapError
from leap_core.labelers import LABELERS, make_labeler
from leap_core.labelers.simulated import (
    MOVED_TERMS,
    Region,
    SimulatedLabeler,
    SimulatedLabelerConfig,
    object_draws,
)
from leap_core.presets import load_preset
from tests.test_simulated_labeler import (
    CAR,
    ROAD,
    SCHEMA,
    SIDEWALK,
    TRUCK,
    H,
    W,
    _argmax_image,
    _dilation_radius,
    _frame_regions,
    _one_frame,
    make_sequence,
)
from tests.test_simulated_presets import _masks_digest

lab_labeler = labfixtures.lab_labeler  # registers the lab's labeler for each test here

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> KittiSequence:
    return make_sequence(tmp_path_factory.mktemp("paper_seq"))


def _lab(**kw: object) -> SimulatedPaperLabeler:
    """The lab's labeler with every noise knob off but those given."""
    return SimulatedPaperLabeler(dataclasses.replace(SimulatedPaperConfig.exact(), **kw))


# ------------------------------------------------------------------------------ the same masks as before
def test_with_every_term_off_its_masks_are_the_product_labelers(seq: KittiSequence) -> None:
    # The terms draw only when on, from streams of their own: off, the lab's labeler is the product's.
    for cfg in (SimulatedLabelerConfig(seed=7), SimulatedLabelerConfig.exact(seed=2)):
        product, paper = (
            SimulatedLabeler(cfg),
            SimulatedPaperLabeler(SimulatedPaperConfig.from_simulated(cfg)),
        )
        assert _masks_digest(paper, seq) == _masks_digest(product, seq)
    assert SimulatedPaperConfig.from_simulated(SimulatedLabelerConfig()) == SimulatedPaperConfig()


def test_tiled_stuff_masks_are_those_of_the_former_simulated_labeler(seq: KittiSequence) -> None:
    # Pinned when these terms were part of the simulated labeler (default settings, seed 7, tiled road and
    # terrain): each part of a split region draws its probabilities from a generator of its own.
    cfg = SimulatedPaperConfig(seed=7, class_confusion={"road": 0.5, "terrain": 0.5}, stuff_tile_px=8)
    assert _masks_digest(SimulatedPaperLabeler(cfg), seq) == "58fef08ec0fffaee"


# ---------------------------------------------------------------------------- registry and config section
def test_importing_the_lab_registers_its_labeler_with_its_config_section() -> None:
    assert LABELERS["simulated-paper"] is LABELER
    assert (LABELER.section, LABELER.config_type, LABELER.presets) == (
        "simulated_paper",
        SimulatedPaperConfig,
        ("default", "paper"),
    )
    cfg = config_from_dict({"labeler": "simulated-paper", "simulated_paper": {"preset": "paper", "seed": 3}})
    assert cfg.labeler_config(SimulatedPaperConfig) == dataclasses.replace(
        SimulatedPaperConfig.from_preset("paper"), seed=3
    )
    # The product's section is untouched, and the dict form has the lab's section beside it.
    assert cfg.labeler_config(SimulatedLabelerConfig) == SimulatedLabelerConfig()
    d = config_to_dict(cfg)
    assert list(d)[:5] == ["labeler", "simulated", "grounded_sam", "sam3", "simulated_paper"]
    assert config_from_dict(d) == cfg
    labeler = make_labeler(cfg)
    assert isinstance(labeler, SimulatedPaperLabeler) and labeler.cfg.seed == 3


def test_the_lab_section_holds_the_terms_the_simulated_section_no_longer_does() -> None:
    # Every moved term is a field of the lab's config, off by default at the value leap_core accepts in a
    # stored simulated section.
    product = {f.name for f in dataclasses.fields(SimulatedLabelerConfig)}
    lab_only = {f.name: f for f in dataclasses.fields(SimulatedPaperConfig) if f.name not in product}
    assert set(lab_only) == set(MOVED_TERMS)
    defaults = SimulatedPaperConfig()
    assert {name: getattr(defaults, name) for name in lab_only} == MOVED_TERMS
    # So a dict that sets one in the lab's section is read, the same value in the simulated section is not.
    cfg = config_from_dict({"simulated_paper": {"box_leak_prob": 0.2}})
    assert cfg.labeler_config(SimulatedPaperConfig).box_leak_prob == 0.2
    with pytest.raises(ConfigError) as err:
        config_from_dict({"simulated": {"box_leak_prob": 0.2}})
    assert err.value.field == ("pipeline", "simulated", "box_leak_prob")


def test_project_file_and_lab_cli_pick_the_paper_preset(tmp_path: Path) -> None:
    from app.cli import _run_config

    project = tmp_path / "p.yaml"
    base = ROOT / "projects" / "semantickitti.yaml"
    extra = "\npipeline:\n  labeler: simulated-paper\n  simulated_paper:\n    preset: paper\n"
    project.write_text(base.read_text() + extra)
    paper = SimulatedPaperConfig.from_preset("paper")
    loaded = load_preset(project).pipeline
    assert loaded.labeler == "simulated-paper" and loaded.labeler_config(SimulatedPaperConfig) == paper
    _, cfg = _run_config("semantickitti", None, "simulated-paper", None, None, "paper")
    assert cfg.labeler == "simulated-paper" and cfg.labeler_config(SimulatedPaperConfig) == paper
    # --labeler-preset names a preset of the chosen labeler's section: the product's has no "paper".
    with pytest.raises(ConfigError, match=r"pipeline\.simulated\.preset: unknown preset 'paper'"):
        _run_config("semantickitti", None, "simulated", None, None, "paper")


def test_unknown_preset_lists_the_labs_presets() -> None:
    with pytest.raises(ConfigError, match=r"unknown preset 'x' \(known: 'default', 'paper'\)") as err:
        config_from_dict({"simulated_paper": {"preset": "x"}})
    assert err.value.field == ("pipeline", "simulated_paper", "preset")


def test_lab_run_gives_the_former_paper_presets_2d_labels(tmp_path: Path) -> None:
    # `python -m lab run` is the leap CLI with the lab's labeler: a run of it writes the 2D labels of the
    # labeler with the paper preset, frame by frame.
    import subprocess
    import sys

    from leap_core.labelers.base import SoftMasks
    from tests.test_pipeline import make_street

    street = make_street(tmp_path / "sequences" / "00", n_frames=2)
    out = tmp_path / "run"
    args = [
        "run",
        str(street),
        "--labeler",
        "simulated-paper",
        "--labeler-preset",
        "paper",
        "--out",
        str(out),
    ]
    done = subprocess.run(
        [sys.executable, "-m", "lab", *args, "--no-3dcn"],
        check=False,
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    lab = SimulatedPaperLabeler(SimulatedPaperConfig.from_preset("paper"))
    seq = KittiSequence(street)
    schema = load_preset(ROOT / "projects" / "semantickitti.yaml").schema
    for frame in seq:
        got = SoftMasks.load(out / "sequences" / "00" / "labels2d" / f"{frame.frame_id}.npz")
        want = lab.label(frame, schema)
        assert got.bits.tobytes() == want.bits.tobytes() and got.probs.tobytes() == want.probs.tobytes()
    # The product's own CLI does not know the lab's labeler.
    done = subprocess.run(
        [sys.executable, "-m", "app.cli", *args], check=False, cwd=ROOT, capture_output=True, text=True
    )
    assert done.returncode != 0 and "simulated-paper" in done.stderr + done.stdout


# ------------------------------------------------------------------------------------- the paper preset


def test_paper_preset_output_is_unchanged(tmp_path: Path) -> None:
    # The paper preset is fitted to the paper's error rates (benchmarks/fit_labeler.py): a change in which
    # draw decides a leak, a merge, a tile or a confusion target moves its masks and so its calibration.
    # Refit the preset, and then update this digest, when that is meant. (It reads world cells: A.7, 13.)
    lab = SimulatedPaperLabeler(dataclasses.replace(SimulatedPaperConfig.from_preset("paper"), seed=7))
    assert _masks_digest(lab, _world_sequence(tmp_path, 3)) == "73c3cb74fd3bbc37"


def test_lattice_draws_hand_computed() -> None:
    # frac(0.1 + k·0.25 + 2·0.5) for k = 0..3.
    np.testing.assert_allclose(lattice_draws([0, 1, 2, 3], 2, 0.1, (0.25, 0.5)), [0.1, 0.35, 0.6, 0.85])
    # With irrational steps the share below q is close to q along keys and along blocks: 40 objects x 12
    # blocks at q = 0.3 give 11-13 hits per block (12 expected) and 3-5 per object (3.6).
    steps = (2**0.5 % 1.0, 3**0.5 % 1.0)
    hits = np.array([lattice_draws(np.arange(1, 41), b, 0.37, steps) for b in range(12)]) < 0.3
    assert set(hits.sum(axis=1)) <= {11, 12, 13} and set(hits.sum(axis=0)) <= {3, 4, 5}
    # Large keys and blocks (instance ids up to 65535) against exact rational arithmetic on the same floats.
    exact = (Fraction(0.999) + 65535 * Fraction(steps[0]) + 10**6 * Fraction(steps[1])) % 1
    assert float(lattice_draws([65535], 10**6, 0.999, steps)[0]) == pytest.approx(float(exact), abs=1e-9)


def _confused(tmp_path: Path, strat: bool, **kw: object) -> list[list[int]]:
    """Per labeler seed 0-9, the predicted class of every car mask of a 12-frame sequence (two cars) with
    car confused half the time, drawn anew in every frame."""
    seq = make_sequence(tmp_path / f"twelve_{strat}", n_frames=12)
    out = []
    for seed in range(10):
        lab = _lab(
            seed=seed, class_confusion={"car": 0.5}, persistence_frames=1, stratified_draws=strat, **kw
        )
        preds = []
        for f in seq:
            m = lab.label(f, SCHEMA)
            # The car masks are the first two (thing regions come first); stuff masks are never cars.
            preds += [int(c) for c in m.probs.argmax(1)[:2]]
        out.append(preds)
    return out


def test_stratified_draws_keep_the_confused_share_near_the_rate(tmp_path: Path) -> None:
    pairs = {"confusion_pairs": (("car", "truck"),)}
    strat = [sum(c == TRUCK for c in p) for p in _confused(tmp_path, True, **pairs)]
    indep = [sum(c == TRUCK for c in p) for p in _confused(tmp_path, False, **pairs)]
    # 24 car masks at rate 0.5: 12 expected. Stratified, every seed lands within one of it; independent
    # draws spread as a binomial (std 2.4; 8-15 over these seeds).
    assert all(abs(n - 12) <= 1 for n in strat), strat
    assert max(indep) - min(indep) >= 4, indep


def test_stratified_draws_of_one_object_are_independent_across_decisions(tmp_path: Path) -> None:
    # A confused car takes truck or sidewalk with equal weight. The target draw has a lattice of its own;
    # were it the confusion's lattice shifted by a phase, the confused cars (u < 0.5) would have their
    # target draws in one half-width window and take mostly one target for a given seed.
    preds = _confused(
        tmp_path,
        True,
        confusion_pairs=(("car", "truck"), ("car", "sidewalk")),
        confusion_targets={"car": {"truck": 1.0, "sidewalk": 1.0}},
    )
    shares = [sum(c == TRUCK for c in p) / max(1, sum(c != CAR for c in p)) for p in preds]
    assert all(0.25 <= s <= 0.75 for s in shares), shares


def _car_flags(seq, drift: bool, q: float, seed: int) -> np.ndarray:
    """(2, frames) whether each of the two cars is confused (taken for a truck) in each frame, with car
    confused at rate ``q``, stratified draws, and blocks of six frames (two blocks in twelve frames)."""
    lab = _lab(
        seed=seed,
        class_confusion={"car": q},
        confusion_pairs=(("car", "truck"),),
        persistence_frames=6,
        stratified_draws=True,
        drift_draws=drift,
    )
    return np.array([lab.label(f, SCHEMA).probs.argmax(1)[:2] == TRUCK for f in seq]).T


def test_drift_draws_let_a_short_lived_objects_error_share_follow_the_rate(tmp_path: Path) -> None:
    seq = make_sequence(tmp_path / "twelve", n_frames=12)
    qs = np.round(np.arange(0.05, 1.0, 0.05), 2)
    for seed in range(3):
        block = np.array([_car_flags(seq, False, q, seed) for q in qs])  # (q, car, frame)
        drift = np.array([_car_flags(seq, True, q, seed) for q in qs])
        # A block decides all six of its frames, so a car's share of wrong frames is 0, 1/2 or 1 whatever
        # q is; drifting, the draw moves by frac(sqrt 3) / 6 = 0.122 a frame, so the share takes many
        # values and stays near q (12 frames span 1.46 turns of the lattice: within 0.25 of q).
        assert np.all(block[:, :, :6] == block[:, :, :1]) and np.all(block[:, :, 6:] == block[:, :, 6:7])
        for car in range(2):
            assert len(set(block[:, car].mean(axis=1))) <= 3
            shares = drift[:, car].mean(axis=1)
            assert len(set(shares)) >= 8, shares
            assert np.all(np.abs(shares - qs) <= 0.25), (seed, car, shares)
        # An error still persists: the drifting flag changes at most four times in twelve frames (about
        # 1.46 turns of the lattice, two crossings of q each), where a new draw each frame changes it ~6.
        assert np.abs(np.diff(drift.astype(int), axis=2)).sum(axis=2).max() <= 4
        # At a block's first frame the drifting draw is the block's draw.
        np.testing.assert_array_equal(drift[:, :, [0, 6]], block[:, :, [0, 6]])


def test_drift_draws_need_stratified_draws() -> None:
    with pytest.raises(ConfigError, match="stratified_draws") as err:
        SimulatedPaperConfig(drift_draws=True)
    assert err.value.field == ("drift_draws",)
    assert SimulatedPaperConfig(drift_draws=True, stratified_draws=True).drift_draws


def test_paper_preset_loads_and_differs_from_default() -> None:
    paper = SimulatedPaperConfig.from_preset("paper")
    default = SimulatedPaperConfig.from_preset("default")
    assert default == SimulatedPaperConfig()
    assert paper != default
    # It uses the terms the default leaves off, so its labels and fingerprint differ.
    assert paper.class_confusion and paper.confusion_targets and paper.box_leak_prob > 0
    assert SimulatedPaperLabeler(paper).fingerprint(SCHEMA) != SimulatedPaperLabeler(default).fingerprint(
        SCHEMA
    )


def test_size_recall() -> None:
    np.testing.assert_allclose(size_recall([0, 75, 150, 300], 150), [0.0, 0.5, 1.0, 1.0])
    np.testing.assert_array_equal(size_recall([3, 5], 0), [1.0, 1.0])


def test_box_leak_crop() -> None:
    # 4 x 10 box at (5, 20), margin 0.5: 2 rows and 5 columns more on each side.
    crop, y0, x0 = box_leak_crop(4, 10, 5, 20, 0.5, (48, 64))
    assert (y0, x0, crop.shape, bool(crop.all())) == (3, 15, (8, 20), True)
    # At the image's top-right corner the grown box is clipped: rows 0..5, columns 58..63.
    crop, y0, x0 = box_leak_crop(4, 4, 0, 60, 0.5, (48, 64))
    assert (y0, x0, crop.shape) == (0, 58, (6, 6))


def test_box_gaps_and_adjacent_partner() -> None:
    boxes = [(0, 0, 10, 10), (0, 12, 10, 20), (30, 30, 40, 40), (11, 0, 20, 10)]
    gaps = box_gaps(boxes)
    assert gaps[0, 1] == 2 and gaps[0, 3] == 1 and gaps[0, 2] == 20 and gaps[1, 3] == 2
    assert gaps[0, 0] == 0 and (gaps == gaps.T).all()
    # B's nearest are A and D (both 2): the lower index wins; C has nobody within 2 px.
    np.testing.assert_array_equal(adjacent_partner(boxes, [True] * 4, 2), [3, 0, -1, 0])
    np.testing.assert_array_equal(adjacent_partner(boxes, [True, True, True, False], 2), [1, 0, -1, 0])
    np.testing.assert_array_equal(adjacent_partner(boxes, [True] * 4, 1), [3, -1, -1, 0])


def test_tile_split() -> None:
    # A 4 x 4 region at row 2, column 6 of an 8 x 12 image in 4-pixel tiles (2 x 3 tiles): tiles (0, 1) and
    # (1, 2) are confused.
    crop = np.ones((4, 4), bool)
    u = np.array([[0.9, 0.1, 0.9], [0.9, 0.9, 0.1]])
    moved = tile_split(crop, 2, 6, 4, u, 0.5)
    expected = np.zeros((4, 4), bool)
    expected[:2, :2] = True  # image rows 2-3, columns 6-7: tile (0, 1)
    expected[2:, 2:] = True  # image rows 4-5, columns 8-9: tile (1, 2)
    np.testing.assert_array_equal(moved, expected)
    # Only the region's own pixels move.
    crop[0, 0] = False
    assert not tile_split(crop, 2, 6, 4, u, 0.5)[0, 0]


def test_confusion_targets_and_pick() -> None:
    table = {"a": {"b": 1.0, "c": 3.0}, "x": {"a": 1.0}, "b": {"c": 0.0, "zz": 2.0}}
    out = confusion_targets(["a", "b", "c"], table)
    assert list(out) == [0]
    assert out[0][0] == [1, 2]
    np.testing.assert_allclose(out[0][1], [0.25, 1.0])
    assert _pick([7], out[0], 0.2) == 1 and _pick([7], out[0], 0.3) == 2
    assert _pick([4, 5], None, 0.2) == 4 and _pick([4, 5], None, 0.7) == 5


def test_class_confusion_and_targets_direct_the_confusion(seq) -> None:
    gt = _argmax_image(_lab().label(seq.frame(0), SCHEMA))
    pairs = (("car", "truck"), ("road", "sidewalk"))
    # Only the classes with a confusion probability are confused (confusion_prob is 0).
    lab = _lab(confusion_pairs=pairs, class_confusion={"car": 1.0})
    img = _argmax_image(lab.label(seq.frame(0), SCHEMA))
    assert (img[gt == CAR] == TRUCK).all() and (img[gt == ROAD] == ROAD).all()
    # A directed target replaces the pair partner: road is taken for terrain here, not for sidewalk.
    lab = _lab(
        confusion_pairs=pairs, class_confusion={"road": 1.0}, confusion_targets={"road": {"terrain": 1.0}}
    )
    img = _argmax_image(lab.label(seq.frame(0), SCHEMA))
    assert (img[gt == ROAD] == SCHEMA.names.index("terrain")).all()


def test_box_leak_turns_thing_masks_into_grown_boxes(seq) -> None:
    masks = _lab(box_leak_prob=1.0, box_leak_margin=0.5).label(seq.frame(0), SCHEMA)
    dense = masks.dense()
    car = [m for m, p in zip(dense, masks.probs, strict=True) if p.argmax() == CAR]
    # Car 2 is rows 26-35, columns 35-54 (10 x 20): grown by 5 rows and 10 columns each side, clipped to
    # the 48 x 64 image: rows 21-40, columns 25-63.
    big = max(car, key=lambda m: int(m[:, 60:].sum()))
    ys, xs = np.nonzero(big)
    assert (ys.min(), ys.max(), xs.min(), xs.max(), int(big.sum())) == (21, 40, 25, 63, 20 * 39)
    # Stuff masks are not boxes.
    road = [m for m, p in zip(dense, masks.probs, strict=True) if p.argmax() == ROAD]
    assert int(road[0].sum()) < 16 * 64


def test_class_box_leak_grows_only_the_named_class_masks(seq) -> None:
    frame = seq.frame(0)

    def car_sizes(**kw: object) -> list[int]:
        masks = _lab(box_leak_margin=0.5, **kw).label(frame, SCHEMA)
        dense = masks.dense()
        return sorted(int(m.sum()) for m, p in zip(dense, masks.probs, strict=True) if p.argmax() == CAR)

    plain = car_sizes()
    boxes = car_sizes(box_leak_prob=1.0)
    assert boxes != plain and 20 * 39 in boxes  # car 2's grown box (test above)
    # The per-class value overrides the global one, both ways; other classes' values leave cars alone.
    assert car_sizes(class_box_leak={"car": 1.0}) == boxes
    assert car_sizes(box_leak_prob=1.0, class_box_leak={"car": 0.0}) == plain
    assert car_sizes(class_box_leak={"truck": 1.0, "unknown": 1.0}) == plain


def test_pair_merge_covers_the_adjacent_object(seq) -> None:
    frame = seq.frame(0)
    plain = [
        m
        for m, p in zip(_lab().label(frame, SCHEMA).dense(), _lab().label(frame, SCHEMA).probs, strict=True)
        if p.argmax() == CAR
    ]
    masks = _lab(pair_merge_prob=1.0, pair_merge_gap_px=20).label(frame, SCHEMA)
    car = [m for m, p in zip(masks.dense(), masks.probs, strict=True) if p.argmax() == CAR]
    # Cars 1 (rows 30-37, columns 5-19) and 2 (rows 26-35, columns 35-54) are 15 px apart: each mask now
    # covers both cars.
    union = plain[0] | plain[1]
    assert len(car) == 2 and all((m == union).all() for m in car)
    # With a gap below 15 px they stay apart.
    masks = _lab(pair_merge_prob=1.0, pair_merge_gap_px=14).label(frame, SCHEMA)
    car = [m for m, p in zip(masks.dense(), masks.probs, strict=True) if p.argmax() == CAR]
    assert sorted(int(m.sum()) for m in car) == sorted(int(m.sum()) for m in plain)


def test_stuff_tiles_confuse_part_of_a_surface(seq) -> None:
    frame = seq.frame(0)
    gt = _argmax_image(_lab().label(frame, SCHEMA))
    lab = _lab(confusion_pairs=(("road", "sidewalk"),), class_confusion={"road": 0.5}, stuff_tile_px=8)
    img = _argmax_image(lab.label(frame, SCHEMA))
    road = gt == ROAD
    moved = img[road] == SIDEWALK
    assert 0 < moved.sum() < road.sum()
    # Whole 8 x 8 tiles move: inside each tile the road pixels agree.
    ys, xs = np.nonzero(road)
    for t in {(y // 8, x // 8) for y, x in zip(ys, xs, strict=True)}:
        sel = (ys // 8 == t[0]) & (xs // 8 == t[1])
        assert len(set(img[ys[sel], xs[sel]].tolist())) == 1
    # Off (0): the whole region keeps one class, drawn once.
    img0 = _argmax_image(
        _lab(confusion_pairs=(("road", "sidewalk"),), class_confusion={"road": 0.5}).label(frame, SCHEMA)
    )
    assert len(set(img0[road].tolist())) == 1


def test_small_region_recall_drops_small_regions_more(seq) -> None:
    frame = seq.frame(0)
    full = _lab().label(frame, SCHEMA).num_masks
    assert _lab(small_region_px=1).label(frame, SCHEMA).num_masks == full
    # Recall = area / 10^6 for every region here: (almost) nothing is kept.
    assert _lab(small_region_px=10**6).label(frame, SCHEMA).num_masks == 0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"class_confusion": {"car": 1.5}}, ("class_confusion", "car")),
        ({"box_leak_prob": 2.0}, ("box_leak_prob",)),
        ({"class_box_leak": {"person": -0.1}}, ("class_box_leak", "person")),
        ({"stuff_tile_px": -1}, ("stuff_tile_px",)),
        ({"confusion_targets": {"car": {"truck": -1.0}}}, ("confusion_targets", "car", "truck")),
    ],
)
def test_new_fields_are_validated(kwargs: dict, field: tuple[str, ...]) -> None:
    with pytest.raises(ConfigError) as err:
        SimulatedPaperConfig(**kwargs)
    assert err.value.field == field


def test_noise_terms_at_the_edges_of_their_domains() -> None:
    # A box at the image's left edge: the leaked crop starts at column 0, rows 0.. (not 1), all True.
    crop, y0, x0 = box_leak_crop(4, 4, 0, 1, 0.5, (48, 64))
    assert (y0, x0, crop.shape, crop.dtype) == (0, 0, (6, 7), np.dtype(bool))
    # A tile whose draw equals the probability is not confused ("below prob").
    assert not tile_split(np.ones((1, 1), bool), 0, 0, 1, np.array([[0.5]]), 0.5).any()
    # Eligibility given as integers, and no or one region.
    boxes = [(0, 0, 10, 10), (0, 12, 10, 20), (11, 0, 20, 10)]
    np.testing.assert_array_equal(adjacent_partner(boxes, [1, 0, 1], 2), [2, 0, 0])
    for n, want in ((0, []), (1, [-1])):
        got = adjacent_partner(boxes[:n], [True] * n, 2)
        assert got.dtype == np.int64 and got.tolist() == want
    assert adjacent_partner(boxes, [True] * 3, 2).dtype == np.int64


def test_pick_at_a_cumulative_weight_and_past_the_last() -> None:
    target = ([3, 5], np.array([0.5, 1.0]))
    assert _pick([], target, 0.5) == 5  # a draw equal to a cumulative weight belongs to the next target
    assert _pick([], target, 0.4999) == 3
    # float rounding can leave the last cumulative weight just below 1: a draw at or above it (here the
    # largest float below 1) picks the last target
    last = np.nextafter(1.0, 0)
    assert _pick([], ([3, 5], np.array([0.5, last])), float(last)) == 5


def test_directed_confusion_targets_decide_the_confused_class_by_weight(seq) -> None:
    # Every car region confused (probability 1), towards sidewalk with all but a millionth of the weight and
    # no confusion pairs: the directed table, and its weights, not a uniform pick, decide the class.
    cfg = dataclasses.replace(
        SimulatedPaperConfig.exact(),
        confusion_prob=1.0,
        peak_prob=(0.8, 0.8),
        confusion_pairs=(),
        confusion_targets={"car": {"sidewalk": 1.0, "road": 1e-6}},
    )
    frame = seq.frame(0)
    true = SimulatedPaperLabeler(SimulatedPaperConfig.exact()).label(frame, SCHEMA).probs.argmax(axis=1)
    assert (true == CAR).sum() >= 2
    for seed in range(6):  # a draw per car region and seed: a uniform pick would land on road in some
        pred = (
            SimulatedPaperLabeler(dataclasses.replace(cfg, seed=seed))
            .label(frame, SCHEMA)
            .probs.argmax(axis=1)
        )
        assert (pred[true == CAR] == SIDEWALK).all()
        assert (pred[true != CAR] == true[true != CAR]).all()  # no pairs: the other classes stay


def test_over_large_stuff_masks_are_dilated_by_one_to_stuff_grow_px(seq) -> None:
    import cv2

    frame = seq.frame(0)
    exact = SimulatedPaperLabeler(SimulatedPaperConfig.exact()).label(frame, SCHEMA)
    cfg = dataclasses.replace(SimulatedPaperConfig.exact(), stuff_grow_prob=1.0, stuff_grow_px=3)
    grown = SimulatedPaperLabeler(cfg).label(frame, SCHEMA)
    assert grown.num_masks == exact.num_masks
    stuff = ~np.isin(exact.probs.argmax(axis=1), [CAR, TRUCK])
    assert stuff.any() and (~stuff).any()
    radii = []
    for m in range(exact.num_masks):
        if not stuff[m]:  # thing masks are left as they are (their bleed is 0 here)
            np.testing.assert_array_equal(grown.dense()[m], exact.dense()[m])
            continue
        r = _dilation_radius(grown.dense()[m], exact.dense()[m], range(1, 4))
        assert r is not None, f"stuff mask {m} is no dilation of radius 1..3 of its exact mask"
        radii.append(r)
    assert len(set(radii)) > 1  # the radius is drawn per region
    one = SimulatedPaperLabeler(dataclasses.replace(cfg, stuff_grow_px=1)).label(
        frame, SCHEMA
    )  # radius 1 only
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    for m in np.flatnonzero(stuff):
        want = cv2.dilate(exact.dense()[m].astype(np.uint8), disc).astype(bool)
        np.testing.assert_array_equal(one.dense()[m], want)
    off = dataclasses.replace(cfg, stuff_grow_px=0)  # no radius: the term is off whatever its probability
    np.testing.assert_array_equal(SimulatedPaperLabeler(off).label(frame, SCHEMA).bits, exact.bits)


def test_tiled_stuff_moves_its_confused_tiles_to_the_weighted_target(seq) -> None:
    # Every tile of a road region confused (probability 1): all of it goes to the confusion target, chosen by
    # weight (sidewalk, all but a millionth) for every seed, not uniformly among the targets.
    cfg = dataclasses.replace(
        SimulatedPaperConfig.exact(),
        confusion_prob=1.0,
        peak_prob=(0.8, 0.8),
        confusion_pairs=(),
        stuff_tile_px=8,
        confusion_targets={"road": {"sidewalk": 1.0, "terrain": 1e-6}},
    )
    frame = seq.frame(0)
    true = _argmax_image(SimulatedPaperLabeler(SimulatedPaperConfig.exact()).label(frame, SCHEMA))
    assert (true == ROAD).any()
    for seed in range(6):
        got = _argmax_image(SimulatedPaperLabeler(dataclasses.replace(cfg, seed=seed)).label(frame, SCHEMA))
        assert (got[true == ROAD] == SIDEWALK).all(), seed
        np.testing.assert_array_equal(got[true != ROAD], true[true != ROAD])


def test_noise_helpers_past_their_usual_inputs() -> None:
    # A box wholly outside the image leaks no pixel (an empty crop, not one row or column).
    for y0, x0 in ((50, 10), (10, 70), (50, 70)):
        crop, _, _ = box_leak_crop(4, 4, y0, x0, 0.0, (48, 64))
        assert crop.size == 0, (y0, x0)
    # Eligibility as a column vector reads as one flag per region.
    boxes = [(0, 0, 10, 10), (0, 12, 10, 20), (11, 0, 20, 10)]
    np.testing.assert_array_equal(adjacent_partner(boxes, np.array([[1], [0], [1]]), 2), [2, 0, 0])
    # A draw of exactly 1 picks the last pair partner.
    assert _pick([4, 5], None, 1.0) == 5 and _pick([4, 5, 6], None, 0.999) == 6


def test_one_pixel_tiles_confuse_single_pixels(seq) -> None:
    # stuff_tile_px = 1 is on: each road pixel is drawn apart, so for every seed part of the road is taken for
    # sidewalk and part stays (one draw for the whole region gives all or nothing).
    frame = seq.frame(0)
    road = _argmax_image(_lab().label(frame, SCHEMA)) == ROAD
    for seed in range(3):
        lab = _lab(
            seed=seed, confusion_pairs=(("road", "sidewalk"),), class_confusion={"road": 0.5}, stuff_tile_px=1
        )
        got = _argmax_image(lab.label(frame, SCHEMA))[road]
        share = float((got == SIDEWALK).mean())
        assert 0.3 < share < 0.7 and ((got == SIDEWALK) | (got == ROAD)).all(), (seed, share)


def test_over_large_stuff_draws_whether_and_how_far_apart(seq) -> None:
    # At probability 1/2 a stuff mask grows or not on one draw and takes its radius 1..4 from another: the
    # grown masks reach radii 3 and 4 too (were one draw to decide both, a grown mask's radius would be 1-2).
    frame = seq.frame(0)
    exact = _lab().label(frame, SCHEMA)
    stuff = np.flatnonzero(~np.isin(exact.probs.argmax(axis=1), [CAR, TRUCK]))
    radii = []
    for seed in range(12):
        grown = _lab(seed=seed, stuff_grow_prob=0.5, stuff_grow_px=4).label(frame, SCHEMA).dense()
        for m in stuff:
            r = _dilation_radius(grown[m], exact.dense()[m], range(5))
            assert r is not None, (seed, m)
            radii.append(r)
    assert 0 in radii and {3, 4} & set(radii), sorted(set(radii))


def test_size_recall_dtype_shape_and_small_thresholds() -> None:
    off = size_recall([0, 3, 5], 0)  # off: ones of the input's shape, as floats (also for an empty region)
    assert off.dtype == np.float64 and off.shape == (3,) and off.tolist() == [1.0, 1.0, 1.0]
    # One pixel is a threshold like any other: an empty region has recall 0 there.
    assert size_recall([0, 2], 1).tolist() == [0.0, 1.0]


def test_merge_partners_of_objects_stacked_vertically() -> None:
    from lab.paper_labeler import _merge_partners

    # A rider (rows 0-9, columns 0-3) above a bicycle (rows 12-21, columns 0-3): 2 px apart vertically; a
    # stuff region 3 px to their right is never a partner and has none. Boxes are taller than wide, so
    # height and width cannot be swapped unnoticed.
    tall = np.ones((10, 4), bool)
    regions = [
        Region(8, True, 1, 0, 0, tall),
        Region(7, True, 2, 12, 0, tall),
        Region(10, False, 0, 0, 7, np.ones((22, 3), bool)),
    ]
    cfg = dataclasses.replace(SimulatedPaperConfig.exact(), pair_merge_prob=0.5, pair_merge_gap_px=2)
    assert _merge_partners(regions, cfg).tolist() == [1, 0, -1]
    assert _merge_partners(regions, dataclasses.replace(cfg, pair_merge_gap_px=1)).tolist() == [-1, -1, -1]
    off = _merge_partners(regions, dataclasses.replace(cfg, pair_merge_prob=0.0))
    assert off.dtype == np.int64 and off.tolist() == [-1, -1, -1]


def test_world_tile_draws_hand_computed() -> None:
    a1, a2 = math.sqrt(2) % 1, math.sqrt(3) % 1  # decision 0's lattice steps
    b1, b2 = math.sqrt(5) % 1, math.sqrt(7) % 1  # decision 1's
    # Cells (ix, iy) = (3, 5), (3, 4), (10, 5), (2, 5); tiles of 2 cells: (1, 2), (1, 2), (5, 2), (1, 2).
    cells = np.array([[(3 << 8) | 5, (3 << 8) | 4], [(10 << 8) | 5, (2 << 8) | 5]], np.uint16)
    u = world_tile_draws(cells, 2, (0.1, 0.7))
    assert u.shape == (2, 2, 2)
    assert u[0, 0, 0] == pytest.approx((0.1 + 1 * a1 + 2 * a2) % 1)
    assert u[1, 0, 0] == pytest.approx((0.7 + 1 * b1 + 2 * b2) % 1)
    assert u[0, 1, 0] == pytest.approx((0.1 + 5 * a1 + 2 * a2) % 1)
    # One tile, one pair of draws, whichever of its cells a pixel sees.
    assert u[0, 0, 1] == u[0, 0, 0] == u[0, 1, 1] and u[1, 0, 1] == u[1, 0, 0]
    # Independent uniforms: the same sharing per tile, reproducible from the key, another key other draws.
    v = world_tile_draws(cells, 2, (0.0, 0.0), stratified=False, seed_key=(0, 7, 3))
    assert v[0, 0, 0] == v[0, 0, 1] == v[0, 1, 1] != v[0, 1, 0]
    np.testing.assert_array_equal(v, world_tile_draws(cells, 2, (0.5, 0.5), False, (0, 7, 3)))
    assert not np.array_equal(v, world_tile_draws(cells, 2, (0.0, 0.0), False, (1, 7, 3)))
    # Tiles of one cell: every cell its own tile.
    w1 = world_tile_draws(cells, 1, (0.1, 0.7))
    assert w1[0, 0, 0] == pytest.approx((0.1 + 3 * a1 + 5 * a2) % 1) != w1[0, 0, 1]


def _world_sequence(tmp_path: Path, n_frames: int = 12):
    """The labeler test sequence with ``gt2d/cell`` images of a camera moving along x: pixel (y, x) of frame
    i sees world cell (ix, iy) = ((x + 3 i) // 4, y // 4)."""
    seq = make_sequence(tmp_path / "world", n_frames)
    ys, xs = np.mgrid[0:H, 0:W]
    for i in range(n_frames):
        cells = ((((xs + 3 * i) // 4) << 8) | (ys // 4)).astype(np.uint16)
        write_png16(seq.root / "gt2d" / "cell" / f"{i:06d}.png", cells)
    return seq


def _confused_cells(lab: SimulatedPaperLabeler, seq) -> list[dict[int, bool]]:
    """Per frame, world cell → whether its road pixels were taken for another class (cells whose road
    pixels all agree; the labels are one-hot with no jitter or bleed)."""
    out = []
    for f in seq:
        img = _argmax_image(lab.label(f, SCHEMA))
        road = f.gt2d_semantic == 40
        cells = f.gt2d_cell
        assert cells is not None
        per: dict[int, bool] = {}
        for c in np.unique(cells[road]):
            moved = img[road & (cells == c)] != ROAD
            assert moved.all() or not moved.any()  # a tile is confused as a whole
            per[int(c)] = bool(moved[0])
        out.append(per)
    return out


@pytest.mark.parametrize("stratified", [True, False])
def test_world_tiles_confuse_the_same_patch_in_every_frame(tmp_path: Path, stratified: bool) -> None:
    kw = dict(
        confusion_pairs=(("road", "sidewalk"),),
        class_confusion={"road": 0.5},
        stuff_tile_px=8,
        stratified_draws=stratified,
    )
    seq = _world_sequence(tmp_path)
    world = _confused_cells(_lab(stuff_world_tile=1, **kw), seq)
    decided: dict[int, bool] = {}
    for per in world:  # frames 0-11: three blocks of persistence_frames = 5
        for c, moved in per.items():
            assert decided.setdefault(c, moved) == moved, c
    share = np.mean(list(decided.values()))
    assert 0.2 < share < 0.8
    # Image tiles follow the camera, not the world: some patch changes its label from frame to frame.
    flips = 0
    seen: dict[int, bool] = {}
    lab = _lab(**kw)
    for f in seq:
        img = _argmax_image(lab.label(f, SCHEMA))
        road = f.gt2d_semantic == 40
        for c in np.unique(f.gt2d_cell[road]):
            moved = bool((img[road & (f.gt2d_cell == c)] != ROAD).any())
            flips += seen.setdefault(int(c), moved) != moved
    assert flips > 0


def test_world_tiles_need_the_cell_images_and_image_tiles(tmp_path: Path, seq) -> None:
    lab = _lab(
        confusion_pairs=(("road", "sidewalk"),),
        class_confusion={"road": 0.5},
        stuff_tile_px=8,
        stuff_world_tile=2,
    )
    with pytest.raises(LeapError, match=r"gt2d/cell: missing"):
        lab.label(seq.frame(0), SCHEMA)
    with pytest.raises(ConfigError) as err:
        SimulatedPaperConfig(stuff_world_tile=2)
    assert err.value.field == ("stuff_world_tile",)
    with pytest.raises(ConfigError):
        SimulatedPaperConfig(stuff_world_tile=-1, stuff_tile_px=8)
    # A cell image of another size names its file.
    bad = _world_sequence(tmp_path, 1)
    write_png16(bad.root / "gt2d" / "cell" / "000000.png", np.zeros((H, W + 1), np.uint16))
    with pytest.raises(LeapError, match=r"000000.png: cell image"):
        lab.label(bad.frame(0), SCHEMA)


def test_small_region_recall_multiplies_the_class_recall(seq: KittiSequence) -> None:
    # small_region_px = 1 leaves every region's size factor at 1: a class recall of 0 still drops the cars.
    got = _argmax_image(_lab(small_region_px=1, class_recall={"car": 0.0}).label(seq.frame(0), SCHEMA))
    assert not (got == CAR).any() and (got == ROAD).any()


def test_a_merged_mask_keeps_its_own_pixels_inside_the_other_objects_box(tmp_path: Path) -> None:
    # A car (rows 10-20, columns 10-30) and an L-shaped truck in front of it (column 25, rows 5-25, and an
    # arm along rows 5-7 to column 35): each box holds pixels of the other object. One mask over both is
    # their union, the pixels of each inside the other's box included.
    sem = np.full((H, W), 40, np.uint16)
    inst = np.zeros((H, W), np.uint16)
    sem[10:21, 10:31], inst[10:21, 10:31] = 10, 1
    sem[5:26, 25], inst[5:26, 25] = 18, 2
    sem[5:8, 25:36], inst[5:8, 25:36] = 18, 2
    frame = _one_frame(tmp_path / "s", sem, inst).frame(0)
    exact = _lab().label(frame, SCHEMA)
    cls = exact.probs.argmax(axis=1)
    union = exact.dense()[cls == CAR][0] | exact.dense()[cls == TRUCK][0]
    merged = _lab(pair_merge_prob=1.0, pair_merge_gap_px=5).label(frame, SCHEMA)
    things = merged.dense()[np.isin(merged.probs.argmax(axis=1), [CAR, TRUCK])]
    assert len(things) == 2 and all(np.array_equal(m, union) for m in things)


def test_pair_merges_follow_the_objects_merge_draw(seq: KittiSequence) -> None:
    # Each region's shape draws are (box leak, pair merge, stuff growth, growth radius): at probability 1/2
    # a car mask covers the other car exactly when its second draw is below 1/2.
    from lab.paper_labeler import _STREAM_SHAPE

    frame = seq.frame(0)
    regions = _frame_regions(frame)
    plain = _lab().label(frame, SCHEMA)
    cars = np.flatnonzero(plain.probs.argmax(axis=1) == CAR)
    assert list(cars) == [0, 1] and all(r.thing for r in regions[:2])  # the two cars are regions 0 and 1
    sizes = plain.dense()[cars].sum(axis=(1, 2))
    seen = set()
    for seed in range(10):
        masks = _lab(seed=seed, pair_merge_prob=0.5, pair_merge_gap_px=20).label(frame, SCHEMA).dense()
        u = object_draws(regions, seed, 0, _STREAM_SHAPE)
        for m in cars:
            merged = bool(masks[m].sum() > sizes[m])
            assert merged == (u[m, 1] < 0.5), (seed, m)
            seen.add(merged)
    assert seen == {True, False}


def _refused(field: tuple[str, ...], **kwargs: object) -> None:
    with pytest.raises(LeapError) as err:
        SimulatedPaperConfig(**kwargs)
    assert err.value.field == field, (kwargs, err.value.field)


def test_config_validation_edges_of_the_terms_ranges() -> None:
    """Each range's ends are accepted and the values just outside are refused, field by field; the
    product config's checks still run (its fields are the lab config's too)."""
    for name in ("box_leak_prob", "pair_merge_prob", "stuff_grow_prob"):
        SimulatedPaperConfig(**{name: 0.0})
        SimulatedPaperConfig(**{name: 1.0})
        _refused((name,), **{name: -0.01})
        _refused((name,), **{name: 1.01})
    for table in ("class_confusion", "class_box_leak"):
        SimulatedPaperConfig(**{table: {"car": 0.0, "road": 1.0}})
        _refused((table, "car"), **{table: {"road": 0.5, "car": -0.01}})
        _refused((table, "car"), **{table: {"car": 1.01}})
    for name in ("small_region_px", "box_leak_margin", "pair_merge_gap_px", "stuff_grow_px", "stuff_tile_px"):
        SimulatedPaperConfig(**{name: 0})
        _refused((name,), **{name: -1})
    _refused(("recall",), recall=1.01)
    _refused(("confusion_pairs",), confusion_pairs=(("road", "road"),))
    SimulatedPaperConfig(
        confusion_pairs=(("car", "truck"),), confusion_targets={"car": {"truck": 0.0, "road": 2.0}}
    )
    _refused(("confusion_targets", "car", "car"), confusion_targets={"car": {"truck": 1.0, "car": 1.0}})
    _refused(
        ("confusion_targets", "road", "car"),
        confusion_targets={"car": {"truck": 1.0}, "road": {"car": float("nan")}},
    )
