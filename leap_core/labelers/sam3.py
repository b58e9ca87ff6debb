"""SAM 3 soft 2D labeler: docs/METHOD.md stage A with one model from class prompts to instance masks.

SAM 3 does promptable concept segmentation: a short noun phrase in, a mask and a score out for every
object in the image that matches it. Per image and per prompt (every prompt of every class, and the
classes' negative prompts when enabled):

1. The vision encoder runs once per image; its features are reused by every prompt of that image.
2. For one prompt SAM 3 returns Q query masks (mask logits), boxes and logits ``l(q)`` with an image-level
   presence logit ``l_p`` (does the concept occur in the image at all). The instance score is
   ``s(q) = σ(l(q)) · σ(l_p)``, transformers' own scoring.
3. Keep the instances with ``s(q) ≥ score_threshold``; each keeps its mask, upsampled bilinearly to the
   image and binarised at ``σ(mask logit) > mask_threshold``. Every kept instance is one mask of the
   result: the labeler's instance output.
4. Negative prompts: an instance of class c is dropped when an instance of one of c's negative prompts
   overlaps it (box IoU ≥ ``match_iou``) with a higher score.
5. The class distribution of an instance found with a prompt of class c: the logit ``logit(s)`` for c;
   for every other class c', the best logit among c''s instances whose box overlaps it with IoU ≥
   ``match_iou`` (the same object named by c''s prompt), else -inf (probability 0); then softmax over
   classes. Its confidence is ``s``. This is the Grounding DINO + SAM labeler's per-class mode
   (:func:`~leap_core.labelers.grounded_sam.assemble_soft_masks`), each prompt a pass.
6. Overlapping masks: a pixel covered by several instances gets their confidence-weighted mean
   distribution (:class:`~leap_core.labelers.base.SoftMasks`); a pixel no kept instance covers carries
   no observation ("no class" is never a class of its own).
7. Instances: every kept instance of a thing class, after step 4, is one of the image's object instances
   (:class:`~leap_core.labelers.base.Instances`) with its score ``s``; where their masks overlap, the
   higher score wins the pixel.

The unit cached is one prompt over one image (:class:`~leap_core.labelers.cache.PassResult` with one
class column): editing one class's prompts recomputes only those prompts. Keys hold the image digest,
the model identity (id + folder hash), the prompt and its role, and every setting that changes the
result.

The image is resized to the model's square input without keeping its aspect ratio and normalised as the
model folder's processor config says (transformers' ``Sam3ImageProcessor``: 1008 × 1008, mean = std =
0.5); resizing uses OpenCV (area averaging when shrinking, bilinear when enlarging) where transformers
resizes with antialiased bilinear interpolation, so the pixels the model sees differ by rounding.
transformers' processor is not used: its image half needs torchvision, which has no CPU build here.

Models load from local folders only (``Runtime.models_dir/sam3`` or the Hugging Face cache), lazily on
the first image not in the cache; torch and transformers are imported only then.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt

from leap_core.bounds import check_bounds, within
from leap_core.errors import LeapError, ModelLoadError
from leap_core.labelers.base import ImageModelLabeler, SoftMasks, model_dtype
from leap_core.labelers.cache import LabelCache, PassResult, cache_key, image_digest, pass_cache_dir
from leap_core.labelers.grounded_sam import (
    assemble_soft_masks,
    check_model_id,
    first_line,
    folder_identity,
    load_model,
    pick_device,
    read_model_type,
    resolve_model_folder,
)
from leap_core.labelers.prompts import box_iou, sigmoid
from leap_core.labelers.tiny_models import is_tiny_random
from leap_core.runtime import Runtime

if TYPE_CHECKING:
    from leap_core.schema import Schema

log = logging.getLogger(__name__)

LABELER_VERSION = 1
"""Bumped when a code change alters the labels for unchanged inputs (part of fingerprints and cache keys)."""

MODEL_TYPES = ("sam3", "sam3_video")
"""``model_type`` values of a SAM 3 folder: the image model, or the video model whose detector it loads."""

_SCORE_EPS = 1e-6
"""Scores are clipped to [ε, 1-ε] before their logit, so a saturated score stays finite."""


@dataclass(frozen=True)
class Sam3LabelerConfig:
    """Settings of the ``sam3`` labeler. Where the model folder is, and the device, are deployment values
    of the run (:class:`~leap_core.runtime.Runtime`): with ``Runtime.models_dir`` the model loads from
    ``models_dir/sam3`` for ``facebook/sam3``."""

    model_id: str = "facebook/sam3"
    """Hugging Face id of the SAM 3 checkpoint (gated: accept its licence on the hub first)."""

    score_threshold: float = field(default=0.5, metadata=within(0, 1, low_open=True, high_open=True))
    """Keep instances whose score σ(logit)·σ(presence) reaches this (0.5, as SAM 3's own examples)."""

    mask_threshold: float = field(default=0.5, metadata=within(0, 1, low_open=True, high_open=True))
    """A pixel belongs to an instance where its upsampled mask probability exceeds this."""

    match_iou: float = field(default=0.7, metadata=within(0, 1, low_open=True))
    """Box IoU at which an instance of one class's prompt counts as the same object as another's."""

    use_negative_prompts: bool = True
    """Run each class's negative prompts too; an instance they find with a higher score rules it out."""

    batch_size: int = field(default=1, metadata=within(1, 64))
    """Images per vision-encoder forward pass."""

    prompts_per_pass: int = field(default=8, metadata=within(1, 256))
    """(image, prompt) pairs per detector and mask-decoder forward pass; bounds their memory (each pair
    holds Q query masks)."""

    flip_votes: bool = False
    """Label each image and its horizontal mirror and average the two (twice the 2D stage's time)."""

    half_precision: bool = False
    """Run the model in float16 on a CUDA GPU (ignored on the CPU)."""

    compile: bool = False
    """``torch.compile`` the model on a CUDA GPU (ignored on the CPU; the first images pay the compile)."""

    def __post_init__(self) -> None:
        check_bounds(self)
        check_model_id(self.model_id, field="model_id")


# ============================================================================================ inputs
Role = Literal["positive", "negative"]


@dataclass(frozen=True)
class PromptJob:
    """One text SAM 3 is asked about: a prompt (or negative prompt) of one class."""

    class_name: str
    text: str
    role: Role


def prompt_jobs(schema: Schema, use_negative_prompts: bool) -> list[PromptJob]:
    """Every (class, prompt, role) of ``schema`` in class order, each class's positives before its
    negatives (a schema holds each prompt of a class once)."""
    jobs: list[PromptJob] = []
    for c in schema.classes:
        roles: list[tuple[Role, Sequence[str]]] = [("positive", c.prompts)]
        if use_negative_prompts:
            roles.append(("negative", c.negative_prompts))
        for role, texts in roles:
            jobs.extend(PromptJob(c.name, text, role) for text in texts)
    return jobs


@dataclass(frozen=True)
class ImageSettings:
    """How a model folder's processor prepares an image (its ``preprocessor_config.json``)."""

    height: int = 1008
    width: int = 1008
    mean: tuple[float, float, float] = (0.5, 0.5, 0.5)
    std: tuple[float, float, float] = (0.5, 0.5, 0.5)
    rescale: float = 1 / 255


def read_image_settings(folder: Path) -> ImageSettings:
    """:class:`ImageSettings` from ``preprocessor_config.json`` (or the ``image_processor`` part of
    ``processor_config.json``); transformers' defaults for what neither says.

    Raises:
        ModelLoadError: a config file that is not readable JSON, or sizes that are not positive integers.
    """
    raw: dict[str, Any] = {}
    for name, part in (("preprocessor_config.json", None), ("processor_config.json", "image_processor")):
        path = folder / name
        if not path.is_file():
            continue
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ModelLoadError(f"{path}: unreadable processor config ({exc})") from exc
        found = doc.get(part) if part is not None and isinstance(doc, dict) else doc
        if isinstance(found, dict):
            raw = found
            break
    base = ImageSettings()
    size = raw.get("size") or {}
    try:
        height, width = int(size.get("height", base.height)), int(size.get("width", base.width))
        mean = tuple(float(v) for v in raw.get("image_mean", base.mean))
        std = tuple(float(v) for v in raw.get("image_std", base.std))
        rescale = float(raw.get("rescale_factor", base.rescale)) if raw.get("do_rescale", True) else 1.0
    except (TypeError, ValueError, AttributeError) as exc:
        raise ModelLoadError(f"{folder}: processor config has unusable image settings ({exc})") from exc
    if height < 1 or width < 1 or len(mean) != 3 or len(std) != 3 or min(std) <= 0:
        raise ModelLoadError(f"{folder}: processor config has unusable image settings ({raw})")
    if not raw.get("do_normalize", True):
        mean, std = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    return ImageSettings(height, width, (mean[0], mean[1], mean[2]), (std[0], std[1], std[2]), rescale)


def prepare_images(
    images: Sequence[npt.NDArray[np.uint8]], settings: ImageSettings
) -> npt.NDArray[np.float32]:
    """(B, 3, h, w) model input of (H, W, 3) uint8 RGB images: resized to the model's (h, w) (aspect ratio
    not kept), scaled by ``rescale`` and normalised per channel, ``x' = (x·rescale - mean) / std``."""
    import cv2

    h, w = settings.height, settings.width
    out = np.empty((len(images), 3, h, w), dtype=np.float32)
    mean = np.asarray(settings.mean, np.float32)
    std = np.asarray(settings.std, np.float32)
    for k, im in enumerate(images):
        shrink = im.shape[0] * im.shape[1] > h * w
        resized = cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        out[k] = ((resized.astype(np.float32) * np.float32(settings.rescale) - mean) / std).transpose(2, 0, 1)
    return out


# ================================================================================== pure stage A
def instance_scores(logits: npt.ArrayLike, presence_logit: float) -> npt.NDArray[np.float32]:
    """(Q,) instance scores ``s(q) = σ(l(q)) · σ(l_p)`` of one prompt's query logits and presence logit."""
    return (sigmoid(logits) * sigmoid(np.float32(presence_logit))).astype(np.float32)


def score_logits(scores: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """``logit(s)`` of scores clipped to [ε, 1-ε]: the class logit of an instance (σ of it gives s back)."""
    s = np.clip(np.asarray(scores, dtype=np.float64), _SCORE_EPS, 1 - _SCORE_EPS)
    return np.log(s / (1 - s)).astype(np.float32)


def drop_negated(positive: PassResult, negatives: Sequence[PassResult], match_iou: float) -> PassResult:
    """``positive`` without the instances that an instance of a negative prompt of the same class overlaps
    (box IoU ≥ ``match_iou``) with a higher score."""
    if positive.num_regions == 0 or not negatives:
        return positive
    neg_boxes = np.concatenate([n.boxes for n in negatives], axis=0)
    if neg_boxes.shape[0] == 0:
        return positive
    neg_scores = np.concatenate([n.scores[:, 0] for n in negatives], axis=0)
    iou = box_iou(positive.boxes, neg_boxes)  # (R, N)
    beaten = ((iou >= np.float32(match_iou)) & (neg_scores[None, :] > positive.scores[:, :1])).any(axis=1)
    keep = ~beaten
    return PassResult(
        positive.height,
        positive.width,
        positive.class_names,
        positive.boxes[keep],
        positive.scores[keep],
        positive.bits[keep],
    )


def assemble_prompt_results(
    jobs: Sequence[PromptJob],
    results: Sequence[PassResult],
    class_names: Sequence[str],
    match_iou: float,
    *,
    things: npt.ArrayLike | None = None,
) -> SoftMasks:
    """One image's :class:`SoftMasks` from the results of its prompt jobs (same order): negatives drop
    the instances they beat (:func:`drop_negated`), then the positives are assembled like Grounding DINO +
    SAM passes (module docstring, step 5), each kept instance of a thing class (``things``, (C,) bool;
    default every class) one of the image's :class:`~leap_core.labelers.base.Instances` with its score."""
    negatives: dict[str, list[PassResult]] = {}
    for job, res in zip(jobs, results, strict=True):
        if job.role == "negative":
            negatives.setdefault(job.class_name, []).append(res)
    kept = [
        drop_negated(res, negatives.get(job.class_name, []), match_iou)
        for job, res in zip(jobs, results, strict=True)
        if job.role == "positive"
    ]
    if not kept:
        h, w = results[0].height, results[0].width
        return SoftMasks.empty(h, w, len(class_names))
    return assemble_soft_masks(kept, class_names, match_iou, things=things)


# ========================================================================================== labeler
@dataclass
class _Loaded:
    model: Any
    """Sam3Model (eval mode, on ``device``)."""
    dtype: Any
    """torch.float32, or float16 with ``half_precision`` on CUDA."""
    device: str


class Sam3Labeler(ImageModelLabeler):
    """SAM 3 labeler (module docstring) with an optional on-disk 2D cache.

    ``runtime`` says where the model folder is, where it runs and, with ``cache_dir``, where per-prompt
    results are kept (the same folder as Grounding DINO + SAM's passes: keys never collide). Construction
    is cheap: the tokenizer loads on the first call that needs it, the weights on the first image not
    found in the cache.
    """

    name = "sam3"

    def __init__(
        self,
        config: Sam3LabelerConfig | None = None,
        runtime: Runtime | None = None,
        *,
        cache: LabelCache | None = None,
    ) -> None:
        self.config = config or Sam3LabelerConfig()
        self.flip_votes = self.config.flip_votes
        self.runtime = runtime or Runtime()
        if cache is None and self.runtime.cache_dir is not None:
            cache = LabelCache(pass_cache_dir(self.runtime.cache_dir))
        self.cache = cache
        self._folder: Path | None = None
        self._identity: str | None = None
        self._tokenizer: Any = None
        self._tokens: dict[tuple[str, ...], tuple[Any, Any]] = {}
        self._image_settings: ImageSettings | None = None
        self._loaded: _Loaded | None = None
        self.vision_calls = 0
        """Vision-encoder forward passes run so far (a batch of images counts once)."""
        self.prompt_calls = 0
        """Detector + mask-decoder forward passes run so far (a batch of (image, prompt) pairs counts
        once)."""

    # ------------------------------------------------------------------------------ model access
    @property
    def folder(self) -> Path:
        """The model folder, resolved once."""
        if self._folder is None:
            rt = self.runtime
            self._folder = resolve_model_folder(self.config.model_id, rt.models_dir, rt.allow_download)
            model_type = read_model_type(self._folder)
            if model_type not in MODEL_TYPES:
                raise ModelLoadError(
                    f"{self._folder}: holds a {model_type or 'unknown'!r} model, expected a SAM 3 model "
                    f"({' or '.join(MODEL_TYPES)}) for {self.config.model_id}"
                )
            if is_tiny_random(self._folder):
                log.warning(
                    "%s holds a tiny RANDOM-weight test model: its labels are meaningless", self._folder
                )
        return self._folder

    @property
    def uses_random_weights(self) -> bool:
        """True when the model folder was written by ``leap make-tiny-models`` (meaningless labels)."""
        return is_tiny_random(self.folder)

    def identity(self) -> str:
        """Model id and folder hash: what the cache keys and fingerprint know about the model."""
        if self._identity is None:
            self._identity = f"{self.config.model_id}@{folder_identity(self.folder)}"
        return self._identity

    @property
    def tokenizer(self) -> Any:
        """The model folder's CLIP tokenizer."""
        if self._tokenizer is None:
            from transformers import AutoTokenizer

            try:
                self._tokenizer = AutoTokenizer.from_pretrained(str(self.folder), local_files_only=True)
            except Exception as exc:  # transformers raises many types for a broken folder
                raise ModelLoadError(
                    f"{self.folder}: cannot read the tokenizer of {self.config.model_id} ({first_line(exc)})"
                ) from exc
        return self._tokenizer

    def text_budget(self) -> int:
        """Text tokens SAM 3 reads per prompt (its text encoder's positions; 32 for the real model)."""
        cfg = json.loads((self.folder / "config.json").read_text(encoding="utf-8"))
        text = cfg.get("text_config") or (cfg.get("detector_config") or {}).get("text_config") or {}
        return int(text.get("max_position_embeddings", 32))

    @property
    def image_settings(self) -> ImageSettings:
        if self._image_settings is None:
            self._image_settings = read_image_settings(self.folder)
        return self._image_settings

    @property
    def loaded(self) -> _Loaded:
        """The model on its device (loads it on first access)."""
        if self._loaded is None:
            import torch

            device = pick_device(self.runtime.device)
            dtype = model_dtype(device, self.config.half_precision)
            model = load_model(self.folder, self.config.model_id, "Sam3Model", device).to(dtype)
            if device == "cuda" and self.config.compile:
                model = torch.compile(model)
            self._loaded = _Loaded(model, dtype, device)
        return self._loaded

    def tokens(self, texts: Sequence[str]) -> tuple[Any, Any]:
        """``(input_ids, attention_mask)`` of ``texts``, padded to the text budget, computed once per list.

        Raises:
            LeapError: a prompt longer than the budget (SAM 3 would read a truncated phrase).
        """
        key = tuple(texts)
        if key not in self._tokens:
            budget = self.text_budget()
            enc = self.tokenizer(list(texts), padding="max_length", max_length=budget, return_tensors="pt")
            if enc["input_ids"].shape[1] > budget:
                lengths = enc["attention_mask"].sum(dim=1).tolist()
                long = [t for t, n in zip(texts, lengths, strict=True) if n > budget]
                raise LeapError(
                    f"prompt {long[0]!r} has more than the {budget} text tokens SAM 3 reads: shorten it"
                )
            self._tokens[key] = (enc["input_ids"], enc["attention_mask"])
        return self._tokens[key]

    # ------------------------------------------------------------------------------- keys
    def _settings(self) -> dict[str, Any]:
        cfg = self.config
        return {
            "labeler": self.name,
            "version": LABELER_VERSION,
            "model": self.identity(),
            "score_threshold": cfg.score_threshold,
            "mask_threshold": cfg.mask_threshold,
            "half_precision": cfg.half_precision,
        }

    def fingerprint(self, schema: Schema) -> str:
        """Changes whenever the labels of an unchanged image would change (model, settings, prompts)."""
        cfg = self.config
        parts = {
            **self._settings(),
            "match_iou": cfg.match_iou,
            "use_negative_prompts": cfg.use_negative_prompts,
            "flip_votes": cfg.flip_votes,
            "classes": [[c.name, list(c.prompts), list(c.negative_prompts)] for c in schema.classes],
        }
        return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]

    def prompt_key(self, digest: str, job: PromptJob) -> str:
        """Cache key of one prompt over the image with content digest ``digest`` (the class name is part
        of the stored result, so it is part of the key)."""
        return cache_key(
            {"image": digest, **self._settings(), "prompt": [job.class_name, job.text, job.role]}
        )

    def jobs(self, schema: Schema) -> list[PromptJob]:
        return prompt_jobs(schema, self.config.use_negative_prompts)

    def cache_keys(self, digest: str, schema: Schema) -> list[str]:
        """The prompt keys of the image with content digest ``digest``."""
        return [self.prompt_key(digest, j) for j in self.jobs(schema)]

    def forward_passes(self) -> dict[str, int]:
        """Forward passes run so far by model part."""
        return {"vision encoder": self.vision_calls, "prompt": self.prompt_calls}

    def work_per_image(self, schema: Schema) -> str:
        """Prompts per image, for a summary line."""
        return f"{len(self.jobs(schema))} prompt(s) per image"

    # -------------------------------------------------------------------------------- labeling
    def _label(self, images: Sequence[npt.NDArray[np.uint8]], schema: Schema) -> list[SoftMasks]:
        """Cached prompt results are read, the others computed (``batch_size`` images per vision pass,
        ``prompts_per_pass`` pairs per prompt pass) and written to the cache."""
        jobs = self.jobs(schema)
        names = [c.name for c in schema.classes]
        keys = [[self.prompt_key(image_digest(im), j) for j in jobs] for im in images]
        results: list[list[PassResult | None]] = [
            [self.cache.get(k) if self.cache is not None else None for k in row] for row in keys
        ]
        todo = [i for i, row in enumerate(results) if any(r is None for r in row)]
        for start in range(0, len(todo), self.config.batch_size):
            chunk = todo[start : start + self.config.batch_size]
            pairs = [(i, j) for i in chunk for j, r in enumerate(results[i]) if r is None]
            for (i, j), res in zip(
                pairs, self._run([images[i] for i in chunk], chunk, pairs, jobs), strict=True
            ):
                results[i][j] = res
                if self.cache is not None:
                    self.cache.put(keys[i][j], res)
        if not jobs:  # a schema whose classes have no prompts: nothing to ask, nothing found
            return [SoftMasks.empty(im.shape[0], im.shape[1], len(names)) for im in images]
        return [
            assemble_prompt_results(
                jobs, [r for r in row if r is not None], names, self.config.match_iou, things=schema.things()
            )
            for row in results
        ]

    # ------------------------------------------------------------------------------ model calls
    def _run(
        self,
        images: Sequence[npt.NDArray[np.uint8]],
        image_ids: Sequence[int],
        pairs: Sequence[tuple[int, int]],
        jobs: Sequence[PromptJob],
    ) -> list[PassResult]:
        """One vision-encoder pass over ``images`` (the images ``image_ids``), then the (image, prompt)
        ``pairs`` in groups of ``prompts_per_pass``: one :class:`PassResult` per pair."""
        import torch

        m = self.loaded
        ids, mask = self.tokens([j.text for j in jobs])
        pixels = torch.from_numpy(prepare_images(images, self.image_settings)).to(m.device, m.dtype)
        with torch.inference_mode():
            vision = m.model.get_vision_features(pixel_values=pixels)
        self.vision_calls += 1
        row_of = {image_id: k for k, image_id in enumerate(image_ids)}
        out: list[PassResult] = []
        step = self.config.prompts_per_pass
        for start in range(0, len(pairs), step):
            group = pairs[start : start + step]
            rows = torch.tensor([row_of[i] for i, _ in group], device=m.device)
            texts = torch.tensor([j for _, j in group])
            embeds = type(vision)(
                **{
                    k: tuple(x.index_select(0, rows) for x in v) if isinstance(v, (tuple, list)) else v
                    for k, v in vision.items()
                }
            )
            with torch.inference_mode():
                res = m.model(
                    vision_embeds=embeds,
                    input_ids=ids[texts].to(m.device),
                    attention_mask=mask[texts].to(m.device),
                )
            self.prompt_calls += 1
            for k, (i, j) in enumerate(group):
                out.append(self._instances(res, k, images[row_of[i]].shape[:2], jobs[j].class_name))
        return out

    def _instances(self, res: Any, k: int, image_hw: tuple[int, ...], class_name: str) -> PassResult:
        """The kept instances of row ``k`` of a model output, as a one-class :class:`PassResult`."""
        import torch

        h, w = int(image_hw[0]), int(image_hw[1])
        logits = res.pred_logits[k].float().cpu().numpy()  # (Q,)
        presence = float(res.presence_logits[k].float().reshape(-1)[0].cpu())
        scores = instance_scores(logits, presence)
        keep = np.flatnonzero(scores >= np.float32(self.config.score_threshold))
        boxes = res.pred_boxes[k].float().cpu().numpy()[keep] * np.array([w, h, w, h], np.float32)
        boxes = np.clip(boxes, 0, np.array([w, h, w, h], np.float32)).astype(np.float32)
        nbytes = (h * w + 7) // 8
        if keep.size == 0:
            bits = np.zeros((0, nbytes), np.uint8)
        else:
            low = res.pred_masks[k][torch.from_numpy(keep).to(res.pred_masks.device)].float()  # (R, h', w')
            up = torch.nn.functional.interpolate(
                low[None], size=(h, w), mode="bilinear", align_corners=False
            )[0]
            cut = float(np.log(self.config.mask_threshold / (1 - self.config.mask_threshold)))
            masks = (up > cut).reshape(keep.size, h * w).cpu().numpy()
            bits = np.packbits(masks, axis=1)
        return PassResult(h, w, (class_name,), boxes, score_logits(scores[keep])[:, None], bits)


__all__ = [
    "LABELER_VERSION",
    "MODEL_TYPES",
    "ImageSettings",
    "PromptJob",
    "Sam3Labeler",
    "Sam3LabelerConfig",
    "assemble_prompt_results",
    "drop_negated",
    "instance_scores",
    "prepare_images",
    "prompt_jobs",
    "read_image_settings",
    "score_logits",
]
