"""The stage functions and :data:`STAGE_TABLE`, the one record per stage the runner works from.

Adding a stage = one :class:`~leap_core.pipeline.context.StageInfo` record in :data:`STAGE_TABLE` plus its
function (docs/ARCHITECTURE.md, "Adding a stage").
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.config import PipelineConfig
from leap_core.consistency.selection import view_counts
from leap_core.errors import DatasetError
from leap_core.export import export_labels
from leap_core.fusion import (
    Observations,
    VoxelGrid,
    apply_overrides,
    fuse,
    last_per_key,
    log_table,
    voxel_keys,
    world_points,
)
from leap_core.io_utils import atomic_save_npz, atomic_write, link_or_copy, read_npz
from leap_core.labelers import LABELERS
from leap_core.labelers.base import SoftMasks
from leap_core.pipeline.apply import RunCorrections, check_scan_points, frame_keys, point_labels
from leap_core.pipeline.context import (
    Ctx,
    FrameFiles,
    StageInfo,
    dataset_identity,
    file_digest,
    frame_input_digest,
    hash_json,
    load_observation,
)
from leap_core.pipeline.evaluation import stage_evaluate
from leap_core.projection import Painted, paint, project_points
from leap_core.run_layout import RunLayout, load_corrections
from leap_core.smoothing import SmoothedGrid, knn_smooth

_3DCN_GRID_SCALE = 1000
"""3D-CN progress is reported in thousandths of an iteration (its own step count is not known upfront)."""


# ------------------------------------------------------------------------------------------ labels2d
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


def stage_labels2d(ctx: Ctx) -> dict[str, Any]:
    """Per frame: the labeler's SoftMasks → ``labels2d/<frame_id>.npz`` (via the shared 2D cache folder
    ``runtime.cache_dir`` when given: entries keyed by the labeler's fingerprint and the frame's inputs,
    hard-linked into the run folder)."""
    labeler = ctx.labeler()
    spec = LABELERS[ctx.cfg.labeler]
    if spec.needs == "gt2d" and not ctx.seq.has_gt2d:
        raise DatasetError(ctx.seq.root / "gt2d" / "semantic", spec.missing)
    lfp = labeler.fingerprint(ctx.schema)
    cache_root = None
    if ctx.cache_dir is not None:
        cache_root = ctx.cache_dir / "labels2d" / hash_json([lfp, ctx.schema.num_classes])[:16]
    hits = 0

    def work(i: int) -> None:
        nonlocal hits
        out = ctx.layout.labels2d(ctx.fid(i))
        frame = ctx.seq.frame(i)
        if cache_root is not None:
            entry = cache_root / f"{frame.frame_id}-{frame_input_digest(ctx.seq, i)[:20]}.npz"
            if entry.is_file():
                try:
                    SoftMasks.load(entry)
                    link_or_copy(entry, out)
                    hits += 1
                    return
                except DatasetError:
                    pass  # A damaged entry is recomputed and replaced atomically below.
            _save_soft(entry, labeler.label(frame, ctx.schema))
            link_or_copy(entry, out)
        else:
            _save_soft(out, labeler.label(frame, ctx.schema))

    extra = ctx.each_frame("labels2d", work)
    extra["cache_hits"] = hits
    extra["labeler"] = labeler.name
    return extra


def _labeler_inputs(ctx: Ctx) -> dict[str, Any]:
    # The labeler's fingerprint covers its own config section and the schema parts (prompts) it reads.
    return {"labeler": ctx.labeler().fingerprint(ctx.schema), "data": dataset_identity(ctx.seq)}


# ------------------------------------------------------------------------------------------- project
def _load_soft(path: Path) -> SoftMasks:
    """:meth:`SoftMasks.load` through :func:`~leap_core.io_utils.read_npz`: the packed masks (compressed,
    ≈ 5 MB unpacked for a demo image) in one zlib call instead of about 20."""
    try:
        z = read_npz(path)
        h, w = (int(x) for x in z["size"])
        return SoftMasks(h, w, z["bits"], z["probs"].astype(np.float32), z["confidence"].astype(np.float32))
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable 2D label file ({exc})") from exc


def stage_project(ctx: Ctx) -> dict[str, Any]:
    """Per frame: project the scan, depth-cluster per mask, paint → ``observations/<frame_id>.npz``.

    Stores the :class:`Painted` arrays plus ``n_points`` and ``in_view`` (packed bits: the point lies in the
    image in front of the camera), which the camera-view evaluation protocol uses. Frames run
    :attr:`Runtime.frame_threads` at a time.
    """
    pcfg = ctx.cfg.projection
    m = ctx.seq.calib.lidar_to_image

    def work(i: int) -> None:
        soft_path = ctx.layout.labels2d(ctx.fid(i))
        soft = _load_soft(soft_path)
        if soft.num_classes != ctx.schema.num_classes:
            raise DatasetError(
                soft_path, f"{soft.num_classes} classes but the schema has {ctx.schema.num_classes}"
            )
        pts = ctx.seq.frame(i).points
        proj = project_points(pts, m, soft.height, soft.width, pcfg.min_depth)
        painted = paint(soft, proj, pcfg)
        in_view = np.zeros(pts.shape[0], bool)
        in_view[proj.idx] = True
        atomic_save_npz(
            ctx.layout.observation(ctx.fid(i)),
            point_idx=painted.point_idx,
            rows=painted.rows,
            table=painted.table,
            n_points=np.asarray(pts.shape[0], np.int64),
            in_view=np.packbits(in_view),
        )

    return ctx.each_frame("project", work, parallel=True)


def observed_keys(ctx: Ctx) -> Iterator[tuple[Painted, npt.NDArray[np.int64]]]:
    """Per frame: its observation and the world voxel key of each observed (painted) point."""
    for i in ctx.frames:
        painted = Painted.load(ctx.layout.observation(ctx.fid(i)))
        frame = ctx.seq.frame(i)
        pts = frame.points[painted.point_idx]
        yield painted, voxel_keys(world_points(pts, frame.pose), ctx.cfg.fusion.voxel_size)


# ---------------------------------------------------------------------------------------------- fuse
def stage_fuse(ctx: Ctx) -> dict[str, Any]:
    """All frames' observations → one voxel grid (log-space Bayes), then corrections → ``grid.npz``."""
    fcfg = ctx.cfg.fusion
    c = ctx.schema.num_classes
    total = len(ctx.frames)

    def batches() -> Iterator[Observations]:
        for k, (painted, keys) in enumerate(observed_keys(ctx)):
            ctx.tick("fuse", k, total)
            yield Observations(keys, painted.rows, log_table(painted.table, fcfg.prob_floor))

    grid = fuse(batches(), c, fcfg)
    n_corr = 0
    if ctx.layout.corrections.is_file():
        # Deduplicated first so an erase (-1) cancels an earlier class on its voxel; erased voxels get no
        # override here (label_points makes their points unlabeled).
        keys, cls = last_per_key(*load_corrections(ctx.layout.corrections, c))
        n_corr = len(keys)
        keep = cls >= 0
        if keep.any():
            grid = apply_overrides(grid, keys[keep], cls[keep], ctx.cfg.correction_strength, fcfg)
    grid.save(ctx.layout.grid)
    ctx.tick("fuse", total, total)
    return {"voxels": grid.num_voxels, "corrections": n_corr}


def _fuse_inputs(ctx: Ctx) -> dict[str, Any]:
    corr = ctx.layout.corrections
    digest = file_digest(corr) if corr.is_file() else None
    return {"frames": hash_json(ctx.frame_ids()), "corrections": digest,
            "strength": ctx.cfg.correction_strength if digest else None}


# -------------------------------------------------------------------------------------------- smooth
def _smooth_and_save(grid: VoxelGrid, ctx: Ctx, path: Path) -> None:
    """kNN-smooth ``grid`` and save it; corrected voxels are then reset to their corrected class.

    A manual correction is the user's final word: kNN smoothing (and a later 3D-CN round) must not move
    it, so it is re-imposed as a one-hot distribution on the smoothed grid, not only fused as evidence.
    """
    probs = knn_smooth(grid.centres(), grid.probs(), ctx.cfg.smoothing)
    if ctx.layout.corrections.is_file():
        keys, cls = last_per_key(*load_corrections(ctx.layout.corrections, grid.num_classes))
        rows = grid.lookup(keys)
        hit = (rows >= 0) & (cls >= 0)  # an erase (-1) has no class to impose
        probs[rows[hit]] = 0.0
        probs[rows[hit], cls[hit]] = 1.0
    SmoothedGrid(grid.keys, probs.astype(np.float16), grid.voxel_size).save(path)


def stage_smooth(ctx: Ctx) -> dict[str, Any]:
    """kNN smoothing of ``grid.npz`` → ``grid_smooth.npz`` (a :class:`SmoothedGrid`)."""
    ctx.tick("smooth", 0, 1)
    grid = VoxelGrid.load(ctx.layout.grid)
    _smooth_and_save(grid, ctx, ctx.layout.grid_smooth)
    ctx.tick("smooth", 1, 1)
    return {"voxels": grid.num_voxels}


# ---------------------------------------------------------------------------------------------- 3dcn
def stage_3dcn(ctx: Ctx) -> dict[str, Any]:
    """The 3D Consistency Network, ``consistency.iterations`` rounds (the table skips it unless enabled).

    Round i: train on the reliable labels of the previous smoothed grid, fuse the network's tempered
    predictions into the previous fused grid → ``grid_3dcn{i}.npz``, smooth → ``grid_smooth_3dcn{i}.npz``.
    A finished round is kept on resume.
    """
    # Imported here: the 3D-CN needs torch, which only this stage may load.
    from leap_core.consistency.stage import run_3dcn_iteration  # noqa: PLC0415  loads torch (see above)

    cn = ctx.cfg.consistency
    lay = ctx.layout
    clip = ctx.cfg.fusion.logp_clip
    fused = VoxelGrid.load(lay.grid)
    views: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None = None
    smoothed = SmoothedGrid.load(lay.grid_smooth).to_voxel_grid(clip)
    # Erased voxels keep their fused evidence (fuse imposes no class on them), so without this their
    # points would train the network on the very labels the user removed.
    erased = RunCorrections.of_run(lay, ctx.schema.num_classes).erased_keys()
    total = cn.iterations * _3DCN_GRID_SCALE
    for it in range(1, cn.iterations + 1):
        grid_path, smooth_path = lay.grid_3dcn(it), lay.grid_smooth_3dcn(it)
        if grid_path.is_file() and smooth_path.is_file():
            fused = VoxelGrid.load(grid_path)
        else:
            offset = (it - 1) * _3DCN_GRID_SCALE

            def prog(done: int, tot: int, offset: int = offset) -> None:
                ctx.tick("3dcn", offset + (done * _3DCN_GRID_SCALE) // max(tot, 1), total)

            if cn.rank_by_views and views is None:
                views = view_counts(obs_keys for _, obs_keys in observed_keys(ctx))
            fused = run_3dcn_iteration(ctx.seq, fused, smoothed, ctx.schema.num_classes, cn, ctx.cfg.fusion,
                                       lay.cn_dir, it, progress=prog, frames=ctx.frames, views=views,
                                       erased=erased)
            fused.save(grid_path)
            _smooth_and_save(fused, ctx, smooth_path)
        smoothed = SmoothedGrid.load(smooth_path).to_voxel_grid(clip)
        ctx.tick("3dcn", it * _3DCN_GRID_SCALE, total)
    return {"iterations": cn.iterations, "voxels": fused.num_voxels}


def _3dcn_outputs(lay: RunLayout, cfg: PipelineConfig) -> tuple[Path, ...]:
    return tuple(lay.grid_smooth_3dcn(i) for i in range(1, cfg.consistency.iterations + 1))


# -------------------------------------------------------------------------------------- label_points
def stage_label_points(ctx: Ctx) -> dict[str, Any]:
    """Per frame: every point takes its voxel's label in the final grid → ``points/<frame_id>.npz``.

    ``label`` (N,) int16 and ``conf`` (N,) float16 from the final smoothed grid (UNLABELED / 0 for points
    in never-observed voxels), then the manual corrections (map scope incl. erase, then this scan's scan
    scope: :func:`leap_core.pipeline.apply.point_labels`); ``point_label`` (N,) int16 from projection alone
    (the paper's "point").
    """
    final = SmoothedGrid.load(ctx.layout.final_grid(ctx.cfg.consistency))
    final.voxel_labels()  # computed once here, not by the first frames' threads at the same time
    vs = ctx.cfg.fusion.voxel_size
    corr = RunCorrections.of_run(ctx.layout, ctx.schema.num_classes)

    def work(i: int) -> None:
        frame = ctx.seq.frame(i)
        keys = frame_keys(frame, vs)
        painted, n, _ = load_observation(ctx.layout.observation(ctx.fid(i)))
        if n != keys.shape[0]:
            raise DatasetError(ctx.seq.scan_path(i), f"{keys.shape[0]} points but its observation has {n}")
        check_scan_points(ctx.layout.corrections_scan, ctx.fid(i), corr, n)
        lab, conf = point_labels(final, keys, ctx.fid(i), corr)
        atomic_save_npz(ctx.layout.points(ctx.fid(i)), label=lab, conf=conf.astype(np.float16),
                        point_label=painted.point_labels(n))

    return ctx.each_frame("label_points", work, parallel=True)


def _label_points_inputs(ctx: Ctx) -> dict[str, Any]:
    # Map-scope corrections reach this stage through fuse's fingerprint; scan-scope ones only here, so a
    # changed scan correction reruns label_points, evaluate and export but not the fusion.
    scan = ctx.layout.corrections_scan
    return {"scan_corrections": file_digest(scan) if scan.is_file() else None}


# -------------------------------------------------------------------------------------------- export
def stage_export(ctx: Ctx) -> dict[str, Any]:
    """Per frame: ``export/<frame_id>.label`` (raw export ids, 0 = unlabeled, instance 0) and ``.conf``."""
    ids = ctx.schema.export_ids()

    def work(i: int) -> None:
        fid = ctx.fid(i)
        path = ctx.layout.points(fid)
        try:
            z = read_npz(path, ("label", "conf"))
            lab, conf = z["label"], z["conf"].astype(np.float32)
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable point labels ({exc})") from exc
        export_labels(ctx.layout.export_label(fid), ctx.layout.export_conf(fid), lab, conf, ids)

    return ctx.each_frame("export", work, parallel=True)


# ---------------------------------------------------------------------------------------- the table
STAGE_TABLE: tuple[StageInfo, ...] = (
    StageInfo(
        "labels2d", "2D labels", "the 2D labeler's soft masks per frame", True, stage_labels2d,
        reads=("labeler",), inputs=_labeler_inputs, frame_files=FrameFiles(RunLayout.LABELS2D),
    ),
    StageInfo(
        "project", "Projection", "projection, per-mask depth clustering and painting per frame", True,
        stage_project, reads=("projection",), upstream=("labels2d",),
        frame_files=FrameFiles(RunLayout.OBSERVATIONS),
    ),
    StageInfo(
        "fuse", "Voxel fusion", "Bayesian fusion of every observation into the voxel grid", False, stage_fuse,
        reads=("fusion",), upstream=("project",), inputs=_fuse_inputs, outputs=lambda lay, _cfg: (lay.grid,),
        needs_poses=True,
    ),
    StageInfo(
        "smooth", "kNN smoothing", "distance-weighted kNN smoothing of the fused grid", False, stage_smooth,
        reads=("smoothing",), upstream=("fuse",), outputs=lambda lay, _cfg: (lay.grid_smooth,),
    ),
    StageInfo(
        "3dcn", "3D-CN", "3D Consistency Network rounds (when enabled)", False, stage_3dcn,
        reads=("consistency",), upstream=("project", "fuse", "smooth"), outputs=_3dcn_outputs,
        stale=lambda lay: lay.cn_grids(), switch="consistency.enabled",
        needs_poses=True,
    ),
    StageInfo(
        "label_points", "Point labels", "label and confidence of every point from the final grid", True,
        stage_label_points, upstream=("project", "smooth", "3dcn"), inputs=_label_points_inputs,
        frame_files=FrameFiles(RunLayout.POINTS),
        needs_poses=True,
    ),
    StageInfo(
        "evaluate", "Evaluation", "point / voxel / 3D-CN metrics against ground truth", False, stage_evaluate,
        upstream=("project", "smooth", "3dcn", "label_points"),
        inputs=lambda ctx: [[c.name, sorted(c.gt_ids), c.category] for c in ctx.schema.classes],
        outputs=lambda lay, _cfg: (lay.metrics,),
        needs_poses=True,
    ),
    StageInfo(
        "export", "Export", "SemanticKITTI .label and .conf files per scan", True, stage_export,
        upstream=("label_points",), inputs=lambda ctx: [int(x) for x in ctx.schema.export_ids()],
        frame_files=FrameFiles(RunLayout.EXPORT, (".label", ".conf")),
    ),
)
"""Every stage in execution order."""

STAGES: tuple[str, ...] = tuple(s.name for s in STAGE_TABLE)
"""Stage names in execution order."""


__all__ = ["STAGES", "STAGE_TABLE", "stage_3dcn", "stage_export", "stage_fuse", "stage_label_points",
           "stage_labels2d", "stage_project", "stage_smooth"]
