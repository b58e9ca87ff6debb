"""Grounding DINO + SAM soft 2D labeler: docs/METHOD.md stage A with Hugging Face transformers.

Per image and per detector pass (see :mod:`leap_core.labelers.prompts` for passes and phrases):

1. The pass text ``"p1 . p2 . … ."`` holds every prompt of the pass's classes (and their negative prompts
   when enabled). The tokenizer's character offsets (``return_offsets_mapping``) map each text-token
   column to its phrase; the detector's own post-processing labels (``text_labels``) are never used.
2. Grounding DINO returns Q query boxes and a Q × T logit matrix L (900 × 256 for the real model; both
   are read from the outputs, not assumed). ``sigmoid(L)`` is the region↔token similarity.
3. Class score ``s(q,c)`` = max of L over the token columns of c's prompts. With negative prompts on,
   ``s(q,c) = -inf`` where a column of c's negatives scores higher than every column of c's prompts.
   Only prompt columns count: [CLS], [SEP] and ``.`` are never a class.
4. Keep regions with ``max_c sigmoid(s(q,c)) ≥ box_threshold``; that max is the region's confidence.
5. SAM turns each kept box into a mask. ``multimask=True`` asks SAM for its 3 candidate masks per box and
   keeps the one with the highest predicted IoU (SAM's own quality estimate; one box is ambiguous
   between part and whole, and the best-scored candidate is what SAM's authors recommend for boxes);
   ``multimask=False`` uses SAM's single-mask output.
6. ``p(q,·)`` = softmax over classes of the class logits. Pixels covered by several masks get the
   confidence-weighted average of their distributions; that is what :class:`SoftMasks` encodes.
7. Instances: each kept box of a thing class (the class of its best logit in its own pass) is one object
   instance, its SAM mask the instance's pixels and its confidence the score; where instance masks
   overlap, the higher score wins the pixel (:class:`~leap_core.labelers.base.Instances`).

Several passes (prompts longer than the text-token budget, or ``mode="per-class"``): every pass
contributes its regions. A region has logits only for its own pass's classes; for a class of another
pass it takes the max logit for that class among that pass's regions whose box overlaps it with
IoU ≥ ``match_iou`` (the same object scored with the other text), else -inf (probability 0). So in
per-class mode a car box that the "truck" pass also found gets a car-vs-truck distribution, while an
object found by one class's pass only gets a one-hot distribution. The confidence always comes from the
region's own pass. Documented limitation: logits of different texts are compared as if from one text.

Models load from local folders only (``Runtime.models_dir/<name>``, or the user's Hugging Face cache); a
missing or unreadable folder raises :class:`~leap_core.errors.ModelLoadError` saying how to get the
weights. Where the models live, the device and the 2D cache folder are deployment values of the run
(:class:`~leap_core.runtime.Runtime`), not settings of :class:`GroundedSamConfig`. Weights load lazily,
on the first image that is not in the 2D cache; transformers and torch are imported only then, so reading
the config costs neither.

With ``half_precision`` on a CUDA GPU both models run in float16 (cast once when loaded, their pixel
inputs cast per call); the detector's logits and boxes and SAM's mask logits are cast back to float32
before the region maths and the mask threshold, so the cache holds float32 results either way. The
setting is part of the cache keys; the CPU ignores it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt

from leap_core.bounds import check_bounds, within
from leap_core.errors import ConfigError, LeapError, ModelLoadError
from leap_core.labelers.base import ImageModelLabeler, Instances, SoftMasks, model_dtype
from leap_core.labelers.cache import LabelCache, PassResult, cache_key, image_digest, pass_cache_dir
from leap_core.labelers.prompts import (
    NEG_INF,
    ClassPrompts,
    PassPlan,
    apply_negatives,
    fill_across_passes,
    keep_regions,
    phrase_max,
    plan_passes,
    sigmoid,
    softmax_classes,
    token_phrase_index,
)
from leap_core.labelers.tiny_models import is_tiny_random
from leap_core.runtime import Runtime

if TYPE_CHECKING:
    from leap_core.schema import Schema

log = logging.getLogger(__name__)

LABELER_VERSION = 1
"""Bumped when a code change alters the labels for unchanged inputs (part of fingerprints and cache keys)."""

_SAM_BOX_CHUNK = 16
"""Boxes per SAM decoder call: bounds the memory of the full-resolution mask upsampling."""


@dataclass(frozen=True)
class GroundedSamConfig:
    """Settings of the ``grounded-sam`` labeler: which models, and how their outputs become labels.

    Where the models are is not a setting here but part of the run's :class:`~leap_core.runtime.Runtime`:
    with ``Runtime.models_dir`` each model loads from ``models_dir/<last part of its id>``, e.g.
    ``models_dir/grounding-dino-tiny`` for ``IDEA-Research/grounding-dino-tiny``; without it the ids are
    resolved from the user's Hugging Face cache.
    """

    detector_id: str = "IDEA-Research/grounding-dino-tiny"
    """Hugging Face id of the Grounding DINO checkpoint (the paper uses Swin-T = grounding-dino-tiny)."""

    segmenter_id: str = "facebook/sam-vit-base"
    """Hugging Face id of the SAM checkpoint (e.g. facebook/sam-vit-huge, nielsr/slimsam-77-uniform)."""

    box_threshold: float = field(default=0.25, metadata=within(0, 1, low_open=True, high_open=True))
    """Keep regions whose max sigmoid region↔token similarity reaches this (paper: 0.25 KITTI, 0.2 UAV)."""

    mode: Literal["joint", "per-class"] = "joint"
    """"joint": all classes' prompts in one text (the paper); "per-class": one detector pass per class."""

    max_text_tokens: int = field(default=256, metadata=within(4, 1024))
    """Text-token budget of one detector pass, [CLS] and [SEP] included (the model's max_text_len)."""

    batch_size: int = field(default=1, metadata=within(1, 64))
    """Images per forward pass of the detector and SAM's image encoder."""

    use_negative_prompts: bool = True
    """Add each class's negative prompts to the text; a region that matches one of class c's negative
    prompts better than all of c's prompts cannot be c."""

    multimask: bool = True
    """Ask SAM for 3 candidate masks per box and keep the one with the highest predicted IoU."""

    mask_threshold: float = field(default=0.0, metadata=within(-100, 100))
    """Threshold on SAM's mask logits when binarising the upscaled masks."""

    match_iou: float = field(default=0.7, metadata=within(0, 1, low_open=True))
    """Box IoU at which a region of one pass takes the class logits of a region of another pass."""

    flip_votes: bool = False
    """Label each image and its horizontal mirror and average the two
    (:func:`~leap_core.labelers.base.with_flip_votes`; twice the 2D stage's time)."""

    half_precision: bool = False
    """Run Grounding DINO and SAM in float16 on a CUDA GPU (ignored on the CPU)."""

    def __post_init__(self) -> None:
        check_bounds(self)
        if self.mode not in ("joint", "per-class"):
            raise ConfigError(f"must be 'joint' or 'per-class', got {self.mode!r}", field=("mode",))
        for name in ("detector_id", "segmenter_id"):
            check_model_id(getattr(self, name), field=name)


# ============================================================================================ models
_MODEL_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*(/[A-Za-z0-9][A-Za-z0-9._-]*)?$")


def check_model_id(model_id: str, *, field: str) -> None:
    """Refuse a model id that is not a Hugging Face id (``name`` or ``owner/name``).

    The id's last part names a subfolder of the models folder (:func:`model_folder_name`), so an id such
    as ``x/..`` or an absolute path would load weights from outside it: a project names models, never
    where they are.

    Raises:
        ConfigError: ``field`` = ``(field,)``.
    """
    if not isinstance(model_id, str) or not _MODEL_ID.match(model_id) or ".." in model_id:
        raise ConfigError(
            f"must be a Hugging Face model id ('name' or 'owner/name': letters, digits, '.', '_', '-'; "
            f"no '..'), got {model_id!r}",
            field=(field,),
        )


def model_folder_name(model_id: str) -> str:
    """Subfolder of ``models_dir`` holding ``model_id``: the id's last path part
    (``IDEA-Research/grounding-dino-tiny`` → ``grounding-dino-tiny``)."""
    return model_id.rstrip("/").split("/")[-1]


def first_line(exc: BaseException) -> str:
    """``Type: first line of the message`` of an exception from a model library (their messages run long)."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def _download_hint(model_id: str, folder: Path) -> str:
    return (
        f"download it with `hf download {model_id} --local-dir {folder}` "
        "(see the README section 'Real 2D labels')"
    )


def resolve_model_folder(model_id: str, models_dir: str | Path | None, allow_download: bool = False) -> Path:
    """The local folder of ``model_id``: ``models_dir/<model_folder_name(id)>``, or its Hugging Face
    cache snapshot when ``models_dir`` is None (downloaded first only if ``allow_download``).

    Raises:
        ModelLoadError: the folder (or cache entry) does not exist or has no ``config.json``; the
            message names the expected folder and the download command.
    """
    if models_dir is not None:
        folder = Path(models_dir) / model_folder_name(model_id)
        if not folder.is_dir():
            raise ModelLoadError(
                f"{folder}: model folder for {model_id} not found; {_download_hint(model_id, folder)}"
            )
    else:
        try:
            from huggingface_hub import snapshot_download

            folder = Path(
                snapshot_download(
                    model_id,
                    local_files_only=not allow_download,
                    allow_patterns=["*.json", "*.txt", "*.safetensors", "*.model"],
                )
            )
        except Exception as exc:  # any hub/cache failure means "not available here"
            example = Path("models") / model_folder_name(model_id)
            raise ModelLoadError(
                f"{model_id}: not in the Hugging Face cache ({type(exc).__name__}); "
                f"{_download_hint(model_id, example)} and pass --models {example.parent}"
            ) from exc
    if not (folder / "config.json").is_file():
        raise ModelLoadError(
            f"{folder}: no config.json, so this is not a model folder for {model_id}; "
            f"{_download_hint(model_id, folder)}"
        )
    return folder


def folder_identity(folder: str | Path) -> str:
    """Hash of a model folder: the content of its JSON/text files and the names and sizes of its weight
    files (hashing GBs of weights on every start would cost seconds; a same-size swap needs a new id)."""
    folder = Path(folder)
    h = hashlib.sha256()
    for p in sorted(folder.iterdir()):
        if not p.is_file():
            continue
        if p.suffix in (".json", ".txt", ".model"):
            h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
        elif p.suffix in (".safetensors", ".bin", ".pt", ".pth"):
            h.update(f"{p.name}\0{p.stat().st_size}\0".encode())
    return h.hexdigest()[:16]


def read_model_type(folder: Path) -> str:
    """The ``model_type`` of a model folder's ``config.json`` ("" when it has none).

    Raises:
        ModelLoadError: the config is unreadable or not a JSON object.
    """
    try:
        cfg = json.loads((folder / "config.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelLoadError(f"{folder / 'config.json'}: unreadable model config ({exc})") from exc
    if not isinstance(cfg, dict):
        raise ModelLoadError(f"{folder / 'config.json'}: model config is not a JSON object")
    return str(cfg.get("model_type", ""))


def pick_device(device: str) -> str:
    """``"cuda"`` or ``"cpu"`` for a :attr:`Runtime.device <leap_core.runtime.Runtime.device>`; "auto"
    prefers CUDA when available."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise LeapError("device 'cuda' was asked for but torch sees no CUDA GPU (use device auto or cpu)")
    return device


@dataclass
class LoadedModels:
    """Grounding DINO and SAM with their processors, on one device."""

    detector: Any
    """GroundingDinoForObjectDetection (eval mode)."""
    detector_processor: Any
    """GroundingDinoProcessor (image processor + BERT tokenizer)."""
    segmenter: Any
    """SamModel (eval mode)."""
    segmenter_processor: Any
    """SamProcessor."""
    device: str
    """"cpu" or "cuda"."""
    dtype: Any
    """torch.float32, or float16 with ``half_precision`` on CUDA (both models' weights)."""


def load_processor(folder: Path, model_id: str, expect_type: str) -> Any:
    """The processor of a model folder, after checking its ``model_type``.

    Raises:
        ModelLoadError: wrong model type, or transformers cannot read the folder.
    """
    model_type = read_model_type(folder)
    if model_type != expect_type:
        raise ModelLoadError(
            f"{folder}: holds a {model_type or 'unknown'!r} model, expected {expect_type!r} for {model_id}; "
            f"{_download_hint(model_id, folder)}"
        )
    from transformers import AutoProcessor

    try:
        proc = AutoProcessor.from_pretrained(  # type: ignore[no-untyped-call]  # transformers: unannotated
            str(folder), local_files_only=True
        )
    except Exception as exc:  # transformers raises many types for a broken folder
        raise ModelLoadError(
            f"{folder}: cannot read the processor of {model_id} ({first_line(exc)}); "
            f"{_download_hint(model_id, folder)}"
        ) from exc
    if expect_type == "grounding-dino":
        tok = getattr(proc, "tokenizer", None)
        if tok is None:
            raise ModelLoadError(
                f"{folder}: no tokenizer files for {model_id}; {_download_hint(model_id, folder)}"
            )
        # Grounding DINO splits phrases at these hard-coded BERT ids; another vocabulary breaks it silently.
        found = {t: tok.convert_tokens_to_ids(t) for t in ("[CLS]", "[SEP]", ".", "?")}
        want = {"[CLS]": 101, "[SEP]": 102, ".": 1012, "?": 1029}
        if found != want:
            raise ModelLoadError(
                f"{folder}: tokenizer ids {found} differ from the BERT ids {want} that Grounding DINO "
                "uses to separate phrases"
            )
    return proc


def load_model(folder: Path, model_id: str, cls_name: str, device: str) -> Any:
    """transformers' ``cls_name`` loaded from ``folder`` (local files only), on ``device``, in eval mode.

    Raises:
        ModelLoadError: naming the folder, the model id and the download command.
    """
    import transformers

    cls = getattr(transformers, cls_name)
    try:
        model = cls.from_pretrained(str(folder), local_files_only=True)
    except Exception as exc:  # transformers raises many types for a broken folder
        raise ModelLoadError(
            f"{folder}: cannot load {model_id} weights ({first_line(exc)}); "
            f"{_download_hint(model_id, folder)}"
        ) from exc
    return model.to(device).eval()


# ================================================================================== pure stage A
def pass_regions(
    logits: npt.ArrayLike,
    boxes_cxcywh: npt.ArrayLike,
    token_phrase: npt.ArrayLike,
    plan: PassPlan,
    threshold: float,
    image_hw: tuple[int, int],
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Kept regions of one pass over one image, from the detector's raw outputs.

    Args:
        logits: (Q, T) region↔token logits (padding columns may be -inf).
        boxes_cxcywh: (Q, 4) boxes as (cx, cy, w, h), normalised to [0, 1] by the image size.
        token_phrase: (T,) phrase index per column (:func:`~leap_core.labelers.prompts.token_phrase_index`).
        plan: the pass (phrase → class roles).
        threshold: τ; keep q iff max_k sigmoid(s'(q,k)) ≥ τ.
        image_hw: (H, W) of the image, to scale boxes to pixels.

    Returns:
        ``(boxes, scores)``: (R, 4) float32 xyxy pixel boxes clipped to the image and (R, K) float32
        class logits s'(q,k) (after negatives) of the kept regions, K = the pass's classes.
    """
    lg = np.asarray(logits, dtype=np.float32)
    pos = phrase_max(lg, token_phrase, plan.positive)
    neg = phrase_max(lg, token_phrase, plan.negative)
    scores = apply_negatives(pos, neg)
    keep = keep_regions(scores, threshold)
    b = np.asarray(boxes_cxcywh, dtype=np.float32)[keep]
    h, w = image_hw
    xyxy = np.stack(
        [b[:, 0] - b[:, 2] / 2, b[:, 1] - b[:, 3] / 2, b[:, 0] + b[:, 2] / 2, b[:, 1] + b[:, 3] / 2], axis=1
    ).reshape(-1, 4) * np.array([w, h, w, h], dtype=np.float32)
    xyxy = np.clip(xyxy, 0, np.array([w, h, w, h], dtype=np.float32))
    return xyxy.astype(np.float32), scores[keep]


def assemble_soft_masks(
    results: Sequence[PassResult],
    class_names: Sequence[str],
    match_iou: float,
    *,
    things: npt.ArrayLike | None = None,
) -> SoftMasks:
    """Combine the pass results of one image into its :class:`SoftMasks` (C = ``len(class_names)``).

    ``probs`` = softmax over classes of the logits filled across passes
    (:func:`~leap_core.labelers.prompts.fill_across_passes`); ``confidence`` = sigmoid of the region's
    best logit in its own pass. Regions whose SAM mask is empty are dropped (they cover no pixel).

    Instances: each kept region whose own class (its best logit's class within its own pass: the class
    of the prompt that found the box) is a thing (``things``: (C,) bool, default every class) is one
    instance, its SAM mask the instance's mask and its confidence the instance's score
    (:class:`~leap_core.labelers.base.Instances`: where masks overlap the higher score wins the pixel).

    Raises:
        ValueError: no results, results of different image sizes, or a class name not in ``class_names``.
    """
    if not results:
        raise ValueError("assemble_soft_masks needs at least one pass result")
    h, w = results[0].height, results[0].width
    if any((r.height, r.width) != (h, w) for r in results):
        raise ValueError("pass results of one image must share its size")
    col = {n: i for i, n in enumerate(class_names)}
    c = len(class_names)
    member = np.zeros((len(results), c), dtype=bool)
    blocks = []
    for p, r in enumerate(results):
        idx = [col[n] for n in r.class_names]
        member[p, idx] = True
        s = np.full((r.num_regions, c), NEG_INF, dtype=np.float32)
        s[:, idx] = r.scores
        blocks.append(s)
    scores = np.concatenate(blocks, axis=0)
    pass_id = np.concatenate([np.full(r.num_regions, p) for p, r in enumerate(results)])
    boxes = np.concatenate([r.boxes for r in results], axis=0)
    bits = np.concatenate([r.bits for r in results], axis=0)
    if scores.shape[0] == 0:
        return SoftMasks.empty(h, w, c)
    own = np.where(member[pass_id], scores, NEG_INF)
    confidence = sigmoid(own.max(axis=1))
    probs = softmax_classes(fill_across_passes(boxes, scores, pass_id, member, match_iou))
    nonempty = bits.any(axis=1)
    thing = np.ones(c, bool) if things is None else np.asarray(things, dtype=bool).reshape(c)
    own_class = own.argmax(axis=1)
    inst = np.flatnonzero(nonempty & thing[own_class])
    instances = Instances.from_bits(bits[inst], h, w, own_class[inst], confidence[inst])
    return SoftMasks(h, w, bits[nonempty], probs[nonempty], confidence[nonempty], instances)


# ========================================================================================== labeler
class GroundedSamLabeler(ImageModelLabeler):
    """Grounding DINO + SAM labeler (module docstring) with an optional on-disk 2D cache.

    ``runtime`` says where the model folders are (``models_dir``, ``allow_download``), where they run
    (``device``) and, with ``cache_dir``, keeps the per-pass results in
    :func:`~leap_core.labelers.cache.pass_cache_dir` of that folder (an explicit ``cache`` wins).
    Construction is cheap: the tokenizer loads on the first call that needs the pass plan, the weights
    on the first image not found in the cache.
    """

    name = "grounded-sam"

    def __init__(
        self,
        config: GroundedSamConfig | None = None,
        runtime: Runtime | None = None,
        *,
        cache: LabelCache | None = None,
    ) -> None:
        self.config = config or GroundedSamConfig()
        self.flip_votes = self.config.flip_votes
        self.runtime = runtime or Runtime()
        if cache is None and self.runtime.cache_dir is not None:
            # Per-pass detector cache beside the per-frame one: a prompt edit of one class then only
            # recomputes that class's pass (per-class mode).
            cache = LabelCache(pass_cache_dir(self.runtime.cache_dir))
        self.cache = cache
        self._folders: tuple[Path, Path] | None = None
        self._identity: dict[str, str] | None = None
        self._det_proc: Any = None
        self._models: LoadedModels | None = None
        self._budget: int | None = None
        self._plans: dict[Schema, list[PassPlan]] = {}
        self.detector_calls = 0
        """Detector forward passes run so far (a batch of images counts once)."""
        self.segmenter_calls = 0
        """SAM image-encoder forward passes run so far (a batch of images counts once)."""

    # ------------------------------------------------------------------------------ model access
    @property
    def folders(self) -> tuple[Path, Path]:
        """(detector folder, segmenter folder), resolved once."""
        if self._folders is None:
            cfg, rt = self.config, self.runtime
            det = resolve_model_folder(cfg.detector_id, rt.models_dir, rt.allow_download)
            seg = resolve_model_folder(cfg.segmenter_id, rt.models_dir, rt.allow_download)
            self._folders = (det, seg)
            for f in self._folders:
                if is_tiny_random(f):
                    log.warning("%s holds a tiny RANDOM-weight test model: its labels are meaningless", f)
        return self._folders

    @property
    def uses_random_weights(self) -> bool:
        """True when a model folder was written by ``leap make-tiny-models`` (meaningless labels)."""
        return any(is_tiny_random(f) for f in self.folders)

    def identity(self) -> dict[str, str]:
        """Model ids and folder hashes: what the cache keys and fingerprint know about the models."""
        if self._identity is None:
            det, seg = self.folders
            cfg = self.config
            self._identity = {
                "detector": f"{cfg.detector_id}@{folder_identity(det)}",
                "segmenter": f"{cfg.segmenter_id}@{folder_identity(seg)}",
            }
        return self._identity

    @property
    def detector_processor(self) -> Any:
        if self._det_proc is None:
            self._det_proc = load_processor(self.folders[0], self.config.detector_id, "grounding-dino")
        return self._det_proc

    @property
    def models(self) -> LoadedModels:
        """The loaded models (loads them on first access)."""
        if self._models is None:
            cfg = self.config
            det, seg = self.folders
            device = pick_device(self.runtime.device)
            dtype = model_dtype(device, cfg.half_precision)
            seg_proc = load_processor(seg, cfg.segmenter_id, "sam")
            detector = load_model(det, cfg.detector_id, "GroundingDinoForObjectDetection", device)
            self._models = LoadedModels(
                detector=detector.to(dtype),
                detector_processor=self.detector_processor,
                segmenter=load_model(seg, cfg.segmenter_id, "SamModel", device).to(dtype),
                segmenter_processor=seg_proc,
                device=device,
                dtype=dtype,
            )
        return self._models

    def text_budget(self) -> int:
        """Text-token columns per pass: ``max_text_tokens`` capped by the detector's ``max_text_len``."""
        if self._budget is None:
            model_cfg = json.loads((self.folders[0] / "config.json").read_text(encoding="utf-8"))
            self._budget = min(self.config.max_text_tokens, int(model_cfg.get("max_text_len", 256)))
        return self._budget

    # ------------------------------------------------------------------------------- planning
    def plan(self, schema: Schema) -> list[PassPlan]:
        """The detector passes for ``schema`` under this config (needs the tokenizer only), made once per
        schema: tokenizing every prompt costs about 20 ms, and the cache check and each batch ask again."""
        if schema not in self._plans:
            self._plans[schema] = self._make_plan(schema)
        return self._plans[schema]

    def _make_plan(self, schema: Schema) -> list[PassPlan]:
        tok = self.detector_processor.tokenizer
        use_neg = self.config.use_negative_prompts
        classes = [
            ClassPrompts(i, c.name, tuple(c.prompts), tuple(c.negative_prompts) if use_neg else ())
            for i, c in enumerate(schema.classes)
        ]

        def count(phrase: str) -> int:
            return len(tok(phrase, add_special_tokens=False)["input_ids"])

        return plan_passes(classes, count, self.text_budget(), self.config.mode)

    def _settings(self) -> dict[str, Any]:
        cfg = self.config
        return {
            "version": LABELER_VERSION,
            **self.identity(),
            "box_threshold": cfg.box_threshold,
            "mode": cfg.mode,
            "multimask": cfg.multimask,
            "mask_threshold": cfg.mask_threshold,
            # Only when on: the keys and fingerprints of labels made before the option existed stay valid.
            **({"half_precision": True} if cfg.half_precision else {}),
        }

    def fingerprint(self, schema: Schema) -> str:
        """Changes whenever the labels of an unchanged image would change (models, settings, prompts)."""
        cfg = self.config
        parts = {
            "labeler": self.name,
            **self._settings(),
            "match_iou": cfg.match_iou,
            "use_negative_prompts": cfg.use_negative_prompts,
            "max_text_tokens": cfg.max_text_tokens,
            "classes": [[c.name, list(c.prompts), list(c.negative_prompts)] for c in schema.classes],
            # Only when on: the fingerprints of runs made before the option existed stay valid.
            **({"flip_votes": True} if cfg.flip_votes else {}),
        }
        return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]

    def pass_key(self, digest: str, plan: PassPlan) -> str:
        """Cache key of one pass over the image with content digest ``digest``."""
        return cache_key({"image": digest, **self._settings(), "pass": plan.key_parts()})

    def cache_keys(self, digest: str, schema: Schema) -> list[str]:
        """The pass keys of the image with content digest ``digest``."""
        return [self.pass_key(digest, p) for p in self.plan(schema)]

    def forward_passes(self) -> dict[str, int]:
        """Forward passes run so far by model part."""
        return {"detector": self.detector_calls, "SAM encoder": self.segmenter_calls}

    def work_per_image(self, schema: Schema) -> str:
        """Detector passes per image, for a summary line."""
        return f"{len(self.plan(schema))} detector pass(es) per image"

    # -------------------------------------------------------------------------------- labeling
    def _label(self, images: Sequence[npt.NDArray[np.uint8]], schema: Schema) -> list[SoftMasks]:
        """Cached passes are read, the others computed (``batch_size`` images per forward pass) and
        written to the cache."""
        plans = self.plan(schema)
        names = [c.name for c in schema.classes]
        digests = [image_digest(im) for im in images]
        keys = [[self.pass_key(d, p) for p in plans] for d in digests]
        results: list[list[PassResult | None]] = [
            [self.cache.get(k) if self.cache is not None else None for k in row] for row in keys
        ]
        # Detector: every missing (image, pass); SAM: once per image over all its new boxes.
        pending: dict[int, list[tuple[int, npt.NDArray[np.float32], npt.NDArray[np.float32]]]] = {}
        for p, plan in enumerate(plans):
            todo = [i for i in range(len(images)) if results[i][p] is None]
            for chunk in _chunks(todo, self.config.batch_size):
                found = self._detect([images[i] for i in chunk], plan)
                for i, (boxes, scores) in zip(chunk, found, strict=True):
                    pending.setdefault(i, []).append((p, boxes, scores))
        todo_img = sorted(pending)
        for chunk in _chunks(todo_img, self.config.batch_size):
            all_boxes = [np.concatenate([b for _, b, _ in pending[i]], axis=0) for i in chunk]
            all_bits = self._segment([images[i] for i in chunk], all_boxes)
            for i, bits in zip(chunk, all_bits, strict=True):
                h, w = images[i].shape[:2]
                start = 0
                for p, boxes, scores in pending[i]:
                    n = boxes.shape[0]
                    res = PassResult(h, w, plans[p].class_names, boxes, scores, bits[start : start + n])
                    start += n
                    results[i][p] = res
                    if self.cache is not None:
                        self.cache.put(keys[i][p], res)
        return [
            assemble_soft_masks(
                [r for r in row if r is not None], names, self.config.match_iou, things=schema.things()
            )
            for row in results
        ]

    # ------------------------------------------------------------------------------ model calls
    def _detect(
        self, images: Sequence[npt.NDArray[np.uint8]], plan: PassPlan
    ) -> list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]]:
        """One detector forward pass over a batch: kept (boxes, scores) per image."""
        import torch

        m = self.models
        tok = m.detector_processor.tokenizer
        enc = tok([plan.text], return_offsets_mapping=True, return_tensors="pt")
        offsets = enc.pop("offset_mapping")[0].numpy()
        budget = self.text_budget()
        if enc["input_ids"].shape[1] > budget:
            raise LeapError(
                f"detector text of classes {', '.join(plan.class_names)} has {enc['input_ids'].shape[1]} "
                f"tokens, more than the budget of {budget}"
            )
        pix = m.detector_processor.image_processor(images=list(images), return_tensors="pt")
        b = len(images)
        inputs = {
            "pixel_values": pix["pixel_values"].to(m.device, m.dtype),
            "pixel_mask": pix["pixel_mask"].to(m.device) if "pixel_mask" in pix else None,
            "input_ids": enc["input_ids"].repeat(b, 1).to(m.device),
            "attention_mask": enc["attention_mask"].repeat(b, 1).to(m.device),
            "token_type_ids": enc["token_type_ids"].repeat(b, 1).to(m.device),
        }
        with torch.inference_mode():
            out = m.detector(**inputs)
        self.detector_calls += 1
        logits = out.logits.float().cpu().numpy()  # (B, Q, T)
        boxes = out.pred_boxes.float().cpu().numpy()  # (B, Q, 4)
        token_phrase = token_phrase_index(offsets, plan.spans, num_columns=logits.shape[2])
        thr = self.config.box_threshold
        return [
            pass_regions(logits[k], boxes[k], token_phrase, plan, thr, images[k].shape[:2]) for k in range(b)
        ]

    def _segment(
        self, images: Sequence[npt.NDArray[np.uint8]], boxes: Sequence[npt.NDArray[np.float32]]
    ) -> list[npt.NDArray[np.uint8]]:
        """SAM masks of xyxy pixel boxes: per image (R_i, ceil(H*W/8)) packed bits."""
        import torch

        m = self.models
        out: list[npt.NDArray[np.uint8]] = []
        need = [i for i, b in enumerate(boxes) if b.shape[0] > 0]
        emb_of: dict[int, Any] = {}
        sizes: dict[int, tuple[list[int], list[int]]] = {}
        if need:
            enc = m.segmenter_processor(images=[images[i] for i in need], return_tensors="pt")
            with torch.inference_mode():
                emb = m.segmenter.get_image_embeddings(enc["pixel_values"].to(m.device, m.dtype))
            self.segmenter_calls += 1
            for k, i in enumerate(need):
                emb_of[i] = emb[k : k + 1]
                sizes[i] = (enc["original_sizes"][k].tolist(), enc["reshaped_input_sizes"][k].tolist())
        for i, (img, b) in enumerate(zip(images, boxes, strict=True)):
            h, w = img.shape[:2]
            nbytes = (h * w + 7) // 8
            if b.shape[0] == 0:
                out.append(np.zeros((0, nbytes), dtype=np.uint8))
                continue
            orig, resized = sizes[i]
            scale = np.array([resized[1] / orig[1], resized[0] / orig[0]] * 2, dtype=np.float32)
            chunks = []
            for start in range(0, b.shape[0], _SAM_BOX_CHUNK):
                # float32 boxes: SAM's prompt encoder scales them to [0, 1] before casting to its dtype.
                sb = torch.from_numpy(b[start : start + _SAM_BOX_CHUNK] * scale)[None].to(m.device)
                with torch.inference_mode():
                    res = m.segmenter(
                        image_embeddings=emb_of[i], input_boxes=sb, multimask_output=self.config.multimask
                    )
                pred = res.pred_masks[0]  # (n, k, h', w') low-resolution mask logits
                best = res.iou_scores[0].argmax(dim=1)  # (n,)
                rows = torch.arange(pred.shape[0], device=pred.device)
                sel = pred[rows, best][:, None]  # (n, 1, h', w')
                masks = m.segmenter_processor.image_processor.post_process_masks(
                    [sel.float().cpu()], [orig], [resized], mask_threshold=self.config.mask_threshold
                )[0]
                chunks.append(np.packbits(masks.reshape(masks.shape[0], h * w).numpy(), axis=1))
            out.append(np.concatenate(chunks, axis=0))
        return out


def _chunks(items: Sequence[int], size: int) -> list[list[int]]:
    return [list(items[i : i + size]) for i in range(0, len(items), size)]


__all__ = [
    "LABELER_VERSION",
    "GroundedSamConfig",
    "GroundedSamLabeler",
    "LoadedModels",
    "assemble_soft_masks",
    "first_line",
    "folder_identity",
    "load_model",
    "load_processor",
    "model_folder_name",
    "pass_regions",
    "pick_device",
    "read_model_type",
    "resolve_model_folder",
]
