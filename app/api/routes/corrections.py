"""A project's manual corrections for the web UI: list (with counts per class and the state of the "apply
corrections" job), add through the API, and the active toggle (undo / redo). Adding or toggling starts the
job (:mod:`app.jobs.apply`), which brings the latest finished run's export up to date without a run."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path as FilePath
from typing import Any

import sqlite_utils
from fastapi import APIRouter, Request, status

from app import crud, models, services
from app.api.deps import DbDep, ReadDbDep, SettingsDep
from app.api.responses import NOT_FOUND
from app.api.types import CorrectionId, ProjectId, SequenceQuery
from app.core.errors import InvalidField, NotFound
from app.jobs.apply import applier
from app.rows import ProjectRow, RunRow

router = APIRouter(tags=["corrections"], responses={**NOT_FOUND})


def _public(c: crud.Correction, matches: Matches | None = None) -> models.CorrectionPublic:
    match = None
    if c.scope == "object" and matches is not None and str(c.id) in matches[1]:
        m = matches[1][str(c.id)]
        run = matches[0]
        match = models.ObjectMatch(
            run_id=run.id,
            run_number=run.number,
            track=m["track"],
            iou=m["iou"],
            applied=m["applied"],
            other_track=m.get("other_track"),
            other_iou=m.get("other_iou"),
            new_track=m.get("new_track"),
        )
    return models.CorrectionPublic(
        id=c.id,
        created_at=c.created_at,
        class_name=c.class_name,
        scope=c.scope,
        frame_id=c.frame_id,
        voxels=int(c.keys.size),
        points=None if c.points is None else int(c.points.size),
        author=c.author,
        active=c.active,
        sequence=c.sequence,
        reviewer=c.reviewer,
        run_id=c.run_id,
        track_id=c.track_id,
        action=c.action if c.scope == "object" else None,
        other_track_id=c.other_track_id,
        split_frame=c.split_frame,
        match=match,
    )


Matches = tuple[RunRow, dict[str, Any]]
"""The latest finished run and its sequence's ``object_matches.json`` (correction id → track, IoU,
applied)."""


def _object_matches(db: sqlite_utils.Database, project_id: int, sequence: str) -> Matches | None:
    """Which track of the latest finished run each object correction met (written by the run's export
    and by the apply job; None when that run has no such file for the sequence)."""
    run = crud.last_finished_run(db, project_id)
    if run is None or sequence not in [s.name for s in run.params.sequences]:
        return None
    path = run.sequence_layout(sequence).object_matches
    try:
        found = json.loads(path.read_text()) if path.is_file() else None
    except (OSError, ValueError):
        return None  # being replaced (atomically) or damaged: the next listing reads it again
    return (run, found) if isinstance(found, dict) else None


def _tell_viewers(request: Request, project_id: int) -> None:
    """Show the changed corrections in the project's open viewer tabs (when the viewer is installed)."""
    viewers = getattr(request.app.state, "viewers", None)
    if viewers is not None:
        viewers.corrections_changed(project_id)


def _check_class(project: ProjectRow, class_name: str) -> None:
    """A correction assigns one of the project's classes (or erases, ``""``): one for a class the project
    does not have would be stored and then dropped by every run and every apply pass."""
    names = [str(c["name"]) for c in project.schema["classes"]]
    if class_name != "" and class_name not in names:
        raise InvalidField(
            ("body", "class_name"),
            f"project {project.id} has no class {class_name!r}; its classes are {', '.join(names)} "
            "('' erases to unlabeled)",
        )


def _check_scan(dataset: FilePath, frame_id: str, points: list[int]) -> None:
    """A scan-scope correction must name a scan of the sequence's dataset and points inside it: stored
    otherwise, it would fail every later run (label_points checks the indices against the scan)."""
    scan = dataset / "velodyne" / f"{frame_id}.bin"
    if not scan.is_file():
        raise InvalidField(("frame_id",), f"scan {frame_id!r} is not in the project's dataset")
    n = scan.stat().st_size // 16  # float32 x, y, z, remission per point
    if points and max(points) >= n:
        raise InvalidField(("points",), f"point index {max(points)} is past scan {frame_id} ({n} points)")


@router.get("/projects/{project_id}/corrections", response_model=models.CorrectionList)
def list_corrections(
    project_id: ProjectId, db: ReadDbDep, settings: SettingsDep, sequence: SequenceQuery = None
) -> models.CorrectionList:
    """Every correction of the project's sequence (default: its first; newest first), active counts per
    class, and the apply job."""
    crud.require_project(db, project_id)
    name = crud.sequence_name(db, project_id, sequence, loc=("query", "sequence"))
    rows = crud.list_corrections(db, project_id, active_only=False, sequence=name)
    matches = _object_matches(db, project_id, name) if any(c.scope == "object" for c in rows) else None
    counts: Counter[str] = Counter()
    voxels: Counter[str] = Counter()
    for c in rows:
        if c.active and c.action == "relabel":  # a merge or a split assigns no class
            counts[c.class_name] += 1
            voxels[c.class_name] += int(c.keys.size)
    return models.CorrectionList(
        corrections=[_public(c, matches) for c in reversed(rows)],
        per_class=[
            models.CorrectionClassCount(class_name=name, corrections=n, voxels=voxels[name])
            for name, n in sorted(counts.items())
        ],
        apply=models.CorrectionApply(**applier(settings).state(project_id).to_dict()),
        latest_run_objects=_latest_run_objects(db, project_id, name),
    )


def _latest_run_objects(db: sqlite_utils.Database, project_id: int, sequence: str) -> bool | None:
    """Whether the latest finished run has tracks for ``sequence`` (None: no finished run of it)."""
    run = crud.last_finished_run(db, project_id)
    if run is None or sequence not in [s.name for s in run.params.sequences]:
        return None
    return run.sequence_layout(sequence).tracks.is_file()


@router.post(
    "/projects/{project_id}/corrections",
    response_model=models.CorrectionPublic,
    status_code=status.HTTP_201_CREATED,
)
def add_correction(
    project_id: ProjectId,
    payload: models.CorrectionCreate,
    db: DbDep,
    settings: SettingsDep,
    request: Request,
) -> models.CorrectionPublic:
    """Store a correction (author "api") and apply it to the latest run's export in the background. 422
    naming ``class_name`` for a class the project does not have; for an object-scope one, naming
    ``run_id`` / ``track_id`` when the run is not a finished run of the project with objects, or has no
    such object, ``other_track_id`` for a merge with itself or with no such object, ``frame`` for a split
    at a scan that does not cut the object (:func:`app.services.object_ref`)."""
    class_name = payload.class_name or ""  # a merge or a split assigns none
    _check_class(crud.require_project(db, project_id), class_name)
    name = crud.sequence_name(db, project_id, payload.sequence, loc=("body", "sequence"))
    if payload.scope == "scan" and payload.frame_id is not None and payload.points is not None:
        dataset = next(s.dataset_path for s in crud.list_sequences(db, project_id) if s.name == name)
        _check_scan(FilePath(dataset), payload.frame_id, payload.points)
    obj = None
    if payload.scope == "object" and payload.run_id is not None and payload.track_id is not None:
        obj = services.object_ref(
            db,
            settings,
            project_id,
            payload.run_id,
            name,
            payload.track_id,
            action=payload.action,
            other_track_id=payload.other_track_id,
            frame=payload.frame,
        )
    cid = crud.add_correction(
        db,
        project_id=project_id,
        class_name=class_name,
        voxel_size=payload.voxel_size,
        keys=payload.keys,
        scope=payload.scope,
        frame_id=payload.frame_id,
        points=payload.points,
        author="api",
        sequence=name,
        obj=obj,
    )
    applier(settings).request(project_id)
    _tell_viewers(request, project_id)
    return _public(crud.get_correction(db, cid))


@router.patch("/projects/{project_id}/corrections/{correction_id}", response_model=models.CorrectionPublic)
def update_correction(
    project_id: ProjectId,
    correction_id: CorrectionId,
    payload: models.CorrectionUpdate,
    db: DbDep,
    settings: SettingsDep,
    request: Request,
) -> models.CorrectionPublic:
    """Turn a correction off (undo) or on again; the export follows in the background."""
    if crud.get_correction(db, correction_id).project_id != project_id:
        raise NotFound(f"Correction {correction_id} not found in project {project_id}")
    crud.set_correction_active(db, correction_id, payload.active)
    applier(settings).request(project_id)
    _tell_viewers(request, project_id)
    return _public(crud.get_correction(db, correction_id))
