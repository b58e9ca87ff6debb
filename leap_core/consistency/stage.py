"""One 3D-CN iteration: select reliable labels, train, predict every point, fuse back
(docs/METHOD.md stage C).

The pipeline runs one round per iteration (1 by default, 2 allowed): :func:`iter_3dcn_round` over the
sequences of a run (one network per round, trained on the reliable labels of every sequence, fused back
into each sequence's own grid); :func:`run_3dcn_iteration` is its
one-sequence form. It reads
labels from the *smoothed* grid but adds the network's evidence to the *un-smoothed* fused grid, so the
smoothing that the pipeline applies afterwards is not applied twice.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch

from leap_core.consistency.backbone import PointSegmenter
from leap_core.consistency.config import ConsistencyConfig, fingerprint_form
from leap_core.consistency.data import PreparedCloud, TensorCloud
from leap_core.consistency.selection import lookup_counts, select_reliable, select_reliable_scans
from leap_core.consistency.train import (
    SourceNetwork,
    class_counts,
    config_to_dict,
    load_checkpoint,
    num_train_steps,
    predict_prepared,
    prepare_views,
    resolve_device,
    resolve_precision,
    save_checkpoint,
    torch_threads,
    train_model,
)
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import LeapError, ModelLoadError
from leap_core.fusion import (
    FusionConfig,
    VoxelGrid,
    fuse_dense,
    fuse_unique,
    merge_sparse,
    rows_in_sorted,
    voxel_keys,
    world_points,
)
from leap_core.heap import cap_heap_growth, release_free_memory
from leap_core.prefetch import prefetched
from leap_core.types import UNLABELED

FUSE_CHUNK_POINTS = 2_000_000
"""Network predictions are fused back in calls of about this many points (≈ 8·C bytes each), so memory
stays bounded on long sequences; between calls the grid is stored (float16, clipped) as after any fusion."""


def checkpoint_path(work_dir: str | Path, iteration: int) -> Path:
    """``work_dir/3dcn_iter{iteration}.pt``."""
    return Path(work_dir) / f"3dcn_iter{iteration}.pt"


def targets_path(work_dir: str | Path, iteration: int) -> Path:
    """``work_dir/.3dcn_targets_iter{iteration}.i16``: the round's training targets while it runs
    (:class:`TargetFile`; deleted when the round ends)."""
    return Path(work_dir) / f".3dcn_targets_iter{iteration}.i16"


def training_fingerprint(
    cfg: ConsistencyConfig,
    num_classes: int,
    frames: range | Sequence[tuple[str, range]],
    targets: Iterable[npt.NDArray[np.int16]],
    source: str | None = None,
) -> str:
    """Hash of everything the trained weights depend on: config, classes, frames, selected labels and, for a
    network fine-tuned from a source, the source file's digest (``source``; None: random weights, hashed as
    before sources existed).

    Stored as ``meta["fingerprint"]`` in each checkpoint; ``cfg`` is the iteration's config (seed offset
    included, as :func:`run_3dcn_iteration` derives it) and ``targets`` are :func:`reliable_targets` (of
    every part, in order; any iterable of them, e.g. a :class:`TargetFile`: they are hashed one scan at a
    time). ``frames`` is the frames of one sequence, or ``(name, frames)`` per part of a
    joint round over several sequences (:func:`iter_3dcn_round`)."""
    h = hashlib.sha256()
    # Fields that only matter after training (T, new voxels' margin, test-time views) or say only where
    # and in what arithmetic it runs (device, precision, threads) are left out: changing them reuses the
    # weights.
    untrained = (
        "enabled",
        "iterations",
        "temperature",
        "network_evidence",
        "new_voxel_margin",
        "test_time_views",
        "device",
        "precision",
        "num_threads",
    )
    trained = {k: v for k, v in fingerprint_form(config_to_dict(cfg)).items() if k not in untrained}
    head: dict[str, object] = {"cfg": trained, "C": num_classes}
    if source is not None:
        head["source"] = source
    if isinstance(frames, range):
        head["frames"] = [frames.start, frames.stop, frames.step]
    else:
        head["parts"] = [[name, fr.start, fr.stop, fr.step] for name, fr in frames]
    h.update(json.dumps(head, sort_keys=True).encode())
    for t in targets:
        h.update(np.ascontiguousarray(t).tobytes())
        h.update(b"|")
    return h.hexdigest()


class TargetFile:
    """Per-scan training targets kept on disk, not in memory: one flat int16 file, scan after scan.

    Written once by :meth:`write` (a temporary file in the 3D-CN's work folder), read back one scan at a
    time (:meth:`read`, iteration), so a sequence's targets cost 2 bytes per point of disk and only the
    scans in use of memory, however long the sequence. :meth:`close` deletes the file.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.offsets: list[int] = [0]
        """Start of scan j's targets (in int16 elements) at ``offsets[j]``; ``offsets[-1]`` = total."""

    @classmethod
    def write(cls, path: Path, targets: Iterable[npt.NDArray[np.int16]]) -> TargetFile:
        """Write every scan's targets in order (the file is replaced)."""
        out = cls(path)
        out.path.parent.mkdir(parents=True, exist_ok=True)
        with open(out.path, "wb") as fh:
            for t in targets:
                a = np.ascontiguousarray(t, dtype=np.int16)
                fh.write(a.data)
                out.offsets.append(out.offsets[-1] + len(a))
        return out

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def read(self, j: int) -> npt.NDArray[np.int16]:
        """(N_j,) int16 targets of the j-th scan written."""
        n = self.offsets[j + 1] - self.offsets[j]
        return np.fromfile(self.path, dtype=np.int16, count=n, offset=2 * self.offsets[j])

    def __iter__(self) -> Iterator[npt.NDArray[np.int16]]:
        return (self.read(j) for j in range(len(self)))

    def close(self) -> None:
        self.path.unlink(missing_ok=True)


def iter_reliable_targets(  # noqa: PLR0913, PLR0917  the selection's inputs, each named in reliable_targets
    seq: KittiSequence,
    smoothed: VoxelGrid,
    num_classes: int,
    cfg: ConsistencyConfig,
    voxel_size: float,
    frames: range,
    views: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None,
    progress: Callable[[], None] | None = None,
    erased: npt.NDArray[np.int64] | None = None,
    moving: MovingRows | None = None,
) -> Iterator[npt.NDArray[np.int16]]:
    """:func:`reliable_targets` one scan at a time, in frame order.

    With ``selection_scope="scan"`` each scan is selected alone (:func:`select_reliable` with seed
    ``cfg.seed + frame number``, what :func:`select_reliable_scans` does per scan), so only one scan's
    labels, confidences and view counts are held at a time. ``"sequence"`` ranks every point of the
    sequence together and so holds them all (≈ 14 bytes per point) while it selects.
    """
    voxel_labels = smoothed.voxel_labels()

    def scan(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        frame = seq.frame(i)
        keys = voxel_keys(world_points(frame.points, frame.pose), voxel_size)
        lab, conf = voxel_labels.at(keys)
        if erased is not None and erased.size:
            lab = np.where(np.isin(keys, erased), np.int16(UNLABELED), lab).astype(lab.dtype)
        if moving is not None:
            # A mover's points take their voxel's label where the mover is, i.e. what it passes.
            lab = lab.copy()
            lab[moving(i)] = UNLABELED
        support = lookup_counts(keys, *views) if views is not None else None
        if progress is not None:
            progress()
        return lab, conf, support

    if cfg.selection_scope == "scan":
        for i in frames:
            lab, conf, support = scan(i)
            mask = select_reliable(
                lab, conf, num_classes, cfg.share, cfg.seed + int(seq.frame_numbers[i]), support
            )
            yield np.where(mask, lab, np.int16(UNLABELED)).astype(np.int16)
        return
    labels: list[np.ndarray] = []
    confs: list[np.ndarray] = []
    supports: list[np.ndarray] = []
    for i in frames:
        lab, conf, support = scan(i)
        labels.append(lab)
        confs.append(conf)
        if support is not None:
            supports.append(support)
    masks = select_reliable_scans(
        labels,
        confs,
        num_classes,
        cfg.share,
        cfg.selection_scope,
        seed=cfg.seed,
        support=supports if views is not None else None,
        scan_numbers=[seq.frame_numbers[i] for i in frames],
    )
    for m, lab in zip(masks, labels, strict=True):
        yield np.where(m, lab, np.int16(UNLABELED)).astype(np.int16)


def reliable_targets(  # noqa: PLR0913, PLR0917  the selection's inputs, each named in the docstring
    seq: KittiSequence,
    smoothed: VoxelGrid,
    num_classes: int,
    cfg: ConsistencyConfig,
    voxel_size: float,
    frames: range,
    views: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None,
    progress: Callable[[], None] | None = None,
    erased: npt.NDArray[np.int64] | None = None,
    moving: MovingRows | None = None,
) -> list[npt.NDArray[np.int16]]:
    """Step 1 of :func:`run_3dcn_iteration`: per scan, the (N_s,) int16 training label of each point, its
    voxel's argmax class in ``smoothed`` where selected, ``UNLABELED`` elsewhere.

    Points take label and confidence of their voxel (``voxel_keys(world_points(points, pose))``); per class
    the ``cfg.share`` most confident become labels (:func:`select_reliable_scans`, scope
    ``cfg.selection_scope``, ties by ``views`` counts, then by ``cfg.seed``'s random order). ``progress()``
    is called once per scan. Points in ``erased`` voxels (map-scope erase corrections) are never labels,
    whatever class the fused evidence gives the voxel; nor are the point rows ``moving(i)`` of scan i (the
    ``motion`` stage's movers, kept out of the fusion: their voxel's label is what they pass). The
    pipeline streams the same targets to disk (:func:`iter_reliable_targets`, :class:`TargetFile`)
    instead of holding this list.
    """
    return list(
        iter_reliable_targets(
            seq,
            smoothed,
            num_classes,
            cfg,
            voxel_size,
            frames,
            views,
            progress=progress,
            erased=erased,
            moving=moving,
        )
    )


def iteration_config(cfg: ConsistencyConfig, iteration: int) -> ConsistencyConfig:
    """``cfg`` with the seed of round ``iteration`` (``seed + 1000·(iteration-1)``): the second round should
    not replay the first one's sampling."""
    return cfg if iteration == 1 else replace(cfg, seed=cfg.seed + 1000 * (iteration - 1))


Predict = Callable[[KittiSequence, range, Path], Iterable[tuple[np.ndarray, np.ndarray]]]
"""``predict(seq, frames, checkpoint)``: per frame index of ``frames``, in order, the ``(keys (N,) int64,
log-probabilities (N, C) float32)`` that the round's own inference gives for the network saved at
``checkpoint``; how :func:`iter_3dcn_round` is handed inference that runs elsewhere (Ray tasks:
:meth:`leap_core.pipeline.executor.RayExecutor.predictor`)."""

GridSource = VoxelGrid | Callable[[], VoxelGrid]
"""A grid, or a function that loads it when a round needs it (a joint round holds one sequence's grids at
a time)."""


KeySource = npt.NDArray[np.int64] | Callable[[], npt.NDArray[np.int64]]
"""Sorted voxel keys, or a function that makes them when the round needs them."""

MovingRows = Callable[[int], npt.NDArray[np.int32]]
"""Frame index → the point rows of that scan that belong to moving objects (``motion.npz``)."""


def _grid(source: GridSource) -> VoxelGrid:
    return source if isinstance(source, VoxelGrid) else source()


def _keys(source: KeySource | None) -> npt.NDArray[np.int64] | None:
    return source if source is None or isinstance(source, np.ndarray) else source()


@dataclass(frozen=True)
class RoundPart:
    """One sequence's share of a 3D-CN round (:func:`iter_3dcn_round`); a single-sequence run is the round
    of one part."""

    seq: KittiSequence
    """The sequence (scans and LiDAR→world poses)."""
    fused: GridSource
    """Its un-smoothed fused grid, which the network's predictions are added to (not modified)."""
    smoothed: GridSource
    """Its kNN-smoothed grid, which the training labels are read from."""
    frames: range | None = None
    """Scans to use (default all)."""
    views: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None = None
    """Sorted voxel keys and the number of frames that observed each
    (:func:`~leap_core.consistency.selection.view_counts`), the tie-break of the selection; None leaves
    ties to the seeded random order."""
    erased: npt.NDArray[np.int64] | None = None
    """Voxel keys the user erased to unlabeled (map-scope erase corrections): their points are never
    training labels, whatever class the fused evidence gives the voxel."""
    name: str = ""
    """The sequence's name in a joint round (part of the checkpoint's fingerprint when there are several
    parts)."""
    in_view: KeySource | None = None
    """Sorted unique keys of the voxels that hold a point inside a camera image in some frame (or a
    function that makes them): ``cfg.new_voxel_margin`` applies to the new voxels among them
    (:func:`keep_known_or_sure`). None counts every voxel as in view."""
    moving: MovingRows | None = None
    """The point rows of each scan that belong to moving objects (the ``motion`` stage's, which the fusion
    left out): never training labels, and their predictions are not fused back, so the round does not put
    the movers into the map again. None: no point is left out."""


def run_3dcn_iteration(  # noqa: PLR0913, PLR0917  a round's inputs, each named in the docstring
    seq: KittiSequence,
    fused: VoxelGrid,
    smoothed: VoxelGrid,
    num_classes: int,
    cfg: ConsistencyConfig,
    fusion_cfg: FusionConfig,
    work_dir: Path,
    iteration: int,
    progress: Callable[[int, int], None] | None = None,
    frames: range | None = None,
    views: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None = None,
    erased: npt.NDArray[np.int64] | None = None,
    in_view: npt.NDArray[np.int64] | None = None,
    source: SourceNetwork | None = None,
) -> VoxelGrid:
    """Self-train the 3D Consistency Network once on one sequence and fuse its predictions into ``fused``:
    :func:`iter_3dcn_round` with one :class:`RoundPart` (whose fields document the arguments; ``source``
    as there).

    Args:
        num_classes: C.
        cfg: 3D-CN parameters.
        fusion_cfg: voxel size and clipping of the grid.
        work_dir: folder for the checkpoint.
        iteration: 1 or 2; names the checkpoint and offsets the seed.
        progress: ``progress(done, total)`` over selection + training steps + inference scans.

    Returns:
        A new grid: ``fused`` plus the tempered network evidence.

    Raises:
        LeapError: when no point of any scan has a label to train on.
    """
    part = RoundPart(seq, fused, smoothed, frames, views, erased, in_view=in_view)
    return next(
        iter_3dcn_round([part], num_classes, cfg, fusion_cfg, work_dir, iteration, progress, source=source)
    )


def iter_3dcn_round(  # noqa: PLR0913, PLR0917  a round's inputs; its steps 1-3 share a counter
    parts: Sequence[RoundPart],
    num_classes: int,
    cfg: ConsistencyConfig,
    fusion_cfg: FusionConfig,
    work_dir: Path,
    iteration: int,
    progress: Callable[[int, int], None] | None = None,
    predict: Predict | None = None,
    source: SourceNetwork | None = None,
) -> Iterator[VoxelGrid]:
    """One 3D-CN round over one or several sequences: ONE network trained on the reliable labels of every
    part, its predictions fused back into each part's own grid. Yields each part's new grid in order;
    training happens before the first one.

    1. **Selection**, per part: every point of every scan goes to world coordinates with its pose, takes
       the label and confidence of its voxel in the part's ``smoothed`` grid, and per class the
       ``cfg.share`` most confident points (equal confidences: voxels more frames observed first, by
       ``views``) become training labels (:func:`reliable_targets`, per scan or over the part's sequence by
       ``cfg.selection_scope``: each sequence ranks its own points, its grid's confidences).
    2. **Training** (:func:`~leap_core.consistency.train.train_model`) on the scans of all parts, in part
       order, class weights from the labels of all parts, from random weights or fine-tuning ``source``;
       checkpoint ``work_dir/3dcn_iter{iteration}.pt``.
       A checkpoint whose fingerprint (config, classes, frames of every part, selected labels) matches is
       reused instead of retraining, so an interrupted run resumes here.
    3. **Inference** on every point of every scan of a part (inside and outside the camera view) and
       **fusion back** into that part's ``fused`` (:func:`fuse_back`, ``cfg.network_evidence``): by default
       each voxel adds the mean of its points' floored network log-probabilities with weight ``1/T``,
       ``L_n(i) ← L_n(i) + (1/T) · mean_{p in n} max(log P_net(i | p), log prob_floor)``. A point whose
       voxel is not in ``fused`` creates it (inside the camera view, ``part.in_view``, only where the network
       is sure of it: ``cfg.new_voxel_margin``), which is how points no camera saw get labels from 3D shape.
       ``T = ∞`` (weight 0) yields every ``fused`` unchanged.

    With one part this is exactly the single-sequence round (:func:`run_3dcn_iteration`): the scans are
    visited in the same order, the fingerprint has the single-sequence form.

    Args:
        parts: the sequences of the round.
        num_classes: C.
        cfg: 3D-CN parameters.
        fusion_cfg: voxel size and clipping of the grids.
        work_dir: folder for the checkpoint.
        iteration: 1 or 2; names the checkpoint and offsets the seed.
        progress: ``progress(done, total)`` over selection + training steps + inference scans (all parts).
        predict: step 3's predictions from the checkpoint instead of this process (:data:`Predict`; the
            same values in the same order, so the same grids); None = here.
        source: the network training starts from (``finetune_lr``, ``finetune_min_steps``); None = random
            weights.

    Raises:
        LeapError: when no point of any scan has a label to train on, or a grid has another C.
    """
    if not parts:
        raise LeapError("3D-CN: a round needs at least one sequence")
    frame_sets = [range(len(p.seq)) if p.frames is None else p.frames for p in parts]
    n = sum(len(f) for f in frame_sets)
    work_dir = Path(work_dir)
    ckpt_path = checkpoint_path(work_dir, iteration)
    cfg_it = iteration_config(cfg, iteration)
    train_steps = num_train_steps(n, cfg, finetune=source is not None)
    total = n + train_steps + n
    done = 0

    def tick(k: int = 1) -> None:
        nonlocal done
        done += k
        if progress is not None:
            progress(done, total)

    def check(grid: VoxelGrid, what: str, part: RoundPart) -> VoxelGrid:
        if grid.num_classes != num_classes:
            where = f" of sequence {part.name}" if part.name else ""
            raise LeapError(
                f"3D-CN: the {what} grid{where} has {grid.num_classes} classes, schema has {num_classes}"
            )
        return grid

    if cfg.temperature == math.inf:
        tick(total)
        for part in parts:
            yield check(_grid(part.fused), "fused", part)
        return

    # Freed tensors and arrays of 1 MiB or more go back to the system from here on; without this the
    # round's resident size grows with its steps and scans (leap_core.heap, README "Memory").
    cap_heap_growth()
    # 1. reliable labels, per part (one smoothed grid in memory at a time), streamed scan by scan into a
    # file in the work folder: no per-point array of the whole round is held (docs/METHOD.md, "Memory")
    counts = np.zeros(num_classes, np.int64)

    def all_targets() -> Iterator[npt.NDArray[np.int16]]:
        for part, frames in zip(parts, frame_sets, strict=True):
            smoothed = check(_grid(part.smoothed), "smoothed", part)
            for t in iter_reliable_targets(
                part.seq,
                smoothed,
                num_classes,
                cfg_it,
                fusion_cfg.voxel_size,
                frames,
                part.views,
                progress=tick,
                erased=part.erased,
                moving=part.moving,
            ):
                counts[:] += class_counts(t, num_classes)
                yield t
            del smoothed

    targets = TargetFile.write(targets_path(work_dir, iteration), all_targets())
    try:
        model = _train(
            parts,
            frame_sets,
            targets,
            counts,
            num_classes,
            cfg_it,
            ckpt_path,
            iteration,
            progress,
            done,
            total,
            source,
        )
    finally:
        targets.close()  # the labels are in the weights now

    done += train_steps
    if progress is not None:
        progress(done, total)

    # 3. per part: predict every point, fuse back into the part's grid with weight 1/T
    device = resolve_device(cfg)
    model = model.to(device)

    for part, frames in zip(parts, frame_sets, strict=True):
        fused = check(_grid(part.fused), "fused", part)
        scans = (
            predict_frames(model, part.seq, frames, cfg, fusion_cfg.voxel_size, tick)
            if predict is None
            else _ticked(predict(part.seq, frames, ckpt_path), tick)
        )
        in_view = _keys(part.in_view) if cfg.new_voxel_margin > 0 else None
        grid = fuse_back(
            fused,
            scans if part.moving is None else without_rows(frames, scans, part.moving),
            num_classes,
            cfg.temperature,
            fusion_cfg,
            cfg.network_evidence,
            new_voxel_margin=cfg.new_voxel_margin,
            in_view=in_view,
        )
        del fused
        release_free_memory()
        yield grid
        del grid


def predict_frames(
    model: PointSegmenter,
    seq: KittiSequence,
    frames: Sequence[int],
    cfg: ConsistencyConfig,
    voxel_size: float,
    tick: Callable[[], None] | None = None,
) -> Iterator[tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]]:
    """Step 3's inference, one scan at a time: per frame of ``frames``, the (N,) voxel keys of its points
    in world coordinates and their (N, C) network log-probabilities
    (:func:`~leap_core.consistency.train.predict_log_probs`, on ``model``'s device, ``cfg.num_threads``
    torch threads, averaged over ``cfg.test_time_views`` views, in ``cfg.precision``). The scan being
    predicted and at most two after it, prepared meanwhile on a background thread, are held; the memory a
    forward pass freed goes back to the system before its scan is yielded
    (:func:`~leap_core.heap.release_free_memory`). ``tick()`` after each scan."""
    device = next(model.parameters()).device
    precision = resolve_precision(cfg, device)
    with torch_threads(cfg.num_threads):
        # The kd-tree queries of the next scan leave one thread to the forward pass they overlap with.
        workers = max(1, torch.get_num_threads() - 1)

        def prepared() -> Iterator[tuple[npt.NDArray[np.int64], list[PreparedCloud | TensorCloud]]]:
            for i in frames:
                frame = seq.frame(i)
                keys = voxel_keys(world_points(frame.points, frame.pose), voxel_size)
                yield keys, prepare_views(frame.points, model.cfg, cfg.test_time_views, device, workers)

        # The next scan is read and prepared on a background thread while this one is predicted.
        for keys, clouds in prefetched(prepared()):
            logp = predict_prepared(model, clouds, device, precision)
            del clouds
            release_free_memory()  # the forward pass's activations, freed by now
            if tick is not None:
                tick()
            yield keys, logp


def without_rows(
    frames: Iterable[int],
    predictions: Iterable[tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]],
    rows: MovingRows,
) -> Iterator[tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]]:
    """Per scan of ``frames`` (in order, as ``predictions`` come), its ``(keys, logp)`` without the point
    rows ``rows(i)``."""
    for i, (keys, logp) in zip(frames, predictions, strict=True):
        keep = np.ones(keys.shape[0], bool)
        keep[rows(i)] = False
        yield (keys, logp) if keep.all() else (keys[keep], logp[keep])


def _ticked(
    pairs: Iterable[tuple[np.ndarray, np.ndarray]], tick: Callable[[], None]
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``pairs``, calling ``tick()`` before each (one per scan predicted, as the local loop reports)."""
    for pair in pairs:
        tick()
        yield pair


def _train(  # noqa: PLR0913, PLR0917  step 2 of iter_3dcn_round, which names each input
    parts: Sequence[RoundPart],
    frame_sets: list[range],
    targets: TargetFile,
    counts: npt.NDArray[np.int64],
    num_classes: int,
    cfg_it: ConsistencyConfig,
    ckpt_path: Path,
    iteration: int,
    progress: Callable[[int, int], None] | None,
    done: int,
    total: int,
    source: SourceNetwork | None = None,
) -> PointSegmenter:
    """Step 2 of :func:`iter_3dcn_round`: the round's network, trained on ``targets`` from random weights or
    from ``source`` (or a checkpoint whose fingerprint matches)."""
    if counts.sum() == 0:
        raise LeapError(
            "3D-CN: no point of any scan has a voxel label to train on (is the fused grid empty?)"
        )
    # 2. train (or reuse a matching checkpoint)
    named: range | list[tuple[str, range]] = (
        frame_sets[0] if len(parts) == 1 else [(p.name, f) for p, f in zip(parts, frame_sets, strict=True)]
    )
    fingerprint = training_fingerprint(
        cfg_it, num_classes, named, targets, None if source is None else source.digest
    )
    model = None
    if ckpt_path.is_file():
        try:
            ck = load_checkpoint(ckpt_path)
            if ck.meta.get("fingerprint") == fingerprint:
                model = ck.model
        except ModelLoadError:
            model = None
    if model is None:
        # Scan j of the round (parts in order, each part's frames in order) → its sequence and frame index;
        # train_model only passes these positions back to load().
        scans = [(p.seq, i) for p, frames in zip(parts, frame_sets, strict=True) for i in frames]

        def load(j: int) -> tuple[np.ndarray, np.ndarray]:
            seq, i = scans[j]
            return seq.frame(i).points, targets.read(j)

        base = done
        model, stats = train_model(
            load,
            range(len(scans)),
            num_classes,
            cfg_it,
            progress=(lambda d, _t: progress(base + d, total)) if progress is not None else None,
            class_counts=counts,
            init=None if source is None else source.model,
        )
        save_checkpoint(
            ckpt_path,
            model,
            cfg_it,
            meta={
                "fingerprint": fingerprint,
                "iteration": iteration,
                "steps": stats.steps,
                "losses": stats.losses,
                "seconds": stats.seconds,
                "class_counts": counts.tolist(),
                **({} if source is None else {"source": source.digest}),
                "frames": (
                    [named.start, named.stop, named.step]
                    if isinstance(named, range)
                    else [[name, f.start, f.stop, f.step] for name, f in named]
                ),
            },
        )
    return model


def voxel_mean_log_probs(
    predictions: Iterable[tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]],
    num_classes: int,
    prob_floor: float,
    chunk_points: int = FUSE_CHUNK_POINTS,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """Per voxel, the mean floored log-probability of all predictions that fall in it (over all scans).

    ``m_n(i) = (1 / |P_n|) · Σ_{p ∈ P_n} max(logp_p(i), log prob_floor)``.

    Args:
        predictions: per scan ``(keys (N,) int64, logp (N, C) float32)``; consumed lazily.
        num_classes: C.
        prob_floor: the fusion's probability floor.
        chunk_points: points reduced at once (bounds memory; the result does not depend on it beyond float
            rounding).

    Returns:
        Sorted unique keys (V,), means (V, C) float32 (each ≥ log prob_floor), point counts (V,) int64.
    """
    floor = float(np.log(prob_floor))
    acc_keys = np.zeros(0, np.int64)
    acc_sum = np.zeros((0, num_classes), np.float32)
    acc_cnt = np.zeros(0, np.int64)
    # The chunk being summed: its sorted keys, float32 sums and counts, grown scan by scan. Each scan is
    # added as it arrives and then dropped, so at most one scan's predictions are held; the sums are the
    # very float32 additions of summing the chunk's scans concatenated (every voxel's row starts at 0 and
    # adds its points in scan and point order; index_add_ adds rows in index order), and the chunk joins
    # the accumulator at the same point count as before, so the means are bit for bit the same.
    ck_keys = np.zeros(0, np.int64)
    ck_sum = torch.zeros((0, num_classes), dtype=torch.float32)
    ck_cnt = np.zeros(0, np.int64)
    pending = 0

    def add_scan(keys: np.ndarray, logp: np.ndarray) -> None:
        nonlocal ck_keys, ck_sum, ck_cnt
        uk = np.unique(keys)
        if len(ck_keys) == 0 or not np.isin(uk, ck_keys, assume_unique=True).all():
            grown = np.union1d(ck_keys, uk)
            old_rows = torch.from_numpy(np.searchsorted(grown, ck_keys))
            sums = torch.zeros((len(grown), num_classes), dtype=torch.float32)
            sums.index_copy_(0, old_rows, ck_sum)
            cnt = np.zeros(len(grown), np.int64)
            cnt[old_rows.numpy()] = ck_cnt
            ck_keys, ck_sum, ck_cnt = grown, sums, cnt
        rows = np.searchsorted(ck_keys, keys)
        # A prediction that came back from Ray is a read-only view of the object store, which torch
        # warns about; clamp_min copies anyway, so the copy here costs only the read-only case.
        lp = torch.from_numpy(np.require(logp, np.float32, "W")).clamp_min(floor)
        ck_sum.index_add_(0, torch.from_numpy(rows), lp)
        ck_cnt += np.bincount(rows, minlength=len(ck_keys))

    def reduce() -> None:
        nonlocal acc_keys, acc_sum, acc_cnt, ck_keys, ck_sum, ck_cnt
        # In place (fusion.merge_sparse): the (V, C) sums are grown, never copied whole; new voxels get
        # 0 + chunk sums, as a zero-filled merge would give them.
        acc_keys, (acc_sum, acc_cnt) = merge_sparse(
            acc_keys, [acc_sum, acc_cnt], ck_keys, [np.array(ck_sum.numpy()), ck_cnt]
        )
        ck_keys = np.zeros(0, np.int64)
        ck_sum = torch.zeros((0, num_classes), dtype=torch.float32)
        ck_cnt = np.zeros(0, np.int64)

    for keys, logp in predictions:
        if logp.ndim != 2 or logp.shape != (len(keys), num_classes):
            raise ValueError(f"predictions must be keys (N,) and logp (N, {num_classes}), got {logp.shape}")
        add_scan(np.asarray(keys, np.int64), logp)
        pending += len(keys)
        del keys, logp  # the generator's next scan need not share memory with this one
        if pending >= chunk_points:
            reduce()
            pending = 0
    if pending:
        reduce()
    denom = np.maximum(acc_cnt, 1)[:, None].astype(np.float32)
    acc_sum /= denom  # the means, in place
    return acc_keys, acc_sum, acc_cnt


def keep_known_or_sure(
    known: npt.NDArray[np.int64],
    keys: npt.NDArray[np.int64],
    means: npt.NDArray[np.float32],
    min_margin: float,
    in_view: npt.NDArray[np.int64] | None = None,
    chunk: int = 1 << 20,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """The rows of per-voxel network means to fuse: every voxel the grid already has, every voxel outside
    the camera view, and a new voxel inside it only where the network is sure of it.

    Row n is kept when ``keys[n] ∈ known``, or ``keys[n] ∉ in_view``, or ``m_n(c1) − m_n(c2) ≥
    min_margin``, with ``m_n`` the voxel's mean floored log-probabilities (:func:`voxel_mean_log_probs`) and
    c1, c2 its best and second-best class: the network's mean evidence for its class beats the runner-up by
    ``min_margin`` nats (at most ``−log prob_floor``). A voxel in view that is not in ``known`` held points
    that a camera saw and no mask labeled (or depth clustering took out of its mask); one outside every
    view no camera could label, and the network is all there is. ``min_margin ≤ 0`` keeps every row.

    Compacts in place: ``keys`` and ``means`` are overwritten chunk by chunk and views of their first kept
    rows are returned, so no second (V, C) array is made.

    Args:
        known: (K,) int64 sorted unique keys of the grid the means are fused into.
        keys: (V,) int64 sorted unique keys of the means.
        means: (V, C) float32.
        min_margin: nats.
        in_view: sorted unique keys of the voxels holding a point inside a camera image (in any frame);
            None counts every voxel as in view.
        chunk: rows handled at once (the result does not depend on it).

    Returns:
        ``(keys[:w], means[:w])``: the kept rows, in their order.
    """
    if min_margin <= 0 or len(keys) == 0:
        return keys, means
    w = 0
    for s in range(0, len(keys), chunk):
        k = keys[s : s + chunk]
        m = means[s : s + chunk]
        if m.shape[1] > 1:
            top = np.partition(m, -2, axis=1)
            margin = top[:, -1] - top[:, -2]
        else:  # one class: nothing to confuse it with
            margin = np.full(len(m), np.inf, np.float32)
        keep = (rows_in_sorted(known, k) >= 0) | (margin >= min_margin)
        if in_view is not None:
            keep |= rows_in_sorted(in_view, k) < 0
        n = int(keep.sum())
        # w <= s: the kept rows move up over rows already read, never over unread ones.
        keys[w : w + n] = k[keep]
        means[w : w + n] = m[keep]
        w += n
    return keys[:w], means[:w]


def fuse_back(  # noqa: PLR0913  the fusion's inputs, each named in the docstring
    grid: VoxelGrid,
    predictions: Iterable[tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]],
    num_classes: int,
    temperature: float,
    fusion_cfg: FusionConfig,
    evidence: str = "voxel",
    *,
    new_voxel_margin: float = 0.0,
    in_view: npt.NDArray[np.int64] | None = None,
    chunk_points: int = FUSE_CHUNK_POINTS,
) -> VoxelGrid:
    """Tempered Bayesian fusion of per-point network log-probabilities into a grid.

    With ``f_p(i) = max(log P_net(i | p), log prob_floor)`` and P_n the predictions in voxel n:

    - ``evidence="voxel"``: ``L_n(i) ← L_n(i) + (1/T) · mean_{p ∈ P_n} f_p(i)``: the network's view of a
      voxel counts as ONE observation, however many points and scans fall in it;
    - ``evidence="point"``: ``L_n(i) ← L_n(i) + (1/T) · Σ_{p ∈ P_n} f_p(i)``: every point prediction counts
      like one painted camera point.

    Then stored as every grid (row max 0, clipped at ``-logp_clip``, float16). ``T = 1`` trusts the network
    like one camera observation; ``T → ∞`` ignores it: ``T = inf`` returns ``grid`` itself (no new voxels
    either, since zero-weight evidence carries no class information). Voxels of ``P`` missing from ``grid``
    are created, so points no camera saw get the network's label; with ``new_voxel_margin > 0`` (voxel
    evidence only), those inside the camera view only where the network is sure (:func:`keep_known_or_sure`),
    the others stay unlabeled.

    Args:
        grid: grid to update (not modified).
        predictions: per scan, ``(keys (N,) int64, logp (N, C) float32)``; consumed lazily.
        num_classes: C.
        temperature: T > 0 (``math.inf`` allowed).
        fusion_cfg: voxel size, probability floor and clipping.
        evidence: "voxel" or "point" (see above).
        new_voxel_margin: nats; a voxel not in ``grid`` is created only where its mean network
            log-probability beats the runner-up class's by this much (0: every one). Voxel evidence only.
        in_view: sorted unique keys of the voxels inside a camera view (the margin applies to those only);
            None: to every new voxel.
        chunk_points: points per reduction / :func:`fuse_dense` call.
    """
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    if evidence not in ("voxel", "point"):
        raise ValueError(f"evidence must be 'voxel' or 'point', got {evidence!r}")
    if new_voxel_margin > 0 and evidence != "voxel":
        raise ValueError(
            f"new_voxel_margin applies to voxel evidence only, got {new_voxel_margin} with {evidence!r}"
        )
    if temperature == math.inf:
        return grid
    weight = 1.0 / temperature
    if evidence == "voxel":
        keys, means, _ = voxel_mean_log_probs(predictions, num_classes, fusion_cfg.prob_floor, chunk_points)
        keys, means = keep_known_or_sure(grid.keys, keys, means, new_voxel_margin, in_view)
        # One row per voxel: fuse_dense's values, computed in the means' own buffer (fuse_unique).
        return fuse_unique(grid, keys, means, num_classes, fusion_cfg, weight=weight)
    out = grid
    pend_keys: list[np.ndarray] = []
    pend_logp: list[np.ndarray] = []
    pending = 0
    for keys, logp in predictions:
        pend_keys.append(keys)
        pend_logp.append(logp)
        pending += len(keys)
        if pending >= chunk_points:
            out = fuse_dense(
                out,
                np.concatenate(pend_keys),
                np.concatenate(pend_logp),
                num_classes,
                fusion_cfg,
                weight=weight,
            )
            pend_keys, pend_logp, pending = [], [], 0
    if pend_keys:
        out = fuse_dense(
            out, np.concatenate(pend_keys), np.concatenate(pend_logp), num_classes, fusion_cfg, weight=weight
        )
    return out


__all__ = [
    "FUSE_CHUNK_POINTS",
    "GridSource",
    "KeySource",
    "MovingRows",
    "Predict",
    "RoundPart",
    "TargetFile",
    "checkpoint_path",
    "fuse_back",
    "iter_3dcn_round",
    "iter_reliable_targets",
    "iteration_config",
    "keep_known_or_sure",
    "predict_frames",
    "reliable_targets",
    "run_3dcn_iteration",
    "targets_path",
    "training_fingerprint",
    "voxel_mean_log_probs",
    "without_rows",
]
