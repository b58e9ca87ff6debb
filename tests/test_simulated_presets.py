"""The simulated labeler's named presets, the default preset's output pinned byte for byte, and its noise
steps' helpers by hand. (The noise terms of the paper-calibrated labeler are the lab's: tests/lab.)"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np
import pytest

from leap_core.config import PipelineConfig, config_from_dict, config_to_dict
from leap_core.errors import ConfigError
from leap_core.labelers.simulated import (
    SIMULATED_PRESETS,
    SimulatedLabeler,
    SimulatedLabelerConfig,
)
from leap_core.presets import load_preset
from tests.test_simulated_labeler import (
    CAR,
    SCHEMA,
    _exact,
    _frame_regions,
    _schema,
    make_sequence,
)


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory):
    return make_sequence(tmp_path_factory.mktemp("preset_seq"))


def _masks_digest(lab: SimulatedLabeler, seq, schema=SCHEMA) -> str:
    """First 16 hex digits of the SHA-256 of every frame's mask bits, probabilities and confidences."""
    h = hashlib.sha256()
    for f in seq:
        m = lab.label(f, schema)
        for a in (m.bits, m.probs, m.confidence):
            h.update(a.tobytes())
    return h.hexdigest()[:16]


# ------------------------------------------------------------------------------------- the default preset
def test_default_preset_output_and_fingerprint_are_unchanged(seq) -> None:
    # Digests taken before the paper preset's terms were added, and kept when they moved to the lab: the
    # default masks (and so every existing run's 2D labels, caches and fingerprints) must not move when
    # terms that it leaves off come or go.
    lab = SimulatedLabeler(SimulatedLabelerConfig(seed=7))
    assert _masks_digest(lab, seq) == "4c8c1284077fa811"
    # Prompts that name the regions loosely (hypernyms, synonyms): confidences scaled by a match factor < 1.
    loose = _schema(car=("vehicle",), road=("street",), vegetation=("plants",))
    assert _masks_digest(lab, seq, loose) == "b03fc46611d14a9c"
    # The fingerprint hashes the lexicon, which gained the agri-uav domain's names (2026-11-27; the masks
    # above did not move): was 1253efe3866bbb09.
    assert SimulatedLabeler().fingerprint(SCHEMA) == "a06e41a427719ec4"
    assert SIMULATED_PRESETS["default"]() == SimulatedLabelerConfig()


# -------------------------------------------------------------------------------------- choosing a preset
def test_preset_key_in_a_config_dict_replaces_the_section_then_applies_the_rest() -> None:
    base = config_from_dict({"simulated": {"recall": 0.5}, "fusion": {"voxel_size": 0.5}})
    cfg = config_from_dict({"simulated": {"preset": "default", "seed": 5}}, base)
    assert cfg.labeler_config(SimulatedLabelerConfig) == SimulatedLabelerConfig(seed=5)  # recall: default's
    # The stored dict form has every value and no preset key, and reads back to the same config.
    assert "preset" not in config_to_dict(cfg)["simulated"]
    assert config_from_dict(config_to_dict(cfg)) == cfg
    # A base config's other sections survive.
    assert cfg.fusion.voxel_size == 0.5


@pytest.mark.parametrize("value", ["nope", 3])
def test_unknown_preset_names_the_field(value: object) -> None:
    with pytest.raises(ConfigError) as err:
        config_from_dict({"simulated": {"preset": value}})
    assert err.value.field == ("pipeline", "simulated", "preset")


def test_project_file_and_cli_pick_the_preset(tmp_path: Path) -> None:
    from app.cli import _run_config

    project = tmp_path / "p.yaml"
    base = Path(__file__).resolve().parents[1] / "projects" / "semantickitti.yaml"
    text = base.read_text() + "\npipeline:\n  simulated:\n    preset: default\n    seed: 4\n"
    project.write_text(text)
    loaded = load_preset(project).pipeline.labeler_config(SimulatedLabelerConfig)
    assert loaded == SimulatedLabelerConfig(seed=4)
    # --labeler-preset replaces the chosen labeler's section (the project's seed goes with it).
    _, cfg = _run_config(None, str(project), None, None, None, "default")
    assert cfg.labeler_config(SimulatedLabelerConfig) == SimulatedLabelerConfig()
    _, cfg = _run_config("semantickitti", None, None, None, None, None)
    assert cfg.labeler_config(SimulatedLabelerConfig) == PipelineConfig().labeler_config(
        SimulatedLabelerConfig
    )
    # The grounded-sam labeler has no presets: a name is refused in its section.
    with pytest.raises(ConfigError) as err:
        _run_config("semantickitti", None, "grounded-sam", None, None, "default")
    assert err.value.field == ("pipeline", "grounded_sam", "preset")


def test_the_paper_preset_is_refused_naming_the_labs_labeler(tmp_path: Path) -> None:
    # The former "paper" preset belongs to the lab's simulated-paper labeler: a project file or command
    # line that still asks the simulated labeler for it is told where it went.
    from app.cli import _run_config

    for ask in (
        lambda: config_from_dict({"simulated": {"preset": "paper"}}),
        lambda: _run_config("semantickitti", None, None, None, None, "paper"),
    ):
        with pytest.raises(
            ConfigError, match=r"unknown preset 'paper' \(known: 'default'\); the paper preset"
        ) as err:
            ask()
        assert err.value.field == ("pipeline", "simulated", "preset")
        assert "simulated-paper" in str(err.value) and "python -m lab" in str(err.value)


def test_unknown_preset_lists_the_known_ones() -> None:
    from leap_core.labelers.simulated import simulated_preset

    with pytest.raises(ConfigError, match=r"unknown preset 'x' \(known: 'default'\)$"):
        simulated_preset("x")


def test_exact_turns_every_noise_knob_off_and_keeps_the_seed() -> None:
    cfg = SimulatedLabelerConfig.exact()
    assert cfg.seed == 0 and SimulatedLabelerConfig.exact(seed=7).seed == 7
    assert (cfg.recall, cfg.class_recall, cfg.min_region_px, cfg.confusion_prob) == (1.0, {}, 0, 0.0)
    assert (cfg.peak_prob, cfg.confidence, cfg.bleed_px, cfg.stuff_bleed_px) == ((1.0, 1.0), (1.0, 1.0), 0, 0)
    assert (cfg.jitter_px, cfg.jitter_deg, cfg.match_temperature) == (0.0, 0.0, 0.0)
    assert set(cfg.match_detection.values()) == set(cfg.match_confidence.values()) == {1.0}


def _dist(
    true_c: int,
    pred_c: int,
    c: int,
    *,
    partners: dict[int, list[int]] | None = None,
    seed: int = 0,
    alpha: float = 1.0,
) -> np.ndarray:
    from leap_core.labelers.simulated import _distribution

    cfg = dataclasses.replace(
        SimulatedLabelerConfig(), peak_prob=(0.6, 0.6), partner_share=0.5, dirichlet_alpha=alpha
    )
    return _distribution(
        true_c,
        pred_c,
        rival=None,
        partners=partners or {},
        num_classes=c,
        cfg=cfg,
        rng=np.random.default_rng(seed),
    )


def test_distribution_peak_partner_share_and_rest_by_hand() -> None:
    # Two classes, confused: the peak on the predicted class, all the rest on the true one.
    p = _dist(0, 1, 2)
    assert p.dtype == np.float32
    np.testing.assert_allclose(p, [0.4, 0.6], rtol=1e-6)
    # Three classes, confused: half the rest (0.2) on the true class, the other half on the third.
    np.testing.assert_allclose(_dist(0, 1, 3), [0.2, 0.6, 0.2], rtol=1e-6)
    # One class: all of it.
    p = _dist(0, 0, 1)
    assert p.dtype == np.float32 and p.tolist() == [1.0]
    # Not confused, two pair partners: the partner draw picks each for some seeds.
    picked = set()
    for seed in range(12):
        p = _dist(0, 0, 4, partners={0: [2, 3]}, seed=seed)
        picked.add(2 if p[2] >= 0.2 - 1e-6 else 3)
        assert max(p[2], p[3]) >= 0.2 - 1e-6
    assert picked == {2, 3}
    # A tiny Dirichlet concentration can give the only class left for the rest exactly 0 (seed 2 does):
    # the rest then goes to the predicted class.
    np.testing.assert_allclose(_dist(0, 1, 3, seed=2, alpha=1e-4), [0.2, 0.8, 0.0], rtol=1e-6)


def test_jitter_shifts_and_rotates_about_the_image_centre() -> None:
    from leap_core.labelers.simulated import _jitter

    h, w = 21, 31
    names = np.zeros((h, w), np.uint16)
    names[10, 15] = 1  # the centre pixel
    names[3, 4] = 2
    inst = names.copy()
    exact = SimulatedLabelerConfig.exact()
    # Rotation only (1 and 20 degrees per unit draw; seed 69 draws 2.66 units): the centre stays, an
    # off-centre pixel moves to its rotated place (to within the nearest-neighbour rounding).
    for deg in (1.0, 20.0):
        cfg = dataclasses.replace(exact, jitter_deg=deg)
        theta = np.random.default_rng(69).normal(0.0, 1.0, size=3)[2] * deg
        got, got_inst, got_cells = _jitter(names, inst, cfg, np.random.default_rng(69), names.copy())
        np.testing.assert_array_equal(got, got_inst)
        np.testing.assert_array_equal(got, got_cells)  # an extra image moves with the label images
        assert got[10, 15] == 1
        a = np.deg2rad(theta)  # (3, 4) rotated by theta about (15, 10), counter-clockwise as seen, y down
        x = 15 + (4 - 15) * np.cos(a) + (3 - 10) * np.sin(a)
        y = 10 - (4 - 15) * np.sin(a) + (3 - 10) * np.cos(a)
        (ys,), (xs,) = np.nonzero(got == 2)
        assert (ys, xs) != (3, 4) and np.hypot(ys - y, xs - x) < 1.0, (theta, ys, xs, y, x)
    # A half turn about the centre of an image with odd sides is the image flipped both ways, pixel for
    # pixel (a centre half a pixel off would move every row by one).
    z = np.random.default_rng(69).normal(0.0, 1.0, size=3)[2]
    half_turn = dataclasses.replace(exact, jitter_deg=180.0 / z)
    got, _, _ = _jitter(names, inst, half_turn, np.random.default_rng(69))
    np.testing.assert_array_equal(got, names[::-1, ::-1])
    # Shift only, one pixel per unit draw: both images move together by the rounded draws.
    cfg = dataclasses.replace(exact, jitter_px=1.0)
    dx, dy = np.random.default_rng(69).normal(0.0, 1.0, size=2)  # 0.71, 0.34 pixels
    got, _, none = _jitter(names, inst, cfg, np.random.default_rng(69))
    assert none is None
    assert (round(dx), round(dy)) != (0, 0)
    assert got[10 + round(dy), 15 + round(dx)] == 1
    # Both terms off: the images themselves, unchanged.
    same = _jitter(names, inst, exact, np.random.default_rng(0), names)
    assert same[0] is names and same[1] is inst and same[2] is names


def test_the_confused_partner_is_the_partner_draw_of_the_object(seq) -> None:
    # Each region's persistent draws are (recall, confusion, partner choice, competition): a confused car
    # with three partners takes the one its third draw picks (uniformly over the partners in index order),
    # whatever its fourth.
    from leap_core.labelers.simulated import _STREAM_OBJECT, object_draws, prompt_matches

    pairs = (("car", "truck"), ("car", "road"), ("car", "sidewalk"))
    partners = sorted(SCHEMA.names.index(n) for n in ("truck", "road", "sidewalk"))
    frame = seq.frame(0)
    regions = _frame_regions(frame)
    named = [i for i, r in enumerate(regions) if prompt_matches(SCHEMA).get(r.name)]
    true = _exact().label(frame, SCHEMA).probs.argmax(axis=1)
    assert len(true) == len(named) and (true == CAR).sum() >= 2
    picks = []
    for seed in range(6):
        lab = _exact(seed=seed, confusion_pairs=pairs, confusion_prob=1.0, peak_prob=(0.8, 0.8))
        pred = lab.label(frame, SCHEMA).probs.argmax(axis=1)
        u = object_draws(regions, seed, 0, _STREAM_OBJECT)
        for m in np.flatnonzero(true == CAR):
            assert pred[m] == partners[min(int(float(u[named[m], 2]) * 3), 2)], (seed, m)
            picks.append(int(pred[m]))
    assert len(set(picks)) == 3


# --------------------------------------------------------------------- the helpers, by hand, at their edges
def test_per_class_takes_float_values_over_an_integer_default() -> None:
    from leap_core.labelers.simulated import per_class

    # A YAML file's "recall: 1" arrives as an int; a class's 0.5 must not be cut to 0.
    got = per_class(["car", "road", "sky"], 1, {"road": 0.5, "boat": 0.1})
    assert got.dtype == np.float64 and got.tolist() == [1.0, 0.5, 1.0]


def test_compete_by_hand() -> None:
    from leap_core.labelers.simulated import _compete

    base = SimulatedLabelerConfig.exact()
    conf = {"exact": 1.0, "synonym": 0.5, "descriptive": 0.5, "hypernym": 0.5}
    # Alone: its own class and strength, no rival.
    assert _compete([(4, 1)], base, 0.7) == (4, 1, None)
    # T = 0: the strongest strength always wins; equal strengths share the win (a draw at the boundary goes
    # to the second, a draw of 1 to the last); the rival is the other class.
    assert _compete([(2, 0), (5, 3)], base, 0.99) == (2, 0, 5)
    assert _compete([(2, 1), (5, 1)], base, 0.4999) == (2, 1, 5)
    assert _compete([(2, 1), (5, 1)], base, 0.5) == (5, 1, 2)
    assert _compete([(2, 1), (5, 1)], base, 1.0) == (5, 1, 2)
    # T = 1: P(exact wins) = e^1 / (e^1 + e^0.5) = 0.6225.
    soft = dataclasses.replace(base, match_temperature=1.0, match_confidence=conf)
    assert _compete([(2, 0), (5, 1)], soft, 0.62) == (2, 0, 5)
    assert _compete([(2, 0), (5, 1)], soft, 0.63) == (5, 1, 2)
    # A small T in any order: exp of the similarities minus their maximum stays finite, the strong one wins.
    sharp = dataclasses.replace(soft, match_temperature=0.001)
    assert _compete([(5, 1), (2, 0)], sharp, 0.5) == (2, 0, 5)


def test_prompt_matches_order_and_negative_prompt_ties() -> None:
    from leap_core.labelers.simulated import prompt_matches
    from leap_core.schema import ClassDef, Schema

    sedan = 1  # leap_core/synth/names.py: "sedan", synonyms "car", "automobile", hypernym "vehicle"
    schema = Schema(
        name="m",
        classes=(
            ClassDef("veh", (1, 2, 3), ("vehicle",), 10, (10,), "vehicle"),
            ClassDef("exact", (1, 2, 3), ("sedan",), 11, (11,), "vehicle"),
            ClassDef("syn", (1, 2, 3), ("car",), 12, (12,), "vehicle", negative_prompts=("automobile",)),
        ),
    )
    # Strongest first (exact, synonym, hypernym), not in class order; a negative prompt as strong as the
    # positive one does not rule the class out (only a strictly stronger one does).
    assert prompt_matches(schema)[sedan] == [(1, 0), (2, 1), (0, 3)]


def test_regions_names_ids_and_canonical_order() -> None:
    from leap_core.labelers.simulated import _regions

    names = np.zeros((8, 12), np.uint16)
    inst = np.zeros((8, 12), np.uint16)
    inst[0:2, 0:2] = 9  # an instance id on unnamed pixels: no region
    names[6:8, 0:3] = 1  # name id 1 (the first of the lexicon) is a name like any other
    inst[6:8, 0:3] = 4
    # Two stuff components of name 10 that start on row 0: B at columns 6-7 of row 0 only; A at columns 9-10
    # of rows 0-1 and columns 4-10 of rows 2-3 (its box starts left of B, its first pixel right of B). In
    # raster order of first pixels B comes first.
    names[0, 6:8] = 10
    names[0:2, 9:11] = 10
    names[2:4, 4:11] = 10
    regions = _regions(names, inst)
    assert [(r.name, r.thing, r.ident) for r in regions] == [(1, True, 4), (10, False, 1), (10, False, 0)]
    assert [(r.y0, r.x0, r.crop.shape) for r in regions[1:]] == [(0, 6, (1, 2)), (0, 4, (4, 7))]


# ----------------------------------------------------------------------------- world tiles (A.7, term 13)
