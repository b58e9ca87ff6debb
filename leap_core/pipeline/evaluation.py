"""The evaluate stage and the result tables of a run (``metrics.json``).

Rows: ``point`` (projection only), ``voxel`` (the smoothed fused grid), with the 3D-CN ``+3D-CN x{i}`` per
round and, when the run tracks objects, ``objects`` (the final row with the tracks' classes: the exported
labels); ``objects`` in ``metrics.json`` holds the object scores. Protocols (:data:`PROTOCOLS`): ``camera``
(points inside the image, unlabeled predictions ignored: the paper's), ``common`` (the camera view's points
that every row labels, so the rows are scored on the same points) and ``all`` (every point, unlabeled = miss),
over the schema's classes; and ``paper`` (:data:`PAPER`): the camera protocol's confusion matrices summed into
the 11 merged classes of the paper's Table 1 (:data:`leap_core.eval_view.PAPER_VIEW`), present only for a
SemanticKITTI schema.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError, LeapError
from leap_core.eval_view import PAPER_VIEW
from leap_core.export import labels_to_raw
from leap_core.fusion import voxel_keys, world_points
from leap_core.io_utils import atomic_write_json, read_npz
from leap_core.metrics import Metrics, confusion_matrix, format_table, merge_confusion, metrics_from_confusion
from leap_core.panoptic import MOS_MOVING, AssociationCounts, MosCounts, PanopticCounts, mos_states
from leap_core.pipeline.context import load_view, ordered_map
from leap_core.pipeline.metrics_file import RowScores, RunMetrics, SequenceMetrics, ViewSpec
from leap_core.pipeline.object_corrections import CorrectedTracks, read_corrected_tracks
from leap_core.run_layout import RunLayout, SequenceLayout
from leap_core.smoothing import SmoothedGrid
from leap_core.types import UNLABELED

if TYPE_CHECKING:
    from leap_core.datasets.kitti import KittiSequence
    from leap_core.pipeline.context import Ctx

ROW_POINT = "point"
ROW_VOXEL = "voxel"
ROW_OBJECTS = "objects"
"""The row of what the export writes when the run tracks objects: the final row with each point of a voted
track (``tracking.vote``) given its track's class (docs/METHOD.md B.6)."""
COMMON = "common"
PROTOCOLS: dict[str, str] = {
    "camera": "camera view: points inside the image, unlabeled predictions ignored (the paper's protocol)",
    COMMON: "camera view, same points: only the points inside the image that every row labels",
    "all": "all points: every point of every scan, an unlabeled prediction counts as a miss",
}
"""metrics.json keys of the protocols counted point by point over the schema's classes, and what they
measure. ``camera`` scores each row on the points it labels, so a row that labels more points (the voxel
row over the point row, the 3D-CN over the voxel row, which labels every point) is scored on more, and
harder, points; ``common`` compares the rows on one set of points. Files written before ``common`` existed
lack it (:data:`OPTIONAL_PROTOCOLS`)."""

PAPER = "paper"
"""metrics.json key of the paper's protocol: ``camera`` merged into the 11 classes of the paper's Table 1."""
OPTIONAL_PROTOCOLS = (COMMON, PAPER)
"""Protocols a ``metrics.json`` may lack: ``paper`` for a schema other than SemanticKITTI's, ``common`` in
files written before it existed."""
METRICS_VERSION = 3
"""Layout of ``metrics.json`` (2: the ``common`` protocol; 3: the object scores). Part of the evaluate
stage's fingerprint, so a finished run is evaluated again, from its stored outputs, on its next
``leap run``."""
PAPER_DESCRIPTION = (
    "the paper's Table 1: camera view, unlabeled predictions ignored, SemanticKITTI's 19 classes merged into "
    f"{len(PAPER_VIEW.classes)} ({', '.join(PAPER_VIEW.names)})"
)
IGNORES_UNLABELED: dict[str, bool] = {"camera": True, COMMON: True, "all": False, PAPER: True}
"""Per protocol key: whether an unlabeled prediction is ignored (True) or a miss (False)."""


def with_paper_protocol(m: SequenceMetrics) -> SequenceMetrics:
    """``m`` with the paper's protocol, from its ``camera`` confusion matrices: per row
    ``merge_confusion(camera confusion, PAPER_VIEW mapping)`` → ``tables["paper"]``, the view's classes →
    ``paper_view``, the description → ``protocols["paper"]``.

    When the view does not apply to ``m.class_names`` (not SemanticKITTI's 19 classes), nothing of the
    protocol is added but ``protocol_notes["paper"]``, a sentence saying why.
    """
    problem = PAPER_VIEW.problem(m.class_names)
    mapping = PAPER_VIEW.mapping(m.class_names)
    if problem is not None or mapping is None:
        return dataclasses.replace(m, protocol_notes={**m.protocol_notes, PAPER: f"not computed: {problem}"})
    camera = m.table("camera")
    return dataclasses.replace(
        m,
        protocols={**m.protocols, PAPER: PAPER_DESCRIPTION},
        tables={
            **m.tables,
            PAPER: {r: RowScores.of(paper_metrics(camera[r].confusion_matrix, mapping)) for r in m.rows},
        },
        paper_view=ViewSpec.from_dict(PAPER_VIEW.to_dict()),
    )


def paper_metrics(confusion: npt.ArrayLike, mapping: npt.NDArray[np.int64]) -> Metrics:
    """The paper's view of a (C, C+1) confusion matrix over the schema's classes: merged into the 11
    classes (``merge_confusion`` with ``mapping = PAPER_VIEW.mapping(class_names)``) and scored with
    unlabeled predictions ignored."""
    merged = merge_confusion(np.asarray(confusion, np.int64), mapping, len(PAPER_VIEW.classes))
    return metrics_from_confusion(
        merged, PAPER_VIEW.names, PAPER_VIEW.categories, ignore_unlabeled_pred=IGNORES_UNLABELED[PAPER]
    )


def common_points(
    in_view: npt.NDArray[np.bool_], preds: Iterable[npt.NDArray[np.int16]]
) -> npt.NDArray[np.bool_]:
    """(N,) bool: the points of the ``common`` protocol, ``in_view ∧ ⋀_r (pred_r ≠ UNLABELED)`` over the
    rows' (N,) predictions."""
    out = np.array(in_view, dtype=bool)
    for pred in preds:
        out &= pred != UNLABELED
    return out


def cn_row(iteration: int) -> str:
    """Result-table row name of the 3D-CN after ``iteration`` rounds ("+3D-CN x1")."""
    return f"+3D-CN x{iteration}"


def no_ground_truth(seq: KittiSequence, frames: Iterable[int]) -> str | None:
    """Why the scans ``frames`` (indices) of ``seq`` cannot be evaluated, or None when each has its
    ``.label`` file: ``no ground truth``, followed by the first entry of ``labels/`` that stands where a
    file should (``: .../labels/000003.label is a directory, not a file``)."""
    missing = [i for i in frames if not seq.label_path(i).is_file()]
    if not missing:
        return None
    for i in missing:
        problem = seq.label_problem(i)
        if problem is not None:
            return f"no ground truth: {seq.label_path(i)} is {problem}"
    return "no ground truth"


def stage_evaluate(ctx: Ctx) -> dict[str, Any]:  # noqa: PLR0915  # one pass over the frames feeds every score
    """Point / voxel / +3D-CN rows against ground truth, every protocol → ``metrics.json``.

    Skipped (status "skipped") when a processed frame has no ground-truth ``.label`` file; the note says
    which entry of ``labels/`` stands in place of one, when one does (``labels/000003.label is a
    directory, not a file``).
    """
    seq, schema, lay = ctx.seq, ctx.schema, ctx.layout
    note = no_ground_truth(seq, ctx.frames)
    if note is not None:
        return {"status": "skipped", "note": note}
    c = schema.num_classes
    # None: read from points/ (the projection-only labels, and the final grid's labels that label_points
    # already looked up); a grid: looked up here (the voxel row when the 3D-CN came after it).
    rows: dict[str, SmoothedGrid | None] = {ROW_POINT: None}
    cn = ctx.cfg.consistency
    if cn.enabled:
        rows[ROW_VOXEL] = SmoothedGrid.load(lay.grid_smooth)
        for it in range(1, cn.iterations + 1):
            rows[cn_row(it)] = None if it == cn.iterations else SmoothedGrid.load(lay.grid_smooth_3dcn(it))
        final_row = cn_row(cn.iterations)
    else:
        rows[ROW_VOXEL] = None
        final_row = ROW_VOXEL
    need_keys = any(v is not None for v in rows.values())
    vs = ctx.cfg.fusion.voxel_size
    objects = ObjectEvaluation.of(ctx)
    from_grid = dict(rows)
    if objects is not None:
        rows[ROW_OBJECTS] = None

    def counts(i: int) -> tuple[dict[str, dict[str, npt.NDArray[np.int64]]], dict[str, int], int, int]:
        """One frame's confusion matrices (protocol → row → (C, C+1)), labeled points per row, points and
        points in view: integers, so their sum does not depend on the order frames finish."""
        frame = seq.frame(i)
        n, in_view = load_view(lay.observation(ctx.fid(i)))
        stored = _read_point_labels(lay.points(ctx.fid(i)), final_row)
        # The scan itself is read only to place its points in the grid: its size gives the count, and
        # it is most of the bytes a frame has.
        if n != frame.num_points or stored[ROW_POINT].shape[0] != n:
            raise DatasetError(seq.scan_path(i), f"{frame.num_points} points but the run's outputs have {n}")
        gt = schema.map_gt(frame.labels)
        keys = voxel_keys(world_points(frame.points, frame.pose), vs) if need_keys else np.zeros(0, np.int64)
        preds = {
            name: stored[name] if grid is None else grid.labels_at(keys)[0]
            for name, grid in from_grid.items()
        }
        if objects is not None:
            preds[ROW_OBJECTS] = objects.add_scan(ctx.fid(i), frame.labels, gt, preds[final_row], in_view)
        common = common_points(in_view, preds.values())
        conf: dict[str, dict[str, npt.NDArray[np.int64]]] = {p: {} for p in PROTOCOLS}
        labeled: dict[str, int] = {}
        for name, pred in preds.items():
            labeled[name] = int((pred != UNLABELED).sum())
            conf["all"][name] = confusion_matrix(gt, pred, c)
            conf["camera"][name] = confusion_matrix(gt[in_view], pred[in_view], c)
            conf[COMMON][name] = confusion_matrix(gt[common], pred[common], c)
        return conf, labeled, n, int(in_view.sum())

    conf = {p: {r: np.zeros((c, c + 1), np.int64) for r in rows} for p in PROTOCOLS}
    n_points = n_view = 0
    labeled_any = dict.fromkeys(rows, 0)
    total = len(ctx.frames)
    ctx.tick("evaluate", 0, total)
    # Frames are read on threads (their files' reads overlap other frames' maths); integer sums.
    with contextlib.closing(ordered_map(counts, ctx.frames, ctx.frame_threads)) as results:
        for k, (f_conf, f_labeled, n, n_in_view) in enumerate(results, start=1):
            n_points += n
            n_view += n_in_view
            for name in rows:
                labeled_any[name] += f_labeled[name]
                for p in PROTOCOLS:
                    conf[p][name] += f_conf[p][name]
            if k < total:
                ctx.tick("evaluate", k, total)
    ctx.tick("evaluate", total, total)
    pl = labeled_any[ROW_POINT]
    out = SequenceMetrics(
        class_names=schema.names,
        categories=schema.categories(),
        rows=list(rows),
        protocols=dict(PROTOCOLS),
        tables={
            p: {
                r: RowScores.of(
                    metrics_from_confusion(
                        conf[p][r],
                        schema.names,
                        schema.categories(),
                        ignore_unlabeled_pred=IGNORES_UNLABELED[p],
                    )
                )
                for r in rows
            }
            for p in PROTOCOLS
        },
        # Frame numbers (first, last + 1), as --frames takes them; positions would shift with a subset.
        frames=[seq.frame_numbers[ctx.frames[0]], seq.frame_numbers[ctx.frames[-1]] + 1],
        n_points=n_points,
        n_points_in_view=n_view,
        # Points (ground truth or not) that got a label, per row, and their share of all points: what the
        # exported .label files leave unlabeled is 1 - that share of the final row.
        labeled_points={r: labeled_any[r] for r in rows},
        labeled_share_all_points={r: (labeled_any[r] / n_points if n_points else None) for r in rows},
        labeler=ctx.cfg.labeler,
        coverage_ratio={r: (labeled_any[r] / pl if pl else None) for r in rows},
        objects=None if objects is None else objects.scores(),
    )
    atomic_write_json(lay.metrics, with_paper_protocol(out).to_dict())
    return {}


ASSOC_BATCH = 1 << 16
"""Rows of scans' S_assoc tables gathered before they are summed into the sequence's
(:class:`ObjectEvaluation`)."""


class ObjectEvaluation:
    """The object scores of one sequence (:mod:`leap_core.panoptic`), summed scan by scan from the labels
    an export writes: the final labels with the ``tracks`` stage's classes, ids and moving ids, and the
    run's object corrections on top (:class:`CorrectedTracks`). Scans may
    be added from several threads in any order: a lock guards the integer sums, and each scan's panoptic
    counts (float IoU sums) are kept apart and summed in frame order, so the scores do not depend on the
    order frames finish."""

    def __init__(self, ctx: Ctx, tracks: CorrectedTracks) -> None:
        schema = ctx.schema
        self.schema = schema
        self.tracks = tracks
        self.things = schema.things()
        self.has_moving = any(c.moving_id is not None for c in schema.classes)
        self.per_scan: dict[str, dict[str, PanopticCounts]] = {}
        self.order = ctx.frame_ids()
        self.mos = MosCounts()
        c = schema.num_classes
        self.moving_right = np.zeros(c, np.int64)
        self.moving_total = np.zeros(c, np.int64)
        # S_assoc's counts: scans' tables wait in ``pending`` until they hold as many rows as ``assoc``
        # (or ASSOC_BATCH), then are summed in at once, so memory follows the tracks, not the points.
        self.assoc = AssociationCounts()
        self.pending: list[AssociationCounts] = []
        self.lock = threading.Lock()

    @classmethod
    def of(cls, ctx: Ctx) -> ObjectEvaluation | None:
        """None when the run did not track objects (``tracking.enabled`` off)."""
        if not ctx.cfg.tracking.enabled:
            return None
        return cls(ctx, read_corrected_tracks(ctx.layout, ctx.schema))

    def add_scan(
        self,
        frame_id: str,
        raw_gt: npt.NDArray[np.uint32],
        gt: npt.NDArray[np.int16],
        final: npt.NDArray[np.int16],
        in_view: npt.NDArray[np.bool_],
    ) -> npt.NDArray[np.int16]:
        """One scan: ``raw_gt`` (N,) its ``.label`` values, ``gt`` (N,) their classes, ``final`` (N,) the
        final labels before the tracks, ``in_view`` (N,) the camera view. Returns the labels the export
        writes (the ``objects`` row)."""
        label, _, instance, moving = self.tracks.point_objects(frame_id, final)
        low = np.where(
            moving,
            labels_to_raw(label, self.schema.moving_export_ids()),
            labels_to_raw(label, self.schema.export_ids()),
        ).astype(np.int64)
        pred_segment = low | (np.where(low > 0, instance, 0).astype(np.int64) << 16)
        gt_segment = raw_gt.astype(np.int64)
        gt_state = mos_states(raw_gt)
        gt_moving = gt_state == MOS_MOVING
        thing_gt = (gt >= 0) & self.things[np.maximum(gt, 0)] & ((gt_segment >> 16) > 0)
        gt_track = np.where(thing_gt, gt.astype(np.int64) * 65536 + (gt_segment >> 16) + 1, 0)
        keep = (gt != UNLABELED) & ((gt_track > 0) | (instance > 0))
        right = np.bincount(gt[gt_moving & (label == gt) & (gt >= 0)], minlength=len(self.things))
        total = np.bincount(gt[gt_moving & (gt >= 0)], minlength=len(self.things))
        scan = {p: PanopticCounts(self.schema.num_classes) for p in ("camera", "all")}
        scan["all"].add(gt, gt_segment, label, pred_segment)
        scan["camera"].add(gt[in_view], gt_segment[in_view], label[in_view], pred_segment[in_view])
        assoc = AssociationCounts.of(gt_track[keep], instance[keep])
        mos = MosCounts()
        if self.has_moving:
            mos.add(gt_state, np.where(label == UNLABELED, 0, mos_states(low)))
        with self.lock:
            self.per_scan[frame_id] = scan
            self.mos.merge(mos)
            self.moving_right += right
            self.moving_total += total
            self.pending.append(assoc)
            if sum(x.entries for x in self.pending) >= max(self.assoc.entries, ASSOC_BATCH):
                self.assoc = AssociationCounts.summed([self.assoc, *self.pending])
                self.pending = []
        return label

    def scores(self) -> dict[str, dict[str, float | None]]:
        out: dict[str, dict[str, float | None]] = {}
        for p in ("camera", "all"):
            counts = PanopticCounts(self.schema.num_classes)
            for fid in self.order:
                if fid in self.per_scan:
                    counts.merge(self.per_scan[fid][p])
            out[p] = {k: (None if np.isnan(v) else v) for k, v in counts.scores(self.things).items()}
        s_assoc = AssociationCounts.summed([self.assoc, *self.pending]).score()
        mos = self.mos.iou if self.has_moving else float("nan")
        out["motion"] = {
            "mos_iou": None if np.isnan(mos) else mos,
            "s_assoc": None if np.isnan(s_assoc) else s_assoc,
            "moving_points": float(self.moving_total.sum()),
        }
        out["moving_right_class"] = {
            name: float(self.moving_right[k] / self.moving_total[k])
            for k, name in enumerate(self.schema.names)
            if self.moving_total[k]
        }
        return out


def _read_point_labels(path: Path, final_row: str) -> dict[str, npt.NDArray[np.int16]]:
    """A ``points/`` file's projection-only labels (row ``point``) and final labels (``final_row``)."""
    try:
        z = read_npz(path, ("point_label", "label"))
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable point labels ({exc})") from exc
    return {ROW_POINT: z["point_label"], final_row: z["label"]}


def read_metrics_json(folder: str | Path) -> SequenceMetrics | None:
    """A sequence's ``metrics.json`` in a run (None when it has none)."""
    path = SequenceLayout(Path(folder)).metrics
    data = read_metrics_file(path)
    return None if data is None else SequenceMetrics.from_dict(data, path)


def read_metrics_file(path: Path) -> dict[str, Any] | None:
    """A metrics file's JSON (a sequence's or a run's; None when there is none).

    Raises:
        DatasetError: the file is not JSON.
    """
    if not path.is_file():
        return None
    try:
        data: dict[str, Any] = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"unreadable metrics ({exc})") from exc
    return data


def load_metrics(folder: str | Path) -> dict[str, dict[str, Metrics]] | None:
    """``{protocol: {row: Metrics}}`` rebuilt from a sequence's ``metrics.json`` (None when it has none)."""
    data = read_metrics_json(folder)
    return None if data is None else metrics_tables(data)


def metrics_tables(data: SequenceMetrics) -> dict[str, dict[str, Metrics]]:
    """``{protocol: {row: Metrics}}`` rebuilt from the confusion matrices of a sequence's metrics (or a
    run's ``overall``): :data:`PROTOCOLS` and ``paper``, those the file has, in that order."""
    tables: dict[str, dict[str, Metrics]] = {}
    for p in (*PROTOCOLS, PAPER):
        if p not in data.tables:
            continue
        view = data.paper_view if p == PAPER else None
        names = data.class_names if view is None else view.class_names
        cats = data.categories if view is None else view.categories
        tables[p] = {
            r: metrics_from_confusion(
                data.tables[p][r].confusion_matrix, names, cats, ignore_unlabeled_pred=IGNORES_UNLABELED[p]
            )
            for r in data.rows
        }
    return tables


def format_result_tables(data: SequenceMetrics) -> str:
    """The result tables (one per protocol) of a sequence's metrics (or a run's ``overall``) as text; a
    protocol the file notes as not computed (the paper's, for a schema other than SemanticKITTI's) gets its
    note."""
    tables = metrics_tables(data)
    labeler = data.labeler or "?"
    described = {**PROTOCOLS, PAPER: PAPER_DESCRIPTION, **data.protocols}
    parts = []
    for p, rows in tables.items():
        names = next(iter(rows.values())).class_names
        parts.append(f"{described[p]}; 2D labels: {labeler}\n{format_table(rows, names)}")
    for p, note in data.protocol_notes.items():
        parts.append(f"{p} protocol {note}")
    ratio = data.coverage_ratio.get(ROW_VOXEL)
    if ratio:
        parts.append(f"voxel labels cover {ratio:.2f}x as many points as projection alone")
    if data.objects:
        parts.append(format_object_scores(data.objects))
    return "\n\n".join(parts)


def format_object_scores(objects: Mapping[str, Mapping[str, float | None]]) -> str:
    """The object scores of a ``metrics.json`` (docs/METHOD.md D.6) as a short text table, in %."""

    def pct(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f}"

    lines = ["objects (%)     camera view  all points", "--------------  -----------  ----------"]
    for key in ("PQ", "PQ_things", "PQ_stuff", "SQ", "RQ"):
        lines.append(f"{key:<14}  {pct(objects['camera'].get(key)):>11}  {pct(objects['all'].get(key)):>10}")
    motion = objects.get("motion", {})
    lines.append(f"{'MOS IoU':<14}  {'':>11}  {pct(motion.get('mos_iou')):>10}")
    lines.append(f"{'S_assoc':<14}  {'':>11}  {pct(motion.get('s_assoc')):>10}")
    right = objects.get("moving_right_class", {})
    if right:
        shares = ", ".join(f"{name} {pct(v)}" for name, v in right.items())
        lines.append(f"moving points with the right class: {shares}")
    return "\n".join(lines)


def result_tables(folder: str | Path) -> str | None:
    """A sequence's result tables as text (one per protocol), or None without metrics."""
    data = read_metrics_json(folder)
    return None if data is None else format_result_tables(data)


# ------------------------------------------------------------------------------- several sequences
_SUMMED = ("n_points", "n_points_in_view")


def overall_metrics(per_sequence: Mapping[str, SequenceMetrics | None]) -> SequenceMetrics | None:
    """The metrics of several sequences taken together: each protocol's and row's confusion matrices
    summed over the sequences, then IoU / mIoU computed from the sum (``IoU_c = TP_c / (TP_c + FP_c +
    FN_c)`` of the summed counts; not a mean of the sequences' mIoUs, which would weigh a short sequence
    like a long one).

    Args:
        per_sequence: sequence name → its metrics, None for a sequence without ground truth (left out).

    Returns:
        The summed metrics, with ``sequences`` (the names summed) and ``frames`` (name → that sequence's
        frames); None when no sequence has metrics.

    Raises:
        LeapError: the sequences' metrics disagree on classes or rows (runs of other settings).
    """
    have = {n: m for n, m in per_sequence.items() if m is not None}
    if not have:
        return None
    first_name, first = next(iter(have.items()))
    for name, m in have.items():
        for key in ("class_names", "rows"):
            if getattr(m, key) != getattr(first, key):
                raise LeapError(
                    f"sequence {name}: metrics {key} {getattr(m, key)} differ from sequence "
                    f"{first_name}'s {getattr(first, key)}; evaluate every sequence with one schema "
                    "and one config"
                )
    names, cats, rows = list(first.class_names), list(first.categories), list(first.rows)
    labeled = {r: sum(m.labeled_points.get(r, 0) for m in have.values()) for r in rows}
    n = sum(m.n_points for m in have.values())
    protocols = dict(PROTOCOLS)
    tables: dict[str, dict[str, RowScores]] = {}
    for p in PROTOCOLS:
        if p in OPTIONAL_PROTOCOLS and not all(p in m.tables for m in have.values()):
            protocols.pop(p)  # a sequence evaluated before the protocol existed
            continue
        tables[p] = {}
        for r in rows:
            conf = sum(m.tables[p][r].confusion_matrix for m in have.values())
            tables[p][r] = RowScores.of(
                metrics_from_confusion(conf, names, cats, ignore_unlabeled_pred=IGNORES_UNLABELED[p])
            )
    pl = labeled.get(ROW_POINT, 0)
    out = SequenceMetrics(
        class_names=names,
        categories=cats,
        rows=rows,
        protocols=protocols,
        tables=tables,
        frames={name: (list(m.frames) if isinstance(m.frames, list) else None) for name, m in have.items()},
        n_points=n,
        n_points_in_view=sum(m.n_points_in_view for m in have.values()),
        labeled_points=labeled,
        labeled_share_all_points={r: (labeled[r] / n if n else None) for r in rows},
        labeler=first.labeler,
        coverage_ratio={r: (labeled[r] / pl if pl else None) for r in rows},
        sequences=list(have),
    )
    # Merging is linear, so the merge of the summed camera matrices is the sum of the sequences' merges.
    return with_paper_protocol(out)


def write_run_metrics(
    layout: RunLayout, per_sequence: Mapping[str, SequenceMetrics | None]
) -> RunMetrics | None:
    """Write ``<root>/metrics.json`` = ``{"overall": overall_metrics(...), "sequences": per_sequence}``
    and return it; remove a stale one and return None when no sequence has metrics."""
    overall = overall_metrics(per_sequence)
    if overall is None:
        layout.metrics.unlink(missing_ok=True)
        return None
    data = RunMetrics(overall, dict(per_sequence))
    atomic_write_json(layout.metrics, data.to_dict())
    return data


__all__ = [
    "COMMON",
    "IGNORES_UNLABELED",
    "METRICS_VERSION",
    "OPTIONAL_PROTOCOLS",
    "PAPER",
    "PAPER_DESCRIPTION",
    "PROTOCOLS",
    "ROW_POINT",
    "ROW_VOXEL",
    "cn_row",
    "common_points",
    "format_result_tables",
    "load_metrics",
    "metrics_tables",
    "overall_metrics",
    "paper_metrics",
    "read_metrics_file",
    "read_metrics_json",
    "result_tables",
    "stage_evaluate",
    "with_paper_protocol",
    "write_run_metrics",
]
