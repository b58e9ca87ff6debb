"""Benchmark: the 2D stage per frame with both engines, Grounding DINO + SAM and SAM 3, at their real
architecture sizes, through the labelers' own ``label_images`` (preprocessing, forward passes, mask
upsampling and packing, assembly), over precisions and batch sizes.

Models: REAL-SIZE architectures from their default transformers configs with random weights (weights do
not change the cost): Grounding DINO Swin-T + BERT-base (= IDEA-Research/grounding-dino-tiny) with SAM
ViT-B (= facebook/sam-vit-base), ``--sam-large`` adds SAM ViT-L; SAM 3 (= facebook/sam3: a 1008 px ViT
with 32 layers, a CLIP text encoder, DETR encoder/decoder, 200 queries). Configs, tokenizers and processor
configs are written to a temp folder and read back by the labelers as downloaded models are; the weights
stay in memory (writing GBs of random weights would only time the disk). ``--quick`` uses the tiny random
models of ``leap make-tiny-models`` instead (a smoke test in seconds).

Data: KITTI-size images (376 × 1241, deterministic noise) and the class prompts of
``projects/semantickitti_expanded.yaml`` (``--schema``; Grounding DINO: one joint pass; SAM 3: one pass per
prompt, so its cost grows with the prompt list).
With random weights, what is detected depends on the weights, so the mask work is pinned: Grounding DINO
keeps its first ``--boxes`` regions and SAM 3 keeps each prompt's ``--instances`` best-scored queries.
No 2D cache: every frame is computed.

Rows: engine × precision (fp16, the labelers' ``half_precision``, only on CUDA) × batch size (images
per forward pass): seconds per frame, frames per second, peak GPU memory, the extrapolated 2D stage of a
4,541-frame sequence (SemanticKITTI 08's length), and the ratio to Grounding DINO + SAM fp32 at batch 1,
measured in the same process on the same frames.

Run: ``.venv/bin/python benchmarks/bench_2d.py --quick`` (seconds, any machine); on a GPU machine
``.venv/bin/python benchmarks/bench_2d.py --device cuda`` (meant to take under 8 minutes on one H100; not yet
run on one); on CPU the real sizes take minutes per frame: ``--device cpu --batches 1 --frames 1
--no-warmup --schema semantickitti_bare`` (each class's name as its only prompt). Writes
``benchmarks/results/bench_2d[_quick][_cuda].json``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_models import real_detector, real_sam
from common import RESULTS_DIR, print_table, write_results

from leap_core.labelers.base import model_dtype
from leap_core.labelers.cache import PassResult
from leap_core.labelers.grounded_sam import GroundedSamConfig, GroundedSamLabeler, LoadedModels
from leap_core.labelers.sam3 import Sam3Labeler, Sam3LabelerConfig, _Loaded
from leap_core.labelers.tiny_models import (
    TinyModelsConfig,
    build_tiny_detector,
    build_tiny_sam3,
    build_tiny_segmenter,
    tiny_clip_tokenizer,
)
from leap_core.runtime import Runtime
from leap_core.schema import Schema, load_project_file, projects_dir

KITTI_HW = (376, 1241)
SEQUENCE_FRAMES = 4541
"""Frames of SemanticKITTI sequence 08, the length the 2D stage is extrapolated to."""


def real_sam3() -> tuple[Any, Any, dict[str, Any]]:
    """SAM 3 at its real size (default config), random weights, a CLIP tokenizer and its image config."""
    import torch
    from transformers import Sam3Config, Sam3Model

    torch.manual_seed(2)
    model = Sam3Model(Sam3Config()).eval()
    image = {"size": {"height": 1008, "width": 1008}, "image_mean": [0.5] * 3, "image_std": [0.5] * 3}
    return model, tiny_clip_tokenizer(32), image


def write_folder(folder: Path, config: Any, processor: Any, extra: dict[str, Any] | None = None) -> None:
    """A model folder as a download has it, without the weights: config, processor/tokenizer files."""
    import json

    folder.mkdir(parents=True, exist_ok=True)
    config.save_pretrained(folder)
    processor.save_pretrained(folder)
    if extra is not None:
        (folder / "preprocessor_config.json").write_text(json.dumps(extra))


def pin_regions(lab: GroundedSamLabeler, keep: int) -> None:
    """Make ``lab`` keep its detector's first ``keep`` regions per image whatever random weights score
    (with a box threshold just above zero every region passes, so SAM always gets ``keep`` boxes)."""
    detect = lab._detect

    def pinned(images: Any, plan: Any) -> Any:
        return [(b[:keep], s[:keep]) for b, s in detect(images, plan)]

    lab._detect = pinned  # type: ignore[method-assign]  # the benchmark pins the mask work


class PinnedSam3(Sam3Labeler):
    """SAM 3 keeping each prompt's ``instances`` best queries whatever random weights score (the mask
    upsampling and packing of a busy frame then always runs)."""

    instances = 5

    def _instances(self, res: Any, k: int, image_hw: tuple[int, ...], class_name: str) -> PassResult:
        import torch

        logits = res.pred_logits.float()
        low = logits.topk(min(self.instances, logits.shape[1]), dim=1).values[:, -1:]
        # The best queries score σ(presence), the others ~1e-9 (below the benchmark's threshold).
        pinned = torch.where(logits >= low, 20.0, -20.0)
        view = SimpleNamespace(
            pred_logits=pinned,
            presence_logits=res.presence_logits,
            pred_boxes=res.pred_boxes,
            pred_masks=res.pred_masks,
        )
        return super()._instances(view, k, image_hw, class_name)


def build_engines(
    args: argparse.Namespace, tmp: Path, schema: Schema
) -> dict[str, Callable[[str, int], Any]]:
    """Engine name → ``make(precision, batch)``: a labeler over in-memory models on ``args.device``."""

    dev = args.device
    words = sorted({w for c in schema.classes for p in (*c.prompts, *c.negative_prompts) for w in p.split()})
    if args.quick:
        tiny = TinyModelsConfig(max_text_len=256)
        det, segs, sam3 = (
            build_tiny_detector(tiny),
            {"SAM": build_tiny_segmenter(tiny)},
            build_tiny_sam3(tiny),
        )
    else:
        det, segs, sam3 = real_detector(words), {"SAM ViT-B": real_sam()}, real_sam3()
        if args.sam_large:
            segs["SAM ViT-L"] = real_sam(large=True)
    det_model = det[0].to(dev)
    engines: dict[str, Callable[[str, int], Any]] = {}
    for name, (seg_model, seg_proc) in segs.items():
        folder = tmp / name.replace(" ", "_")
        write_folder(folder / "grounding-dino-tiny", det[0].config, det[1])
        write_folder(folder / "sam-vit-base", seg_model.config, seg_proc)
        seg_on = seg_model.to(dev)

        def make_gs(
            precision: str, batch: int, folder: Path = folder, seg: Any = seg_on, sp: Any = seg_proc
        ) -> Any:
            if precision == "fp16" and dev != "cuda":
                return None
            # Threshold just above zero similarity: every region is kept, then pinned to --boxes below.
            cfg = GroundedSamConfig(batch_size=batch, box_threshold=1e-6, half_precision=precision == "fp16")
            lab = GroundedSamLabeler(cfg, Runtime(models_dir=folder, device=dev))
            # Cast in place, as the labeler casts what it loads; the next row casts back if it needs to.
            dtype = model_dtype(dev, cfg.half_precision)
            lab._models = LoadedModels(
                det_model.to(dtype), lab.detector_processor, seg.to(dtype), sp, dev, dtype
            )
            pin_regions(lab, args.boxes)
            return lab

        engines[f"Grounding DINO-T + {name}"] = make_gs
    s3_model, s3_tok, s3_image = sam3
    s3_folder = tmp / "models" / "sam3"
    write_folder(s3_folder, s3_model.config, s3_tok, s3_image)
    s3_on = s3_model.to(dev)

    def make_sam3(precision: str, batch: int) -> Any:
        if precision == "fp16" and dev != "cuda":
            return None
        cfg = Sam3LabelerConfig(
            score_threshold=1e-4,  # the pinned queries score σ(presence), the others ~1e-9
            batch_size=batch,
            prompts_per_pass=args.prompts_per_pass,
            half_precision=precision == "fp16",
        )
        lab = PinnedSam3(cfg, Runtime(models_dir=s3_folder.parent, device=dev))
        lab.instances = args.instances
        dtype = model_dtype(dev, cfg.half_precision)
        lab._loaded = _Loaded(s3_on.to(dtype), dtype, dev)
        return lab

    engines["SAM 3"] = make_sam3
    return engines


def main() -> None:  # one table of many measured figures
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny random models instead of real-size ones")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="where the models run")
    ap.add_argument("--batches", default="1,4,8", help="images per forward pass to time, comma-separated")
    ap.add_argument("--precisions", default="fp32,fp16", help="fp32 and/or fp16 (fp16 on CUDA only)")
    ap.add_argument("--frames", type=int, default=8, help="timed frames per row (after one warm-up batch)")
    ap.add_argument("--boxes", type=int, default=50, help="Grounding DINO regions given to SAM per image")
    ap.add_argument("--instances", type=int, default=5, help="SAM 3 instances kept per prompt")
    ap.add_argument("--prompts-per-pass", type=int, default=16, help="SAM 3 (image, prompt) pairs per pass")
    ap.add_argument("--sam-large", action="store_true", help="also time SAM ViT-L (the paper's SAM)")
    ap.add_argument(
        "--schema",
        default="semantickitti_expanded",
        help="class preset whose prompts are labeled (semantickitti_bare: each class's name only)",
    )
    ap.add_argument(
        "--no-warmup",
        action="store_true",
        help="time the first batch too (on a CPU nothing is compiled; real sizes take minutes per frame)",
    )
    ap.add_argument("--results-dir", type=Path, default=None, help="where the JSON goes")
    args = ap.parse_args()

    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        sys.exit("--device cuda: torch sees no CUDA GPU")
    schema, _ = load_project_file(projects_dir() / f"{args.schema}.yaml")
    rng = np.random.default_rng(0)
    tmp = Path(tempfile.mkdtemp(prefix="leap-bench-2d-"))
    engines = build_engines(args, tmp, schema)
    batches = [int(b) for b in args.batches.split(",")]
    precisions = [p.strip() for p in args.precisions.split(",")]

    rows: list[dict[str, Any]] = []
    for engine, make in engines.items():
        for precision in precisions:
            for batch in batches:
                lab = make(precision, batch)
                if lab is None:
                    continue
                n = max(args.frames, batch)
                first = 0 if args.no_warmup else batch
                frames = [rng.integers(0, 256, (*KITTI_HW, 3), dtype=np.uint8) for _ in range(n + first)]
                sync = torch.cuda.synchronize if args.device == "cuda" else (lambda: None)
                if first:
                    lab.label_images(frames[:first], schema)  # warm-up: kernels, allocator, lazy loads
                sync()
                if args.device == "cuda":
                    torch.cuda.reset_peak_memory_stats()
                start = time.perf_counter()
                for i in range(first, n + first, batch):
                    lab.label_images(frames[i : i + batch], schema)
                sync()
                per_frame = (time.perf_counter() - start) / n
                peak = torch.cuda.max_memory_allocated() / 2**30 if args.device == "cuda" else None
                rows.append(
                    {
                        "engine": engine,
                        "precision": precision,
                        "batch": batch,
                        "frames": n,
                        "s_per_frame": per_frame,
                        "fps": 1 / per_frame,
                        "peak_gpu_gib": peak,
                        "sequence_min": per_frame * SEQUENCE_FRAMES / 60,
                        "passes": lab.forward_passes(),
                    }
                )
                print(f"  {engine} {precision} batch {batch}: {per_frame:.3f} s/frame", flush=True)

    base = next(r for r in rows if r["engine"].startswith("Grounding") and r["batch"] == batches[0])
    base_name = f"{base['engine']} {base['precision']} batch {base['batch']}"
    where = (
        torch.cuda.get_device_name() if args.device == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    )
    prompts = sum(len(c.prompts) + len(c.negative_prompts) for c in schema.classes)
    print_table(
        f"2D stage per {KITTI_HW[1]}x{KITTI_HW[0]} frame, {where}, {'tiny' if args.quick else 'real-size'} "
        f"random-weight models, {prompts} prompts; ratio = {base_name} / row",
        [
            "engine",
            "precision",
            "batch",
            "s/frame",
            "frames/s",
            "peak GPU GiB",
            f"{SEQUENCE_FRAMES} frames min",
            "ratio",
        ],
        [
            [
                r["engine"],
                r["precision"],
                r["batch"],
                r["s_per_frame"],
                r["fps"],
                "-" if r["peak_gpu_gib"] is None else r["peak_gpu_gib"],
                r["sequence_min"],
                base["s_per_frame"] / r["s_per_frame"],
            ]
            for r in rows
        ],
    )
    name = "bench_2d" + ("_quick" if args.quick else "") + ("_cuda" if args.device == "cuda" else "")
    payload = {"image_hw": KITTI_HW, "schema": args.schema, "prompts": prompts, "device": where, "rows": rows}
    path = write_results(name, payload, args.results_dir or RESULTS_DIR)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
