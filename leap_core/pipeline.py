"""The labeling pipeline as separable, cached, resumable stages on a run directory.

Stages (:data:`STAGES`, in order) and what each writes into ``run_dir`` (docs/ARCHITECTURE.md):

============  ================================================================================================
labels2d      ``labels2d/<frame_id>.npz``: the 2D labeler's :class:`SoftMasks` per frame (METHOD.md stage A)
project       ``observations/<frame_id>.npz``: projection + per-mask depth clustering + painting (B.1-B.2)
fuse          ``grid.npz``: Bayesian log-space fusion of every observation, then manual corrections (B.3)
smooth        ``grid_smooth.npz``: distance-weighted kNN smoothing of the fused grid (B.4)
3dcn          ``grid_3dcn{i}.npz`` / ``grid_smooth_3dcn{i}.npz`` per iteration i (stage C, when enabled)
label_points  ``points/<frame_id>.npz``: label + confidence of every point from the final grid (B.5)
evaluate      ``metrics.json``: point / voxel / +3D-CN rows, camera-view and all-points protocols
export        ``export/<frame_id>.label`` + ``.conf`` per scan
============  ================================================================================================

Caching. Every stage has a fingerprint: a hash of the config parts it reads, the schema parts it reads, the
fingerprints of the stages it reads from and the dataset's identity (paths, sizes and modification times of
its files, contents of ``calib.txt`` / ``poses.txt``). ``stages.json`` records each stage's fingerprint and
status; a stage whose record matches and whose outputs exist is skipped. So editing, e.g., the smoothing
``k`` reruns ``smooth`` and what follows, and a class colour edit reruns nothing.

Resuming. Per-frame stages (labels2d, project, label_points, export) write one file per frame atomically and
only compute frames whose file is missing; the folder is cleared first only when the stage's fingerprint
changed. Everything is seeded per frame and reduced in frame order, so a run that was killed (or
cancelled through the progress callback) and run again yields byte-identical final labels.

A shared 2D cache (``cache_dir``) lets runs of one project reuse 2D results: entries are keyed by the
labeler's fingerprint and a digest of the frame's input files, and hard-linked into the run folder.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.config import PipelineConfig, config_to_dict
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import Cancelled, DatasetError, LeapError
from leap_core.fusion import (
    Observations,
    VoxelGrid,
    apply_overrides,
    fuse,
    log_table,
    rows_in_sorted,
    voxel_keys,
)
from leap_core.io_utils import atomic_save_npz, atomic_write, atomic_write_json
from leap_core.labelers.base import SoftMasks
from leap_core.metrics import Metrics, confusion_matrix, format_table, metrics_from_confusion
from leap_core.projection import Painted, paint, project_points
from leap_core.runtime import Runtime
from leap_core.schema import Schema
from leap_core.smoothing import knn_smooth
from leap_core.types import UNLABELED

@dataclass(frozen=True)
class StageInfo:
    """What the app and the CLI show of one stage."""

    name: str
    """Key in ``stages.json``, progress messages and the API."""
    label: str
    """Short human name ("Voxel fusion")."""
    description: str
    """One line: what the stage computes and writes."""
    per_frame: bool
    """True when the stage works (and resumes) frame by frame."""


STAGE_TABLE: tuple[StageInfo, ...] = (
    StageInfo("labels2d", "2D labels", "the 2D labeler's soft masks per frame", True),
    StageInfo("project", "Projection", "projection, per-mask depth clustering and painting per frame", True),
    StageInfo("fuse", "Voxel fusion", "Bayesian fusion of every observation into the voxel grid", False),
    StageInfo("smooth", "kNN smoothing", "distance-weighted kNN smoothing of the fused grid", False),
    StageInfo("3dcn", "3D-CN", "3D Consistency Network rounds (when enabled)", False),
    StageInfo("label_points", "Point labels", "label and confidence of every point from the final grid", True),
    StageInfo("evaluate", "Evaluation", "point / voxel / 3D-CN metrics against ground truth", False),
    StageInfo("export", "Export", "SemanticKITTI .label and .conf files per scan", True),
)
"""Every stage in execution order."""

STAGES: tuple[str, ...] = tuple(s.name for s in STAGE_TABLE)
"""Stage names in execution order."""

PIPELINE_VERSION = 1
"""Bumped when a code change alters a stage's output for unchanged inputs (part of every fingerprint)."""

ProgressCallback = Callable[[str, int, int], None]
"""``progress(stage, done, total)``; may raise :class:`~leap_core.errors.Cancelled`."""

ROW_POINT = "point"
ROW_VOXEL = "voxel"
PROTOCOLS: dict[str, str] = {
    "camera": "camera view: points inside the image, unlabeled predictions ignored (the paper's protocol)",
    "all": "all points: every point of every scan, an unlabeled prediction counts as a miss",
}
"""metrics.json protocol keys and what they measure."""

_STATE_FILE = "stages.json"
_CORRECTIONS_FILE = "corrections.npz"
_3DCN_GRID_SCALE = 1000
"""3D-CN progress is reported in thousandths of an iteration (its own step count is not known upfront)."""


def cn_row(iteration: int) -> str:
    """Result-table row name of the 3D-CN after ``iteration`` rounds ("+3D-CN x1")."""
    return f"+3D-CN x{iteration}"


# ------------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class StageReport:
    """What one stage did in one :func:`run_pipeline` call."""

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
class RunResult:
    """Outcome of :func:`run_pipeline`."""

    run_dir: Path
    stages: dict[str, StageReport]
    """Per stage, in :data:`STAGES` order (only stages up to ``until``)."""
    frames: tuple[int, ...]
    """Frame indices processed."""
    export_dir: Path | None
    """Folder of the ``.label`` / ``.conf`` files, when the export stage ran or was cached."""
    metrics: dict[str, Any] | None
    """Content of ``metrics.json`` (None without ground truth)."""

    @property
    def ran(self) -> list[str]:
        return [n for n, r in self.stages.items() if r.ran]

    @property
    def skipped(self) -> list[str]:
        return [n for n, r in self.stages.items() if not r.ran]


# ------------------------------------------------------------------------------------- fingerprints
def _hash(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:24]


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def dataset_identity(seq: KittiSequence) -> str:
    """Hash of a sequence's location, calibration, poses and the size + mtime of every per-frame file."""
    root = seq.root.resolve()
    parts: list[Any] = [str(root), _file_digest(root / "calib.txt"), _file_digest(root / "poses.txt")]
    folders = ["velodyne", "labels", "image_2", "gt2d/semantic", "gt2d/instance"]
    for name in folders:
        folder = root / name
        if not folder.is_dir():
            parts.append([name, None])
            continue
        with os.scandir(folder) as it:
            entries = sorted((e.name, e.stat().st_size, e.stat().st_mtime_ns) for e in it if e.is_file())
        parts.append([name, entries])
    return _hash(parts)


def _frame_input_digest(seq: KittiSequence, index: int) -> str:
    """Content digest of what a 2D labeler reads for one frame (its image and 2D ground truth, if any)."""
    h = hashlib.sha256(f"{index}|{seq.frame_ids[index]}".encode())
    fid = seq.frame_ids[index]
    paths = [seq.image_path(index), seq.root / "gt2d" / "semantic" / f"{fid}.png",
             seq.root / "gt2d" / "instance" / f"{fid}.png"]
    for p in paths:
        if p is not None and p.is_file():
            h.update(p.name.encode())
            h.update(_file_digest(p).encode())
    return h.hexdigest()[:32]


def _schema_eval_parts(schema: Schema) -> list[Any]:
    return [[c.name, sorted(c.gt_ids), c.category] for c in schema.classes]


# -------------------------------------------------------------------------------------------- state
def _read_state(run_dir: Path) -> dict[str, dict[str, Any]]:
    path = run_dir / _STATE_FILE
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"unreadable stage record ({exc}); delete it to recompute the run") from exc
    if not isinstance(data, dict):
        raise DatasetError(path, "stage record must be a JSON object")
    return data


def stage_status(run_dir: str | Path) -> dict[str, dict[str, Any]]:
    """Each stage's record from ``stages.json`` (``{"status": "pending"}`` for stages never started).

    Statuses: ``pending``, ``running`` (also what a killed run leaves behind), ``cancelled``, ``failed``
    (with ``error``), ``done``, ``skipped`` (3dcn off, evaluate without ground truth). Records also carry
    ``fingerprint``, ``seconds`` and, for per-frame stages, ``frames_done``.
    """
    state = _read_state(Path(run_dir))
    return {name: dict(state.get(name, {"status": "pending"})) for name in STAGES}


# ---------------------------------------------------------------------------------------- geometry
def world_points(points: npt.NDArray[np.float32], pose: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(N, 3) float64 world coordinates ``R · p + t`` of LiDAR-frame points (the 3D-CN uses the same)."""
    pose = np.asarray(pose, dtype=np.float64)
    return points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]


def smoothed_to_grid(keys: npt.NDArray[np.int64], probs: npt.NDArray[np.floating], voxel_size: float,
                     logp_clip: float) -> VoxelGrid:
    """A :class:`VoxelGrid` whose ``probs()`` give back smoothed distributions: ``logp = log p − max log p``.

    Probabilities below ``e^-logp_clip`` (relative to the row max) clip to that floor like any grid.
    """
    p = np.asarray(probs, dtype=np.float32)
    with np.errstate(divide="ignore"):
        lp = np.log(p)
    if len(lp):
        lp -= lp.max(axis=1, keepdims=True)
    np.maximum(lp, np.float32(-logp_clip), out=lp)
    return VoxelGrid(np.asarray(keys, dtype=np.int64), lp.astype(np.float16), float(voxel_size))


def _load_smooth(path: Path) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float16], float]:
    try:
        with np.load(path) as z:
            return z["keys"], z["probs"], float(z["voxel_size"])
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable smoothed grid ({exc})") from exc


def _voxel_labels(probs: npt.NDArray[np.floating]) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
    """Per voxel: argmax class and its (smoothed) probability, in chunks to bound float32 temporaries."""
    v = probs.shape[0]
    lab = np.empty(v, np.int16)
    conf = np.empty(v, np.float32)
    step = 1 << 20
    for s in range(0, v, step):
        block = probs[s : s + step]
        am = block.argmax(axis=1)
        lab[s : s + step] = am
        conf[s : s + step] = np.take_along_axis(block, am[:, None], axis=1)[:, 0]
    return lab, conf


class _GridLabels:
    """Per-point labels from a smoothed grid file: argmax + probability of each point's voxel."""

    def __init__(self, path: Path) -> None:
        self.keys, probs, self.voxel_size = _load_smooth(path)
        self.labels, self.conf = _voxel_labels(probs)

    def __call__(self, keys: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]]:
        n = keys.shape[0]
        lab = np.full(n, UNLABELED, np.int16)
        conf = np.zeros(n, np.float32)
        rows = rows_in_sorted(self.keys, keys)
        hit = rows >= 0
        lab[hit] = self.labels[rows[hit]]
        conf[hit] = self.conf[rows[hit]]
        return lab, conf


# ------------------------------------------------------------------------------------------ context
@dataclass
class _Ctx:
    seq: KittiSequence
    schema: Schema
    cfg: PipelineConfig
    run_dir: Path
    frames: range
    cache_dir: Path | None
    progress: ProgressCallback | None
    state: dict[str, dict[str, Any]] = field(default_factory=dict)
    fp: dict[str, str] = field(default_factory=dict)
    runtime: Runtime = field(default_factory=Runtime)
    _labeler: Any = None

    @property
    def indices(self) -> list[int]:
        return list(self.frames)

    def tick(self, stage: str, done: int, total: int) -> None:
        if self.progress is not None:
            self.progress(stage, done, total)

    def save_state(self) -> None:
        atomic_write_json(self.run_dir / _STATE_FILE, self.state)

    def labeler(self) -> Any:
        if self._labeler is None:
            from leap_core.labelers import make_labeler

            self._labeler = make_labeler(self.cfg, self.runtime)
        return self._labeler

    def path(self, folder: str, index: int, suffix: str = ".npz") -> Path:
        return self.run_dir / folder / f"{self.seq.frame_ids[index]}{suffix}"


def _fingerprints(ctx: _Ctx) -> dict[str, str]:
    """Every stage's fingerprint (cheap: config, schema, dataset identity; no outputs are read)."""
    cfg = ctx.cfg
    d = config_to_dict(cfg)
    ident = dataset_identity(ctx.seq)
    frames = [ctx.frames.start, ctx.frames.stop, ctx.frames.step]
    fp: dict[str, str] = {}
    base = {"v": PIPELINE_VERSION, "C": ctx.schema.num_classes}
    fp["labels2d"] = _hash({**base, "labeler": ctx.labeler().fingerprint(ctx.schema), "data": ident})
    fp["project"] = _hash({**base, "projection": d["projection"], "up": fp["labels2d"]})
    corr = ctx.run_dir / _CORRECTIONS_FILE
    corr_digest = _file_digest(corr) if corr.is_file() else None
    strength = cfg.correction_strength if corr_digest else None
    fp["fuse"] = _hash({**base, "fusion": d["fusion"], "up": fp["project"], "frames": frames,
                        "corrections": corr_digest, "strength": strength})
    fp["smooth"] = _hash({**base, "smoothing": d["smoothing"], "up": fp["fuse"]})
    cn = d["consistency"] if cfg.consistency.enabled else {"enabled": False}
    fp["3dcn"] = _hash({**base, "consistency": cn, "up": fp["smooth"]})
    final = fp["3dcn"] if cfg.consistency.enabled else fp["smooth"]
    fp["label_points"] = _hash({**base, "grid": final, "project": fp["project"]})
    fp["evaluate"] = _hash({**base, "eval": _schema_eval_parts(ctx.schema), "points": fp["label_points"],
                            "3dcn": fp["3dcn"], "smooth": fp["smooth"]})
    ids = [int(x) for x in ctx.schema.export_ids()]
    fp["export"] = _hash({**base, "ids": ids, "points": fp["label_points"]})
    return fp


# ---------------------------------------------------------------------------------- stage machinery
_PER_FRAME_DIRS: dict[str, tuple[str, str]] = {
    "labels2d": ("labels2d", ".npz"),
    "project": ("observations", ".npz"),
    "label_points": ("points", ".npz"),
    "export": ("export", ".label"),
}


def _per_frame_todo(ctx: _Ctx, stage: str) -> list[int]:
    folder, suffix = _PER_FRAME_DIRS[stage]
    todo = [i for i in ctx.frames if not ctx.path(folder, i, suffix).is_file()]
    if stage == "export":
        todo = [i for i in ctx.frames if i in set(todo) or not ctx.path(folder, i, ".conf").is_file()]
    return todo


def _whole_outputs(ctx: _Ctx, stage: str) -> list[Path]:
    r = ctx.run_dir
    if stage == "fuse":
        return [r / "grid.npz"]
    if stage == "smooth":
        return [r / "grid_smooth.npz"]
    if stage == "3dcn":
        if not ctx.cfg.consistency.enabled:
            return []
        return [r / f"grid_smooth_3dcn{i}.npz" for i in range(1, ctx.cfg.consistency.iterations + 1)]
    if stage == "evaluate":
        return [r / "metrics.json"] if ctx.state.get("evaluate", {}).get("status") == "done" else []
    return []


def _is_current(ctx: _Ctx, stage: str) -> bool:
    rec = ctx.state.get(stage)
    if not rec or rec.get("fingerprint") != ctx.fp[stage] or rec.get("status") not in ("done", "skipped"):
        return False
    if stage in _PER_FRAME_DIRS:
        return not _per_frame_todo(ctx, stage)
    return all(p.is_file() for p in _whole_outputs(ctx, stage))


def _clear(ctx: _Ctx, stage: str) -> None:
    """Remove a stage's outputs (its fingerprint changed, so they belong to other settings)."""
    r = ctx.run_dir
    if stage in _PER_FRAME_DIRS:
        shutil.rmtree(r / _PER_FRAME_DIRS[stage][0], ignore_errors=True)
    elif stage == "3dcn":
        for p in r.glob("grid*_3dcn*.npz"):
            p.unlink()
    elif stage == "evaluate":
        (r / "metrics.json").unlink(missing_ok=True)


def _run_stage(ctx: _Ctx, stage: str, fn: Callable[[_Ctx], dict[str, Any]]) -> StageReport:
    if _is_current(ctx, stage):
        rec = ctx.state[stage]
        n = len(ctx.frames)
        ctx.tick(stage, n, n)
        return StageReport(stage, False, rec["status"], 0.0)
    rec = ctx.state.get(stage)
    if not rec or rec.get("fingerprint") != ctx.fp[stage]:
        _clear(ctx, stage)
    elif stage in _PER_FRAME_DIRS:
        # Temp files a killed run left behind (atomic writes that never reached their rename).
        for tmp in (ctx.run_dir / _PER_FRAME_DIRS[stage][0]).glob(".*.tmp"):
            tmp.unlink(missing_ok=True)
    ctx.state[stage] = {"status": "running", "fingerprint": ctx.fp[stage], "started": time.time()}
    ctx.save_state()
    t0 = time.perf_counter()
    try:
        extra = fn(ctx)
    except (Cancelled, KeyboardInterrupt):
        ctx.state[stage].update(status="cancelled", seconds=time.perf_counter() - t0)
        ctx.save_state()
        raise
    except BaseException as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        ctx.state[stage].update(status="failed", error=message, seconds=time.perf_counter() - t0)
        ctx.save_state()
        raise
    seconds = time.perf_counter() - t0
    status = extra.pop("status", "done")
    if status == "skipped":
        ctx.tick(stage, len(ctx.frames), len(ctx.frames))
    ctx.state[stage].update(status=status, seconds=round(seconds, 3), finished=time.time(), **extra)
    ctx.save_state()
    # A disabled stage (3dcn off, evaluate without ground truth) computed nothing: report it as not run.
    return StageReport(stage, status != "skipped", status, seconds, int(extra.get("frames_computed", 0)))


def _per_frame(ctx: _Ctx, stage: str, work: Callable[[int], None]) -> dict[str, Any]:
    todo = set(_per_frame_todo(ctx, stage))
    total = len(ctx.frames)
    done = total - len(todo)
    ctx.tick(stage, done, total)
    for i in ctx.frames:
        if i not in todo:
            continue
        work(i)
        done += 1
        ctx.tick(stage, done, total)
    return {"frames_done": total, "frames_computed": len(todo)}


# --------------------------------------------------------------------------------------- the stages
def _save_soft(path: Path, soft: SoftMasks) -> None:
    # Compressed: packed masks are mostly zero bytes (≈ 10× smaller), and SoftMasks.load reads either form.
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(
            fh,
            size=np.array([soft.height, soft.width], dtype=np.int64),
            bits=soft.bits,
            probs=soft.probs,
            confidence=soft.confidence,
        )


def _link_or_copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.link")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def stage_labels2d(ctx: _Ctx) -> dict[str, Any]:
    """Per frame: the labeler's SoftMasks → ``labels2d/<frame_id>.npz`` (via ``cache_dir`` when given)."""
    labeler = ctx.labeler()
    if ctx.cfg.labeler == "simulated" and not ctx.seq.has_gt2d:
        raise DatasetError(
            ctx.seq.root / "gt2d" / "semantic",
            "the simulated labeler needs 2D ground truth (gt2d/semantic, gt2d/instance); "
            "use --labeler grounded-sam for real camera images",
        )
    lfp = labeler.fingerprint(ctx.schema)
    cache_root = None
    if ctx.cache_dir is not None:
        cache_root = ctx.cache_dir / "labels2d" / _hash([lfp, ctx.schema.num_classes])[:16]
    hits = 0

    def work(i: int) -> None:
        nonlocal hits
        out = ctx.path("labels2d", i)
        frame = ctx.seq.frame(i)
        if cache_root is not None:
            entry = cache_root / f"{frame.frame_id}-{_frame_input_digest(ctx.seq, i)[:20]}.npz"
            if entry.is_file():
                try:
                    SoftMasks.load(entry)
                    _link_or_copy(entry, out)
                    hits += 1
                    return
                except DatasetError:
                    pass  # A damaged entry is recomputed and replaced atomically below.
            _save_soft(entry, labeler.label(frame, ctx.schema))
            _link_or_copy(entry, out)
        else:
            _save_soft(out, labeler.label(frame, ctx.schema))

    extra = _per_frame(ctx, "labels2d", work)
    extra["cache_hits"] = hits
    extra["labeler"] = labeler.name
    return extra


def stage_project(ctx: _Ctx) -> dict[str, Any]:
    """Per frame: project the scan, depth-cluster per mask, paint → ``observations/<frame_id>.npz``.

    Stores the :class:`Painted` arrays plus ``n_points`` and ``in_view`` (packed bits: the point lies in the
    image in front of the camera), which the camera-view evaluation protocol uses.
    """
    pcfg = ctx.cfg.projection
    m = ctx.seq.calib.lidar_to_image

    def work(i: int) -> None:
        soft = SoftMasks.load(ctx.path("labels2d", i))
        if soft.num_classes != ctx.schema.num_classes:
            raise DatasetError(ctx.path("labels2d", i),
                               f"{soft.num_classes} classes but the schema has {ctx.schema.num_classes}")
        pts = ctx.seq.frame(i).points
        proj = project_points(pts, m, soft.height, soft.width, pcfg.min_depth)
        painted = paint(soft, proj, pcfg)
        in_view = np.zeros(pts.shape[0], bool)
        in_view[proj.idx] = True
        atomic_save_npz(
            ctx.path("observations", i),
            point_idx=painted.point_idx,
            rows=painted.rows,
            table=painted.table,
            n_points=np.int64(pts.shape[0]),
            in_view=np.packbits(in_view),
        )

    return _per_frame(ctx, "project", work)


def _load_observation(path: Path) -> tuple[Painted, int, npt.NDArray[np.bool_]]:
    painted = Painted.load(path)
    try:
        with np.load(path) as z:
            n = int(z["n_points"])
            in_view = np.unpackbits(z["in_view"], count=n).astype(bool)
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable observation file ({exc})") from exc
    return painted, n, in_view


def _load_corrections(path: Path, num_classes: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    try:
        with np.load(path) as z:
            keys, cls = np.asarray(z["keys"]), np.asarray(z["class_idx"])
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable corrections (need arrays 'keys', 'class_idx'): {exc}") from exc
    if keys.ndim != 1 or cls.shape != keys.shape:
        raise DatasetError(path, f"'keys' {keys.shape} and 'class_idx' {cls.shape} must be equal-length 1-D")
    if not (np.issubdtype(keys.dtype, np.integer) and np.issubdtype(cls.dtype, np.integer)):
        raise DatasetError(path, "'keys' and 'class_idx' must be integer arrays")
    if len(cls) and (cls.min() < 0 or cls.max() >= num_classes):
        raise DatasetError(path, f"'class_idx' must be in 0..{num_classes - 1}")
    return keys.astype(np.int64), cls.astype(np.int64)


def _observations(ctx: _Ctx) -> Iterator[tuple[Painted, npt.NDArray[np.int64]]]:
    """Per frame: its observation and the world voxel key of each observed (painted) point."""
    for i in ctx.frames:
        painted = Painted.load(ctx.path("observations", i))
        frame = ctx.seq.frame(i)
        pts = frame.points[painted.point_idx]
        yield painted, voxel_keys(world_points(pts, frame.pose), ctx.cfg.fusion.voxel_size)


def stage_fuse(ctx: _Ctx) -> dict[str, Any]:
    """All frames' observations → one voxel grid (log-space Bayes), then corrections → ``grid.npz``."""
    fcfg = ctx.cfg.fusion
    c = ctx.schema.num_classes
    total = len(ctx.frames)

    def batches() -> Iterator[Observations]:
        for k, (painted, keys) in enumerate(_observations(ctx)):
            ctx.tick("fuse", k, total)
            yield Observations(keys, painted.rows, log_table(painted.table, fcfg.prob_floor))

    grid = fuse(batches(), c, fcfg)
    n_corr = 0
    corr = ctx.run_dir / _CORRECTIONS_FILE
    if corr.is_file():
        keys, cls = _load_corrections(corr, c)
        n_corr = len(keys)
        if n_corr:
            grid = apply_overrides(grid, keys, cls, ctx.cfg.correction_strength, fcfg)
    grid.save(ctx.run_dir / "grid.npz")
    ctx.tick("fuse", total, total)
    return {"voxels": grid.num_voxels, "corrections": n_corr}


def _smooth_and_save(grid: VoxelGrid, ctx: _Ctx, path: Path) -> None:
    """kNN-smooth ``grid`` and save it; corrected voxels are then reset to their corrected class.

    A manual correction is the user's final word: kNN smoothing (and a later 3D-CN round) must not move
    it, so it is re-imposed as a one-hot distribution on the smoothed grid, not only fused as evidence.
    """
    probs = knn_smooth(grid.centres(), grid.probs(), ctx.cfg.smoothing)
    corr = ctx.run_dir / _CORRECTIONS_FILE
    if corr.is_file():
        keys, cls = _load_corrections(corr, grid.num_classes)
        # Later corrections of the same voxel win: keep each key's last occurrence.
        _, last = np.unique(keys[::-1], return_index=True)
        keys, cls = keys[::-1][last], cls[::-1][last]
        rows = grid.lookup(keys)
        hit = rows >= 0
        probs[rows[hit]] = 0.0
        probs[rows[hit], cls[hit]] = 1.0
    atomic_save_npz(
        path, keys=grid.keys, probs=probs.astype(np.float16), voxel_size=np.float64(grid.voxel_size)
    )


def stage_smooth(ctx: _Ctx) -> dict[str, Any]:
    """kNN smoothing of ``grid.npz`` → ``grid_smooth.npz`` (keys, probs float16, voxel_size)."""
    ctx.tick("smooth", 0, 1)
    grid = VoxelGrid.load(ctx.run_dir / "grid.npz")
    _smooth_and_save(grid, ctx, ctx.run_dir / "grid_smooth.npz")
    ctx.tick("smooth", 1, 1)
    return {"voxels": grid.num_voxels}


def stage_3dcn(ctx: _Ctx) -> dict[str, Any]:
    """The 3D Consistency Network, ``consistency.iterations`` rounds (skipped unless enabled).

    Round i: train on the reliable labels of the previous smoothed grid, fuse the network's tempered
    predictions into the previous fused grid → ``grid_3dcn{i}.npz``, smooth → ``grid_smooth_3dcn{i}.npz``.
    A finished round is kept on resume.
    """
    cn = ctx.cfg.consistency
    if not cn.enabled:
        return {"status": "skipped", "note": "3D-CN disabled"}
    from leap_core.consistency.selection import view_counts
    from leap_core.consistency.stage import run_3dcn_iteration

    c = ctx.schema.num_classes
    r = ctx.run_dir
    fused = VoxelGrid.load(r / "grid.npz")
    views: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None = None
    keys, probs, vs = _load_smooth(r / "grid_smooth.npz")
    smoothed = smoothed_to_grid(keys, probs, vs, ctx.cfg.fusion.logp_clip)
    total = cn.iterations * _3DCN_GRID_SCALE
    for it in range(1, cn.iterations + 1):
        grid_path, smooth_path = r / f"grid_3dcn{it}.npz", r / f"grid_smooth_3dcn{it}.npz"
        if grid_path.is_file() and smooth_path.is_file():
            fused = VoxelGrid.load(grid_path)
        else:
            offset = (it - 1) * _3DCN_GRID_SCALE

            def prog(done: int, tot: int, offset: int = offset) -> None:
                ctx.tick("3dcn", offset + (done * _3DCN_GRID_SCALE) // max(tot, 1), total)

            if cn.rank_by_views and views is None:
                views = view_counts(obs_keys for _, obs_keys in _observations(ctx))
            fused = run_3dcn_iteration(ctx.seq, fused, smoothed, c, cn, ctx.cfg.fusion, r / "3dcn", it,
                                       progress=prog, frames=ctx.frames, views=views)
            fused.save(grid_path)
            _smooth_and_save(fused, ctx, smooth_path)
        keys, probs, vs = _load_smooth(smooth_path)
        smoothed = smoothed_to_grid(keys, probs, vs, ctx.cfg.fusion.logp_clip)
        ctx.tick("3dcn", it * _3DCN_GRID_SCALE, total)
    return {"iterations": cn.iterations, "voxels": fused.num_voxels}


def _final_grid_path(ctx: _Ctx) -> Path:
    cn = ctx.cfg.consistency
    if cn.enabled:
        return ctx.run_dir / f"grid_smooth_3dcn{cn.iterations}.npz"
    return ctx.run_dir / "grid_smooth.npz"


def stage_label_points(ctx: _Ctx) -> dict[str, Any]:
    """Per frame: every point takes its voxel's label in the final grid → ``points/<frame_id>.npz``.

    ``label`` (N,) int16 and ``conf`` (N,) float16 from the final smoothed grid (UNLABELED / 0 for points
    in never-observed voxels); ``point_label`` (N,) int16 from projection alone (the paper's "point").
    """
    lookup = _GridLabels(_final_grid_path(ctx))
    vs = ctx.cfg.fusion.voxel_size

    def work(i: int) -> None:
        frame = ctx.seq.frame(i)
        pts = frame.points
        keys = voxel_keys(world_points(pts, frame.pose), vs)
        lab, conf = lookup(keys)
        painted, n, _ = _load_observation(ctx.path("observations", i))
        if n != pts.shape[0]:
            raise DatasetError(ctx.seq.scan_path(i), f"{pts.shape[0]} points but its observation has {n}")
        atomic_save_npz(ctx.path("points", i), label=lab, conf=conf.astype(np.float16),
                        point_label=painted.point_labels(n))

    return _per_frame(ctx, "label_points", work)


def stage_evaluate(ctx: _Ctx) -> dict[str, Any]:
    """Point / voxel / +3D-CN rows against ground truth, both protocols → ``metrics.json``.

    Skipped (status "skipped") when a processed frame has no ground-truth ``.label`` file.
    """
    seq, schema = ctx.seq, ctx.schema
    if not all(seq.label_path(i).is_file() for i in ctx.frames):
        return {"status": "skipped", "note": "no ground truth"}
    c = schema.num_classes
    # None: read from points/ (the projection-only labels, and the final grid's labels that label_points
    # already looked up); a grid: looked up here (the voxel row when the 3D-CN came after it).
    rows: dict[str, _GridLabels | None] = {ROW_POINT: None}
    cn = ctx.cfg.consistency
    if cn.enabled:
        rows[ROW_VOXEL] = _GridLabels(ctx.run_dir / "grid_smooth.npz")
        for it in range(1, cn.iterations + 1):
            rows[cn_row(it)] = None if it == cn.iterations else _GridLabels(
                ctx.run_dir / f"grid_smooth_3dcn{it}.npz")
        final_row = cn_row(cn.iterations)
    else:
        rows[ROW_VOXEL] = None
        final_row = ROW_VOXEL
    need_keys = any(v is not None for v in rows.values())
    conf = {p: {r: np.zeros((c, c + 1), np.int64) for r in rows} for p in PROTOCOLS}
    n_points = n_view = 0
    labeled_any = {r: 0 for r in rows}
    vs = ctx.cfg.fusion.voxel_size
    total = len(ctx.frames)
    for k, i in enumerate(ctx.frames):
        ctx.tick("evaluate", k, total)
        frame = seq.frame(i)
        pts = frame.points
        gt = schema.map_gt(frame.labels)
        _, n, in_view = _load_observation(ctx.path("observations", i))
        with np.load(ctx.path("points", i)) as z:
            stored = {ROW_POINT: z["point_label"], final_row: z["label"]}
        if n != pts.shape[0] or stored[ROW_POINT].shape[0] != n:
            raise DatasetError(ctx.seq.scan_path(i), f"{pts.shape[0]} points but the run's outputs have {n}")
        keys = voxel_keys(world_points(pts, frame.pose), vs) if need_keys else None
        n_points += n
        n_view += int(in_view.sum())
        for name, lookup in rows.items():
            pred = stored[name] if lookup is None else lookup(keys)[0]
            labeled_any[name] += int((pred != UNLABELED).sum())
            conf["all"][name] += confusion_matrix(gt, pred, c)
            conf["camera"][name] += confusion_matrix(gt[in_view], pred[in_view], c)
    ctx.tick("evaluate", total, total)
    out: dict[str, Any] = {
        "class_names": schema.names,
        "categories": schema.categories(),
        "rows": list(rows),
        "protocols": dict(PROTOCOLS),
        "frames": [ctx.frames.start, ctx.frames.stop, ctx.frames.step],
        "n_points": n_points,
        "n_points_in_view": n_view,
        # Share of ALL points (ground truth or not) that got a label, per row.
        "labeled_points": {r: labeled_any[r] for r in rows},
        "labeler": ctx.cfg.labeler,
    }
    for p in PROTOCOLS:
        out[p] = {
            r: metrics_from_confusion(conf[p][r], schema.names, schema.categories(),
                                      ignore_unlabeled_pred=(p == "camera")).to_dict()
            for r in rows
        }
    pl = labeled_any[ROW_POINT]
    out["coverage_ratio"] = {r: (labeled_any[r] / pl if pl else None) for r in rows}
    atomic_write_json(ctx.run_dir / "metrics.json", out)
    return {}


def stage_export(ctx: _Ctx) -> dict[str, Any]:
    """Per frame: ``export/<frame_id>.label`` (raw export ids, 0 = unlabeled, instance 0) and ``.conf``."""
    from leap_core.export import export_labels

    ids = ctx.schema.export_ids()
    out_dir = ctx.run_dir / "export"

    def work(i: int) -> None:
        path = ctx.path("points", i)
        try:
            with np.load(path) as z:
                lab, conf = z["label"], z["conf"].astype(np.float32)
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable point labels ({exc})") from exc
        export_labels(out_dir, ctx.seq.frame_ids[i], lab, conf, ids)

    return _per_frame(ctx, "export", work)


_STAGE_FNS: dict[str, Callable[[_Ctx], dict[str, Any]]] = {
    "labels2d": stage_labels2d,
    "project": stage_project,
    "fuse": stage_fuse,
    "smooth": stage_smooth,
    "3dcn": stage_3dcn,
    "label_points": stage_label_points,
    "evaluate": stage_evaluate,
    "export": stage_export,
}


# ---------------------------------------------------------------------------------------- public API
def _frames(seq: KittiSequence, frames: range | None) -> range:
    n = len(seq)
    if frames is None:
        return range(n)
    if not isinstance(frames, range):
        raise LeapError(f"frames must be a range, got {type(frames).__name__}")
    if len(frames) == 0:
        raise LeapError(f"frames {frames.start}:{frames.stop} select no frame (the sequence has {n})")
    if frames.step <= 0 or frames.start < 0 or frames[-1] >= n:
        raise LeapError(
            f"frames {frames.start}:{frames.stop} out of range: the sequence has frames 0..{n - 1}"
        )
    return frames


def _context(
    dataset: Path, schema: Schema, config: PipelineConfig, run_dir: Path, progress: ProgressCallback | None,
    frames: range | None, cache_dir: Path | None, runtime: Runtime | None = None,
) -> _Ctx:
    # Transitional (config branch): `runtime` carries the models folder; `cache_dir` is kept beside it
    # until the core branch's run_pipeline(runtime=...) replaces both.
    runtime = runtime or Runtime()
    if cache_dir is not None:
        runtime = replace(runtime, cache_dir=Path(cache_dir))
    cache_dir = runtime.cache_dir
    seq = KittiSequence(dataset)
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise LeapError(f"{run_dir}: run folder path exists and is not a folder")
    run_dir.mkdir(parents=True, exist_ok=True)
    ctx = _Ctx(seq, schema, config, run_dir, _frames(seq, frames), Path(cache_dir) if cache_dir else None,
               progress, runtime=runtime)
    ctx.state = _read_state(run_dir)
    ctx.fp = _fingerprints(ctx)
    return ctx


def plan_stages(
    dataset: Path, schema: Schema, config: PipelineConfig, run_dir: Path, *, frames: range | None = None,
    cache_dir: Path | None = None, runtime: Runtime | None = None,
) -> dict[str, bool]:
    """Which stages :func:`run_pipeline` would compute (True) or skip as cached (False); writes nothing."""
    ctx = _context(dataset, schema, config, run_dir, None, frames, cache_dir, runtime)
    return {s: not _is_current(ctx, s) for s in STAGES}


def run_pipeline(
    dataset: Path,
    schema: Schema,
    config: PipelineConfig,
    run_dir: Path,
    *,
    progress: ProgressCallback | None = None,
    frames: range | None = None,
    cache_dir: Path | None = None,
    runtime: Runtime | None = None,
    until: str | None = None,
) -> RunResult:
    """Run (or resume) every stage on ``run_dir``, skipping stages whose cached outputs are current.

    Args:
        dataset: a KITTI-layout sequence folder (``.../sequences/NN``).
        schema: the class schema.
        config: pipeline parameters.
        run_dir: the run folder (created if missing); see the module docstring for its layout.
        progress: ``progress(stage, done, total)`` after each unit of work; raising
            :class:`~leap_core.errors.Cancelled` stops the run cleanly (finished frames are kept).
        frames: the frames to process (default: all).
        cache_dir: shared 2D cache folder (reused across runs of a project); None = no sharing.
        runtime: deployment values (models folder, 2D cache folder, device); ``cache_dir`` overrides its
            ``cache_dir``.
        until: stop after this stage (e.g. "smooth" to only build the grid).

    Returns:
        :class:`RunResult` with per-stage reports, the export folder and the metrics (when GT exists).

    Raises:
        LeapError: bad dataset, schema/config or run folder (one line, naming the file or field).
        Cancelled: raised by ``progress``; the stage is recorded as "cancelled" and a rerun resumes.
    """
    if until is not None and until not in STAGES:
        raise LeapError(f"until: unknown stage {until!r} (stages: {', '.join(STAGES)})")
    ctx = _context(Path(dataset), schema, config, Path(run_dir), progress, frames, cache_dir, runtime)
    last = STAGES.index(until) if until else len(STAGES) - 1
    reports: dict[str, StageReport] = {}
    for name in STAGES[: last + 1]:
        reports[name] = _run_stage(ctx, name, _STAGE_FNS[name])
    metrics_path = ctx.run_dir / "metrics.json"
    metrics = None
    if "evaluate" in reports and reports["evaluate"].status == "done" and metrics_path.is_file():
        metrics = json.loads(metrics_path.read_text())
    export_dir = ctx.run_dir / "export" if "export" in reports else None
    return RunResult(ctx.run_dir, reports, tuple(ctx.frames), export_dir, metrics)


def load_metrics(run_dir: str | Path) -> dict[str, dict[str, Metrics]] | None:
    """``{protocol: {row: Metrics}}`` rebuilt from ``metrics.json`` (None when the run has none)."""
    path = Path(run_dir) / "metrics.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        names, cats = data["class_names"], data["categories"]
        return {
            p: {
                r: metrics_from_confusion(np.asarray(data[p][r]["confusion"], np.int64), names, cats,
                                          ignore_unlabeled_pred=(p == "camera"))
                for r in data["rows"]
            }
            for p in PROTOCOLS
        }
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(path, f"unreadable metrics ({exc})") from exc


def result_tables(run_dir: str | Path) -> str | None:
    """The run's result tables as text (one per protocol), or None without metrics."""
    tables = load_metrics(run_dir)
    if tables is None:
        return None
    data = json.loads((Path(run_dir) / "metrics.json").read_text())
    labeler = data.get("labeler", "?")
    parts = []
    for p, rows in tables.items():
        names = next(iter(rows.values())).class_names
        parts.append(f"{PROTOCOLS[p]}; 2D labels: {labeler}\n{format_table(rows, names)}")
    ratio = data.get("coverage_ratio", {}).get(ROW_VOXEL)
    if ratio:
        parts.append(f"voxel labels cover {ratio:.2f}x as many points as projection alone")
    return "\n\n".join(parts)


__all__ = [
    "PIPELINE_VERSION",
    "PROTOCOLS",
    "STAGES",
    "STAGE_TABLE",
    "StageInfo",
    "ProgressCallback",
    "RunResult",
    "StageReport",
    "cn_row",
    "dataset_identity",
    "load_metrics",
    "plan_stages",
    "result_tables",
    "run_pipeline",
    "smoothed_to_grid",
    "stage_status",
    "world_points",
]
