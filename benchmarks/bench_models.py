"""Benchmark: per-image cost of the grounded-sam labeler on this machine, detector and segmenter apart,
and the cost of a 2D cache hit.

Models: the REAL-SIZE architectures built from their default transformers configs with random weights
(weights do not change the cost): Grounding DINO with the Swin-T backbone and BERT-base text encoder
(= IDEA-Research/grounding-dino-tiny, 800 px short side / 1333 px long side, Q = 900, T = 256) and SAM
ViT-B (= facebook/sam-vit-base, 1024 px input); ``--sam-large`` adds SAM ViT-L (the paper's SAM).
Their configs and processors are written to a temp folder and read back by the labeler exactly as a
downloaded model is; the weights stay in memory (writing ~1 GB of random weights would only time the disk).

Data: one KITTI-size image (376 × 1241, deterministic noise; the cost does not depend on the content).
The detector text is the whole ``projects/semantickitti_expanded.yaml`` prompt list in one pass (joint
mode, as in the paper). SAM gets ``--boxes`` boxes (default 50, a busy KITTI frame) so its decoder cost
does not depend on what random weights happen to detect.

Rows:
- detector: one joint pass (image preprocessing, forward, region maths) for one image;
- SAM encoder: the image encoder alone (once per image, whatever the number of boxes);
- SAM encoder + decoder: the labeler's segmentation step for ``--boxes`` boxes (masks upsampled to the
  image size and packed);
- total compute = detector + SAM encoder + decoder: the baseline of the ratio column;
- cache hit: ``label_images`` on an image whose pass result is in the 2D cache (digest, read, assemble).

Run: ``.venv/bin/python benchmarks/bench_models.py`` (about 2 minutes on 2 CPU cores; ``--quick`` runs the
tiny random models in seconds as a smoke test). Writes ``benchmarks/results/models.json``
(``models_quick.json`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import print_table, time_it, write_results

from leap_core.labelers.base import model_dtype
from leap_core.labelers.cache import LabelCache, PassResult, image_digest
from leap_core.labelers.grounded_sam import GroundedSamConfig, GroundedSamLabeler, LoadedModels
from leap_core.labelers.tiny_models import (
    TinyModelsConfig,
    build_tiny_detector,
    build_tiny_segmenter,
    tiny_vocab,
)
from leap_core.runtime import Runtime
from leap_core.schema import load_project_file, projects_dir

KITTI_HW = (376, 1241)


def real_detector(words: list[str]):
    """Grounding DINO Swin-T + BERT-base from default configs, random weights, and its processor.

    The vocabulary is 30522 entries like bert-base-uncased, with the BERT special ids and every word of
    the prompt list as one word piece (the real vocabulary has nearly all of them)."""
    import torch
    from transformers import BertTokenizer, GroundingDinoConfig, GroundingDinoForObjectDetection
    from transformers.models.grounding_dino.image_processing_pil_grounding_dino import (
        GroundingDinoImageProcessorPil,
    )
    from transformers.models.grounding_dino.processing_grounding_dino import GroundingDinoProcessor

    vocab = tiny_vocab()
    for w in words:
        if w not in vocab:
            vocab[w] = len(vocab)
    for i in range(len(vocab), 30522):
        vocab[f"[unused{i}]"] = i
    torch.manual_seed(0)
    model = GroundingDinoForObjectDetection(GroundingDinoConfig()).eval()
    proc = GroundingDinoProcessor(
        image_processor=GroundingDinoImageProcessorPil(),
        tokenizer=BertTokenizer(vocab=vocab, do_lower_case=True),
    )
    return model, proc


def real_sam(large: bool = False):
    """SAM ViT-B (default config) or ViT-L, random weights, and its processor (1024 px)."""
    import torch
    from transformers import SamConfig, SamModel
    from transformers.models.sam.image_processing_pil_sam import SamImageProcessorPil
    from transformers.models.sam.processing_sam import SamProcessor

    vision = {}
    if large:  # ViT-L: facebook/sam-vit-large's encoder
        vision = {
            "hidden_size": 1024,
            "num_hidden_layers": 24,
            "num_attention_heads": 16,
            "global_attn_indexes": [5, 11, 17, 23],
        }
    torch.manual_seed(1)
    model = SamModel(SamConfig(vision_config=vision)).eval()
    return model, SamProcessor(image_processor=SamImageProcessorPil())


def make_labeler(
    folder: Path, det: tuple, seg: tuple, cache: Path, device: str = "cpu"
) -> GroundedSamLabeler:
    """A labeler whose folders hold the models' configs and processors and whose weights are in memory
    (moved to ``device``)."""
    det_dir, seg_dir = folder / "grounding-dino-tiny", folder / "sam-vit-base"
    for d, (model, proc) in ((det_dir, det), (seg_dir, seg)):
        d.mkdir(parents=True, exist_ok=True)
        model.config.save_pretrained(d)
        proc.save_pretrained(d)
    lab = GroundedSamLabeler(
        GroundedSamConfig(), Runtime(models_dir=folder, device=device), cache=LabelCache(cache)
    )
    dtype = model_dtype(device, lab.config.half_precision)
    lab._models = LoadedModels(
        det[0].to(device, dtype), lab.detector_processor, seg[0].to(device, dtype), seg[1], device, dtype
    )
    return lab


def random_boxes(n: int, hw: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    h, w = hw
    x0, y0 = rng.uniform(0, w * 0.8, n), rng.uniform(0, h * 0.7, n)
    bw, bh = rng.uniform(20, w * 0.2, n), rng.uniform(20, h * 0.3, n)
    return np.stack([x0, y0, np.minimum(x0 + bw, w), np.minimum(y0 + bh, h)], axis=1).astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boxes", type=int, default=50, help="boxes given to SAM per image")
    ap.add_argument("--repeat", type=int, default=2, help="timed runs per row (after one warm-up run)")
    ap.add_argument("--sam-large", action="store_true", help="also time SAM ViT-L (the paper's SAM)")
    ap.add_argument("--quick", action="store_true", help="tiny random models instead of real-size ones")
    ap.add_argument(
        "--device",
        choices=("cpu", "cuda"),
        default="cpu",
        help="where the models run (results of cuda go to models_cuda.json)",
    )
    args = ap.parse_args()

    import torch

    dev = args.device

    def timed(fn):  # a CUDA call returns before the GPU is done: wait for it inside the timed function
        if dev != "cuda":
            return fn
        return lambda: (fn(), torch.cuda.synchronize())

    schema, _ = load_project_file(projects_dir() / "semantickitti_expanded.yaml")
    words = sorted(
        {w for c in schema.classes for p in (*c.prompts, *c.negative_prompts) for w in p.lower().split()}
    )
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (*KITTI_HW, 3), dtype=np.uint8)
    boxes = random_boxes(args.boxes, KITTI_HW, rng)
    tmp = Path(tempfile.mkdtemp(prefix="leap-bench-models-"))

    if args.quick:
        tiny = TinyModelsConfig(max_text_len=256)
        det, segs = build_tiny_detector(tiny), {"tiny SAM": build_tiny_segmenter(tiny)}
        det_name = "tiny Grounding DINO"
    else:
        det, segs = real_detector(words), {"SAM ViT-B": real_sam()}
        if args.sam_large:
            segs["SAM ViT-L"] = real_sam(large=True)
        det_name = "Grounding DINO Swin-T"

    rows, results = [], {}
    lab = make_labeler(tmp / "m0", det, next(iter(segs.values())), tmp / "cache", dev)
    plans = lab.plan(schema)
    t_det = time_it(timed(lambda: lab._detect([image], plans[0])), repeat=args.repeat, warmup=1)
    n_q = det[0].config.num_queries
    results["detector"] = {
        **t_det.to_dict(),
        "passes": len(plans),
        "text_tokens": plans[0].num_tokens,
        "queries": n_q,
    }
    seg_times = {}
    for name, seg in segs.items():
        slab = make_labeler(tmp / name.replace(" ", "_"), det, seg, tmp / "cache", dev)
        pix = seg[1](images=[image], return_tensors="pt")["pixel_values"].to(dev)

        def encode(m=seg[0], p=pix) -> None:
            with torch.inference_mode():
                m.get_image_embeddings(p)

        t_enc = time_it(timed(encode), repeat=args.repeat, warmup=1)
        t_full = time_it(timed(lambda s=slab: s._segment([image], [boxes])), repeat=args.repeat, warmup=1)
        seg_times[name] = (t_enc, t_full)
        results[name] = {
            "encoder": t_enc.to_dict(),
            "encoder_plus_decoder": t_full.to_dict(),
            "boxes": args.boxes,
        }

    # Cache hit: pass results with --boxes regions in all, stored under the keys the labeler computes.
    h, w = KITTI_HW
    digest = image_digest(image)
    cache = lab.cache
    assert cache is not None, "make_labeler gives the labeler a 2D cache"
    for part, plan in zip(np.array_split(np.arange(args.boxes), len(plans)), plans, strict=True):
        masks = np.zeros((len(part), h, w), dtype=bool)
        for j, (x0, y0, x1, y1) in enumerate(boxes[part].astype(int)):
            masks[j, y0:y1, x0:x1] = True
        k = len(plan.class_names)
        logits = rng.normal(0, 2, (len(part), k)).astype(np.float32)
        res = PassResult(
            h, w, plan.class_names, boxes[part], logits, np.packbits(masks.reshape(len(part), -1), axis=1)
        )
        cache.put(lab.pass_key(digest, plan), res)
    calls_before = lab.detector_calls
    t_hit = time_it(lambda: lab.label_images([image], schema), repeat=5, warmup=1)
    assert lab.detector_calls == calls_before, "a cache hit must not run the detector"
    results["cache_hit"] = t_hit.to_dict()

    def row(label: str, t: float, cpu: float, base: float) -> list:
        return [label, t, cpu, base / t if t > 0 else float("inf")]

    _, first_full = next(iter(seg_times.values()))
    baseline = t_det.median + first_full.median
    rows.append(row(f"{det_name}: 1 joint pass", t_det.median, t_det.cpu_median, baseline))
    for name, (t_enc, t_full) in seg_times.items():
        rows.append(row(f"{name} encoder", t_enc.median, t_enc.cpu_median, baseline))
        rows.append(
            row(f"{name} encoder + decoder ({args.boxes} boxes)", t_full.median, t_full.cpu_median, baseline)
        )
        rows.append(
            row(
                f"total compute, {det_name} + {name}",
                t_det.median + t_full.median,
                t_det.cpu_median + t_full.cpu_median,
                baseline,
            )
        )
    rows.append(row("2D cache hit (read + assemble)", t_hit.median, t_hit.cpu_median, baseline))
    where = torch.cuda.get_device_name() if dev == "cuda" else f"{torch.get_num_threads()} torch threads"
    title = (
        f"grounded-sam per image, {KITTI_HW[1]}x{KITTI_HW[0]} px, {where}, "
        f"text {plans[0].num_tokens} tokens in {len(plans)} pass(es), Q={n_q}; "
        f"ratio = total compute ({det_name} + {next(iter(seg_times))}) / row"
    )
    print_table(title, ["step", "median s", "cpu s", "x faster than compute"], rows)
    n_classes = schema.num_classes
    print(
        f"per-class mode runs the detector {n_classes}x per image: "
        f"about {n_classes * t_det.median:.0f} s here.\n"
    )
    name = ("models_quick" if args.quick else "models") + ("_cuda" if dev == "cuda" else "")
    path = write_results(
        name, {"image_hw": KITTI_HW, "schema": "semantickitti_expanded", "device": where, "results": results}
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
