"""The grounded-sam labeler: exact stage-A maths on fabricated detector outputs, and the real code path
with tiny RANDOM-weight Grounding DINO + SAM models built from configs, saved to a temp folder and loaded
back exactly as a user's downloaded models are (their labels are meaningless; the wiring is what is
tested)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytest
import torch
from runhelpers import folder

from leap_core.config import config_from_dict, config_to_dict
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import ConfigError, LeapError, ModelLoadError
from leap_core.labelers.base import SoftMasks, model_dtype
from leap_core.labelers.cache import LabelCache, PassResult, cache_key, image_digest
from leap_core.labelers.grounded_sam import (
    LABELER_VERSION,
    GroundedSamConfig,
    GroundedSamLabeler,
    assemble_soft_masks,
    model_folder_name,
    pass_regions,
    pick_device,
)
from leap_core.labelers.prompts import ClassPrompts, make_pass, sigmoid
from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
from leap_core.runtime import Runtime
from leap_core.schema import ClassDef, Schema, save_schema

NINF = -np.inf


# ============================================================================ fabricated outputs
def test_pass_regions_thresholds_scores_and_converts_boxes() -> None:
    car = ClassPrompts(0, "car", ("car", "van"), ())
    road = ClassPrompts(1, "road", ("road",), ("sidewalk",))
    plan = make_pass([car, road], lambda _phrase: 1)  # text "car . van . road . sidewalk ."
    assert plan.text == "car . van . road . sidewalk ."
    # columns: [CLS] car . van . road . sidewalk . [SEP] pad pad
    token_phrase = np.array([-1, 0, -1, 1, -1, 2, -1, 3, -1, -1, -1, -1])
    logits = np.full((4, 12), -9.0, dtype=np.float32)
    logits[:, 10:] = NINF
    logits[0, [1, 3, 5]] = [0.5, 2.0, -3.0]  # car = max(0.5, 2.0) = 2.0
    logits[1, [5, 7]] = [1.0, 0.0]  # road 1.0 beats its negative 0.0
    logits[2, [5, 7]] = [1.0, 4.0]  # road ruled out by "sidewalk"; nothing else reaches the threshold
    logits[3, 0] = 50.0  # only [CLS] fires: not a class match
    boxes = np.array([[0.5, 0.5, 0.2, 0.4], [0.1, 0.9, 0.4, 0.4], [0.5, 0.5, 1, 1], [0.5, 0.5, 1, 1]])
    got_boxes, got_scores = pass_regions(logits, boxes, token_phrase, plan, 0.25, (100, 200))
    np.testing.assert_allclose(got_boxes, [[80, 30, 120, 70], [0, 70, 60, 100]])  # second one clipped
    np.testing.assert_array_equal(got_scores, [[2.0, -3.0], [-9.0, 1.0]])


def _result(
    names: tuple[str, ...], boxes: list[list[float]], scores: list[list[float]], masks: np.ndarray
) -> PassResult:
    m = np.asarray(masks, dtype=bool)
    r, h, w = m.shape
    return PassResult(
        h,
        w,
        names,
        np.asarray(boxes, np.float32).reshape(r, 4),
        np.asarray(scores, np.float32).reshape(r, len(names)),
        np.packbits(m.reshape(r, h * w), axis=1),
    )


def test_assemble_one_pass_softmax_confidence_and_overlap_weighting() -> None:
    # 2×3 image; mask A covers columns 0-1, mask B columns 1-2: they overlap in column 1.
    a = np.array([[1, 1, 0], [1, 1, 0]])
    b = np.array([[0, 1, 1], [0, 1, 1]])
    la, lb = math.log(3.0), math.log(1 / 3)
    res = _result(("x", "y"), [[0, 0, 2, 2], [1, 0, 3, 2]], [[la, 0.0], [0.0, la]], np.stack([a, b]))
    sm = assemble_soft_masks([res], ["x", "y"], match_iou=0.7)
    np.testing.assert_allclose(sm.probs, [[0.75, 0.25], [0.25, 0.75]], rtol=1e-6)
    np.testing.assert_allclose(sm.confidence, [0.75, 0.75], rtol=1e-6)  # sigmoid(log 3)
    # Column 1: equal confidences -> plain average; change B's confidence to check the weighting.
    res2 = _result(("x", "y"), [[0, 0, 2, 2], [1, 0, 3, 2]], [[la, 0.0], [lb, 0.0]], np.stack([a, b]))
    sm2 = assemble_soft_masks([res2], ["x", "y"], match_iou=0.7)
    wa, wb = 0.75, 0.5  # sigmoid(log 3), sigmoid(max(log 1/3, 0))
    pa, pb = np.array([0.75, 0.25]), np.array([0.25, 0.75])
    px = sm2.pixel_probs()
    np.testing.assert_allclose(px[0, 0], pa, rtol=1e-6)
    np.testing.assert_allclose(px[1, 1], (wa * pa + wb * pb) / (wa + wb), rtol=1e-6)
    np.testing.assert_allclose(px[0, 2], pb, rtol=1e-6)


def test_assemble_maps_pass_columns_to_schema_order_fills_and_drops_empty_masks() -> None:
    full = np.ones((1, 2, 2), dtype=bool)
    empty = np.zeros((1, 2, 2), dtype=bool)
    p_road = _result(("road",), [[0, 0, 2, 2]], [[0.0]], full)
    p_car = _result(
        ("car", "truck"),
        [[0, 0, 2, 2], [0, 0, 1, 1]],
        [[math.log(2), 0.0], [5.0, 5.0]],
        np.concatenate([full, empty]),
    )
    sm = assemble_soft_masks([p_road, p_car], ["car", "truck", "road"], match_iou=0.9)
    assert sm.num_masks == 2 and sm.num_classes == 3  # the empty-mask region is gone
    # Road region: its own road logit 0, car/truck from the matched box (log 2, 0) -> weights 1 : 2 : 1.
    np.testing.assert_allclose(sm.probs[0], [0.5, 0.25, 0.25], rtol=1e-6)
    np.testing.assert_allclose(sm.probs[1], [0.5, 0.25, 0.25], rtol=1e-6)
    np.testing.assert_allclose(sm.confidence, [0.5, 2 / 3], rtol=1e-6)  # own pass only
    none = assemble_soft_masks([_result(("car",), [], [], np.zeros((0, 2, 2)))], ["car"], 0.7)
    assert none.num_masks == 0 and none.num_classes == 1


# ================================================================================ tiny real models
@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # 12 queries instead of 30: fewer SAM boxes keep the file fast on a shared 2-core CPU.
    return make_tiny_models(tmp_path_factory.mktemp("models"), TinyModelsConfig(num_queries=12)).models_dir


def small_schema(**edits: tuple[str, ...]) -> Schema:
    classes = [
        ("car", (255, 0, 0), ("car", "automobile"), 10),
        ("road", (0, 0, 255), ("road", "street"), 40),
        ("pole", (0, 255, 0), ("pole", "lamp post"), 80),
    ]
    return Schema("small", tuple(ClassDef(n, c, edits.get(n, p), e) for n, c, p, e in classes))


def images(n: int = 2, hw: tuple[int, int] = (40, 96)) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, (*hw, 3), dtype=np.uint8) for _ in range(n)]


def counting(labeler: GroundedSamLabeler) -> dict[str, int]:
    """Count real forward calls of the detector and of SAM's image encoder."""
    calls = {"detector": 0, "sam": 0}

    def hook(name: str) -> Callable[..., None]:
        def f(*_: object) -> None:
            calls[name] += 1

        return f

    labeler.models.detector.register_forward_hook(hook("detector"))
    labeler.models.segmenter.vision_encoder.register_forward_hook(hook("sam"))
    return calls


def direct_scores(
    det_dir: Path, image: np.ndarray, text: str, phrase_classes: list[tuple[str, int]], c: int
) -> tuple[np.ndarray, np.ndarray]:
    """Class logits (Q, C) and xyxy boxes computed straight from transformers, locating each phrase's
    token columns by searching its token ids in the text's ids (independent of offsets)."""
    from transformers import AutoProcessor, GroundingDinoForObjectDetection

    proc = AutoProcessor.from_pretrained(det_dir, local_files_only=True)
    model = GroundingDinoForObjectDetection.from_pretrained(det_dir, local_files_only=True).eval()
    inputs = proc(images=[image], text=text, return_tensors="pt")
    with torch.no_grad():
        out = model(**inputs)
    logits = out.logits[0].numpy()
    ids = inputs["input_ids"][0].tolist()
    s = np.full((logits.shape[0], c), NINF, dtype=np.float32)
    pos = 1
    for phrase, cls in phrase_classes:
        pid = proc.tokenizer(phrase, add_special_tokens=False)["input_ids"]
        while ids[pos : pos + len(pid)] != pid:
            pos += 1
        cols = list(range(pos, pos + len(pid)))
        pos += len(pid)
        s[:, cls] = np.maximum(s[:, cls], logits[:, cols].max(axis=1))
    h, w = image.shape[:2]
    cx, cy, bw, bh = out.pred_boxes[0].numpy().T
    xyxy = np.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], 1)
    boxes = np.clip(xyxy * [w, h, w, h], 0, [w, h, w, h])
    return s, boxes


def test_labeler_matches_a_direct_transformers_computation(tiny_dir: Path, tmp_path: Path) -> None:
    schema = small_schema()
    img = images(1)[0]
    det_dir = tiny_dir / "grounding-dino-tiny"
    phrase_classes = [
        ("car", 0),
        ("automobile", 0),
        ("road", 1),
        ("street", 1),
        ("pole", 2),
        ("lamp post", 2),
    ]
    text = "car . automobile . road . street . pole . lamp post ."
    s, boxes = direct_scores(det_dir, img, text, phrase_classes, 3)
    conf = 1 / (1 + np.exp(-s.max(axis=1)))
    c = np.sort(conf)
    i = int(np.argmax(np.diff(c)))
    thr = float((c[i] + c[i + 1]) / 2)  # in the widest gap: some regions are kept, some are not
    lab = GroundedSamLabeler(
        GroundedSamConfig(box_threshold=thr), Runtime(models_dir=tiny_dir), cache=LabelCache(tmp_path)
    )
    sm = lab.label_images([img], schema)[0]
    plans = lab.plan(schema)
    assert len(plans) == 1 and plans[0].text == "car . automobile . road . street . pole . lamp post ."
    assert lab.cache is not None
    stored = lab.cache.get(lab.pass_key(image_digest(img), plans[0]))
    assert stored is not None
    keep = conf >= np.float32(thr)
    assert 0 < keep.sum() < len(keep)
    np.testing.assert_allclose(stored.scores, s[keep], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(stored.boxes, boxes[keep], rtol=1e-4, atol=1e-3)
    # SoftMasks: softmax of the same logits for the regions whose SAM mask is not empty.
    nonempty = stored.bits.any(axis=1)
    e = np.exp(s[keep] - s[keep].max(axis=1, keepdims=True))
    np.testing.assert_allclose(sm.probs, (e / e.sum(1, keepdims=True))[nonempty], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(sm.confidence, conf[keep][nonempty], rtol=1e-5)
    assert (sm.height, sm.width) == img.shape[:2]


def test_sam_masks_match_a_direct_sam_call(tiny_dir: Path) -> None:
    from transformers import AutoProcessor, SamModel

    img = images(1)[0]
    lab = GroundedSamLabeler(GroundedSamConfig(box_threshold=0.01), Runtime(models_dir=tiny_dir))
    boxes = np.array([[5, 4, 60, 30], [0, 0, 96, 40], [70, 10, 90, 39]], dtype=np.float32)
    bits = lab._segment([img], [boxes])[0]
    seg_dir = tiny_dir / "sam-vit-base"
    proc = AutoProcessor.from_pretrained(seg_dir, local_files_only=True)
    model = SamModel.from_pretrained(seg_dir, local_files_only=True).eval()
    inputs = proc(images=[img], input_boxes=[boxes.tolist()], return_tensors="pt")
    with torch.no_grad():
        out = model(**inputs, multimask_output=True)
    masks = proc.image_processor.post_process_masks(
        out.pred_masks, inputs["original_sizes"], inputs["reshaped_input_sizes"]
    )[0]
    best = out.iou_scores[0].argmax(dim=1)
    want = masks[torch.arange(3), best].numpy()  # (3, H, W)
    got = np.unpackbits(bits, axis=1, count=40 * 96).reshape(3, 40, 96).astype(bool)
    assert (got == want).mean() > 0.999  # one bilinear pass per chunk: equal up to rounding at edges


def test_frames_of_a_sequence_through_the_labeler(tiny_dir: Path, tmp_path: Path) -> None:
    from conftest import build_tiny_sequence

    from leap_core.datasets.kitti import KittiSequence

    seq = KittiSequence(build_tiny_sequence(tmp_path, n_frames=2).root)
    lab = GroundedSamLabeler(
        GroundedSamConfig(box_threshold=0.05, batch_size=2), Runtime(models_dir=tiny_dir)
    )
    frames = list(seq)
    out = lab.label_frames(frames, small_schema())
    assert lab.detector_calls == 1 and lab.segmenter_calls == 1  # both frames in one batch
    for f, sm in zip(frames, out, strict=True):
        assert isinstance(sm, SoftMasks) and (sm.height, sm.width) == f.image.shape[:2]
        assert sm.num_classes == 3 and sm.num_masks > 0
        np.testing.assert_allclose(sm.probs.sum(axis=1), 1.0, rtol=1e-5)
        assert (sm.confidence >= 0.05).all() and (sm.confidence <= 1).all()
    single = lab.label(frames[1], small_schema())
    np.testing.assert_array_equal(single.bits, out[1].bits)
    np.testing.assert_allclose(single.probs, out[1].probs, rtol=1e-5, atol=1e-6)


def test_cache_hit_calls_no_model(tiny_dir: Path, tmp_path: Path) -> None:
    cfg = GroundedSamConfig(box_threshold=0.05, batch_size=2)
    rt = Runtime(models_dir=tiny_dir, cache_dir=tmp_path / "c")
    first = GroundedSamLabeler(cfg, rt)
    calls = counting(first)
    a = first.label_images(images(2), small_schema())
    assert calls == {"detector": 1, "sam": 1}
    second = GroundedSamLabeler(cfg, rt)  # a new process would start like this
    b = second.label_images(images(2), small_schema())
    assert second._models is None  # the weights were never even loaded
    assert second.detector_calls == 0 and second.segmenter_calls == 0
    assert second.cache is not None and second.cache.hits == 2
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.bits, y.bits)
        np.testing.assert_array_equal(x.probs, y.probs)
    # Joint mode: editing one class's prompts changes the single text, so the pass reruns.
    third = GroundedSamLabeler(cfg, rt)
    third.label_images(images(2), small_schema(pole=("pole", "utility pole")))
    assert third.detector_calls == 1


@pytest.mark.slow
def test_per_class_mode_reruns_only_the_edited_class(tiny_dir: Path, tmp_path: Path) -> None:
    cfg = GroundedSamConfig(box_threshold=0.05, mode="per-class")
    lab = GroundedSamLabeler(cfg, Runtime(models_dir=tiny_dir, cache_dir=tmp_path))
    calls = counting(lab)
    before = lab.label_images(images(1), small_schema())[0]
    assert calls == {"detector": 3, "sam": 1}  # one detector pass per class, one SAM encoding per image
    assert [p.text for p in lab.plan(small_schema())] == [
        "car . automobile .",
        "road . street .",
        "pole . lamp post .",
    ]
    edited = small_schema(road=("road", "asphalt"))
    after = lab.label_images(images(1), edited)[0]
    assert calls == {"detector": 4, "sam": 2}  # only the road pass ran again
    assert lab.cache is not None and lab.cache.hits == 2  # car and pole
    assert after.num_classes == 3 and before.num_classes == 3
    np.testing.assert_allclose(after.probs.sum(axis=1), 1.0, rtol=1e-5)


def test_prompts_over_the_token_budget_run_in_several_passes(tiny_dir: Path) -> None:
    schema = small_schema()
    cfg = GroundedSamConfig(box_threshold=0.05, max_text_tokens=9)
    lab = GroundedSamLabeler(cfg, Runtime(models_dir=tiny_dir))
    plans = lab.plan(schema)
    # car . automobile . = 2 + 1 + 1 + 1 + 1 tokens ... car alone is 6, car + road 10, pole alone 7.
    assert [p.class_names for p in plans] == [("car",), ("road",), ("pole",)]
    assert all(p.num_tokens <= 9 for p in plans)
    calls = counting(lab)
    sm = lab.label_images(images(1), schema)[0]
    assert calls["detector"] == 3 and calls["sam"] == 1
    np.testing.assert_allclose(sm.probs.sum(axis=1), 1.0, rtol=1e-5)
    wide = GroundedSamLabeler(dataclasses.replace(cfg, max_text_tokens=256), Runtime(models_dir=tiny_dir))
    assert len(wide.plan(schema)) == 1


def test_flip_votes_join_each_image_with_its_mirror_and_change_the_fingerprint(tiny_dir: Path) -> None:
    img = images(1)[0]
    plain = GroundedSamLabeler(GroundedSamConfig(box_threshold=0.05), Runtime(models_dir=tiny_dir))
    flip = GroundedSamLabeler(
        GroundedSamConfig(box_threshold=0.05, flip_votes=True), Runtime(models_dir=tiny_dir)
    )
    voted = flip.label_images([img], small_schema())[0]
    one, mirror = plain.label_images([img, np.ascontiguousarray(img[:, ::-1])], small_schema())
    assert one.num_masks > 0 and mirror.num_masks > 0
    want = one.joined(mirror.mirrored())
    np.testing.assert_array_equal(voted.bits, want.bits)
    np.testing.assert_allclose(voted.probs, want.probs, rtol=1e-5, atol=1e-6)
    assert flip.detector_calls == 2  # the image and its mirror: twice the detector work
    assert plain.fingerprint(small_schema()) != flip.fingerprint(small_schema())


def test_fingerprint_tracks_prompts_settings_and_weights(tiny_dir: Path, tmp_path: Path) -> None:
    cfg = GroundedSamConfig()
    rt = Runtime(models_dir=tiny_dir)
    fp = GroundedSamLabeler(cfg, rt).fingerprint(small_schema())
    assert fp == GroundedSamLabeler(cfg, rt).fingerprint(small_schema())
    assert fp != GroundedSamLabeler(cfg, rt).fingerprint(small_schema(car=("car",)))
    other_threshold = dataclasses.replace(cfg, box_threshold=0.3)
    assert fp != GroundedSamLabeler(other_threshold, rt).fingerprint(small_schema())
    assert fp == GroundedSamLabeler(dataclasses.replace(cfg, batch_size=4), rt).fingerprint(small_schema())
    # Deployment values are not part of the labels' identity; the models' contents are.
    moved = copy_models(tiny_dir, tmp_path)
    elsewhere = Runtime(models_dir=moved, device="cpu", cache_dir=tmp_path)
    assert fp == GroundedSamLabeler(cfg, elsewhere).fingerprint(small_schema())
    other = make_tiny_models(tmp_path / "other", TinyModelsConfig(num_queries=20))
    assert fp != GroundedSamLabeler(cfg, Runtime(models_dir=other.models_dir)).fingerprint(small_schema())


def test_half_precision_is_ignored_on_the_cpu_and_keys_its_own_cache_entries(
    tiny_dir: Path, tmp_path: Path
) -> None:
    assert model_dtype("cuda", True) == torch.float16
    assert model_dtype("cuda", False) == model_dtype("cpu", True) == torch.float32
    schema, img = small_schema(), images(1)[0]
    cfg = GroundedSamConfig(box_threshold=0.05)
    rt = Runtime(models_dir=tiny_dir, device="cpu", cache_dir=tmp_path)
    plain = GroundedSamLabeler(cfg, rt)
    half = GroundedSamLabeler(dataclasses.replace(cfg, half_precision=True), rt)
    (a,) = plain.label_images([img], schema)
    (b,) = half.label_images([img], schema)
    assert half.detector_calls == 1  # the float32 run's cache entries are not served to it
    assert half.models.dtype == torch.float32
    assert {p.dtype for m in (half.models.detector, half.models.segmenter) for p in m.parameters()} == {
        torch.float32
    }
    assert a.num_masks > 0 and a.arrays().keys() == b.arrays().keys()
    for name, x in a.arrays().items():  # the CPU computed the same thing byte for byte
        assert x.dtype == b.arrays()[name].dtype and x.tobytes() == b.arrays()[name].tobytes(), name
    digest, (plan,) = image_digest(img), plain.plan(schema)
    assert plain.pass_key(digest, plan) != half.pass_key(digest, plan)
    assert plain.fingerprint(schema) != half.fingerprint(schema)
    # Off, the key is what it was before the setting existed: caches filled then stay valid.
    before = {"version": LABELER_VERSION, **plain.identity(), "box_threshold": 0.05, "mode": "joint"}
    before |= {"multimask": True, "mask_threshold": 0.0}
    assert plain.pass_key(digest, plan) == cache_key({"image": digest, **before, "pass": plan.key_parts()})
    # A project setting like any other: read, written back, and a switch must be a switch.
    read = config_from_dict({"grounded_sam": {"half_precision": True}})
    assert read.labeler_config(GroundedSamConfig).half_precision is True
    assert config_to_dict(read)["grounded_sam"]["half_precision"] is True
    assert config_from_dict(config_to_dict(read)) == read
    with pytest.raises(ConfigError, match="must be true or false") as err:
        config_from_dict({"grounded_sam": {"half_precision": 1}})
    assert err.value.field[-2:] == ("grounded_sam", "half_precision")


def half_precision_agreement(full: Sequence[PassResult], half: Sequence[PassResult]) -> tuple[float, float]:
    """How closely float16 pass results follow float32 ones of the same images: the share of float32
    regions found again (a float16 region with its box within 1 px and every class logit within 0.1), and
    the median share of mask pixels the same between such pairs. Random weights leave near-ties that
    float16 rounding flips (which encoder proposals become queries, which of SAM's 3 candidates wins), so
    neither is 1."""
    found, agree = [], []
    for a, b in zip(full, half, strict=True):
        near = (np.abs(a.boxes[:, None] - b.boxes[None]).max(axis=2) <= 1.0) & (
            np.abs(a.scores[:, None] - b.scores[None]).max(axis=2) <= 0.1
        )
        found.extend(near.any(axis=1))
        ua, ub = np.unpackbits(a.bits, axis=1), np.unpackbits(b.bits, axis=1)
        agree.extend((ua[i] == ub[near[i].argmax()]).mean() for i in np.flatnonzero(near.any(axis=1)))
    return float(np.mean(found)), float(np.median(agree))


def test_float16_models_give_float32_results_near_the_float32_ones(tiny_dir: Path, tmp_path: Path) -> None:
    """The CUDA float16 path run on the CPU, with the models cast by hand as the benchmarks hold them: the
    pixel inputs follow the models' dtype and the cached results come back float32."""
    schema, imgs = small_schema(), images(2)
    # A threshold just above zero: every query is kept in both precisions, whatever its rounding.
    cfg = GroundedSamConfig(box_threshold=1e-6, batch_size=2)
    full = GroundedSamLabeler(cfg, Runtime(models_dir=tiny_dir), cache=LabelCache(tmp_path / "full"))
    half = GroundedSamLabeler(
        dataclasses.replace(cfg, half_precision=True),
        Runtime(models_dir=tiny_dir),
        cache=LabelCache(tmp_path / "half"),
    )
    m = half.models
    half._models = dataclasses.replace(
        m, detector=m.detector.half(), segmenter=m.segmenter.half(), dtype=torch.float16
    )
    full.label_images(imgs, schema)
    out = half.label_images(imgs, schema)
    assert all(sm.num_masks > 0 and sm.probs.dtype == np.float32 for sm in out)
    (plan,) = half.plan(schema)
    results = []
    for lab in (full, half):
        assert lab.cache is not None
        got = [lab.cache.get(lab.pass_key(image_digest(im), plan)) for im in imgs]
        assert all(r is not None and r.scores.dtype == r.boxes.dtype == np.float32 for r in got)
        results.append([r for r in got if r is not None])
    found, agree = half_precision_agreement(results[0], results[1])
    assert found >= 0.75 and agree >= 0.9, (found, agree)


@pytest.mark.parametrize("umask", [0o022, 0o002])
def test_make_tiny_models_and_folder_exports_write_files_with_the_umasks_mode(
    tmp_path: Path, umask: int
) -> None:
    """``leap make-tiny-models`` writes every file with 0o666 & ~umask (0644, 0664) like ``open()``, not the
    0600 of the temp file transformers writes weights through; a folder export of a 0600 ``.label`` file
    gets the umask's mode too (a colleague can read what is exported)."""
    import os
    import stat

    from typer.testing import CliRunner

    from app.cli import cli
    from leap_core.export import write_export_folder
    from leap_core.io_utils import atomic_copy

    private = tmp_path / "run" / "000000.label"
    private.parent.mkdir()
    private.write_bytes(b"\x0a\x00\x00\x00")
    private.chmod(0o600)
    old = os.umask(umask)
    try:
        res = CliRunner().invoke(cli, ["make-tiny-models", str(tmp_path / "models")])
        write_export_folder(tmp_path / "out" / "predictions", [private])
        atomic_copy(private, tmp_path / "copy" / "000000.label")
    finally:
        os.umask(old)
    assert res.exit_code == 0, res.output
    written = [tmp_path / "out" / "predictions" / "000000.label", tmp_path / "copy" / "000000.label"]
    written += [p for p in (tmp_path / "models").rglob("*") if p.is_file()]
    assert {p.name for p in written} >= {"model.safetensors", "config.json", "README.txt", "000000.label"}
    modes = {str(p.relative_to(tmp_path)): oct(stat.S_IMODE(p.stat().st_mode)) for p in written}
    assert set(modes.values()) == {oct(0o666 & ~umask)}, modes
    folders = [p for p in (tmp_path / "models").rglob("*") if p.is_dir()]
    assert {oct(stat.S_IMODE(p.stat().st_mode)) for p in folders} == {oct(0o777 & ~umask)}
    assert (tmp_path / "copy" / "000000.label").read_bytes() == private.read_bytes()


# ============================================================================== loading errors
def test_missing_model_folder_says_where_and_how_to_download(tmp_path: Path) -> None:
    lab = GroundedSamLabeler(GroundedSamConfig(), Runtime(models_dir=tmp_path / "models"))
    with pytest.raises(ModelLoadError) as err:
        lab.plan(small_schema())
    msg = str(err.value)
    assert str(tmp_path / "models" / "grounding-dino-tiny") in msg
    assert "hf download IDEA-Research/grounding-dino-tiny --local-dir" in msg
    assert "\n" not in msg


def test_model_not_in_the_hugging_face_cache_is_a_clear_error() -> None:
    cfg = GroundedSamConfig(detector_id="leap-studio-tests/no-such-model")
    with pytest.raises(
        ModelLoadError, match=r"leap-studio-tests/no-such-model: not in the Hugging Face cache.*hf download"
    ):
        GroundedSamLabeler(cfg).plan(small_schema())


def copy_models(tiny_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "m"
    shutil.copytree(tiny_dir, dst)
    return dst


def test_unreadable_config_and_weights_are_clear_errors(tiny_dir: Path, tmp_path: Path) -> None:
    models = copy_models(tiny_dir, tmp_path)
    (models / "grounding-dino-tiny" / "config.json").write_text("{not json")
    with pytest.raises(ModelLoadError, match=r"grounding-dino-tiny/config\.json: unreadable model config"):
        GroundedSamLabeler(GroundedSamConfig(), Runtime(models_dir=models)).plan(small_schema())
    config = "grounding-dino-tiny/config.json"
    shutil.copy(tiny_dir / config, models / config)
    (models / "sam-vit-base" / "model.safetensors").write_bytes(b"truncated")
    lab = GroundedSamLabeler(GroundedSamConfig(), Runtime(models_dir=models))
    with pytest.raises(
        ModelLoadError, match=r"sam-vit-base: cannot load facebook/sam-vit-base weights.*hf download"
    ):
        lab.label_images(images(1), small_schema())


def test_wrong_model_in_a_folder_is_a_clear_error(tiny_dir: Path) -> None:
    cfg = GroundedSamConfig(detector_id="facebook/sam-vit-base")
    with pytest.raises(ModelLoadError, match="holds a 'sam' model, expected 'grounding-dino'"):
        GroundedSamLabeler(cfg, Runtime(models_dir=tiny_dir)).plan(small_schema())


def test_tokenizer_without_bert_special_ids_is_refused(tiny_dir: Path, tmp_path: Path) -> None:
    from transformers import BertTokenizer

    models = copy_models(tiny_dir, tmp_path)
    folder = models / "grounding-dino-tiny"
    vocab = {"[PAD]": 0, "[UNK]": 1, "[CLS]": 2, "[SEP]": 3, "[MASK]": 4, ".": 5, "?": 6, "car": 7}
    BertTokenizer(vocab=vocab).save_pretrained(folder)
    with pytest.raises(ModelLoadError, match="differ from the BERT ids"):
        GroundedSamLabeler(GroundedSamConfig(), Runtime(models_dir=models)).plan(small_schema())


def test_config_validation_and_device_choice() -> None:
    with pytest.raises(ConfigError, match=r"^box_threshold: must be in \(0, 1\)") as err:
        GroundedSamConfig(box_threshold=0.0)
    assert err.value.field == ("box_threshold",)
    with pytest.raises(ConfigError, match=r"^mode: must be"):
        GroundedSamConfig(mode="both")  # type: ignore[arg-type]  # invalid on purpose: the check under test
    with pytest.raises(ConfigError, match=r"^device: must be") as err:
        Runtime(device="gpu")  # type: ignore[arg-type]  # invalid on purpose: the check under test
    assert err.value.field == ("device",)
    assert model_folder_name("IDEA-Research/grounding-dino-tiny") == "grounding-dino-tiny"
    assert pick_device("cpu") == "cpu"
    assert pick_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(LeapError, match="no CUDA GPU"):
            pick_device("cuda")


def test_tiny_folders_are_marked_as_random(tiny_dir: Path) -> None:
    lab = GroundedSamLabeler(GroundedSamConfig(), Runtime(models_dir=tiny_dir))
    assert lab.uses_random_weights
    cfg = json.loads((tiny_dir / "grounding-dino-tiny" / "config.json").read_text())
    assert cfg["decoder_layers"] >= 2 and cfg["model_type"] == "grounding-dino"


# ====================================================================================== commands
@pytest.mark.slow
def test_labels2d_command_precomputes_and_resumes(tiny_dir: Path, tmp_path: Path) -> None:
    from conftest import build_tiny_sequence
    from typer.testing import CliRunner

    from app.cli import cli as app

    root = build_tiny_sequence(tmp_path, n_frames=3).root
    (root / "poses.txt").unlink()  # 2D labels need no poses (most recordings come without)
    cache = tmp_path / "cache"
    schema = tmp_path / "small.yaml"
    save_schema(
        small_schema(), schema, pipeline={"grounded_sam": {"box_threshold": 0.05, "mode": "per-class"}}
    )
    args = [
        "labels2d",
        str(root),
        "--schema",
        str(schema),
        "--models",
        str(tiny_dir),
        "--cache",
        str(cache),
        "--batch-size",
        "2",
    ]
    runner = CliRunner()
    first = runner.invoke(app, args)
    assert first.exit_code == 0, first.output
    assert "0 cached, 3 to label; 3 detector pass(es) per image" in first.output  # per-class from the project
    assert "done: 3 frames labeled, 6 detector and 2 SAM encoder" in first.output  # batches of 2 + 1 frames
    assert len(list(cache.rglob("*.npz"))) == 3 * 3
    # Interrupted runs resume: remove one frame's entries and run again.
    victim = sorted(cache.rglob("*.npz"))[0]
    victim.unlink()
    second = runner.invoke(app, args)
    assert second.exit_code == 0, second.output
    assert "2 cached, 1 to label" in second.output
    assert "done: 1 frames labeled, 1 detector and 1 SAM encoder" in second.output
    bad = runner.invoke(app, ["labels2d", str(root), "--models", str(tmp_path / "nowhere")])
    assert bad.exit_code == 2 and "hf download" in bad.output


@pytest.mark.slow
def test_leap_run_with_grounded_sam_end_to_end_reads_the_labels2d_cache(
    tiny_dir: Path, tmp_path: Path
) -> None:
    from conftest import build_tiny_sequence
    from typer.testing import CliRunner

    from app.cli import cli as app

    root = build_tiny_sequence(tmp_path, n_frames=3).root
    models = copy_models(tiny_dir, tmp_path)
    proj = tmp_path / "small.yaml"
    gs = {"box_threshold": 0.05, "mode": "per-class"}
    save_schema(small_schema(), proj, pipeline={"grounded_sam": gs})
    cache = tmp_path / "cache"
    runner = CliRunner()
    pre = runner.invoke(
        app, ["labels2d", str(root), "--schema", str(proj), "--cache", str(cache), "--models", str(models)]
    )
    assert pre.exit_code == 0, pre.output
    # Same-size garbage weights keep the model identity (and so the cache keys) but make any model load
    # fail: the run below can only succeed by reading the 2D cache.
    for f in models.rglob("model.safetensors"):
        f.write_bytes(b"\0" * f.stat().st_size)
    run = runner.invoke(
        app,
        [
            "run",
            str(root),
            "--out",
            str(tmp_path / "run"),
            "--project-file",
            str(proj),
            "--labeler",
            "grounded-sam",
            "--cache",
            str(cache),
            "--models",
            str(models),
        ],
    )
    assert run.exit_code == 0, run.output
    assert "2D labels: grounded-sam" in run.output and "3 .label files" in run.output
    direct = GroundedSamLabeler(
        GroundedSamConfig(**gs), Runtime(models_dir=models), cache=LabelCache(cache / "passes")
    )
    for fid in ("000000", "000001", "000002"):
        soft = SoftMasks.load(folder(tmp_path / "run") / "labels2d" / f"{fid}.npz")
        want = direct.label_images([KittiSequence(root).frame(int(fid)).image], small_schema())[0]
        np.testing.assert_array_equal(soft.bits, want.bits)
        np.testing.assert_allclose(soft.probs, want.probs)
        assert (folder(tmp_path / "run") / "export" / f"{fid}.label").is_file()
    assert direct._models is None
    # Without the cache the (now broken) weights are needed: a one-line error, not a crash.
    bad = runner.invoke(
        app,
        [
            "run",
            str(root),
            "--out",
            str(tmp_path / "run2"),
            "--project-file",
            str(proj),
            "--labeler",
            "grounded-sam",
            "--models",
            str(models),
        ],
    )
    assert bad.exit_code == 2 and "cannot load IDEA-Research/grounding-dino-tiny weights" in bad.output


def test_make_tiny_models_command(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import cli as app

    res = CliRunner().invoke(app, ["make-tiny-models", str(tmp_path / "tm")])
    assert res.exit_code == 0, res.output
    assert "RANDOM weights" in res.output
    lab = GroundedSamLabeler(GroundedSamConfig(box_threshold=0.05), Runtime(models_dir=tmp_path / "tm"))
    assert lab.label_images(images(1), small_schema())[0].num_classes == 3


@pytest.mark.slow
def test_a_frames_cameras_are_labeled_in_one_batch(
    tiny_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The labels2d stage on a two-camera sequence hands the labeler each frame's two images at once (one
    batch through the models), and each camera's file holds what labeling its image alone gives."""
    from conftest import TINY_IMAGE_HW, build_tiny_sequence
    from runhelpers import label

    from leap_core.config import config_from_dict
    from leap_core.datasets.kitti import KittiSequence, write_image

    tiny = build_tiny_sequence(tmp_path, n_frames=2)
    for fid, img in zip(tiny.frame_ids, images(2, TINY_IMAGE_HW), strict=True):
        write_image(tiny.root / "image_3" / f"{fid}.png", img)
    # A second camera 0.5 m to the right of the first: P2 with its own x offset (f · 0.5 m).
    calib = tiny.root / "calib.txt"
    p2 = next(line for line in calib.read_text().splitlines() if line.startswith("P2:")).split()[1:]
    p3 = [*p2[:3], f"{float(p2[3]) - 0.5 * float(p2[0]):.12e}", *p2[4:]]
    calib.write_text(calib.read_text() + "P3: " + " ".join(p3) + "\n")
    calls: list[int] = []
    real = GroundedSamLabeler.label_frames

    def spy(self: GroundedSamLabeler, frames: list[object], schema: Schema) -> list[SoftMasks]:
        calls.append(len(frames))
        return real(self, frames, schema)  # type: ignore[arg-type]

    monkeypatch.setattr(GroundedSamLabeler, "label_frames", spy)
    cfg = config_from_dict(
        {"labeler": "grounded-sam", "grounded_sam": {"box_threshold": 0.05, "batch_size": 2}}
    )
    run = label(
        tiny.root,
        small_schema(),
        cfg,
        tmp_path / "run",
        runtime=Runtime(models_dir=tiny_dir),
        until="labels2d",
    )
    assert calls == [2, 2]  # per frame: image_3's and image_2's images together
    seq = KittiSequence(tiny.root)
    lab = GroundedSamLabeler(
        GroundedSamConfig(box_threshold=0.05, batch_size=2), Runtime(models_dir=tiny_dir)
    )
    for i, fid in enumerate(tiny.frame_ids):
        for cam, path in (
            (0, run.folder / "labels2d" / f"{fid}.npz"),
            (1, run.folder / "labels2d" / "image_3" / f"{fid}.npz"),
        ):
            alone = lab.label(seq.frame(i, cam), small_schema())
            got = SoftMasks.load(path)
            np.testing.assert_array_equal(got.bits, alone.bits)
            np.testing.assert_allclose(got.probs, alone.probs, rtol=1e-5, atol=1e-6)
    # `leap labels2d` precomputes every camera's image.
    from typer.testing import CliRunner

    from app.cli import cli

    args = ["labels2d", str(tiny.root), "--models", str(tiny_dir), "--cache", str(tmp_path / "cache")]
    out = CliRunner().invoke(cli, [*args, "--threshold", "0.05"])
    assert out.exit_code == 0, out.output
    assert "4 images of 2 frames from 2 cameras, 0 cached, 4 to label" in out.output
    assert "done: 4 images labeled" in out.output


def test_each_kept_box_of_a_thing_class_is_an_instance(tiny_dir: Path, tmp_path: Path) -> None:
    """Through the tiny models: an instance per kept box whose own class is a thing (car here), its SAM
    mask as its pixels less those of higher-scoring instances, its confidence as its score."""
    schema = small_schema()
    assert schema.things().tolist() == [True, False, False]
    img = images(1)[0]
    lab = GroundedSamLabeler(
        GroundedSamConfig(box_threshold=0.05), Runtime(models_dir=tiny_dir), cache=LabelCache(tmp_path)
    )
    sm = lab.label_images([img], schema)[0]
    assert lab.cache is not None
    stored = lab.cache.get(lab.pass_key(image_digest(img), lab.plan(schema)[0]))
    assert stored is not None and sm.instances is not None
    h, w = img.shape[:2]
    masks = np.unpackbits(stored.bits, axis=1, count=h * w).reshape(-1, h, w).astype(bool)
    conf = sigmoid(stored.scores.max(axis=1))  # the labeler's confidence of each box
    car = (stored.scores.argmax(axis=1) == 0) & masks.any(axis=(1, 2))
    assert 1 < car.sum() < len(car)  # some boxes are cars, some are not
    # Per pixel: the best score among the car masks covering it (0 where none) is its instance's score.
    best = np.where(masks[car], conf[car][:, None, None], 0).max(axis=0)
    ins = sm.instances
    got = np.where(ins.ids > 0, ins.score[np.maximum(ins.ids, 1) - 1], 0)
    np.testing.assert_array_equal(got, best)
    assert (ins.label == 0).all() and ins.num_instances <= car.sum()
    assert (np.diff(ins.score) <= 0).all()  # instance 1 scores highest
