"""The stage functions and :data:`STAGE_TABLE`, the one record per stage the runner works from.

Adding a stage = one :class:`~leap_core.pipeline.context.StageInfo` record in :data:`STAGE_TABLE` plus its
function (docs/ARCHITECTURE.md, "Adding a stage").
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from functools import cache, partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
import numpy.typing as npt

from leap_core.config import PipelineConfig
from leap_core.consistency.selection import view_counts
from leap_core.datasets.kitti import Frame
from leap_core.errors import DatasetError, LeapError, ModelLoadError
from leap_core.eval_view import PAPER_VIEW
from leap_core.export import export_labels
from leap_core.fusion import (
    Observations,
    VoxelGrid,
    apply_overrides,
    fuse_to_file,
    last_per_key,
    log_table,
    voxel_keys,
    world_points,
)
from leap_core.io_utils import atomic_save_npz, atomic_write, atomic_write_json, link_or_copy, read_npz
from leap_core.labelers import LABELERS, LabelerInput, labeler_weights, missing_input
from leap_core.labelers.base import ImageModelLabeler, Instances, SoftMasks
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
    load_view,
)
from leap_core.pipeline.evaluation import METRICS_VERSION, stage_evaluate
from leap_core.pipeline.object_corrections import CorrectedTracks, read_corrected_tracks
from leap_core.pipeline.objects import motion_enabled, motion_inputs, read_motion, stage_motion, stage_tracks
from leap_core.projection import Painted, paint, project_points
from leap_core.run_layout import RunLayout, SequenceLayout, load_corrections
from leap_core.smoothing import SMOOTH_CHUNK, SmoothedGrid, smooth_grid_blocks

if TYPE_CHECKING:
    from leap_core.consistency.stage import Predict
    from leap_core.consistency.train import SourceNetwork

_3DCN_GRID_SCALE = 1000
"""3D-CN progress is reported in thousandths of an iteration (its own step count is not known upfront)."""


# ------------------------------------------------------------------------------------------ labels2d
def _save_soft(path: Path, soft: SoftMasks) -> None:
    """Write a 2D label file; labels without instances (a labeler that gives none) are written with an
    empty set, so the file is not taken for one from before instances existed (whose 2D cache entry would
    then be recomputed on every run)."""
    if soft.instances is None:
        soft = dataclasses.replace(soft, instances=Instances.empty(soft.height, soft.width))
    # Compressed: packed masks are mostly zero bytes (≈ 10× smaller), and SoftMasks.load reads either form.
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(fh, **cast(dict[str, Any], soft.arrays()))


def stage_labels2d(ctx: Ctx) -> dict[str, Any]:
    """Per frame: the labeler's SoftMasks → ``labels2d/<frame_id>.npz`` (via the shared 2D cache folder
    ``runtime.cache_dir`` when given: entries keyed by the labeler's fingerprint and the frame's inputs,
    hard-linked into the run folder).

    A cache entry without instances (written before labelers gave them) is recomputed, not served: the
    record's ``cache_refreshed`` counts them (absent when none)."""
    labeler = ctx.labeler()
    spec = LABELERS[ctx.cfg.labeler]
    if spec.needs == "gt2d" and not ctx.seq.has_gt2d:
        has: list[LabelerInput] = ["images"] if ctx.seq.has_images else []
        raise DatasetError(ctx.seq.root / "gt2d" / "semantic", missing_input(spec, has))
    lfp = labeler.fingerprint(ctx.schema)
    cache_root = None
    if ctx.cache_dir is not None:
        cache_root = ctx.cache_dir / "labels2d" / hash_json([lfp, ctx.schema.num_classes])[:16]
    hits = refreshed = 0
    cameras = [0] * len(ctx.seq.cameras)

    def cache_entry(frame: Frame) -> tuple[Path | None, bool]:
        """The frame's 2D cache entry (None: no cache) and whether it holds a good one."""
        if cache_root is None:
            return None, False
        digest = frame_input_digest(ctx.seq, frame.index, frame.camera)
        entry = cache_root / f"{frame.frame_id}-{digest[:20]}.npz"
        state = _cache_state(entry)
        if state == "stale":
            nonlocal refreshed
            refreshed += 1
        return entry, state == "hit"

    def work(i: int) -> None:
        nonlocal hits
        frame = ctx.seq.frame(i)
        views = [v for v in frame.cameras()[1:] if _has_2d_input(v, spec.needs)] + [frame]
        entries = [cache_entry(v) for v in views]
        todo = [v for v, (_, hit) in zip(views, entries, strict=True) if not hit]
        if len(todo) > 1 and isinstance(labeler, ImageModelLabeler):
            # A model labeler takes the frame's cameras in one batch (one forward pass on a GPU).
            computed = iter(labeler.label_frames(todo, ctx.schema))
        else:
            computed = (labeler.label(v, ctx.schema) for v in todo)
        # In camera order, the primary camera's file last: its presence marks the frame done on resume.
        for view, (entry, hit) in zip(views, entries, strict=True):
            cameras[view.camera] += 1
            out = ctx.layout.labels2d(ctx.fid(i), view.rig_camera.name if view.camera else None)
            hits += hit
            if not hit:
                soft = next(computed)
                _save_soft(entry or out, soft)
            if entry is not None:
                link_or_copy(entry, out)

    extra = ctx.each_frame("labels2d", work)
    extra["cache_hits"] = hits
    if refreshed:
        extra["cache_refreshed"] = refreshed
    if len(cameras) > 1:
        extra["camera_images"] = dict(zip((c.name for c in ctx.seq.cameras), cameras, strict=True))
    extra["labeler"] = labeler.name
    extra["weights"] = labeler_weights(labeler)  # the export's provenance: real or random-weight models
    return extra


def _cache_state(entry: Path) -> Literal["hit", "miss", "stale"]:
    """A 2D cache entry is a ``hit``, a ``miss`` (absent or damaged: recomputed and replaced atomically)
    or ``stale``: it predates instances, so it is recomputed whole under the same key."""
    if not entry.is_file():
        return "miss"
    try:
        cached = load_soft(entry)
    except DatasetError:
        return "miss"
    return "stale" if cached.instances is None else "hit"


def _has_2d_input(frame: Frame, needs: str) -> bool:
    """Whether the frame's camera has what the labeler reads: its image, or its 2D ground truth."""
    if needs == "gt2d":
        return frame.gt2d_path("semantic").is_file()
    return frame.has_image


def _labeler_inputs(ctx: Ctx) -> dict[str, Any]:
    # The labeler's fingerprint covers its own config section and the schema parts (prompts) it reads.
    return {"labeler": ctx.labeler().fingerprint(ctx.schema), "data": dataset_identity(ctx.seq)}


# ------------------------------------------------------------------------------------------- project
def load_soft(path: Path) -> SoftMasks:
    """:meth:`SoftMasks.load` through :func:`~leap_core.io_utils.read_npz`: the packed masks (compressed,
    ≈ 5 MB unpacked for a demo image) in one zlib call instead of about 20."""
    try:
        return SoftMasks.from_arrays(read_npz(path))
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable 2D label file ({exc})") from exc


def stage_project(ctx: Ctx) -> dict[str, Any]:
    """Per frame: project the scan into each camera, depth-cluster per mask, paint →
    ``observations/<frame_id>.npz``.

    Stores the :class:`Painted` arrays plus ``n_points`` and ``in_view`` (packed bits: the point lies in
    some camera's image in front of it), which the camera-view evaluation protocol uses. With several
    cameras the cameras' observations are joined (:meth:`Painted.joined`: a point two cameras painted has
    two observations) and ``camera`` (uint8, per painted row of ``point_idx``) says which camera made each;
    a camera without 2D labels for the frame adds nothing. Frames run :attr:`Runtime.frame_threads` at a
    time.
    """
    pcfg = ctx.cfg.projection
    rig = ctx.seq.cameras

    def work(i: int) -> None:
        pts = ctx.seq.frame(i).points
        parts: list[Painted] = []
        used: list[int] = []
        in_view = np.zeros(pts.shape[0], bool)
        for k, cam in enumerate(rig):
            soft_path = ctx.layout.labels2d(ctx.fid(i), cam.name if k else None)
            if k and not soft_path.is_file():
                continue
            soft = load_soft(soft_path)
            if soft.num_classes != ctx.schema.num_classes:
                raise DatasetError(
                    soft_path, f"{soft.num_classes} classes but the schema has {ctx.schema.num_classes}"
                )
            m = ctx.seq.lidar_to_image(i, k)
            proj = project_points(pts, m, soft.height, soft.width, pcfg.min_depth)
            parts.append(paint(soft, proj, pcfg))
            used.append(k)
            in_view[proj.idx] = True
        painted = Painted.joined(parts, ctx.schema.num_classes)
        extra: dict[str, npt.NDArray[Any]] = {}
        if len(rig) > 1:
            extra["camera"] = np.repeat(np.asarray(used, np.uint8), [len(p) for p in parts])
        atomic_save_npz(
            ctx.layout.observation(ctx.fid(i)),
            point_idx=painted.point_idx,
            rows=painted.rows,
            table=painted.table,
            n_points=np.asarray(pts.shape[0], np.int64),
            in_view=np.packbits(in_view),
            **extra,
        )

    return ctx.each_frame("project", work, parallel=True)


def fused_observation(painted: Painted, moving: npt.NDArray[np.int32] | None) -> Painted:
    """The observations of a scan that the fusion adds: all but those of the ``moving`` point rows (the
    ``motion`` stage's movers; None: all)."""
    if moving is None or not moving.size:
        return painted
    keep = ~np.isin(painted.point_idx, moving)
    return Painted(painted.point_idx[keep], painted.rows[keep], painted.table)


def observed_keys(ctx: Ctx) -> Iterator[tuple[Painted, npt.NDArray[np.int64]]]:
    """Per frame: its observation and the world voxel key of each observed (painted) point, without the
    points of moving objects when the ``motion`` stage found them (docs/METHOD.md B.6)."""
    movers = read_motion(ctx)
    for i in ctx.frames:
        painted = Painted.load(ctx.layout.observation(ctx.fid(i)))
        if movers is not None:
            painted = fused_observation(painted, movers.scan(ctx.fid(i)).rows)
        frame = ctx.seq.frame(i)
        pts = frame.points_at(painted.point_idx)
        yield painted, voxel_keys(world_points(pts, frame.pose), ctx.cfg.fusion.voxel_size)


def camera_view_keys(ctx: Ctx) -> npt.NDArray[np.int64]:
    """Sorted unique world voxel keys of the points inside a camera image, over the run's frames (the
    observations' ``in_view`` masks): where the camera could have labeled a voxel."""

    def per_frame() -> Iterator[npt.NDArray[np.int64]]:
        for i in ctx.frames:
            _, in_view = load_view(ctx.layout.observation(ctx.fid(i)))
            yield frame_keys(ctx.seq.frame(i), ctx.cfg.fusion.voxel_size)[in_view]

    return view_counts(per_frame())[0]


# ---------------------------------------------------------------------------------------------- fuse
def stage_fuse(ctx: Ctx) -> dict[str, Any]:
    """All frames' observations → one voxel grid (log-space Bayes), then corrections → ``grid.npz``. The
    points of moving objects (``motion.npz``, when ``tracking.exclude_moving``) are left out.

    Written by :func:`~leap_core.fusion.fuse_to_file` (the bytes of ``fuse`` + ``apply_overrides``): the
    per-chunk sums wait on disk in ``<run>/.fuse_spill/`` and the grid is summed, finalised and written a
    block of voxels at a time, so the stage holds 8 bytes per voxel (the sorted keys) plus one chunk and
    one block, never the (V, C) grid (docs/METHOD.md, "Memory").
    """
    fcfg = ctx.cfg.fusion
    c = ctx.schema.num_classes
    total = len(ctx.frames)

    def batches() -> Iterator[Observations]:
        for k, (painted, keys) in enumerate(observed_keys(ctx)):
            ctx.tick("fuse", k, total)
            yield Observations(keys, painted.rows, log_table(painted.table, fcfg.prob_floor))

    overrides, n_corr = _fuse_overrides(ctx)
    spill = ctx.layout.folder / ".fuse_spill"
    try:
        voxels = fuse_to_file(batches(), c, ctx.layout.grid, spill, fcfg, overrides=overrides)
    finally:
        shutil.rmtree(spill, ignore_errors=True)
    ctx.tick("fuse", total, total)
    return {"voxels": voxels, "corrections": n_corr}


def _fuse_overrides(ctx: Ctx) -> tuple[tuple[npt.NDArray[np.int64], npt.NDArray[Any], float] | None, int]:
    """The run's map corrections as :func:`~leap_core.fusion.apply_overrides` arguments ``(keys, class_idx,
    strength)`` (None when there is no class to impose) and the number of corrected voxels."""
    if not ctx.layout.corrections.is_file():
        return None, 0
    # Deduplicated first so an erase (-1) cancels an earlier class on its voxel; erased voxels get no
    # override here (label_points makes their points unlabeled).
    keys, cls = last_per_key(*load_corrections(ctx.layout.corrections, ctx.schema.num_classes))
    keep = cls >= 0
    if not keep.any():
        return None, len(keys)
    return (keys[keep], cls[keep], ctx.cfg.correction_strength), len(keys)


def finish_fuse(ctx: Ctx, grid: VoxelGrid) -> dict[str, Any]:
    """The end of the distributed engine's fusion (its partial grids already folded into ``grid``): the
    manual corrections, then ``grid.npz``; the same bytes as :func:`stage_fuse`'s
    :func:`~leap_core.fusion.fuse_to_file`."""
    overrides, n_corr = _fuse_overrides(ctx)
    if overrides is not None:
        grid = apply_overrides(grid, *overrides, ctx.cfg.fusion)
    grid.save(ctx.layout.grid)
    total = len(ctx.frames)
    ctx.tick("fuse", total, total)
    return {"voxels": grid.num_voxels, "corrections": n_corr}


def _fuse_inputs(ctx: Ctx) -> dict[str, Any]:
    corr = ctx.layout.corrections
    digest = file_digest(corr) if corr.is_file() else None
    return {
        "frames": hash_json(ctx.frame_ids()),
        "corrections": digest,
        "strength": ctx.cfg.correction_strength if digest else None,
    }


# -------------------------------------------------------------------------------------------- smooth
def _smooth_and_save(grid: VoxelGrid, ctx: Ctx, path: Path, chunk: int = SMOOTH_CHUNK) -> None:
    """kNN-smooth ``grid`` and save it; corrected voxels are then reset to their corrected class.

    A manual correction is the user's final word: kNN smoothing (and a later 3D-CN round) must not move
    it, so it is re-imposed as a one-hot distribution on the smoothed grid, not only fused as evidence.

    Streams (docs/METHOD.md, "Memory"): rows are smoothed a chunk at a time
    (:func:`~leap_core.smoothing.smooth_grid_blocks`, ``chunk`` rows each), corrected, cast to float16 and
    written to the file as they come, so besides the grid and its kd-tree only one chunk is held; the file
    is the one :meth:`SmoothedGrid.save` writes.
    """
    rows = np.zeros(0, np.int64)
    cls = np.zeros(0, np.int64)
    if ctx.layout.corrections.is_file():
        keys, cls = last_per_key(*load_corrections(ctx.layout.corrections, grid.num_classes))
        rows = grid.lookup(keys)
        hit = (rows >= 0) & (cls >= 0)  # an erase (-1) has no class to impose
        order = np.argsort(rows[hit], kind="stable")
        rows, cls = rows[hit][order], cls[hit][order]

    def blocks() -> Iterator[npt.NDArray[np.float16]]:
        for s, probs in smooth_grid_blocks(grid, ctx.cfg.smoothing, chunk):
            lo, hi = np.searchsorted(rows, [s, s + len(probs)])
            r = rows[lo:hi] - s
            probs[r] = 0.0
            probs[r, cls[lo:hi]] = 1.0
            yield probs.astype(np.float16)

    SmoothedGrid.save_blocks(path, grid.keys, grid.num_classes, blocks(), grid.voxel_size)


def stage_smooth(ctx: Ctx) -> dict[str, Any]:
    """kNN smoothing of ``grid.npz`` → ``grid_smooth.npz`` (a :class:`SmoothedGrid`); the grid is
    memory-mapped, not read whole."""
    ctx.tick("smooth", 0, 1)
    grid = VoxelGrid.load(ctx.layout.grid, mmap=True)
    _smooth_and_save(grid, ctx, ctx.layout.grid_smooth)
    ctx.tick("smooth", 1, 1)
    return {"voxels": grid.num_voxels}


# ---------------------------------------------------------------------------------------------- 3dcn
@dataclass(frozen=True)
class CnMember:
    """A sequence in :func:`cn_rounds`: its run (whose fused / smoothed grids, frames and corrections the
    rounds read) and where its round grids go."""

    ctx: Ctx
    rounds: SequenceLayout
    """``grid_3dcn{i}.npz`` / ``grid_smooth_3dcn{i}.npz`` are written here (the run's staging folder of
    the sequence)."""
    name: str = ""


def cn_rounds(
    members: Sequence[CnMember],
    checkpoints: Path,
    progress: Callable[[int, int], None] | None = None,
    predict: Predict | None = None,
) -> list[int]:
    """The 3D Consistency Network's ``consistency.iterations`` rounds over one or several sequences (one
    network per round: :func:`~leap_core.consistency.stage.iter_3dcn_round`).

    Round i: train on the reliable labels of every member's previous smoothed grid, fuse the network's
    tempered predictions into each member's previous fused grid → ``grid_3dcn{i}.npz``, smooth →
    ``grid_smooth_3dcn{i}.npz`` (both in ``member.rounds``). A round whose grids every member has is kept
    on resume; checkpoints go to ``checkpoints`` and are reused when their fingerprint matches.
    ``progress(done, total)`` counts thousandths of a round. ``predict``: the rounds' inference elsewhere
    (Ray tasks, same bytes; :data:`~leap_core.consistency.stage.Predict`). Returns each member's final
    voxel count.
    """
    # Imported here: the 3D-CN needs torch, which only this stage may load.
    from leap_core.consistency.stage import RoundPart, iter_3dcn_round  # noqa: PLC0415  loads torch

    cfg = members[0].ctx.cfg
    cn = cfg.consistency
    c = members[0].ctx.schema.num_classes
    clip = cfg.fusion.logp_clip
    # Loaded (and checked against the run's backbone and classes) before the first round's selection, so a
    # wrong file fails at once rather than after it.
    source = _source_network(members[0].ctx)
    fused: list[Path] = [m.ctx.layout.grid for m in members]
    smoothed: list[Path] = [m.ctx.layout.grid_smooth for m in members]
    # Erased voxels keep their fused evidence (fuse imposes no class on them), so without this their
    # points would train the network on the very labels the user removed.
    erased = [RunCorrections.of_run(m.ctx.layout, c).erased_keys() for m in members]
    views: list[tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None] = [None] * len(members)
    # The margin for new voxels applies inside the camera view (keep_known_or_sure): each member's keys
    # are made when a round first fuses that member, and kept for a second round (as the view counts are).
    in_view = [cache(partial(camera_view_keys, m.ctx)) for m in members]
    # The movers the fusion left out stay out of the rounds too: no training labels, no evidence back.
    moving = [_moving_rows(m.ctx) for m in members]
    total = cn.iterations * _3DCN_GRID_SCALE

    def tick(done: int, tot: int) -> None:
        if progress is not None:
            progress(done, tot)

    for it in range(1, cn.iterations + 1):
        paths = [(m.rounds.grid_3dcn(it), m.rounds.grid_smooth_3dcn(it)) for m in members]
        if not all(g.is_file() and sm.is_file() for g, sm in paths):
            offset = (it - 1) * _3DCN_GRID_SCALE

            def prog(done: int, tot: int, offset: int = offset) -> None:
                tick(offset + (done * _3DCN_GRID_SCALE) // max(tot, 1), total)

            if cn.rank_by_views:
                views = [
                    v if v is not None else view_counts(keys for _, keys in observed_keys(m.ctx))
                    for m, v in zip(members, views, strict=True)
                ]
            parts = [
                RoundPart(
                    m.ctx.seq,
                    partial(VoxelGrid.load, f, mmap=True),
                    partial(_load_smoothed, s, clip),
                    m.ctx.frames,
                    v,
                    e,
                    m.name,
                    in_view=iv,
                    moving=mv,
                )
                for m, f, s, v, e, iv, mv in zip(
                    members, fused, smoothed, views, erased, in_view, moving, strict=True
                )
            ]
            round_grids = iter_3dcn_round(
                parts, c, cn, cfg.fusion, checkpoints, it, progress=prog, predict=predict, source=source
            )
            for m, grid, (grid_path, smooth_path) in zip(members, round_grids, paths, strict=True):
                grid.save(grid_path)
                _smooth_and_save(grid, m.ctx, smooth_path)
        fused = [g for g, _ in paths]
        smoothed = [sm for _, sm in paths]
        tick(it * _3DCN_GRID_SCALE, total)
    return [VoxelGrid.load(f).num_voxels for f in fused]


def _moving_rows(ctx: Ctx) -> Callable[[int], npt.NDArray[np.int32]] | None:
    """Frame index → the rows of the ``motion`` stage's movers in that scan; None when it did not run."""
    movers = read_motion(ctx)
    if movers is None:
        return None
    return lambda i: movers.scan(ctx.fid(i)).rows


def source_digest(path: Path) -> str:
    """SHA-256 of a source network's checkpoint (``runtime.init_3dcn``), for the 3D-CN's fingerprints.

    Raises:
        ModelLoadError: naming the file, when it cannot be read.
    """
    try:
        return file_digest(path)
    except OSError as exc:
        raise ModelLoadError(
            f"{path}: 3D-CN source network (--3dcn-init) cannot be read ({exc.strerror or exc})"
        ) from None


def _source_network(ctx: Ctx) -> SourceNetwork | None:
    """The network of ``runtime.init_3dcn`` that every round starts from (None: random weights)."""
    path = None if ctx.runtime is None else ctx.runtime.init_3dcn
    if path is None:
        return None
    from leap_core.consistency.train import load_source  # noqa: PLC0415  loads torch

    return load_source(path, ctx.cfg.consistency.backbone, ctx.schema.num_classes)


def _load_smoothed(path: Path, clip: float) -> VoxelGrid:
    return SmoothedGrid.load(path, mmap=True).to_voxel_grid(clip)


def stage_3dcn(ctx: Ctx) -> dict[str, Any]:
    """The 3D Consistency Network's grids of this sequence (the table skips it unless enabled).

    The rounds train one network on every sequence of the run at once (:func:`cn_rounds`, run by
    :func:`leap_core.pipeline.run.run_pipeline` between the sequences' ``smooth`` and ``3dcn`` stages);
    this stage hard-links the sequence's round grids from the run's staging folder
    (``<run>/3dcn/rounds/<name>/``) after checking that they belong to the round the sequence's
    ``3dcn_joint.json`` names.
    """
    note_path = ctx.layout.joint_3dcn
    if not note_path.is_file():
        raise LeapError(
            f"{ctx.layout.folder}: no 3D-CN round for this sequence ({note_path.name} is missing); the "
            "3D-CN runs over a whole run: leap run SEQ ... --out RUN"
        )
    try:
        note = json.loads(note_path.read_text())
        name, fingerprint = str(note["name"]), str(note["fingerprint"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(note_path, f"unreadable 3D-CN record ({exc})") from exc
    root = RunLayout(ctx.layout.folder.parent.parent)
    staged = root.joint_rounds(name)
    state = root.joint_state
    try:
        current = (
            name == ctx.layout.folder.name
            and state.is_file()
            and json.loads(state.read_text()).get("fingerprint") == fingerprint
        )
    except (OSError, ValueError, AttributeError) as exc:
        raise DatasetError(state, f"unreadable 3D-CN record ({exc})") from exc
    iterations = ctx.cfg.consistency.iterations
    files = [(staged.grid_3dcn(i), ctx.layout.grid_3dcn(i)) for i in range(1, iterations + 1)]
    files += [(staged.grid_smooth_3dcn(i), ctx.layout.grid_smooth_3dcn(i)) for i in range(1, iterations + 1)]
    if not current or not all(src.is_file() for src, _ in files):
        raise LeapError(
            f"{ctx.layout.folder}: sequence {name} of the run {root.root}, whose 3D-CN has not run for "
            f"these settings; run it again (leap run SEQ ... --out {root.root})"
        )
    for src, dst in files:
        link_or_copy(src, dst)
    ctx.tick("3dcn", 1, 1)
    return {
        "iterations": iterations,
        "voxels": VoxelGrid.load(ctx.layout.grid_3dcn(iterations)).num_voxels,
        "joint": fingerprint,
    }


def _3dcn_inputs(ctx: Ctx) -> str | dict[str, str | None] | None:
    # The sequence takes its 3D-CN from the round its record names, so the record's digest is part of the
    # stage's fingerprint (None before the rounds ran). A source network (runtime.init_3dcn) adds its
    # file's digest, so another file, or none, trains again.
    note = ctx.layout.joint_3dcn
    joint = file_digest(note) if note.is_file() else None
    source = None if ctx.runtime is None else ctx.runtime.init_3dcn
    if source is None:
        return joint
    return {"joint": joint, "source": source_digest(source)}


def _3dcn_outputs(lay: SequenceLayout, cfg: PipelineConfig) -> tuple[Path, ...]:
    return tuple(lay.grid_smooth_3dcn(i) for i in range(1, cfg.consistency.iterations + 1))


# -------------------------------------------------------------------------------------- label_points
def stage_label_points(ctx: Ctx) -> dict[str, Any]:
    """Per frame: every point takes its voxel's label in the final grid → ``points/<frame_id>.npz``.

    ``label`` (N,) int16 and ``conf`` (N,) float16 from the final smoothed grid (UNLABELED / 0 for points
    in never-observed voxels), then the manual corrections (map scope incl. erase, then this scan's scan
    scope: :func:`leap_core.pipeline.apply.point_labels`); ``point_label`` (N,) int16 from projection alone
    (the paper's "point").
    """
    final = SmoothedGrid.load(ctx.layout.final_grid(ctx.cfg.consistency), mmap=True)
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
        atomic_save_npz(
            ctx.layout.points(ctx.fid(i)),
            label=lab,
            conf=conf.astype(np.float16),
            point_label=painted.point_labels(n),
        )

    return ctx.each_frame("label_points", work, parallel=True)


def _label_points_inputs(ctx: Ctx) -> dict[str, Any]:
    # Map-scope corrections reach this stage through fuse's fingerprint; scan-scope ones only here, so a
    # changed scan correction reruns label_points, evaluate and export but not the fusion.
    scan = ctx.layout.corrections_scan
    return {"scan_corrections": file_digest(scan) if scan.is_file() else None}


def object_corrections_inputs(ctx: Ctx) -> list[dict[str, str]]:
    """The object corrections' part of the export's and the evaluation's fingerprints (they apply there
    only, over the tracks: a changed object correction reruns neither the fusion nor the tracks; none
    leaves the fingerprints as they were before object corrections existed)."""
    path = ctx.layout.corrections_object
    return [{"object_corrections": file_digest(path)}] if path.is_file() else []


# -------------------------------------------------------------------------------------------- export
def stage_export(ctx: Ctx) -> dict[str, Any]:
    """Per frame: ``export/<frame_id>.label`` and ``.conf``. A label is the raw export id (0 = unlabeled)
    with the point's track id in the upper 16 bits (0 for stuff and untracked points); a point of a voted
    track (``tracking.vote``, by default a moving one) takes its track's class, and while the track moves
    the class's moving id (``ClassDef.moving_id``). The object corrections then relabel the tracks they
    match (:class:`~leap_core.pipeline.object_corrections.CorrectedTracks`), and which track each met is
    written to ``object_matches.json``."""
    ids = ctx.schema.export_ids()
    moving_ids = ctx.schema.moving_export_ids()
    tracks = read_tracks(ctx)
    # The report belongs to the export it describes: a run that reuses the export keeps it, one that
    # writes another (or none, without tracks) must not show the one before.
    ctx.layout.object_matches.unlink(missing_ok=True)

    def work(i: int) -> None:
        fid = ctx.fid(i)
        path = ctx.layout.points(fid)
        try:
            z = read_npz(path, ("label", "conf"))
            lab, conf = z["label"], z["conf"].astype(np.float32)
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable point labels ({exc})") from exc
        if tracks is None:
            export_labels(ctx.layout.export_label(fid), ctx.layout.export_conf(fid), lab, conf, ids)
            return
        lab, conf, instance, moving = tracks.point_objects(fid, lab, conf)
        export_labels(
            ctx.layout.export_label(fid),
            ctx.layout.export_conf(fid),
            lab,
            conf,
            ids,
            instance=instance,
            moving=moving,
            moving_ids=moving_ids,
        )

    out = ctx.each_frame("export", work, parallel=True)
    if tracks is not None:
        atomic_write_json(ctx.layout.object_matches, tracks.report())
    return out


def read_tracks(ctx: Ctx) -> CorrectedTracks | None:
    """The ``tracks`` stage's objects with the run's object corrections on top, or None when tracking is
    off."""
    if not ctx.cfg.tracking.enabled:
        return None
    return read_corrected_tracks(ctx.layout, ctx.schema)


# ---------------------------------------------------------------------------------------- the table
STAGE_TABLE: tuple[StageInfo, ...] = (
    StageInfo(
        "labels2d",
        "2D labels",
        "the 2D labeler's soft masks per frame",
        True,
        stage_labels2d,
        reads=("labeler",),
        inputs=_labeler_inputs,
        frame_files=FrameFiles(SequenceLayout.LABELS2D),
    ),
    StageInfo(
        "project",
        "Projection",
        "projection, per-mask depth clustering and painting per frame",
        True,
        stage_project,
        reads=("projection",),
        upstream=("labels2d",),
        frame_files=FrameFiles(SequenceLayout.OBSERVATIONS),
    ),
    StageInfo(
        "motion",
        "Moving objects",
        "moving objects from the per-scan projected labels, kept out of the fusion",
        False,
        stage_motion,
        upstream=("project",),
        # Only the tracking settings it uses (motion_inputs): trying another tracking.vote fuses nothing.
        inputs=motion_inputs,
        outputs=lambda lay, _cfg: (lay.motion,),
        switch="tracking.enabled",
        enabled=lambda cfg: motion_enabled(cfg.tracking),
        needs_poses=True,
    ),
    StageInfo(
        "fuse",
        "Voxel fusion",
        "Bayesian fusion of the observations (but moving objects') into the voxel grid",
        False,
        stage_fuse,
        reads=("fusion",),
        upstream=("project", "motion"),
        inputs=_fuse_inputs,
        outputs=lambda lay, _cfg: (lay.grid,),
        needs_poses=True,
    ),
    StageInfo(
        "smooth",
        "kNN smoothing",
        "distance-weighted kNN smoothing of the fused grid",
        False,
        stage_smooth,
        reads=("smoothing",),
        upstream=("fuse",),
        outputs=lambda lay, _cfg: (lay.grid_smooth,),
    ),
    StageInfo(
        "3dcn",
        "3D-CN",
        "3D Consistency Network rounds (when enabled)",
        False,
        stage_3dcn,
        reads=("consistency",),
        upstream=("project", "fuse", "smooth"),
        outputs=_3dcn_outputs,
        stale=lambda lay: lay.cn_grids(),
        switch="consistency.enabled",
        inputs=_3dcn_inputs,
        needs_poses=True,
    ),
    StageInfo(
        "label_points",
        "Point labels",
        "label and confidence of every point from the final grid",
        True,
        stage_label_points,
        upstream=("project", "smooth", "3dcn"),
        inputs=_label_points_inputs,
        frame_files=FrameFiles(SequenceLayout.POINTS),
        needs_poses=True,
    ),
    StageInfo(
        "tracks",
        "Objects",
        "segments of thing points per scan, tracks through the sequence, class votes and motion",
        False,
        stage_tracks,
        reads=("tracking",),
        upstream=("motion", "label_points"),
        inputs=lambda ctx: [[c.name, bool(c.thing)] for c in ctx.schema.classes],
        outputs=lambda lay, _cfg: (lay.tracks,),
        switch="tracking.enabled",
        needs_poses=True,
    ),
    StageInfo(
        "evaluate",
        "Evaluation",
        "point / voxel / 3D-CN metrics against ground truth",
        False,
        stage_evaluate,
        upstream=("project", "smooth", "3dcn", "label_points", "tracks"),
        # The paper's merge and the file's layout are inputs too: a change of either re-evaluates. So are
        # the moving ids when the run tracks objects: the moving-object IoU reads what the export writes.
        inputs=lambda ctx: (
            [[c.name, sorted(c.gt_ids), c.category] for c in ctx.schema.classes]
            + [PAPER_VIEW.to_dict(), {"metrics_version": METRICS_VERSION}]
            + object_corrections_inputs(ctx)
            + (
                [{"moving_ids": [int(x) for x in ctx.schema.moving_export_ids()]}]
                if ctx.cfg.tracking.enabled
                else []
            )
        ),
        outputs=lambda lay, _cfg: (lay.metrics,),
        needs_poses=True,
    ),
    StageInfo(
        "export",
        "Export",
        "SemanticKITTI .label and .conf files per scan",
        True,
        stage_export,
        upstream=("label_points", "tracks"),
        inputs=lambda ctx: [
            [int(x) for x in ctx.schema.export_ids()],
            [int(x) for x in ctx.schema.moving_export_ids()],
            *object_corrections_inputs(ctx),
        ],
        frame_files=FrameFiles(SequenceLayout.EXPORT, (".label", ".conf")),
    ),
)
"""Every stage in execution order."""

STAGES: tuple[str, ...] = tuple(s.name for s in STAGE_TABLE)
"""Stage names in execution order."""


__all__ = [
    "STAGES",
    "STAGE_TABLE",
    "CnMember",
    "camera_view_keys",
    "cn_rounds",
    "finish_fuse",
    "fused_observation",
    "observed_keys",
    "stage_3dcn",
    "stage_export",
    "stage_fuse",
    "stage_label_points",
    "stage_labels2d",
    "stage_motion",
    "stage_project",
    "stage_smooth",
    "stage_tracks",
]
