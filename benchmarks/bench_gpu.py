"""Benchmark: a whole sequence on one GPU, end to end: the 2D stage through the real-size models (random
weights, batched), the 3D stages and one 3D-CN round, with per-stage seconds, GPU busy share and peak
memory, extrapolated to a 4,541-frame sequence (SemanticKITTI 08's length).

Set-up, timed but not part of the figures: ``leap synth``'s generator writes ``--frames`` frames (default
300) of the demo street, one worker process per core; the 2D models are built (bench_2d.py's real-size
Grounding DINO Swin-T + SAM ViT-B, or SAM 3 with ``--engine sam3``: random weights, which cost what
trained ones do) and warmed up once per batch size.

Timed, in the order ``leap labels2d`` and ``leap run --cache`` work on a GPU machine:

1. the 2D stage as ``leap labels2d`` runs it (:func:`leap_core.pipeline.executor.label_cache_task`,
   ``--batch`` images per forward pass into the 2D cache), in fp16 on CUDA (the labelers'
   ``half_precision``; fp32 on a CPU). Same-process baseline: the same engine at batch 1 in fp32 on the
   first ``--baseline-frames`` frames, into a cache of its own. The mask work is pinned as
   in bench_2d.py (``--boxes`` SAM boxes per image, ``--instances`` SAM 3 instances per prompt), since
   what random weights detect says nothing about a real frame;
2. ``run_pipeline`` (what ``leap run`` calls) with that cache: its ``labels2d`` stage reads the cached
   passes, then project, motion, fuse, smooth, ONE 3D-CN round (the default consistency settings,
   ``device auto``), label_points, tracks, evaluate, export. The round is split into its selection,
   training steps and inference (with the fusion back and smoothing) by its own progress reports, which
   count scans, steps and scans (to within one unit: they arrive in thousandths of the round).

The models reach the labelers that the pipeline builds through a benchmark labeler registered with
:func:`leap_core.labelers.register_labeler` (``bench-grounded-sam`` / ``bench-sam3``: the product's
labeler classes with the weights in memory and the mask work pinned). The models leave the GPU before the
run, so a 2D cache miss in the run would fail rather than be computed unseen.

Per row: seconds (each pipeline stage's own record; for the 2D stage and the round's phases, the span
between progress reports), seconds per frame (per step for the round's training), GPU busy share (the
mean of ``utilization.gpu`` sampled every ``--sample-interval`` s through pynvml when installed, else
``nvidia-smi``; "no GPU" on a CPU), peak GPU memory (``torch.cuda.max_memory_allocated``, reset at each
stage's first progress report; the round's phases show the round's) and peak host RSS (the process's
high-water mark, reset likewise), and the minutes at 4,541 frames: per-frame stages linearly, the
round's training by its step rule (``num_train_steps``: ``max(epochs · ⌈S / scans_per_step⌉,
min_steps)`` steps for S scans, 500 at 300 scans and 4,541 at 4,541 with the defaults) and its selection
and inference per scan. Their sum is set against the target: a 4,541-frame sequence end to end in at
most 30 minutes on one H100.

``--budget`` (default 440 s from the start of ``main``, after the imports) stops the run through the
pipeline's own cancellation at its next progress report once spent, so the command ends within 8 minutes
and prints what it measured (a round stopped in training still gives its seconds per step; the whole-run
figure is then an estimate that says what it lacks).

Run: ``.venv/bin/python benchmarks/bench_gpu.py`` on a GPU machine (not run on a GPU yet; without a CUDA
GPU it stops at once unless ``--device cpu`` insists, when a real-size frame takes minutes). ``--quick``:
2 small frames, the tiny random models of ``leap make-tiny-models`` and bench_3dcn.py's small 3D-CN
settings, seconds on any machine (a smoke test, not a measurement; on a GPU machine, a first try of the
CUDA path). Writes ``benchmarks/results/bench_gpu[_quick].json`` (or into ``$LEAP_BENCH_RESULTS``), with
the time line of windows and GPU samples.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import logging
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_2d import PinnedSam3, pin_regions, real_sam3, write_folder
from bench_3dcn import QUICK_CONFIG
from bench_models import real_detector, real_sam
from common import RESULTS_DIR, PeakMemory, print_table, write_results

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.consistency.train import num_train_steps
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import Cancelled
from leap_core.labelers import LabelerSpec, register_labeler
from leap_core.labelers.base import ImageModelLabeler, Labeler, model_dtype
from leap_core.labelers.grounded_sam import GroundedSamConfig, GroundedSamLabeler, LoadedModels
from leap_core.labelers.sam3 import Sam3LabelerConfig, _Loaded
from leap_core.labelers.tiny_models import (
    TinyModelsConfig,
    build_tiny_detector,
    build_tiny_sam3,
    build_tiny_segmenter,
)
from leap_core.pipeline import STAGES, SequenceSpec, run_pipeline
from leap_core.pipeline.context import read_state
from leap_core.pipeline.executor import StopSignal, label_cache_task
from leap_core.pipeline.run import JOINT
from leap_core.presets import load_preset
from leap_core.run_layout import RunLayout
from leap_core.runtime import MAX_FRAME_THREADS, Runtime
from leap_core.schema import Schema
from leap_core.synth import SynthConfig, generate_sequence
from leap_core.synth.camera import CameraConfig
from leap_core.synth.lidar import LidarConfig

SEQUENCE_FRAMES = 4541
"""Frames of SemanticKITTI sequence 08, the length the run is extrapolated to."""
TARGET_MIN = 30.0
"""A 4,541-frame sequence end to end (2D + 3D + one 3D-CN round) in at most this many minutes on one H100."""
QUICK_FRAMES = 2
QUICK_SYNTH: dict[str, Any] = {
    "lidar": LidarConfig(beams=16, azimuth_step_deg=0.4),
    "camera": CameraConfig().scaled(0.25),
    "shadows": False,
}
"""``--quick``: the demo street with an eighth of its points per scan and a quarter-size image, so the smoke
test's generator, 2D models and 3D stages take a second or two each."""
DISK_PER_FRAME = 16 * 2**20
"""Free space asked for per frame: the synthetic frame (about 3.3 MB), its run files and both 2D caches,
with room to spare."""
ENGINES = {"grounded-sam": "Grounding DINO-T + SAM ViT-B", "sam3": "SAM 3"}
NEEDS: dict[str, list[tuple[str, str]]] = {
    # engine: the (module, name) its models and processors are built from
    "grounded-sam": [
        ("transformers", "GroundingDinoForObjectDetection"),
        ("transformers", "SamModel"),
        ("transformers", "BertTokenizer"),
        (
            "transformers.models.grounding_dino.image_processing_pil_grounding_dino",
            "GroundingDinoImageProcessorPil",
        ),
        ("transformers.models.sam.image_processing_pil_sam", "SamImageProcessorPil"),
    ],
    "sam3": [("transformers", "Sam3Model"), ("transformers", "CLIPTokenizer")],
}


# ------------------------------------------------------------------------------------- fail early
def check_stack(args: argparse.Namespace) -> str:
    """The device the 2D models use ("cuda" or "cpu"); exits with one line, before any minute is spent,
    when something the run needs is missing."""
    try:
        import torch
        import transformers
    except ModuleNotFoundError as exc:
        sys.exit(f"bench_gpu: {exc.name} is not installed (bash scripts/install.sh)")
    cuda = torch.cuda.is_available()
    if args.device == "cuda" and not cuda:
        sys.exit(f"bench_gpu: --device cuda, but torch {torch.__version__} sees no CUDA GPU")
    device = "cuda" if cuda and args.device != "cpu" else "cpu"
    if args.device == "auto" and not cuda and not args.quick:
        sys.exit(
            f"bench_gpu: torch {torch.__version__} (CUDA {torch.version.cuda}) sees no CUDA GPU (a CPU "
            "build?); the real-size models take minutes per frame on a CPU: run with --quick, or --device "
            "cpu to insist"
        )
    for module, name in NEEDS[args.engine]:
        try:
            ok = hasattr(importlib.import_module(module), name)
        except ImportError:
            ok = False
        if not ok:
            sys.exit(
                f"bench_gpu: transformers {transformers.__version__} has no {module}.{name}, which "
                f"--engine {args.engine} needs: install a newer transformers into .venv"
            )
    work = args.work if args.work is not None else Path(tempfile.gettempdir())
    if not work.is_dir():
        sys.exit(f"bench_gpu: --work {work}: not a folder")
    free, need = shutil.disk_usage(work).free, args.frames * DISK_PER_FRAME
    if free < need:
        sys.exit(
            f"bench_gpu: {work} has {free / 2**30:.1f} GiB free, {args.frames} frames need about "
            f"{need / 2**30:.1f} GiB: pass --work on a larger disk"
        )
    return device


# ------------------------------------------------------------------------------------ measurement
class GpuSampler:
    """The GPU's busy share (``utilization.gpu``, %) and memory in use (MiB) every ``interval`` seconds
    in a background thread, through pynvml when it is installed, else ``nvidia-smi``; ``source`` is ""
    when neither answers (nothing is sampled then)."""

    def __init__(self, interval: float) -> None:
        self.interval = interval
        self.samples: list[tuple[float, float, float]] = []
        """(``perf_counter`` time, busy %, memory MiB)."""
        # The GPU torch uses: the first of CUDA_VISIBLE_DEVICES (an index or a UUID), else GPU 0.
        self.gpu = (os.environ.get("CUDA_VISIBLE_DEVICES") or "0").split(",")[0].strip() or "0"
        self.source = ""
        self._read: Callable[[], tuple[float, float]] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        for source, make in (("pynvml", self._nvml), ("nvidia-smi", self._smi)):
            with contextlib.suppress(
                Exception
            ):  # not installed, no driver: try the next, else sample nothing
                read = make()
                read()
                self._read, self.source = read, source
                break

    def _nvml(self) -> Callable[[], tuple[float, float]]:
        import pynvml

        pynvml.nvmlInit()
        get = pynvml.nvmlDeviceGetHandleByIndex if self.gpu.isdigit() else pynvml.nvmlDeviceGetHandleByUUID
        handle = get(int(self.gpu) if self.gpu.isdigit() else self.gpu)

        def read() -> tuple[float, float]:
            util = pynvml.nvmlDeviceGetUtilizationRates(handle)
            return float(util.gpu), pynvml.nvmlDeviceGetMemoryInfo(handle).used / 2**20

        return read

    def _smi(self) -> Callable[[], tuple[float, float]]:
        query = "--query-gpu=utilization.gpu,memory.used"
        command = ["nvidia-smi", query, "--format=csv,noheader,nounits", "-i", self.gpu]

        def read() -> tuple[float, float]:
            out = subprocess.run(command, capture_output=True, text=True, timeout=10, check=True)
            busy, mem = out.stdout.strip().splitlines()[0].split(",")
            return float(busy), float(mem)

        return read

    def start(self) -> None:
        read = self._read
        if read is None:
            return

        def loop() -> None:
            while not self._stop.is_set():
                t = time.perf_counter()
                with contextlib.suppress(Exception):  # a missed sample is a gap, not an error
                    busy, mem = read()
                    self.samples.append((t, busy, mem))
                self._stop.wait(max(0.0, self.interval - (time.perf_counter() - t)))

        self._thread = threading.Thread(target=loop, name="gpu-sampler", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=15)

    def between(self, t0: float, t1: float) -> list[tuple[float, float, float]]:
        return [s for s in self.samples if t0 <= s[0] <= t1]


@dataclass
class Window:
    """A span of the run: a stage, a part of the 2D stage or a phase of the 3D-CN round."""

    name: str
    t0: float
    t1: float = math.nan
    peak_gpu_gib: float | None = None
    peak_rss_gib: float | None = None

    @property
    def seconds(self) -> float:
        return self.t1 - self.t0


@dataclass
class Meter:
    """One :class:`Window` per stage as the pipeline reports progress (they tile the time line: one ends
    where the next begins, at the last report before the next stage's first), resetting torch's peak GPU
    memory and the process's RSS high-water mark as each opens."""

    cuda: bool
    windows: list[Window] = field(default_factory=list)
    current: Window | None = None
    last_report: float = field(default_factory=time.perf_counter)
    marks: list[tuple[float, int]] = field(default_factory=list)
    """(time, thousandths done) of the 3D-CN round's progress reports."""
    _rss: PeakMemory = field(default_factory=PeakMemory)

    def open(self, name: str, t0: float | None = None) -> None:
        start = time.perf_counter() if t0 is None else t0
        self.close(start)
        if self.cuda:
            import torch

            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        self._rss.start()
        self.current = Window(name, start)

    def close(self, t1: float | None = None) -> None:
        w = self.current
        if w is None:
            return
        if self.cuda:
            import torch

            torch.cuda.synchronize()
            w.peak_gpu_gib = torch.cuda.max_memory_allocated() / 2**30
        self._rss.stop()
        w.peak_rss_gib = self._rss.peak / 2**30
        w.t1 = time.perf_counter() if t1 is None else t1
        self.windows.append(w)
        self.current = None

    def report(self, sequence: str, stage: str, done: int, _total: int) -> None:
        """``run_pipeline``'s progress callback (the round reports as the sequence ``JOINT``)."""
        now = time.perf_counter()
        name = "3dcn round" if sequence == JOINT else stage
        if self.current is None or self.current.name != name:
            self.open(name, self.last_report)
        if sequence == JOINT:
            self.marks.append((now, done))
        self.last_report = now

    def named(self, name: str) -> list[Window]:
        return [w for w in self.windows if w.name == name]


@contextlib.contextmanager
def deadline(stop: StopSignal, seconds: float) -> Iterator[None]:
    """Set ``stop`` once ``seconds`` have passed (what ``label_cache_task`` and the progress callback
    check)."""
    timer = threading.Timer(max(seconds, 0.0), stop.set)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


# ----------------------------------------------------------------------------------------- engines
@dataclass
class Engine:
    """One 2D engine's models, held in memory and served to every labeler that ``make_labeler`` builds
    for the registered benchmark labeler ``spec`` (``label_cache_task``'s and the pipeline's)."""

    name: str
    spec: LabelerSpec[Any]
    held: dict[str, Any]
    """The models while the 2D stage runs; emptied after it (a labeler built then has no weights)."""

    def config(
        self, batch: int, fp16: bool, args: argparse.Namespace, base: PipelineConfig
    ) -> PipelineConfig:
        """``base`` with this labeler at ``batch`` images per pass (thresholds just above zero, so the
        pinned regions or instances are kept whatever random weights score) and one 3D-CN round."""
        section: dict[str, Any] = {"batch_size": batch, "box_threshold": 1e-6, "half_precision": fp16}
        if self.name == "sam3":
            section = {
                "batch_size": batch,
                "score_threshold": 1e-4,
                "prompts_per_pass": args.prompts_per_pass,
                "half_precision": fp16,
            }
        consistency: dict[str, Any] = {"enabled": True, "iterations": 1}
        if args.quick:
            consistency.update(QUICK_CONFIG)
        d = {"labeler": self.spec.name, self.spec.section: section, "consistency": consistency}
        return config_from_dict(d, base)


def build_engine(args: argparse.Namespace, device: str, models: Path, schema: Schema) -> Engine:
    """The ``args.engine`` models (real size; tiny with ``--quick``) on ``device``, their configs and
    processors written into ``models`` as a download has them, and the benchmark labeler registered."""
    if args.engine == "grounded-sam":
        if args.quick:
            tiny = TinyModelsConfig(max_text_len=256)
            det, seg = build_tiny_detector(tiny), build_tiny_segmenter(tiny)
        else:
            prompts = (p for c in schema.classes for p in (*c.prompts, *c.negative_prompts))
            det, seg = real_detector(sorted({w for p in prompts for w in p.split()})), real_sam()
        write_folder(models / "grounding-dino-tiny", det[0].config, det[1])
        write_folder(models / "sam-vit-base", seg[0].config, seg[1])
        held: dict[str, Any] = {"detector": det[0].to(device), "sam": seg[0].to(device), "sam_proc": seg[1]}

        def make_gs(cfg: GroundedSamConfig, runtime: Runtime) -> Labeler:
            lab = GroundedSamLabeler(cfg, runtime)
            if held:
                # Cast in place, as the labeler casts what it loads (the baseline's fp32 and the batched
                # run's fp16 labelers are built and used one after the other).
                dtype = model_dtype(device, cfg.half_precision)
                det, sam = held["detector"].to(dtype), held["sam"].to(dtype)
                lab._models = LoadedModels(det, lab.detector_processor, sam, held["sam_proc"], device, dtype)
                pin_regions(lab, args.boxes)
            return lab

        spec: LabelerSpec[Any] = LabelerSpec(
            name="bench-grounded-sam",
            label="Grounding DINO + SAM, weights in memory (bench_gpu.py)",
            description="grounded-sam with the benchmark's in-memory models and pinned regions",
            section="bench_grounded_sam",
            config_type=GroundedSamConfig,
            factory=make_gs,
            needs="images",
            missing="the benchmark labeler needs camera images (image_2/)",
        )
    else:
        tiny = TinyModelsConfig(max_text_len=256)
        model, tokenizer, image = build_tiny_sam3(tiny) if args.quick else real_sam3()
        write_folder(models / "sam3", model.config, tokenizer, image)
        held = {"sam3": model.to(device)}

        def make_sam3(cfg: Sam3LabelerConfig, runtime: Runtime) -> Labeler:
            lab = PinnedSam3(cfg, runtime)
            lab.instances = args.instances
            if held:
                dtype = model_dtype(device, cfg.half_precision)
                lab._loaded = _Loaded(held["sam3"].to(dtype), dtype, device)
            return lab

        spec = LabelerSpec(
            name="bench-sam3",
            label="SAM 3, weights in memory (bench_gpu.py)",
            description="sam3 with the benchmark's in-memory model and pinned instances",
            section="bench_sam3",
            config_type=Sam3LabelerConfig,
            factory=make_sam3,
            needs="images",
            missing="the benchmark labeler needs camera images (image_2/)",
        )
    register_labeler(spec)
    return Engine(args.engine, spec, held)


# ------------------------------------------------------------------------------------------- figures
@dataclass
class Row:
    """One line of the table."""

    name: str
    seconds: float
    units: int | None
    """What the per-unit column divides by (None: unknown, a part stopped by the budget)."""
    unit: str
    windows: list[Window]
    """Where its GPU samples come from."""
    at_length: int
    """Its units at 4,541 frames."""
    peaks: tuple[float | None, float | None] = (None, None)
    """Peak GPU memory (None without CUDA) and peak host RSS, GiB."""
    complete: bool = True
    in_whole: bool = True
    """Part of the whole run's figure (the 2D baseline is not: the batched run is the 2D stage)."""

    @property
    def per_unit(self) -> float | None:
        return self.seconds / self.units if self.units else None

    @property
    def minutes_at_length(self) -> float | None:
        per = self.per_unit
        return None if per is None else per * self.at_length / 60


def busy_share(windows: list[Window], sampler: GpuSampler | None) -> float | str:
    """Mean sampled busy % over ``windows``: a number, "no GPU", "not sampled" or "-" (no sample fell in)."""
    if sampler is None:
        return "no GPU"
    if not sampler.source:
        return "not sampled"
    values = [s[1] for w in windows for s in sampler.between(w.t0, w.t1)]
    return float(np.mean(values)) if values else "-"


def window_peaks(windows: list[Window], cuda: bool) -> tuple[float | None, float | None]:
    """The highest peak GPU memory (None without CUDA) and host RSS of ``windows``, GiB."""
    gpu = max((w.peak_gpu_gib or 0.0 for w in windows), default=None) if cuda else None
    return gpu, max((w.peak_rss_gib or 0.0 for w in windows), default=None)


def round_phases(meter: Meter, n: int, steps: int) -> list[tuple[Window, int, bool]]:
    """The 3D-CN round's selection, training and inference (with the fusion back and smoothing), each a
    window with the scans or steps it covered and whether it finished (a round stopped by the budget ends
    in one of them), from the round's reports over ``n + steps + n`` units in thousandths."""
    rounds = meter.named("3dcn round")
    if not rounds or not meter.marks:
        return []
    total = 2 * n + steps
    phases = (
        (f"3D-CN selection ({n} scans)", n, 0),
        (f"3D-CN training ({steps} steps)", steps, n),
        ("3D-CN inference, fusion back, smoothing", n, n + steps),
    )
    last_t, last_th = meter.marks[-1]
    out: list[tuple[Window, int, bool]] = []
    start = rounds[0].t0
    for name, size, base in phases:
        reached = next((t for t, th in meter.marks if th >= 1000 * (base + size) // total), None)
        if reached is None:  # stopped inside this phase: what it did so far
            out.append((Window(name, start, last_t), max(last_th * total // 1000 - base, 0), False))
            break
        end = rounds[-1].t1 if base + size == total else reached
        out.append((Window(name, start, end), size, True))
        start = end
    return out


def table_rows(
    meter: Meter,
    records: dict[str, dict[str, Any]],
    frames: int,
    config: PipelineConfig,
    done_2d: dict[str, int],
) -> list[Row]:
    """The 2D stage's baseline and batched runs (``done_2d``: the frames of those that finished), each
    pipeline stage that finished (its own record's seconds) and the 3D-CN round's phases."""
    rows = []
    for key in ("baseline", "batched"):
        for w in meter.named(f"2D {key}"):
            units = done_2d.get(key)
            peaks = (w.peak_gpu_gib, w.peak_rss_gib)
            row = Row(f"2D {key}", w.seconds, units, "frame", [w], SEQUENCE_FRAMES, peaks, units is not None)
            row.in_whole = key == "batched"
            rows.append(row)
    for stage in STAGES:
        if stage == "3dcn":
            cn = config.consistency
            at = (SEQUENCE_FRAMES, num_train_steps(SEQUENCE_FRAMES, cn), SEQUENCE_FRAMES)
            peaks = window_peaks(meter.named("3dcn round"), meter.cuda)
            phases = round_phases(meter, frames, num_train_steps(frames, cn))
            for (w, units, done), n_at in zip(phases, at, strict=False):
                unit = "step" if "training" in w.name else "scan"
                rows.append(Row(w.name, w.seconds, units, unit, [w], n_at, peaks, done))
        rec = records.get(stage)
        if rec and rec.get("status") == "done":
            ws = meter.named(stage)
            name = "3dcn (the round's grids linked)" if stage == "3dcn" else stage
            peaks = window_peaks(ws, meter.cuda)
            rows.append(Row(name, float(rec["seconds"]), frames, "frame", ws, SEQUENCE_FRAMES, peaks))
    return rows


def not_reached(records: dict[str, dict[str, Any]], rows: list[Row]) -> list[str]:
    """The stages without a finished or skipped record, the 3D-CN round when its phases are not all
    there, and the 2D stage when it did not finish: what a stopped run lacks."""
    out = [] if any(r.name == "2D batched" and r.complete for r in rows) else ["the 2D stage"]
    for phase in ("selection", "training", "inference"):
        if not any(r.name.startswith(f"3D-CN {phase}") for r in rows):
            out.append(f"the 3D-CN's {phase}")
    ended = {s for s, rec in records.items() if rec.get("status") in ("done", "skipped")}
    return out + [s for s in STAGES if s not in ended and s != "3dcn"]


def cell(v: float | str | None, digits: int = 3) -> float | str:
    return "-" if v is None else (round(v, digits) if isinstance(v, float) else v)


def print_report(
    args: argparse.Namespace,
    rows: list[Row],
    sampler: GpuSampler | None,
    title: str,
    stopped: bool,
    missing: list[str],
) -> dict[str, Any]:
    """Print the table and the summary lines; returns the figures for the result file. ``missing``: the
    parts of the run that a stopped run did not reach."""
    header = ["stage", "seconds", "per unit s", "unit", "GPU busy %", "peak GPU GiB", "peak RSS GiB"]
    header.append(f"{SEQUENCE_FRAMES} frames min")
    busy = [busy_share(r.windows, sampler) for r in rows]
    table = [
        [
            r.name + ("" if r.complete else " (stopped)"),
            cell(r.seconds),
            cell(r.per_unit, 4),
            r.unit,
            cell(b, 1),
            cell(r.peaks[0] if sampler is not None else "no GPU"),
            cell(r.peaks[1]),
            cell(r.minutes_at_length, 2) if r.in_whole else f"({cell(r.minutes_at_length, 2)})",
        ]
        for r, b in zip(rows, busy, strict=True)
    ]
    print()
    print_table(title, header, table)
    per = {r.name: r.per_unit for r in rows if r.name.startswith("2D ")}
    base, batched = per.get("2D baseline"), per.get("2D batched")
    ratio = base / batched if base and batched else None
    if ratio is not None:
        print(
            f"2D stage: batched is {ratio:.2f}x batch 1 fp32 per frame (same process and models; the "
            f"baseline labels the run's first {args.baseline_frames} frame(s); not in the whole run)"
        )
    whole = [r for r in rows if r.in_whole]
    total_s = sum(r.seconds for r in whole)
    total_min = sum(r.minutes_at_length or 0.0 for r in whole)
    partial = [r.name for r in whole if not r.complete and r.per_unit is not None]
    missing = missing + [r.name for r in whole if r.per_unit is None]  # stopped before its first unit
    complete = not stopped and not missing and not partial
    if complete:
        verdict = f"{total_min / TARGET_MIN:.2f}x the target of at most {TARGET_MIN:.0f} min on one H100"
    else:
        parts = [f"from the part done of {', '.join(partial)}"] if partial else []
        parts += [f"without {', '.join(missing)} (not reached)"] if missing else []
        verdict = "an estimate " + "; ".join(parts or ["of a stopped run"])
    print(
        f"whole run (2D batched, every stage, one 3D-CN round): {total_s:.1f} s for {args.frames} frames; "
        f"at {SEQUENCE_FRAMES} frames {total_min:.1f} min, {verdict}"
    )
    training = next((r for r, b in zip(rows, busy, strict=True) if "training" in r.name), None)
    if training is not None and sampler is not None:
        share = cell(busy_share(training.windows, sampler), 1)
        print(f"GPU busy during the 3D-CN's training: {share} % (target: at least 70 %)")
    return {
        "rows": [
            {
                "name": r.name,
                "seconds": r.seconds,
                "units": r.units,
                "unit": r.unit,
                "per_unit_s": r.per_unit,
                "gpu_busy_pct": b,
                "peak_gpu_gib": r.peaks[0],
                "peak_rss_gib": r.peaks[1],
                "units_at_length": r.at_length,
                "minutes_at_length": r.minutes_at_length,
                "complete": r.complete,
                "in_whole": r.in_whole,
            }
            for r, b in zip(rows, busy, strict=True)
        ],
        "batched_over_baseline": ratio,
        "whole_run_s": total_s,
        "sequence_frames": SEQUENCE_FRAMES,
        "sequence_min": total_min,
        "sequence_complete": complete,
        "not_reached": missing,
        "target_min": TARGET_MIN,
    }


# -------------------------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny random models and a few frames (smoke test)")
    ap.add_argument(
        "--frames", type=int, default=None, help=f"frames to generate (300; --quick {QUICK_FRAMES})"
    )
    ap.add_argument(
        "--engine",
        choices=tuple(ENGINES),
        default="grounded-sam",
        help="the 2D models (sam3 runs once per prompt: --schema semantickitti_bare has the fewest, 19)",
    )
    ap.add_argument("--batch", type=int, default=None, help="images per forward pass (8; --quick 2)")
    ap.add_argument(
        "--baseline-frames", type=int, default=None, help="frames of the batch-1 baseline (16; --quick 1)"
    )
    ap.add_argument(
        "--boxes",
        type=int,
        default=None,
        help="Grounding DINO regions given to SAM per image (50; --quick 8)",
    )
    ap.add_argument("--instances", type=int, default=5, help="SAM 3 instances kept per prompt")
    ap.add_argument("--prompts-per-pass", type=int, default=16, help="SAM 3 (image, prompt) pairs per pass")
    ap.add_argument(
        "--schema", default="semantickitti_expanded", help="class preset whose prompts are labeled"
    )
    ap.add_argument(
        "--device", choices=("auto", "cpu", "cuda"), default="auto", help="where the 2D models run"
    )
    ap.add_argument(
        "--frame-threads", type=int, default=None, help="leap run --frame-threads (default: the cores)"
    )
    ap.add_argument(
        "--budget", type=float, default=440.0, help="seconds from the start after which the run stops"
    )
    ap.add_argument("--sample-interval", type=float, default=0.25, help="seconds between GPU samples")
    ap.add_argument(
        "--work", type=Path, default=None, help="folder for the sequence and run, kept (default: a temp one)"
    )
    ap.add_argument("--results-dir", type=Path, default=None, help="where the JSON goes")
    args = ap.parse_args(argv)
    args.frames = args.frames or (QUICK_FRAMES if args.quick else 300)
    args.batch = args.batch or (2 if args.quick else 8)
    args.boxes = args.boxes or (8 if args.quick else 50)
    args.baseline_frames = min(args.baseline_frames or (1 if args.quick else 16), args.frames)
    if min(args.frames, args.batch, args.baseline_frames) < 1:
        ap.error("--frames, --batch and --baseline-frames must be at least 1")
    return args


def main(argv: list[str] | None = None) -> int:
    started = time.perf_counter()
    args = parse_args(argv)
    device = check_stack(args)
    # Random weights leave classes without pixels: the run's warnings about them say nothing about speed.
    logging.getLogger("leap_core.pipeline.runner").setLevel(logging.ERROR)
    import torch
    import transformers

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    threads = min(args.frame_threads or cores, MAX_FRAME_THREADS)
    schema = load_preset(args.schema).schema
    where = torch.cuda.get_device_name() if device == "cuda" else "CPU"
    versions = (
        f"torch {torch.__version__}, CUDA {torch.version.cuda}, transformers {transformers.__version__}"
    )
    print(f"bench_gpu: device {where}; {versions}; {cores} cores, frame threads {threads}", flush=True)
    load_before = os.getloadavg()
    work = Path(tempfile.mkdtemp(prefix="leap-bench-gpu-", dir=args.work))
    setup: dict[str, float] = {}
    meter = Meter(cuda=device == "cuda")
    sampler = GpuSampler(args.sample_interval) if device == "cuda" else None
    done_2d: dict[str, int] = {}
    records: dict[str, dict[str, Any]] = {}
    stopped = False
    runs: dict[str, tuple[int, PipelineConfig]] = {}
    fp16 = device == "cuda"
    try:
        # -------------------------------------------------------------------- set-up (not in the figures)
        t = time.perf_counter()
        synth = SynthConfig(frames=args.frames, **(QUICK_SYNTH if args.quick else {}))
        seq_path = generate_sequence(work / "data", synth, workers=cores).path
        setup["synth_s"] = time.perf_counter() - t
        print(
            f"  set-up: {args.frames} frames generated in {setup['synth_s']:.1f} s ({cores} processes)",
            flush=True,
        )
        t = time.perf_counter()
        engine = build_engine(args, device, work / "models", schema)
        setup["models_s"] = time.perf_counter() - t
        size = "tiny" if args.quick else "real-size"
        print(f"  set-up: {size} {ENGINES[args.engine]} built in {setup['models_s']:.1f} s", flush=True)
        base = load_preset(args.schema).pipeline  # read again: a config made before it lacks its section
        runs = {
            "baseline": (1, engine.config(1, False, args, base)),
            "batched": (args.batch, engine.config(args.batch, fp16, args, base)),
        }
        seq = KittiSequence(seq_path)
        ids = list(seq.frame_ids)
        warm_images = [seq.frame(i).image for i in range(min(args.batch, len(seq)))]
        stop = StopSignal(work)
        if sampler is not None:
            sampler.start()
        with deadline(stop, args.budget - (time.perf_counter() - started)):
            # ----------------------------------------------------- 1. the 2D stage, as leap labels2d runs it
            setup["warmup_s"] = 0.0
            for key, (batch, config) in runs.items():
                t = time.perf_counter()
                warm = engine.spec.factory(
                    engine.spec.config_of(config), Runtime(models_dir=work / "models", device=device)
                )
                assert isinstance(warm, ImageModelLabeler)
                warm.label_images(warm_images[:batch], schema)  # kernels, allocator, lazy loads: not timed
                del warm
                setup["warmup_s"] += time.perf_counter() - t
                todo = ids[: args.baseline_frames] if key == "baseline" else ids
                runtime = Runtime(models_dir=work / "models", cache_dir=work / f"cache-{key}", device=device)
                meter.open(f"2D {key}")
                try:
                    label_cache_task(seq_path, schema, config, runtime, todo, stop)
                finally:
                    meter.close()
                done_2d[key] = len(todo)
                print(f"  2D {key}: {len(todo)} frame(s) in {meter.windows[-1].seconds:.1f} s", flush=True)
            engine.held.clear()  # the run's labelers get no weights: a 2D cache miss fails, never computes
            gc.collect()
            if device == "cuda":
                torch.cuda.empty_cache()
            # --------------------------------------------------------------- 2. leap run with that cache
            runtime = Runtime(
                models_dir=work / "models",
                cache_dir=work / "cache-batched",
                device=device,
                frame_threads=threads,
            )

            def on_progress(sequence: str, stage: str, done: int, total: int) -> None:
                stop.check()
                meter.report(sequence, stage, done, total)

            meter.last_report = time.perf_counter()
            spec = SequenceSpec.of(seq_path)
            try:
                run_pipeline(
                    [spec], schema, runs["batched"][1], work / "run", progress=on_progress, runtime=runtime
                )
            finally:
                meter.close()
                with contextlib.suppress(Exception):  # a run stopped at its start may have no record
                    records = read_state(RunLayout(work / "run").sequence(spec.name))
    except Cancelled:
        stopped = True
        print(f"  stopped at the budget ({args.budget:.0f} s): what follows is what was measured", flush=True)
    finally:
        if sampler is not None:
            sampler.stop()
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    load_after = os.getloadavg()
    rows = table_rows(meter, records, args.frames, runs["batched"][1], done_2d) if runs else []
    precision = "fp16" if fp16 else "fp32"
    models = "tiny" if args.quick else "real-size"
    title = (
        f"A {args.frames}-frame sequence end to end on {where}: {ENGINES[args.engine]} ({models} random "
        f"weights), 2D batch {args.batch} {precision}; load average {load_before[0]:.1f} -> "
        f"{load_after[0]:.1f}"
    )
    figures = print_report(args, rows, sampler, title, stopped, not_reached(records, rows))
    samples = f"{sampler.source or 'none'}, {len(sampler.samples)} samples" if sampler else "no GPU"
    print(
        f"set-up, not in the figures: generating {setup.get('synth_s', 0):.1f} s, building the models "
        f"{setup.get('models_s', 0):.1f} s, warm-up {setup.get('warmup_s', 0):.1f} s; GPU sampling: "
        f"{samples}; {time.perf_counter() - started:.0f} s since the start"
    )
    payload = {
        "device": where,
        "versions": {
            "torch": torch.__version__,
            "cuda": torch.version.cuda,
            "transformers": transformers.__version__,
        },
        "engine": args.engine,
        "models": models,
        "frames": args.frames,
        "batch": args.batch,
        "precision": precision,
        "baseline_frames": args.baseline_frames,
        "boxes": args.boxes,
        "schema": args.schema,
        "frame_threads": threads,
        "load_average": [load_before, load_after],
        "setup_s": setup,
        "budget_s": args.budget,
        "stopped_at_budget": stopped,
        "gpu_sampling": samples,
        # The time line, in seconds from the start: each window, and each GPU sample (busy %, MiB in use).
        "windows": [[w.name, w.t0 - started, w.t1 - started] for w in meter.windows],
        "gpu_samples": [[t - started, busy, mem] for t, busy, mem in (sampler.samples if sampler else [])],
        **figures,
    }
    path = write_results(
        "bench_gpu_quick" if args.quick else "bench_gpu", payload, args.results_dir or RESULTS_DIR
    )
    print(f"wrote {path}")
    return 0  # a run stopped at the budget measured what it could: its file says so


if __name__ == "__main__":
    sys.exit(main())
