"""Exact tests of the stage-A prompt and region maths (leap_core.labelers.prompts) on hand-made arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from leap_core.errors import SchemaError
from leap_core.labelers.grounded_sam import GroundedSamConfig
from leap_core.labelers.prompts import (
    ClassPrompts,
    apply_negatives,
    box_iou,
    build_text,
    fill_across_passes,
    keep_regions,
    make_pass,
    phrase_max,
    plan_passes,
    sigmoid,
    softmax_classes,
    token_phrase_index,
)
from leap_core.schema import Schema

NINF = -np.inf


def words(phrase: str) -> int:
    """A stand-in tokenizer for planning tests: one token per word."""
    return len(phrase.split())


# ------------------------------------------------------------------------------------------- text
def test_build_text_spans_point_at_each_phrase() -> None:
    text, spans = build_text(["car", "parking lot", "other  vehicle"])
    assert text == "car . parking lot . other vehicle ."
    assert spans == [(0, 3), (6, 17), (20, 33)]
    assert [text[s:e] for s, e in spans] == ["car", "parking lot", "other vehicle"]


@pytest.mark.parametrize("bad", ["st. bernard", "what?", "  "])
def test_build_text_rejects_phrase_separators(bad: str) -> None:
    with pytest.raises(ValueError, match="separate detector phrases"):
        build_text(["car", bad])


def test_token_phrase_index_from_offsets() -> None:
    # "car . parking lot ." tokenized as [CLS] car . parking lot . [SEP], padded to 9 columns.
    offsets = [(0, 0), (0, 3), (4, 5), (6, 13), (14, 17), (18, 19), (0, 0)]
    got = token_phrase_index(offsets, [(0, 3), (6, 17)], num_columns=9)
    assert got.tolist() == [-1, 0, -1, 1, 1, -1, -1, -1, -1]


def test_token_phrase_index_with_a_real_word_piece_tokenizer() -> None:
    from transformers import BertTokenizer

    from leap_core.labelers.tiny_models import tiny_vocab

    tok = BertTokenizer(vocab=tiny_vocab(), do_lower_case=True)
    text, spans = build_text(["car", "other-vehicle", "zebra crossing"])
    enc = tok(text, return_offsets_mapping=True)
    got = token_phrase_index(enc["offset_mapping"], spans)
    pieces = tok.convert_ids_to_tokens(enc["input_ids"])
    # Each phrase's word pieces (hyphen and ##-continuations included) map to it; separators to -1.
    by_phrase = {j: [p for p, g in zip(pieces, got, strict=True) if g == j] for j in range(3)}
    assert by_phrase[0] == ["car"]
    assert "".join(by_phrase[1]).replace("##", "") == "other-vehicle"
    assert "".join(by_phrase[2]).replace("##", "") == "zebracrossing"
    assert [p for p, g in zip(pieces, got, strict=True) if g == -1] == ["[CLS]", ".", ".", ".", "[SEP]"]
    assert enc["input_ids"][0] == 101 and enc["input_ids"][-1] == 102
    assert sum(1 for i in enc["input_ids"] if i == 1012) == 3


# ------------------------------------------------------------------------------------------ passes
def test_make_pass_dedups_phrases_and_records_roles() -> None:
    car = ClassPrompts(0, "car", ("car", "van"), ())
    truck = ClassPrompts(1, "truck", ("truck",), ("Van",))  # a truck pass must not take vans
    plan = make_pass([car, truck], words)
    assert plan.phrases == ("car", "van", "truck")
    assert plan.text == "car . van . truck ."
    assert plan.positive.tolist() == [[True, False], [True, False], [False, True]]
    assert plan.negative.tolist() == [[False, False], [False, True], [False, False]]
    assert plan.num_tokens == 2 + 3 * (1 + 1)  # [CLS] [SEP] + (word + ".") per phrase


def test_plan_passes_joint_packs_classes_in_order_within_budget() -> None:
    classes = [
        ClassPrompts(0, "a", ("a1 a1", "a2")),  # 2 + (2+1) + (1+1) = 7 alone
        ClassPrompts(1, "b", ("b1",)),  # +2
        ClassPrompts(2, "c", ("c1 c1 c1",)),  # +4
        ClassPrompts(3, "d", ("d1",)),  # +2
    ]
    plans = plan_passes(classes, words, budget=11)
    assert [p.class_names for p in plans] == [("a", "b"), ("c", "d")]
    assert [p.num_tokens for p in plans] == [9, 8]
    one = plan_passes(classes, words, budget=15)
    assert [p.class_names for p in one] == [("a", "b", "c", "d")] and one[0].num_tokens == 15
    per = plan_passes(classes, words, budget=15, mode="per-class")
    assert [p.class_names for p in per] == [("a",), ("b",), ("c",), ("d",)]


def test_plan_passes_refuses_a_class_larger_than_the_budget() -> None:
    classes = [ClassPrompts(0, "a", ("a",)), ClassPrompts(1, "big", ("x y z", "u v w"))]
    with pytest.raises(SchemaError, match=r"class 'big': its prompts need 10 text tokens, more than .* 9"):
        plan_passes(classes, words, budget=9)


# ------------------------------------------------------------------------------------ region maths
def test_phrase_max_is_the_max_over_a_class_prompt_columns() -> None:
    logits = np.array(
        [
            [9.0, 1.0, 5.0, 2.0, 3.0, 7.0, -np.inf],
            [9.0, -1.0, -2.0, 4.0, 0.5, 7.0, -np.inf],
        ]
    )
    token_phrase = np.array([-1, 0, -1, 1, 1, -1, -1])  # [CLS] car . parking lot . pad
    # class 0 = {car}, class 1 = {parking lot}, class 2 = {car, parking lot}, class 3 = {}
    member = np.array([[True, False, True, False], [False, True, True, False]])
    got = phrase_max(logits, token_phrase, member)
    # Special columns (9.0, 7.0) never count.
    np.testing.assert_array_equal(got, [[1.0, 3.0, 3.0, NINF], [-1.0, 4.0, 4.0, NINF]])


def test_apply_negatives_rules_out_a_class_only_where_the_negative_wins() -> None:
    pos = np.array([[2.0, 1.0], [2.0, 1.0]])
    neg = np.array([[3.0, NINF], [1.5, NINF]])
    np.testing.assert_array_equal(apply_negatives(pos, neg), [[NINF, 1.0], [2.0, 1.0]])


def test_keep_regions_thresholds_the_max_sigmoid() -> None:
    thr = 0.25
    at = math.log(thr / (1 - thr))  # sigmoid(at) == 0.25
    scores = np.array([[at + 1e-3, NINF], [at - 1e-3, at - 0.5], [NINF, 0.0], [NINF, NINF]])
    assert keep_regions(scores, thr).tolist() == [True, False, True, False]
    assert keep_regions(np.zeros((2, 0)), thr).tolist() == [False, False]


def test_sigmoid_is_stable_at_the_extremes() -> None:
    got = sigmoid([-np.inf, -1000.0, 0.0, 1000.0, math.log(3)])
    np.testing.assert_allclose(got, [0.0, 0.0, 0.5, 1.0, 0.75], atol=1e-7)


def test_softmax_classes_hand_values_and_minus_inf() -> None:
    got = softmax_classes([[0.0, math.log(3.0), NINF], [5.0, 5.0, 5.0]])
    np.testing.assert_allclose(got, [[0.25, 0.75, 0.0], [1 / 3, 1 / 3, 1 / 3]], rtol=1e-6)
    assert softmax_classes(np.zeros((0, 4))).shape == (0, 4)
    with pytest.raises(ValueError, match="at least one finite"):
        softmax_classes([[NINF, NINF]])


def test_box_iou_hand_values() -> None:
    a = [[0, 0, 2, 2], [0, 0, 0, 0]]
    b = [[1, 1, 3, 3], [0, 0, 2, 2], [5, 5, 6, 6]]
    np.testing.assert_allclose(box_iou(a, b), [[1 / 7, 1.0, 0.0], [0.0, 0.0, 0.0]], rtol=1e-6)


def test_fill_across_passes_takes_matched_logits_of_other_passes() -> None:
    # Classes: 0 car, 1 truck (pass 0), 2 road (pass 1). Regions 0,1 from pass 0; 2,3 from pass 1.
    boxes = np.array(
        [
            [0, 0, 10, 10],  # r0: same box as r2
            [50, 50, 60, 60],  # r1: matches nothing
            [0, 0, 10, 10.5],  # r2: IoU with r0 = 100/105
            [0, 0, 10, 20],  # r3: IoU with r0 = 0.5
        ],
        dtype=np.float32,
    )
    scores = np.array(
        [
            [2.0, 1.0, 99.0],  # 99 is outside r0's pass and must be ignored
            [0.5, NINF, 99.0],  # truck ruled out by a negative in its own pass: stays -inf
            [99.0, 99.0, -1.0],
            [99.0, 99.0, 3.0],
        ],
        dtype=np.float32,
    )
    member = np.array([[True, True, False], [False, False, True]])
    got = fill_across_passes(boxes, scores, np.array([0, 0, 1, 1]), member, match_iou=0.9)
    np.testing.assert_array_equal(
        got,
        [
            [2.0, 1.0, -1.0],  # road from r2 (r3 has IoU 0.5 < 0.9)
            [0.5, NINF, NINF],
            [2.0, 1.0, -1.0],  # car, truck from r0
            [NINF, NINF, 3.0],
        ],
    )
    lower = fill_across_passes(boxes, scores, np.array([0, 0, 1, 1]), member, match_iou=0.5)
    assert lower[0, 2] == 3.0  # max over r2 (-1) and r3 (3)
    single = fill_across_passes(boxes[:2], scores[:2], np.array([0, 0]), member, match_iou=0.5)
    np.testing.assert_array_equal(single, [[2.0, 1.0, NINF], [0.5, NINF, NINF]])


# ------------------------------------------------------------------------------------------ presets
def _words_by_class(schema: Schema) -> dict[str, set[str]]:
    owners: dict[str, set[str]] = {}
    for c in schema.classes:
        for p in c.prompts:
            for w in p.lower().split():
                owners.setdefault(w, set()).add(c.name)
    return owners


def test_expanded_semantickitti_preset_keeps_the_ids_and_never_shares_a_word() -> None:
    from leap_core.config import config_from_dict
    from leap_core.schema import builtin_schema, load_project_file, projects_dir

    schema, pipeline = load_project_file(projects_dir() / "semantickitti_expanded.yaml")
    base = builtin_schema("semantickitti")
    key = [(c.name, c.color, c.export_id, c.gt_ids, c.category) for c in base.classes]
    assert [(c.name, c.color, c.export_id, c.gt_ids, c.category) for c in schema.classes] == key
    assert all(len(c.prompts) >= 2 for c in schema.classes)  # every class is expanded
    assert {w: o for w, o in _words_by_class(schema).items() if len(o) > 1} == {}
    cfg = config_from_dict(pipeline)
    assert cfg.labeler == "grounded-sam" and cfg.labeler_config(GroundedSamConfig).box_threshold == 0.25
    # One pass of 256 tokens holds every prompt when each word is one word piece.
    classes = [ClassPrompts(i, c.name, c.prompts, c.negative_prompts) for i, c in enumerate(schema.classes)]
    assert len(plan_passes(classes, words, budget=256)) == 1


def test_agri_uav_preset_uses_the_paper_threshold_and_seven_classes() -> None:
    from leap_core.config import config_from_dict
    from leap_core.schema import load_project_file, projects_dir

    schema, pipeline = load_project_file(projects_dir() / "agri_uav.yaml")
    assert schema.names == ["tree", "pole", "fence", "wire", "person", "building", "ground"]
    assert {w: o for w, o in _words_by_class(schema).items() if len(o) > 1} == {}
    cfg = config_from_dict(pipeline)
    assert cfg.labeler == "grounded-sam" and cfg.labeler_config(GroundedSamConfig).box_threshold == 0.2
