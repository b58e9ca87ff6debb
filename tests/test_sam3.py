"""The sam3 labeler: its stage-A maths on fabricated results, and the real code path with a tiny
RANDOM-weight SAM 3 built from a config, saved to a temp folder and loaded back as a user's downloaded
model is (its labels are meaningless; the wiring is what is tested): each prompt's instances against a
direct transformers call, the prompt-to-class mapping, batching, the cache, flip votes and the
commands."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from runhelpers import folder

from leap_core.errors import ConfigError, LeapError, ModelLoadError
from leap_core.labelers.base import SoftMasks, with_flip_votes
from leap_core.labelers.cache import LabelCache, PassResult, image_digest
from leap_core.labelers.prompts import sigmoid
from leap_core.labelers.sam3 import (
    ImageSettings,
    PromptJob,
    Sam3Labeler,
    Sam3LabelerConfig,
    assemble_prompt_results,
    drop_negated,
    instance_scores,
    prepare_images,
    prompt_jobs,
    read_image_settings,
    score_logits,
)
from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
from leap_core.runtime import Runtime
from leap_core.schema import ClassDef, Schema, save_schema


# ============================================================================ fabricated results
def _one(
    class_name: str, boxes: list[list[float]], scores: list[float], hw: tuple[int, int] = (4, 8)
) -> PassResult:
    h, w = hw
    bits = np.zeros((len(boxes), (h * w + 7) // 8), np.uint8)
    for r, (x0, y0, x1, y1) in enumerate(boxes):
        m = np.zeros((h, w), bool)
        m[int(y0) : int(y1), int(x0) : int(x1)] = True
        bits[r] = np.packbits(m.reshape(-1))
    return PassResult(
        h, w, (class_name,), np.array(boxes, np.float32).reshape(-1, 4), score_logits(scores)[:, None], bits
    )


def test_instance_scores_are_query_times_presence_and_their_logits_invert() -> None:
    s = instance_scores([0.0, 2.0, -40.0], 1.0)
    sig = 1 / (1 + np.exp(-np.array([0.0, 2.0, -40.0])))
    np.testing.assert_allclose(s, sig * (1 / (1 + np.exp(-1.0))), rtol=1e-6)
    logit = score_logits([0.25, 0.5, 0.9])
    np.testing.assert_allclose(1 / (1 + np.exp(-logit)), [0.25, 0.5, 0.9], rtol=1e-6)
    assert np.isfinite(score_logits([0.0, 1.0])).all()  # clipped, never ±inf


def test_a_negative_prompt_drops_only_the_overlapping_instances_it_beats() -> None:
    car = _one("car", [[0, 0, 4, 4], [4, 0, 8, 4], [0, 0, 2, 2]], [0.6, 0.6, 0.6])
    bus = _one("car", [[0, 0, 4, 4], [4, 0, 8, 4]], [0.9, 0.3])  # beats the first, loses to the second
    kept = drop_negated(car, [bus], match_iou=0.7)
    np.testing.assert_array_equal(kept.boxes, [[4, 0, 8, 4], [0, 0, 2, 2]])
    assert kept.scores.shape == (2, 1) and kept.bits.shape == (2, 4)
    assert drop_negated(car, [], 0.7) is car


def test_prompts_of_each_class_land_in_its_column_and_overlaps_share_their_logits() -> None:
    names = ["car", "road", "pole"]
    jobs = [
        PromptJob("car", "car", "positive"),
        PromptJob("car", "automobile", "positive"),
        PromptJob("road", "road", "positive"),
        PromptJob("road", "sidewalk", "negative"),
        PromptJob("pole", "pole", "positive"),
    ]
    results = [
        _one("car", [[0, 0, 4, 4]], [0.8]),
        _one("car", [], []),
        _one("road", [[0, 0, 4, 4], [4, 0, 8, 4]], [0.4, 0.7]),  # the first is the car's box too
        _one("road", [[4, 0, 8, 4]], [0.9]),  # "sidewalk" beats the second road instance
        _one("pole", [[6, 2, 8, 4]], [0.6]),
    ]
    sm = assemble_prompt_results(jobs, results, names, match_iou=0.7)
    assert sm.num_masks == 3 and sm.num_classes == 3
    l_car, l_road = score_logits([0.8])[0], score_logits([0.4])[0]
    e = np.exp([l_car - max(l_car, l_road), l_road - max(l_car, l_road)])
    p_car = e / e.sum()
    # car instance: car and the overlapping road instance's logit; road instance: the same pair
    np.testing.assert_allclose(sm.probs[0], [p_car[0], p_car[1], 0.0], rtol=1e-5)
    np.testing.assert_allclose(sm.probs[1], [p_car[0], p_car[1], 0.0], rtol=1e-5)
    np.testing.assert_allclose(sm.probs[2], [0.0, 0.0, 1.0])  # pole: no other class saw it
    np.testing.assert_allclose(sm.confidence, [0.8, 0.4, 0.6], rtol=1e-5)
    # Every pixel no kept instance covers carries no observation.
    covered = sm.dense().any(axis=0)
    assert covered.sum() == 16 + 4 and not covered[0, 4:6].any()


def test_prompt_jobs_follow_the_schema_and_leave_negatives_out_when_off() -> None:
    schema = Schema(
        "s",
        (
            ClassDef("car", (1, 2, 3), ("car", "van"), 10, negative_prompts=("bus",)),
            ClassDef("road", (4, 5, 6), ("road",), 40),
        ),
    )
    assert [(j.class_name, j.text, j.role) for j in prompt_jobs(schema, True)] == [
        ("car", "car", "positive"),
        ("car", "van", "positive"),
        ("car", "bus", "negative"),
        ("road", "road", "positive"),
    ]
    assert [j.text for j in prompt_jobs(schema, False)] == ["car", "van", "road"]


def test_images_are_resized_to_the_model_input_and_normalised(tmp_path: Path) -> None:
    img = np.full((30, 50, 3), [0, 255, 51], np.uint8)
    out = prepare_images([img, img[:, :20]], ImageSettings(14, 28, (0.5, 0.5, 0.5), (0.5, 0.25, 0.5)))
    assert out.shape == (2, 3, 14, 28) and out.dtype == np.float32
    np.testing.assert_allclose(out[0, :, 5, 5], [-1.0, 2.0, -0.6], atol=1e-6)
    (tmp_path / "preprocessor_config.json").write_text(
        json.dumps({"size": {"height": 56, "width": 84}, "image_mean": [0, 0, 0], "image_std": [1, 1, 1]})
    )
    assert read_image_settings(tmp_path) == ImageSettings(56, 84, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    (tmp_path / "preprocessor_config.json").write_text('{"size": {"height": 0}}')
    with pytest.raises(ModelLoadError, match="unusable image settings"):
        read_image_settings(tmp_path)
    assert read_image_settings(tmp_path / "nothing") == ImageSettings()  # transformers' defaults


def test_mirrored_masks_and_joined_votes() -> None:
    masks = np.zeros((1, 2, 3), bool)
    masks[0, 0, 0] = True
    sm = SoftMasks.from_dense(masks, [[0.25, 0.75]], [0.5])
    assert sm.mirrored().dense()[0, 0, 2] and sm.mirrored().dense().sum() == 1
    mirror_view = SoftMasks.from_dense(masks[:, :, ::-1], [[1.0, 0.0]], [1.0])

    def label(ims: list[np.ndarray]) -> list[SoftMasks]:
        return [sm, mirror_view] if ims[0].shape == (2, 3, 3) and len(ims) == 2 else []

    (voted,) = with_flip_votes([np.zeros((2, 3, 3), np.uint8)], label)
    # Pixel (0, 0): both views cover it; confidence-weighted mean of (0.25, 0.75)·0.5 and (1, 0)·1.
    np.testing.assert_allclose(voted.pixel_probs()[0, 0], [(0.125 + 1.0) / 1.5, 0.375 / 1.5], rtol=1e-6)
    assert not voted.dense()[:, 0, 2].any()
    with pytest.raises(ValueError, match="cannot join"):
        sm.joined(SoftMasks.empty(2, 3, 3))


def test_config_bounds_and_model_id() -> None:
    with pytest.raises(ConfigError, match=r"^score_threshold: must be in \(0, 1\)"):
        Sam3LabelerConfig(score_threshold=1.0)
    with pytest.raises(ConfigError, match=r"^prompts_per_pass: must be in \[1, 256\]"):
        Sam3LabelerConfig(prompts_per_pass=0)
    with pytest.raises(ConfigError, match=r"^model_id: must be a Hugging Face model id"):
        Sam3LabelerConfig(model_id="../sam3")


# ============================================================================ tiny random model
@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tiny_models(tmp_path_factory.mktemp("models"), TinyModelsConfig(num_queries=12)).models_dir


def small_schema() -> Schema:
    return Schema(
        "small",
        (
            ClassDef("car", (255, 0, 0), ("car", "automobile"), 10, negative_prompts=("truck",)),
            ClassDef("road", (0, 0, 255), ("road", "street"), 40),
            ClassDef("pole", (0, 255, 0), ("pole",), 80),
        ),
    )


def images(n: int = 2, hw: tuple[int, int] = (40, 96)) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, (*hw, 3), dtype=np.uint8) for _ in range(n)]


def direct_call(sam3_dir: Path, image: np.ndarray, text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(scores (Q,), xyxy pixel boxes (Q, 4), mask logits resized to the image with OpenCV (Q, H, W)) of one
    prompt, straight from transformers with the prompt tokenized on its own."""
    from transformers import AutoTokenizer, Sam3Model

    model = Sam3Model.from_pretrained(sam3_dir, local_files_only=True).eval()
    tok = AutoTokenizer.from_pretrained(sam3_dir, local_files_only=True)
    enc = tok([text], padding="max_length", max_length=32, return_tensors="pt")
    pixels = torch.from_numpy(prepare_images([image], read_image_settings(sam3_dir)))
    with torch.no_grad():
        out = model(pixel_values=pixels, input_ids=enc["input_ids"], attention_mask=enc["attention_mask"])
    scores = torch.sigmoid(out.pred_logits[0]) * torch.sigmoid(out.presence_logits[0, 0])
    h, w = image.shape[:2]
    boxes = np.clip(out.pred_boxes[0].numpy() * [w, h, w, h], 0, [w, h, w, h])
    low = out.pred_masks[0].numpy()
    up = np.stack([cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR) for m in low])
    return scores.numpy(), boxes, up


def test_each_prompts_instances_match_a_direct_transformers_call(tiny_dir: Path, tmp_path: Path) -> None:
    img = images(1)[0]
    schema = small_schema()
    direct = {j.text: direct_call(tiny_dir / "sam3", img, j.text) for j in prompt_jobs(schema, True)}
    scores = np.stack([d[0] for d in direct.values()])
    assert np.abs(scores - scores[0]).max() > 1e-4  # prompts score differently: a swapped one shows
    thr = float(np.median(scores))  # some instances kept, some not
    lab = Sam3Labeler(
        Sam3LabelerConfig(score_threshold=thr, prompts_per_pass=2),
        Runtime(models_dir=tiny_dir),
        cache=LabelCache(tmp_path),
    )
    sm = lab.label_images([img], schema)[0]
    assert lab.vision_calls == 1 and lab.prompt_calls == 3  # 6 prompts, 2 per pass
    kept_total = 0
    for job in lab.jobs(schema):
        stored = lab.cache.get(lab.prompt_key(image_digest(img), job)) if lab.cache else None
        assert stored is not None and stored.class_names == (job.class_name,)
        s, boxes, up = direct[job.text]
        keep = s >= np.float32(thr)
        np.testing.assert_allclose(stored.scores[:, 0], score_logits(s[keep]), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(stored.boxes, boxes[keep], rtol=1e-4, atol=1e-3)
        got = np.unpackbits(stored.bits, axis=1, count=40 * 96).reshape(-1, 40, 96).astype(bool)
        assert (got == (up[keep] > 0)).mean() > 0.995  # bilinear in torch vs OpenCV: rounding at edges
        kept_total += int(keep.sum()) if job.role == "positive" else 0
    assert 0 < sm.num_masks <= kept_total
    assert (sm.height, sm.width, sm.num_classes) == (40, 96, 3)
    np.testing.assert_allclose(sm.probs.sum(axis=1), 1.0, rtol=1e-5)
    assert (sm.confidence >= thr - 1e-6).all()
    # Instances: the car prompts' kept instances (car is the schema's one thing), negatives applied; per
    # pixel the best score of the car masks covering it.
    results = (
        {j: lab.cache.get(lab.prompt_key(image_digest(img), j)) for j in lab.jobs(schema)}
        if lab.cache
        else {}
    )
    negatives = [r for j, r in results.items() if j.class_name == "car" and j.role == "negative"]
    cars = [
        drop_negated(r, negatives, lab.config.match_iou)
        for j, r in results.items()
        if j.class_name == "car" and j.role == "positive"
    ]
    masks = np.concatenate([np.unpackbits(r.bits, axis=1, count=40 * 96) for r in cars]).reshape(-1, 40, 96)
    score = sigmoid(np.concatenate([r.scores[:, 0] for r in cars]))
    best = np.where(masks.astype(bool), score[:, None, None], 0).max(axis=0)
    ins = sm.instances
    assert ins is not None and ins.num_instances > 0 and (ins.label == 0).all()
    np.testing.assert_array_equal(np.where(ins.ids > 0, ins.score[np.maximum(ins.ids, 1) - 1], 0), best)


def test_batches_and_the_cache(tiny_dir: Path, tmp_path: Path) -> None:
    cfg = Sam3LabelerConfig(score_threshold=0.01, batch_size=2)
    lab = Sam3Labeler(cfg, Runtime(models_dir=tiny_dir, cache_dir=tmp_path))
    ims = images(3)
    out = lab.label_images(ims, small_schema())
    # 3 images in batches of 2 and 1; 6 prompts each: 12 pairs in 2 passes of 8, then 6 in 1.
    assert lab.forward_passes() == {"vision encoder": 2, "prompt": 3}
    single = Sam3Labeler(cfg, Runtime(models_dir=tiny_dir)).label_images(ims[1:2], small_schema())[0]
    np.testing.assert_array_equal(single.bits, out[1].bits)
    np.testing.assert_allclose(single.probs, out[1].probs, rtol=1e-4, atol=1e-5)
    again = Sam3Labeler(cfg, Runtime(models_dir=tiny_dir, cache_dir=tmp_path))
    assert all(again.is_cached(im, small_schema()) for im in ims)
    cached = again.label_images(ims, small_schema())
    assert again._loaded is None  # answered from the cache: no model loaded
    np.testing.assert_array_equal(cached[2].bits, out[2].bits)
    # An edited prompt misses the cache; the other prompts' results are kept.
    edited = Schema("small", (small_schema().classes[0], ClassDef("road", (0, 0, 255), ("lane",), 40)))
    again.label_images(ims[:1], edited)
    assert again.forward_passes() == {"vision encoder": 1, "prompt": 1}


def test_flip_votes_join_the_image_with_its_mirror(tiny_dir: Path) -> None:
    img = images(1)[0]
    plain = Sam3Labeler(Sam3LabelerConfig(score_threshold=0.01), Runtime(models_dir=tiny_dir))
    flip = Sam3Labeler(Sam3LabelerConfig(score_threshold=0.01, flip_votes=True), Runtime(models_dir=tiny_dir))
    voted = flip.label_images([img], small_schema())[0]
    one, mirror = plain.label_images([img, np.ascontiguousarray(img[:, ::-1])], small_schema())
    want = one.joined(mirror.mirrored())
    np.testing.assert_array_equal(voted.bits, want.bits)
    np.testing.assert_allclose(voted.probs, want.probs, rtol=1e-4, atol=1e-5)
    assert voted.num_masks == one.num_masks + mirror.num_masks
    assert plain.fingerprint(small_schema()) != flip.fingerprint(small_schema())


def test_model_folder_errors_name_the_folder_and_the_fix(tiny_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ModelLoadError, match=r"sam3: model folder for facebook/sam3 not found.*hf download"):
        Sam3Labeler(Sam3LabelerConfig(), Runtime(models_dir=tmp_path)).label_images(images(1), small_schema())
    with pytest.raises(ModelLoadError, match="holds a 'sam' model, expected a SAM 3 model"):
        _ = Sam3Labeler(
            Sam3LabelerConfig(model_id="facebook/sam-vit-base"), Runtime(models_dir=tiny_dir)
        ).folder
    models = tmp_path / "m"
    shutil.copytree(tiny_dir, models)
    (models / "sam3" / "model.safetensors").write_bytes(b"truncated")
    with pytest.raises(ModelLoadError, match=r"sam3: cannot load facebook/sam3 weights"):
        Sam3Labeler(Sam3LabelerConfig(), Runtime(models_dir=models)).label_images(images(1), small_schema())
    long = Schema("s", (ClassDef("car", (1, 1, 1), ("car " * 40,), 10),))
    with pytest.raises(LeapError, match="more than the 32 text tokens SAM 3 reads: shorten it"):
        Sam3Labeler(Sam3LabelerConfig(), Runtime(models_dir=tiny_dir)).label_images(images(1), long)
    assert Sam3Labeler(Sam3LabelerConfig(), Runtime(models_dir=tiny_dir)).uses_random_weights


# ====================================================================================== commands
@pytest.mark.slow
def test_labels2d_and_leap_run_with_sam3_end_to_end(tiny_dir: Path, tmp_path: Path) -> None:
    from conftest import build_tiny_sequence
    from typer.testing import CliRunner

    from app.cli import cli as app

    root = build_tiny_sequence(tmp_path, n_frames=3).root
    proj = tmp_path / "small.yaml"
    save_schema(small_schema(), proj, pipeline={"sam3": {"score_threshold": 0.01}})
    cache = tmp_path / "cache"
    runner = CliRunner()
    args = ["--schema", str(proj), "--cache", str(cache), "--models", str(tiny_dir)]
    pre = runner.invoke(app, ["labels2d", str(root), "--labeler", "sam3", *args])
    assert pre.exit_code == 0, pre.output
    assert "0 cached, 3 to label; 6 prompt(s) per image" in pre.output
    assert "done: 3 frames labeled, 3 vision encoder and 3 prompt forward passes" in pre.output
    again = runner.invoke(app, ["labels2d", str(root), "--labeler", "sam3", *args])
    assert "3 cached, 0 to label" in again.output
    wrong = runner.invoke(app, ["labels2d", str(root), "--labeler", "simulated", *args])
    assert wrong.exit_code == 2 and "use grounded-sam or sam3" in wrong.output
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
            "sam3",
            "--cache",
            str(cache),
            "--models",
            str(tiny_dir),
        ],
    )
    assert run.exit_code == 0, run.output
    assert "2D labels: sam3" in run.output and "3 .label files" in run.output
    assert "RANDOM-weight" in run.output
    direct = Sam3Labeler(
        Sam3LabelerConfig(score_threshold=0.01),
        Runtime(models_dir=tiny_dir),
        cache=LabelCache(cache / "passes"),
    )
    from leap_core.datasets.kitti import KittiSequence

    for fid in ("000000", "000002"):
        soft = SoftMasks.load(folder(tmp_path / "run") / "labels2d" / f"{fid}.npz")
        want = direct.label_images([KittiSequence(root).frame(int(fid)).image], small_schema())[0]
        np.testing.assert_array_equal(soft.bits, want.bits)
        assert (folder(tmp_path / "run") / "export" / f"{fid}.label").is_file()
    assert direct._loaded is None  # the run's labels came from the cache labels2d filled
