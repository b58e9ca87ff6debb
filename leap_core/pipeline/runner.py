"""Running the stage table on one sequence's folder of a run: fingerprints, the stage records in
``stages.json``, skipping, clearing and resuming, all derived from
:data:`~leap_core.pipeline.stages.STAGE_TABLE`. A run (:func:`leap_core.pipeline.run.run_pipeline`) calls
:func:`run_sequence` for each of its sequences."""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from leap_core.config import PipelineConfig, config_to_dict
from leap_core.consistency.config import fingerprint_form
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import Cancelled, LeapError, PosesMissingError
from leap_core.labelers import LABELERS
from leap_core.pipeline.class_presence import (
    RECORD_KEY,
    SilentClass,
    class_pixels,
    silent_classes,
    warning_text,
)
from leap_core.pipeline.context import Ctx, ProgressCallback, StageInfo, hash_json, read_state
from leap_core.pipeline.evaluation import read_metrics_json
from leap_core.pipeline.executor import Executor, LocalExecutor, make_executor
from leap_core.pipeline.metrics_file import SequenceMetrics
from leap_core.pipeline.stages import STAGE_TABLE, STAGES, load_soft
from leap_core.run_layout import SequenceLayout
from leap_core.runtime import Runtime
from leap_core.schema import Schema

log = logging.getLogger(__name__)

PIPELINE_VERSION = 1
"""Bumped when a code change alters a stage's output for unchanged inputs (part of every fingerprint)."""


@dataclass(frozen=True)
class StageReport:
    """What one stage did in one :func:`run_sequence` call."""

    name: str
    ran: bool
    """False when the stage was skipped (cached, or disabled / nothing to do)."""
    status: str
    """"done" or "skipped" (3dcn off, evaluate without ground truth)."""
    seconds: float
    """Wall time spent in this call (≈ 0 when skipped)."""
    frames_computed: int = 0
    """Per-frame stages: frames computed in this call (the rest came from earlier runs or the 2D cache)."""


@dataclass(frozen=True)
class SequenceResult:
    """What :func:`run_sequence` did in one sequence's folder."""

    folder: Path
    stages: dict[str, StageReport]
    """Per stage, in :data:`STAGES` order (only stages up to ``until``)."""
    frames: tuple[int, ...]
    """Indices (positions in ``KittiSequence.frame_ids``) of the frames processed."""
    export_dir: Path | None
    """Folder of the ``.label`` / ``.conf`` files, when the export stage ran or was cached."""
    metrics: SequenceMetrics | None
    """Its ``metrics.json`` (None without ground truth)."""

    @property
    def ran(self) -> list[str]:
        return [n for n, r in self.stages.items() if r.ran]

    @property
    def skipped(self) -> list[str]:
        return [n for n, r in self.stages.items() if not r.ran]


def stage_status(folder: str | Path) -> dict[str, dict[str, Any]]:
    """Each stage's record from a sequence folder's ``stages.json`` (``{"status": "pending"}`` for stages
    never started).

    Statuses: ``pending``, ``running`` (also what a killed run leaves behind), ``cancelled``, ``failed``
    (with ``error``), ``done``, ``skipped`` (3dcn off, evaluate without ground truth). Records also carry
    ``fingerprint``, ``seconds`` and, for per-frame stages, ``frames_done``.
    """
    state = read_state(SequenceLayout(Path(folder)))
    return {name: dict(state.get(name, {"status": "pending"})) for name in STAGES}


UNCHANGED = "unchanged since the last run"
""":func:`skip_reason` of a stage whose outputs an earlier run (or attempt) in the folder left current."""


def skip_reason(folder: str | Path, stage: str, since: float) -> str | None:
    """Why a stage that reported itself complete computed nothing in a run started at ``since``
    (``time.time()``), or None when it computed.

    The pipeline reports a stage it skips as complete at once, after recording it in ``stages.json``:
    ``skipped`` with its note ("no ground truth", "3D-CN disabled"), or ``done`` by an earlier run when its
    outputs were current (:data:`UNCHANGED`). Progress displays (the CLI's bars, the app's run log) call
    this when a stage reports completion, so a skipped stage reads "skipped (reason)" and not "done 0 s".
    """
    try:
        record = stage_status(folder).get(stage, {})
    except LeapError:
        return None
    if record.get("status") == "skipped":
        return str(record.get("note") or "nothing to do")
    if record.get("status") == "done" and float(record.get("finished") or since) < since:
        return UNCHANGED
    return None


# ------------------------------------------------------------------------------------- fingerprints
def _fingerprints(ctx: Ctx) -> dict[str, str]:
    """Every stage's fingerprint: the config sections it reads, its upstream stages' fingerprints and its
    other inputs (cheap: nothing the stages wrote is read)."""
    sections = config_to_dict(ctx.cfg)
    sections["consistency"] = fingerprint_form(sections["consistency"])
    fp: dict[str, str] = {}
    for stage in STAGE_TABLE:
        parts: dict[str, Any] = {
            "v": PIPELINE_VERSION,
            "C": ctx.schema.num_classes,
            "stage": stage.name,
            "up": [fp[u] for u in stage.upstream],
        }
        if stage.is_enabled(ctx.cfg):
            parts["config"] = {s: sections[s] for s in stage.reads}
            inputs = None if stage.inputs is None else stage.inputs(ctx)
            if inputs is not None:  # an absent optional input (3dcn's joint record) changes nothing
                parts["inputs"] = inputs
        else:
            parts["enabled"] = False
        fp[stage.name] = hash_json(parts)
    return fp


# ---------------------------------------------------------------------------------- stage machinery
def _is_current(ctx: Ctx, stage: StageInfo) -> bool:
    rec = ctx.state.get(stage.name)
    if not rec or rec.get("fingerprint") != ctx.fp[stage.name]:
        return False
    if rec.get("status") not in ("done", "skipped"):
        return False
    if stage.frame_files is not None:
        return not ctx.missing_frames(stage.name)
    if rec["status"] == "skipped":
        return True  # a disabled stage, or one with nothing to do, wrote nothing
    return all(p.is_file() for p in stage.outputs(ctx.layout, ctx.cfg))


def _clear(ctx: Ctx, stage: StageInfo) -> None:
    """Remove a stage's outputs (its fingerprint changed, so they belong to other settings)."""
    if stage.frame_files is not None:
        shutil.rmtree(ctx.layout.frame_folder(stage.frame_files.folder), ignore_errors=True)
        return
    stale = stage.outputs(ctx.layout, ctx.cfg) if stage.stale is None else stage.stale(ctx.layout)
    for path in stale:
        path.unlink(missing_ok=True)


def _run_stage(ctx: Ctx, stage: StageInfo, executor: Executor | None = None) -> StageReport:
    name = stage.name
    if _is_current(ctx, stage):
        n = len(ctx.frames)
        ctx.tick(name, n, n)
        return StageReport(name, False, ctx.state[name]["status"], 0.0)
    rec = ctx.state.get(name)
    if not rec or rec.get("fingerprint") != ctx.fp[name]:
        _clear(ctx, stage)
    elif stage.frame_files is not None:
        # Temp files a killed run left behind (atomic writes that never reached their rename).
        for tmp in ctx.layout.frame_folder(stage.frame_files.folder).glob(".*.tmp"):
            tmp.unlink(missing_ok=True)
    ctx.state[name] = {"status": "running", "fingerprint": ctx.fp[name], "started": time.time()}
    ctx.save_state()
    t0 = time.perf_counter()
    try:
        engine = executor or LocalExecutor()
        extra = (
            engine.run_stage(ctx, stage)
            if stage.is_enabled(ctx.cfg)
            else {"status": "skipped", "note": f"{stage.label} disabled"}
        )
    except (Cancelled, KeyboardInterrupt):
        ctx.state[name].update(status="cancelled", seconds=time.perf_counter() - t0)
        ctx.save_state()
        raise
    except BaseException as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        ctx.state[name].update(status="failed", error=message, seconds=time.perf_counter() - t0)
        ctx.save_state()
        raise
    seconds = time.perf_counter() - t0
    status = extra.pop("status", "done")
    ctx.state[name].update(status=status, seconds=round(seconds, 3), finished=time.time(), **extra)
    ctx.save_state()
    if status == "skipped":
        # After the record: a progress listener that sees the stage complete can read why (skip_reason).
        ctx.tick(name, len(ctx.frames), len(ctx.frames))
    # A disabled stage (3dcn off, evaluate without ground truth) computed nothing: report it as not run.
    return StageReport(name, status != "skipped", status, seconds, int(extra.get("frames_computed", 0)))


def _record_class_pixels(ctx: Ctx) -> None:
    """Put each class's pixels over the run's frames into the ``labels2d`` record (once per set of
    frames: a cached stage keeps it), for :func:`warn_silent_classes` and the export's summary."""
    rec = ctx.state.get("labels2d")
    if not rec or rec.get("status") != "done":
        return
    key = hash_json([ctx.fid(i) for i in ctx.frames])[:16]
    kept = rec.get(RECORD_KEY)
    if isinstance(kept, dict) and kept.get("frames") == key:
        return
    mass = np.zeros(ctx.schema.num_classes, np.float64)
    for i in ctx.frames:
        mass += class_pixels(load_soft(ctx.layout.labels2d(ctx.fid(i))))
    rec[RECORD_KEY] = {"frames": key, "count": len(ctx.frames), "pixels": [round(float(m), 1) for m in mass]}
    ctx.save_state()


def recorded_silent_classes(
    layout: SequenceLayout, schema: Schema, metrics: SequenceMetrics | None
) -> list[SilentClass]:
    """The sequence's classes with (almost) no 2D pixels (:func:`~leap_core.pipeline.class_presence.
    silent_classes`), from its ``labels2d`` record and, when it was evaluated, its ground truth; [] when
    the record has no pixel counts (a run written before they were recorded)."""
    try:
        kept = read_state(layout).get("labels2d", {}).get(RECORD_KEY)
    except LeapError:
        return []
    if not isinstance(kept, dict) or len(kept.get("pixels") or []) != schema.num_classes:
        return []
    gt = None
    if metrics is not None:
        try:
            confusion = metrics.table("all")["point"].confusion_matrix
            per_name = dict(zip(metrics.class_names, confusion.sum(axis=1).tolist(), strict=False))
            gt = [int(per_name.get(c.name, 0)) for c in schema.classes]
        except KeyError:
            gt = None
    return silent_classes(
        schema.names,
        [c.prompts for c in schema.classes],
        kept["pixels"],
        int(kept.get("count") or 0),
        gt,
    )


def warn_silent_classes(
    layout: SequenceLayout, schema: Schema, metrics: SequenceMetrics | None, sequence: str
) -> list[SilentClass]:
    """Log one warning per class with (almost) no 2D pixels (:func:`recorded_silent_classes`); returns
    them. Every run logs them, a cached one too, so the CLI and the app show them each time."""
    silent = recorded_silent_classes(layout, schema, metrics)
    for c in silent:
        log.warning("%s", warning_text(c, sequence))
    return silent


# ---------------------------------------------------------------------------------------- public API
def warn_missing_images(seq: KittiSequence, frames: range, labeler: str) -> list[str]:
    """Log a warning naming the run's frames that have no camera image; returns their frame ids.

    A labeler that reads 2D ground truth (the simulated one) still labels such a frame, so without this
    warning a deleted image would go unnoticed in a run that ends ``done``; an image labeler fails on it.
    """
    missing = [seq.frame_ids[i] for i in frames if seq.image_path(i) is None]
    if missing:
        shown = ", ".join(missing[:5]) + (", …" if len(missing) > 5 else "")
        consequence = (
            "the simulated labeler labels them from the 2D ground truth only"
            if LABELERS[labeler].needs == "gt2d"
            else "the 2D labeler cannot label them"
        )
        log.warning(
            "%d of %d frames have no camera image in %s (frames %s): %s",
            len(missing),
            len(frames),
            seq.root / "image_2",
            shown,
            consequence,
        )
    return missing


def require_poses(seq: KittiSequence, config: PipelineConfig, stages: Iterable[StageInfo]) -> None:
    """Refuse, before any work, a run that would reach a stage needing poses on a sequence without them.

    The one place a run checks for poses, so a caller can catch the error and add its own advice.

    Raises:
        PosesMissingError: naming the poses file and the stages that need it.
    """
    if seq.has_poses:
        return
    needing = [s.name for s in stages if s.needs_poses and s.is_enabled(config)]
    if needing:
        raise PosesMissingError(
            seq.poses_path, f"no poses: the 3D stages ({', '.join(needing)}) need one pose per scan"
        )


def _context(
    dataset: Path,
    schema: Schema,
    config: PipelineConfig,
    folder: Path,
    *,
    progress: ProgressCallback | None,
    frames: range | None,
    runtime: Runtime | None,
    until: str | None = None,
) -> Ctx:
    """The run's context; with ``until`` (a run, not a preview) first :func:`require_poses` for the
    stages up to it, so a missing poses file stops the run before anything (the labeler included) loads.
    The sequence reads the dataset's poses, else estimated ones in the run folder
    (:meth:`SequenceLayout.open_sequence`)."""
    folder = Path(folder)
    seq = SequenceLayout(folder).open_sequence(dataset)
    if until is not None:
        require_poses(seq, config, STAGE_TABLE[: STAGES.index(until) + 1])
    if folder.exists() and not folder.is_dir():
        raise LeapError(f"{folder}: run folder path exists and is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    layout = SequenceLayout(folder)
    ctx = Ctx(
        seq, schema, config, layout, seq.select(frames), runtime, progress, {s.name: s for s in STAGE_TABLE}
    )
    ctx.state = read_state(layout)
    ctx.fp = _fingerprints(ctx)
    return ctx


def plan_stages(
    dataset: Path,
    schema: Schema,
    config: PipelineConfig,
    folder: Path,
    *,
    frames: range | None = None,
    runtime: Runtime | None = None,
) -> dict[str, bool]:
    """Which stages :func:`run_sequence` would compute (True) or skip as cached (False) in the sequence's
    folder ``folder``; writes nothing but the folder itself."""
    ctx = _context(dataset, schema, config, folder, progress=None, frames=frames, runtime=runtime)
    return {s.name: not _is_current(ctx, s) for s in STAGE_TABLE}


def stage_fingerprints(
    dataset: Path,
    schema: Schema,
    config: PipelineConfig,
    folder: Path,
    *,
    frames: range | None = None,
    runtime: Runtime | None = None,
) -> dict[str, str]:
    """Each stage's fingerprint for these inputs in the sequence's folder ``folder`` (whose
    ``corrections.npz``, if any, is part of the fuse stage's); compared with a ``stages.json`` they say
    which stages a run would recompute (:func:`leap_core.pipeline.steering.recompute_plan`). Reads no
    stage output."""
    ctx = _context(Path(dataset), schema, config, Path(folder), progress=None, frames=frames, runtime=runtime)
    return dict(ctx.fp)


def run_sequence(
    dataset: Path,
    schema: Schema,
    config: PipelineConfig,
    folder: Path,
    *,
    progress: ProgressCallback | None = None,
    frames: range | None = None,
    runtime: Runtime | None = None,
    until: str | None = None,
) -> SequenceResult:
    """Run (or resume) the stages of one sequence of a run in its folder, skipping stages whose cached
    outputs are current; :func:`leap_core.pipeline.run.run_pipeline` calls it for each sequence (the
    3D-CN's rounds, which span the run's sequences, run between two such calls).

    Args:
        dataset: a KITTI-layout sequence folder (``.../sequences/NN``).
        schema: the class schema.
        config: pipeline parameters.
        folder: the sequence's folder in the run (created if missing); see :mod:`leap_core.run_layout`.
        progress: ``progress(stage, done, total)`` after each unit of work; raising
            :class:`~leap_core.errors.Cancelled` stops the run cleanly (finished frames are kept).
        frames: the frame numbers to process (``range(10, 20)`` = scans 000010..000019, gaps allowed;
            default: all), see :meth:`~leap_core.datasets.kitti.KittiSequence.select`.
        runtime: where the run executes: models folder, shared 2D cache folder (``cache_dir``, reused
            across runs of a project), device, and the engine (``ray_address``: per-frame stages and
            fusion as Ray tasks, same bytes; :mod:`leap_core.pipeline.executor`). None = defaults, no
            shared cache, this process only.
        until: stop after this stage (e.g. "smooth" to only build the grid).

    Returns:
        :class:`SequenceResult` with per-stage reports, the export folder and the metrics (when GT exists).

    Raises:
        LeapError: bad dataset, schema/config or run folder (one line, naming the file or field).
        PosesMissingError: the sequence has no poses and a stage up to ``until`` needs them
            (:func:`require_poses`, raised before any stage runs).
        Cancelled: raised by ``progress``; the stage is recorded as "cancelled" and a rerun resumes.
    """
    if until is not None and until not in STAGES:
        raise LeapError(f"until: unknown stage {until!r} (stages: {', '.join(STAGES)})")
    last = STAGES.index(until) if until else len(STAGES) - 1
    ctx = _context(
        Path(dataset),
        schema,
        config,
        Path(folder),
        progress=progress,
        frames=frames,
        runtime=runtime,
        until=STAGES[last],
    )
    warn_missing_images(ctx.seq, ctx.frames, config.labeler)
    executor = make_executor(runtime)
    reports: dict[str, StageReport] = {}
    for stage in STAGE_TABLE[: last + 1]:
        reports[stage.name] = _run_stage(ctx, stage, executor)
        if stage.name == "labels2d":
            _record_class_pixels(ctx)
    metrics = None
    if "evaluate" in reports and reports["evaluate"].status == "done":
        metrics = read_metrics_json(ctx.layout.folder)
    if last == len(STAGES) - 1:
        warn_silent_classes(ctx.layout, schema, metrics, Path(folder).name)
    export_dir = ctx.layout.export_dir if "export" in reports else None
    return SequenceResult(ctx.layout.folder, reports, tuple(ctx.frames), export_dir, metrics)


__all__ = [
    "PIPELINE_VERSION",
    "UNCHANGED",
    "SequenceResult",
    "StageReport",
    "plan_stages",
    "recorded_silent_classes",
    "require_poses",
    "run_sequence",
    "skip_reason",
    "stage_fingerprints",
    "stage_status",
    "warn_silent_classes",
]
