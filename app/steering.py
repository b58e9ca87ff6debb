"""Steering between runs: what the next run of a project recomputes, and how a run compares with an
earlier one (Δ per class, what changed). Routes call these; the rules live in
:mod:`leap_core.pipeline.steering`.

A module of its own because the preview needs the job manager's rule for a new run's corrections, and the
job manager imports :mod:`app.services`.
"""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
from pathlib import Path
from typing import Any

import sqlite_utils

from app import crud, models
from app.core.config import Settings
from app.core.errors import InvalidField
from app.forms import PATH_LABELS
from app.jobs.manager import active_correction_ids, run_corrections, seed_source
from app.jobs.poses import cache_folder, needs_estimate
from app.rows import ProjectRow, RunParams, RunRow, RunSequence
from app.services import metrics_public, overall, project_config, stale_results
from leap_core.errors import LeapError
from leap_core.io_utils import link_or_copy
from leap_core.pipeline import STAGE_TABLE, stage_fingerprints
from leap_core.pipeline.context import read_state
from leap_core.pipeline.steering import (
    OBJECT_FIELDS,
    Change,
    CorrectionNote,
    StagePlan,
    changed_sections,
    correction_changes,
    recompute_plan,
    run_changes,
)
from leap_core.run_layout import SequenceLayout
from leap_core.runtime import Runtime
from leap_core.schema import Schema


# ------------------------------------------------------------------------------------------ steering
def _change_public(change: Change) -> models.ChangePublic:
    return models.ChangePublic(
        kind=change.kind, subject=change.subject, text=change.text, ignored=change.ignored, field=change.field
    )


def project_snapshot(db: sqlite_utils.Database, project: ProjectRow) -> RunParams:
    """The inputs a new run of all frames would snapshot, its corrections included (what
    :func:`what_changed` compares; no stages)."""
    return RunParams(
        sequences=tuple(RunSequence(s.name, Path(s.dataset_path)) for s in project.sequences),
        dataset_kind=project.dataset_kind,
        schema=project.schema,
        pipeline=project.pipeline,
        estimate_poses=project.estimate_poses,
        corrections=active_correction_ids(db, project),
    )


def _correction_text(c: crud.Correction) -> str:
    what = c.class_name or "erase"
    if c.scope == "scan":
        n = 0 if c.points is None else int(c.points.shape[0])
        return f"{what}, scan {c.frame_id}, {n} point{'' if n == 1 else 's'}"
    if c.scope == "object" and c.action == "merge":
        return f"merge of objects {c.track_id} and {c.other_track_id} of run id {c.run_id}"
    if c.scope == "object" and c.action == "split":
        return f"split of object {c.track_id} of run id {c.run_id} at scan {c.split_frame}"
    if c.scope == "object":
        return f"{what}, object {c.track_id} of run id {c.run_id}"
    n = int(c.keys.shape[0])
    return f"{what}, map, {n} voxel{'' if n == 1 else 's'}"


def what_changed(
    db: sqlite_utils.Database, project_id: int, base: RunRow, new: RunParams
) -> list[models.ChangePublic]:
    """``base`` → ``new``: sequences, pose estimation, classes, parameters (:func:`run_changes`), and the
    corrections each got (:func:`correction_changes`; left out when ``base`` predates recorded ones).
    Pose estimation switched on changes nothing where every sequence has its own ``poses.txt``."""
    changes = run_changes(base.params.to_dict(), new.to_dict(), PATH_LABELS)
    if not any(needs_estimate(s.dataset) for s in new.sequences):
        changes = [
            dataclasses.replace(c, ignored="every sequence has its own poses.txt, which a run keeps")
            if c.kind == "poses"
            else c
            for c in changes
        ]
    if base.params.corrections is not None and new.corrections is not None:
        notes = {
            c.id: CorrectionNote(_correction_text(c), made_after=c.created_at > base.created_at)
            for name in dict.fromkeys([*base.params.corrections, *new.corrections])
            for c in crud.list_corrections(db, project_id, active_only=False, sequence=name)
        }
        changes += correction_changes(base.params.corrections, new.corrections, notes)
    return [_change_public(c) for c in changes]


def _link_estimated_poses(dataset: Path, layout: SequenceLayout, cache_root: Path) -> bool:
    """Put the estimate a run of ``dataset`` would reuse into the preview's folder ``layout`` (as
    :func:`app.jobs.poses.prepare_run_poses` links it into the run's), so the fingerprints hash the poses
    the run will read; False when the run would estimate them afresh."""
    from leap_core.datasets.kitti import POSES_NOTE, KittiSequence  # noqa: PLC0415
    from leap_core.odometry import OdometryConfig, reusable_estimate  # noqa: PLC0415  (KISS-ICP loads)

    cached = cache_folder(cache_root, dataset) / "poses.txt"
    if not reusable_estimate(KittiSequence(dataset), cached, OdometryConfig()):
        return False
    link_or_copy(cached, layout.poses)
    link_or_copy(cached.parent / POSES_NOTE, layout.poses.parent / POSES_NOTE)
    return True


def run_preview(db: sqlite_utils.Database, settings: Settings, project_id: int) -> models.RunPreview:
    """Which stages the next run (all frames) recomputes: the fingerprints it would have against those in
    the ``stages.json`` of the finished run its folder would be seeded from (the job manager's rule: the
    latest finished run, when it covered the same dataset and all frames)."""
    project = crud.require_project(db, project_id)
    snapshot = project_snapshot(db, project)
    base = seed_source(db, project_id, snapshot)
    changes = [] if base is None else what_changed(db, project_id, base, snapshot)
    basis = None if base is None else models.RunBasis(id=base.id, number=base.number)
    # A run of other sequences seeds nothing (seed_source): say why instead of "no earlier run".
    stale = None if base is not None else stale_results(project, crud.list_runs(db, project_id))

    def everything(reason: str, problem: str | None = None) -> models.RunPreview:
        stages = [
            models.StagePlanPublic(name=s.name, label=s.label, action="recompute", reason=reason)
            for s in STAGE_TABLE
        ]
        return models.RunPreview(
            base_run=basis,
            stages=stages,
            recompute=[s.name for s in stages],
            changes=changes,
            problem=problem,
            stale=stale,
        )

    if not all((s.dataset / "velodyne").is_dir() for s in snapshot.sequences):
        return everything("the dataset does not exist yet")
    config = project_config(project)
    sections = [] if base is None else changed_sections(base.params.pipeline, project.pipeline)
    kinds = {
        "class": "the classes or prompts changed",
        "dataset": "the dataset changed",
        "frames": "the frames changed",
        "correction": "the corrections changed",
        "poses": "the poses changed",
    }
    hint = "; ".join(
        dict.fromkeys(_change_hint(c, kinds) for c in changes if c.kind in kinds and c.ignored is None)
    )
    per_sequence = []
    try:
        schema = Schema.from_dict(project.schema, source="classes")
        runtime = Runtime(models_dir=settings.models_dir, cache_dir=settings.cache_dir / f"p{project_id}")
        settings.work_dir.mkdir(parents=True, exist_ok=True)
        for seq in snapshot.sequences:
            name, dataset = seq.name, seq.dataset
            with tempfile.TemporaryDirectory(prefix="preview-", dir=settings.work_dir) as tmp:
                corrections = crud.list_corrections(db, project_id, active_only=True, sequence=name)
                lay = SequenceLayout(Path(tmp))
                run_corrections(corrections, snapshot, settings.work_dir).write_run(lay)
                estimated = project.estimate_poses and needs_estimate(dataset)
                if estimated and not _link_estimated_poses(dataset, lay, settings.cache_dir):
                    fresh = "the poses will be estimated"
                    hint = f"{hint}; {fresh}" if hint and fresh not in hint else hint or fresh
                base_lay = None if base is None else base.sequence_layout(name)
                if base_lay is not None and base_lay.joint_3dcn.is_file():
                    # A sequence's 3D-CN fingerprint covers the round it took; a change anywhere that
                    # reruns the rounds shows up as another sequence's recompute (merged below).
                    shutil.copyfile(base_lay.joint_3dcn, lay.joint_3dcn)
                fps = stage_fingerprints(dataset, schema, config, Path(tmp), runtime=runtime)
            previous = None if base_lay is None else read_state(base_lay)
            per_sequence.append(
                (
                    name,
                    recompute_plan(config, fps, previous, sections, **({"input_hint": hint} if hint else {})),
                )
            )
    except LeapError as exc:
        return everything("its inputs could not be fingerprinted", problem=str(exc))
    plans = _merged_plans(per_sequence)
    if stale is not None:
        plans = [
            dataclasses.replace(p, reason=f"the sequences changed since run {stale.run_number}")
            if p.action == "recompute"
            else p
            for p in plans
        ]
    stages = [
        models.StagePlanPublic(name=p.name, label=p.label, action=p.action, reason=p.reason) for p in plans
    ]
    return models.RunPreview(
        base_run=basis,
        stages=stages,
        recompute=[p.name for p in plans if p.action == "recompute"],
        changes=changes,
        stale=stale,
    )


def _change_hint(change: models.ChangePublic, kinds: dict[str, str]) -> str:
    """The reason a change gives a stage it reruns: a class's thing flag or moving id is named as such, as
    only the object stages (tracks, evaluation, export) read them."""
    if change.kind == "class" and change.field in OBJECT_FIELDS:
        return "a class's thing flag or moving id changed"
    return kinds[change.kind]


def _merged_plans(per_sequence: list[tuple[str, list[StagePlan]]]) -> list[StagePlan]:
    """One plan per stage over every sequence: a stage any sequence recomputes is recomputed (the reason
    names the first such sequence); else the first sequence's plan."""
    if len(per_sequence) == 1:
        return per_sequence[0][1]
    merged = []
    for i, first in enumerate(per_sequence[0][1]):
        chosen = next(((n, p[i]) for n, p in per_sequence if p[i].action == "recompute"), None)
        if chosen is None:
            merged.append(first)
        else:
            name, plan = chosen
            merged.append(dataclasses.replace(plan, reason=f"sequence {name}: {plan.reason}"))
    return merged


def _num(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _delta(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a - b


def compare_runs(db: sqlite_utils.Database, run_id: int, base_id: int) -> models.ComparePublic:
    """``run`` against ``base``: per protocol and shared result row the mIoU and per-class IoU deltas
    (classes matched by name: a class only one run has gets a null delta), and the input changes."""
    run = crud.require_run(db, run_id)
    base = crud.require_run(db, base_id)
    if run.project_id != base.project_id:
        raise InvalidField(["path", "base_id"], f"run {base_id} belongs to another project than run {run_id}")
    changes = what_changed(db, run.project_id, base, run.params)
    rows: list[models.RowDelta] = []
    ma, mb = metrics_public(overall(run)), metrics_public(overall(base))
    if ma is not None and mb is not None:
        names = [c["name"] for c in run.params.schema["classes"]]
        names += [c["name"] for c in base.params.schema["classes"] if c["name"] not in names]
        for protocol, table in ma["protocols"].items():
            other = mb["protocols"].get(protocol, {})
            for row, values in table.items():
                if row not in other:
                    continue
                ia, ib = values.get("iou") or {}, other[row].get("iou") or {}
                # A protocol over merged classes (the paper's) has its own classes, not the schema's.
                view = ma["views"].get(protocol)
                order = list(view["class_names"]) if view else names
                classes = [
                    models.ClassDelta(
                        name=n,
                        iou=_num(ia.get(n)),
                        base_iou=_num(ib.get(n)),
                        delta=_delta(_num(ia.get(n)), _num(ib.get(n))),
                    )
                    for n in order
                ]
                a, b = _num(values.get("miou")), _num(other[row].get("miou"))
                rows.append(
                    models.RowDelta(
                        protocol=protocol, row=row, miou=a, base_miou=b, delta=_delta(a, b), classes=classes
                    )
                )
    return models.ComparePublic(run_id=run_id, base_run_id=base_id, changes=changes, rows=rows)
