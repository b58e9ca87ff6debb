"""Tiny RANDOM-WEIGHT Grounding DINO, SAM and SAM 3 checkpoints, built offline from configs.

These models exercise the real code paths of the ``grounded-sam`` and ``sam3`` labelers (folder loading,
tokenizers, detector outputs, masks, caching) in tests and on machines without the real weights.
**Their weights are random: the labels they produce are meaningless.** They are written in the same
folder layout as real checkpoints (``<dir>/grounding-dino-tiny``, ``<dir>/sam-vit-base``, ``<dir>/sam3``),
so ``leap labels2d … --models <dir>`` and ``leap run --labeler grounded-sam|sam3`` accept them unchanged; each
folder carries a :data:`MARKER_FILE` so the app can warn that the labels are not real.

Details that a tiny Grounding DINO must get right (docs/METHOD.md, "Facts about the tools"):

* at least 2 decoder layers;
* the text model hard-codes token ids 101 [CLS], 102 [SEP], 1012 ``.`` and 1029 ``?`` to split phrases,
  so the tiny BERT vocabulary puts those tokens at exactly those ids (phrases otherwise stop separating);
* SAM's vision ``num_pos_feats`` must be half the prompt-encoder hidden size.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from leap_core.io_utils import atomic_copy, atomic_write_bytes

MARKER_FILE = "LEAP_TINY_RANDOM_MODEL.txt"
"""Present in every folder written here; its presence means "random weights, meaningless labels"."""

_MARKER_TEXT = (
    "This is a tiny model with RANDOM weights, written by `leap make-tiny-models`.\n"
    "It exercises LeAP Studio's model labelers' code paths only; its labels are meaningless.\n"
    "For real labels download the real weights (see the README section 'Real 2D labels').\n"
)

# Whole-word entries make token counts of common prompts realistic; any other lowercase word still
# tokenizes, into single-character word pieces.
_WORDS = [
    "car",
    "automobile",
    "van",
    "jeep",
    "bicycle",
    "bike",
    "motorcycle",
    "motorbike",
    "scooter",
    "truck",
    "lorry",
    "pickup",
    "bus",
    "train",
    "tram",
    "trailer",
    "vehicle",
    "other",
    "person",
    "pedestrian",
    "people",
    "human",
    "child",
    "bicyclist",
    "cyclist",
    "rider",
    "motorcyclist",
    "biker",
    "road",
    "street",
    "lane",
    "marking",
    "parking",
    "lot",
    "space",
    "sidewalk",
    "footpath",
    "pavement",
    "curb",
    "ground",
    "median",
    "strip",
    "central",
    "reservation",
    "gravel",
    "dirt",
    "building",
    "house",
    "wall",
    "roof",
    "fence",
    "railing",
    "guardrail",
    "barrier",
    "vegetation",
    "tree",
    "bush",
    "hedge",
    "shrub",
    "plant",
    "trunk",
    "bark",
    "branch",
    "terrain",
    "grass",
    "soil",
    "lawn",
    "field",
    "pole",
    "lamp",
    "post",
    "utility",
    "traffic",
    "sign",
    "signboard",
    "light",
    "wire",
    "cable",
    "power",
    "line",
    "drone",
    "crop",
    "orchard",
    "row",
    "tower",
    "barn",
    "shed",
    "farm",
    "a",
    "an",
    "the",
    "of",
    "on",
    "in",
    "with",
    "and",
    "or",
]

SPECIAL_IDS = {"[PAD]": 0, "[UNK]": 100, "[CLS]": 101, "[SEP]": 102, "[MASK]": 103, ".": 1012, "?": 1029}
"""Token ids the tiny vocabulary must share with bert-base-uncased (Grounding DINO relies on them)."""


def tiny_vocab() -> dict[str, int]:
    """A BERT WordPiece vocabulary of 1100 entries with :data:`SPECIAL_IDS` at their BERT ids."""
    size = 1100
    slots: list[str | None] = [None] * size
    for tok, i in SPECIAL_IDS.items():
        slots[i] = tok
    chars = list("abcdefghijklmnopqrstuvwxyz0123456789")
    punct = ["-", ",", "'", "(", ")", "/", "&", ":", ";", "!"]
    regular = list(dict.fromkeys([*chars, *("##" + c for c in chars), *punct, *_WORDS]))
    free = (i for i in range(104, size) if slots[i] is None)
    for tok in regular:
        slots[next(free)] = tok
    vocab: dict[str, int] = {}
    for i, slot in enumerate(slots):
        vocab[slot if slot is not None else f"[unused{i}]"] = i
    return vocab


@dataclass(frozen=True)
class TinyModelsConfig:
    """Sizes of the tiny random models (small enough to run a frame in well under a second on a CPU)."""

    seed: int = 0
    """Seed of the random weights (the same seed writes the same weights)."""
    max_text_len: int = 128
    """Detector text-token budget (the real model has 256); small values force multi-pass splitting."""
    num_queries: int = 30
    """Detector query regions Q (the real model has 900)."""
    detector_shortest_edge: int = 96
    """Detector image processor: resize so the short side is this many pixels ..."""
    detector_longest_edge: int = 192
    """... and the long side at most this many."""
    sam_image_size: int = 64
    """SAM input size (the real one is 1024); images are resized to this long side and padded square."""
    sam3_image_size: int = 112
    """SAM 3 input size (the real one is 1008): a multiple of 14 · 2 (patches, and two attention windows
    per side)."""


def build_tiny_detector(cfg: TinyModelsConfig | None = None) -> tuple[Any, Any]:
    """``(model, processor)``: a tiny random GroundingDinoForObjectDetection and its processor (typed Any:
    transformers is unannotated)."""
    import torch
    from transformers import BertTokenizer, GroundingDinoConfig, GroundingDinoForObjectDetection
    from transformers.models.grounding_dino.image_processing_pil_grounding_dino import (
        GroundingDinoImageProcessorPil,
    )
    from transformers.models.grounding_dino.processing_grounding_dino import GroundingDinoProcessor

    cfg = cfg or TinyModelsConfig()
    vocab = tiny_vocab()
    config = GroundingDinoConfig(
        backbone_config={
            "model_type": "swin",
            "embed_dim": 16,
            "depths": [1, 1, 1, 1],
            "num_heads": [1, 1, 1, 1],
            "window_size": 4,
            "image_size": cfg.detector_shortest_edge,
            "out_indices": [2, 3, 4],
        },
        text_config={
            "model_type": "bert",
            "vocab_size": max(vocab.values()) + 1,
            "hidden_size": 32,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "intermediate_size": 64,
            "max_position_embeddings": max(cfg.max_text_len, 64),
        },
        num_queries=cfg.num_queries,
        encoder_layers=1,
        decoder_layers=2,
        d_model=32,
        encoder_ffn_dim=64,
        decoder_ffn_dim=64,
        encoder_attention_heads=2,
        decoder_attention_heads=2,
        max_text_len=cfg.max_text_len,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        model = GroundingDinoForObjectDetection(config).eval()  # type: ignore[no-untyped-call]  # transformers: unannotated eval()
    tokenizer = BertTokenizer(vocab=vocab, do_lower_case=True, model_max_length=cfg.max_text_len)
    image_processor = GroundingDinoImageProcessorPil(
        size={"shortest_edge": cfg.detector_shortest_edge, "longest_edge": cfg.detector_longest_edge}
    )
    processor = GroundingDinoProcessor(  # type: ignore[no-untyped-call]  # transformers: unannotated __init__
        image_processor=image_processor, tokenizer=tokenizer
    )
    return model, processor


def build_tiny_segmenter(cfg: TinyModelsConfig | None = None) -> tuple[Any, Any]:
    """``(model, processor)``: a tiny random SamModel and its processor (typed Any: transformers is
    unannotated)."""
    import torch
    from transformers import SamConfig, SamModel
    from transformers.models.sam.image_processing_pil_sam import SamImageProcessorPil
    from transformers.models.sam.processing_sam import SamProcessor

    cfg = cfg or TinyModelsConfig()
    size = cfg.sam_image_size
    prompt_hidden = 16
    config = SamConfig(
        vision_config={
            "hidden_size": 32,
            "output_channels": prompt_hidden,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "image_size": size,
            "patch_size": 8,
            "window_size": 4,
            "global_attn_indexes": [1],
            "num_pos_feats": prompt_hidden // 2,
            "mlp_dim": 64,
            "initializer_range": 0.02,
        },
        prompt_encoder_config={"hidden_size": prompt_hidden, "image_size": size, "patch_size": 8},
        mask_decoder_config={
            "hidden_size": prompt_hidden,
            "mlp_dim": 32,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "iou_head_hidden_dim": 16,
        },
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed + 1)
        model = SamModel(config).eval()  # type: ignore[no-untyped-call]  # transformers: unannotated eval()
    image_processor = SamImageProcessorPil(
        size={"longest_edge": size}, pad_size={"height": size, "width": size}
    )
    processor = SamProcessor(image_processor=image_processor)  # type: ignore[no-untyped-call]  # transformers: unannotated
    return model, processor


def tiny_clip_tokenizer(max_length: int) -> Any:
    """A byte-level BPE CLIP tokenizer (the kind SAM 3 reads) whose vocabulary holds the lowercase
    letters, digits and punctuation, each alone and word-final (``a</w>``), and the whole words of the
    tiny BERT vocabulary as single tokens (typed Any: transformers is unannotated)."""
    from transformers import CLIPTokenizer

    symbols = list("abcdefghijklmnopqrstuvwxyz0123456789") + list("-,'()/&:;!.")
    vocab: dict[str, int] = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for sym in [*symbols, *(c + "</w>" for c in symbols)]:
        vocab.setdefault(sym, len(vocab))
    merges: list[tuple[str, str]] = []
    for word in _WORDS:
        # Left to right: "car" → (c, a), (ca, r</w>); each word ends as one token.
        parts = [*word[:-1], word[-1] + "</w>"]
        while len(parts) > 1:
            pair = (parts[0], parts[1])
            if pair not in merges:
                merges.append(pair)
            parts = [parts[0] + parts[1], *parts[2:]]
            vocab.setdefault(parts[0], len(vocab))
    # The tokenizers BPE model takes merges as pairs; transformers annotates them as strings only.
    return CLIPTokenizer(vocab=vocab, merges=merges, model_max_length=max_length)  # type: ignore[arg-type]


def build_tiny_sam3(cfg: TinyModelsConfig | None = None) -> tuple[Any, Any, dict[str, Any]]:
    """``(model, tokenizer, image processor config)``: a tiny random Sam3Model, its CLIP tokenizer and
    the ``preprocessor_config.json`` content the ``sam3`` labeler reads (typed Any: transformers is
    unannotated). The image side needs ``sam3_image_size / 14`` patches divisible by the window size."""
    import torch
    from transformers import Sam3Config, Sam3Model

    cfg = cfg or TinyModelsConfig()
    tokenizer = tiny_clip_tokenizer(32)
    size, hidden = cfg.sam3_image_size, 32
    grid = size // 14  # patches per side; the FPN's levels are 4×, 2× and 1× that
    layers = {"hidden_size": hidden, "num_attention_heads": 2, "intermediate_size": 64}
    config = Sam3Config(
        vision_config={
            "backbone_config": {
                "model_type": "sam3_vit_model",
                **layers,
                "num_hidden_layers": 2,
                "image_size": size,
                "patch_size": 14,
                "window_size": grid // 2,
                "global_attn_indexes": [1],
                "pretrain_image_size": size // 2,
            },
            "fpn_hidden_size": hidden,
            "backbone_feature_sizes": [[4 * grid, 4 * grid], [2 * grid, 2 * grid], [grid, grid]],
        },
        text_config={
            "model_type": "clip_text_model",
            **layers,
            "vocab_size": len(tokenizer.get_vocab()),
            "projection_dim": hidden,
            "num_hidden_layers": 1,
            "max_position_embeddings": 32,
            "bos_token_id": 0,
            "eos_token_id": 1,
            "pad_token_id": 1,
        },
        geometry_encoder_config={**layers, "num_layers": 1},
        detr_encoder_config={**layers, "num_layers": 1},
        detr_decoder_config={**layers, "num_layers": 2, "num_queries": cfg.num_queries},
        mask_decoder_config={"hidden_size": hidden, "num_attention_heads": 2},
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed + 2)
        model = Sam3Model(config).eval()  # type: ignore[no-untyped-call]  # transformers: unannotated eval()
        # Random initial weights give every query a logit within ±0.01 of 0 and the image a presence of
        # 0.5: every score would sit near 0.25, below the default threshold, and a run would keep nothing.
        # A confident presence and query logits spread by ±0.6 keep about half the queries, so the whole
        # path (masks, projection, fusion) runs at the default settings; the labels stay meaningless.
        with torch.no_grad():
            model.detr_decoder.presence_head.layer3.bias.fill_(4.0)
            model.dot_product_scoring.query_proj.weight.mul_(60.0)
    image_config = {
        "image_processor_type": "Sam3ImageProcessor",
        "size": {"height": size, "width": size},
        "image_mean": [0.5, 0.5, 0.5],
        "image_std": [0.5, 0.5, 0.5],
        "do_rescale": True,
        "rescale_factor": 1 / 255,
        "do_normalize": True,
    }
    return model, tokenizer, image_config


@dataclass(frozen=True)
class TinyModelPaths:
    """Folders written by :func:`make_tiny_models`."""

    models_dir: Path
    """Pass this as ``--models`` / ``Runtime.models_dir``."""
    detector: Path
    """``models_dir/grounding-dino-tiny``"""
    segmenter: Path
    """``models_dir/sam-vit-base``"""
    sam3: Path
    """``models_dir/sam3``"""


def make_tiny_models(
    models_dir: str | Path,
    cfg: TinyModelsConfig | None = None,
    detector_name: str = "grounding-dino-tiny",
    segmenter_name: str = "sam-vit-base",
    sam3_name: str = "sam3",
) -> TinyModelPaths:
    """Write tiny random Grounding DINO, SAM and SAM 3 folders (weights, configs, processors, marker files).

    The folder names default to the last part of the labeler's default model ids, so pointing
    ``Runtime.models_dir`` at ``models_dir`` loads them with no other setting.
    RANDOM WEIGHTS: the labels these models produce are meaningless; they only exercise the code path.
    """
    root = Path(models_dir)
    det_dir, seg_dir, sam3_dir = root / detector_name, root / segmenter_name, root / sam3_name
    det_model, det_proc = build_tiny_detector(cfg)
    seg_model, seg_proc = build_tiny_segmenter(cfg)
    sam3_model, sam3_tok, sam3_image = build_tiny_sam3(cfg)
    for folder, model, proc in (
        (det_dir, det_model, det_proc),
        (seg_dir, seg_model, seg_proc),
        (sam3_dir, sam3_model, sam3_tok),
    ):
        folder.mkdir(parents=True, exist_ok=True)
        # transformers writes the weights through a temp file of its own, whose 0600 mode the rename
        # keeps: written to a staging folder, each file is copied in by leap's atomic writer instead.
        with tempfile.TemporaryDirectory(prefix="leap-tiny-") as staging:
            model.save_pretrained(staging)
            proc.save_pretrained(staging)
            for path in sorted(p for p in Path(staging).rglob("*") if p.is_file()):
                atomic_copy(path, folder / path.relative_to(staging))
        atomic_write_bytes(folder / MARKER_FILE, _MARKER_TEXT.encode())
    # SAM 3's image processor needs torchvision to be built, so its config is written as JSON.
    atomic_write_bytes(sam3_dir / "preprocessor_config.json", json.dumps(sam3_image, indent=2).encode())
    atomic_write_bytes(root / "README.txt", _MARKER_TEXT.encode())
    return TinyModelPaths(models_dir=root, detector=det_dir, segmenter=seg_dir, sam3=sam3_dir)


def is_tiny_random(folder: str | Path) -> bool:
    """True when ``folder`` was written by :func:`make_tiny_models` (random weights)."""
    return (Path(folder) / MARKER_FILE).is_file()


__all__ = [
    "MARKER_FILE",
    "SPECIAL_IDS",
    "TinyModelPaths",
    "TinyModelsConfig",
    "build_tiny_detector",
    "build_tiny_sam3",
    "build_tiny_segmenter",
    "is_tiny_random",
    "make_tiny_models",
    "tiny_clip_tokenizer",
    "tiny_vocab",
]
