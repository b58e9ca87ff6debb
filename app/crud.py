"""Plain database functions (no HTTP, no pipeline). Rows come back typed (:mod:`app.rows`) with their JSON
columns decoded.

Every function takes the sqlite-utils ``Database`` first and its other arguments by keyword.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import numpy.typing as npt
import sqlite_utils

from app.core.db import transaction, utcnow
from app.core.errors import InvalidField, NotFound
from app.rows import (
    DatasetKind,
    ModelJobKind,
    ModelJobRow,
    ModelJobStatus,
    ProjectRow,
    RunParams,
    RunRow,
    RunStatus,
    SequenceRow,
)
from leap_core.pipeline.metrics_file import RunMetrics

_JSON_COLUMNS = {
    "schema_json": "schema",
    "pipeline_json": "pipeline",
    "params_json": "params",
    "stages_json": "stages",
    "metrics_json": "metrics",
}


def _decode(row: dict[str, Any]) -> dict[str, Any]:
    """A row with its JSON columns parsed (``schema_json`` → ``schema``, ...)."""
    out = dict(row)
    for column, key in _JSON_COLUMNS.items():
        if column in out:
            raw = out.pop(column)
            out[key] = None if raw is None else json.loads(raw)
    return out


def _rows(db: sqlite_utils.Database, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]:
    cursor = db.execute(sql, list(params))
    names = [d[0] for d in cursor.description]
    return [_decode(dict(zip(names, r, strict=True))) for r in cursor.fetchall()]


def _one(db: sqlite_utils.Database, sql: str, params: Sequence[Any] = ()) -> dict[str, Any] | None:
    rows = _rows(db, sql, params)
    return rows[0] if rows else None


def _inserted_id(cursor: sqlite3.Cursor) -> int:
    """The id of the row an ``INSERT`` just added (sqlite3 types ``lastrowid`` as optional)."""
    rowid = cursor.lastrowid
    if rowid is None:
        raise RuntimeError("the statement inserted no row")
    return int(rowid)


def _dumps(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"))


_ID_TABLES = ("projects", "runs")
"""Tables whose ids are never handed out twice (:func:`_new_id`)."""


def _last_id_key(table: str) -> str:
    return f"last_id.{table}"


def _new_id(db: sqlite_utils.Database, table: str) -> int:
    """An id of ``table`` never handed out before: one past the highest it holds or held (kept in ``meta``).

    SQLite's own choice (the highest present + 1) gives a deleted row's id to the next row, and a project's
    or run's id names its folders (``runs/p<P>/r<R>``, ``cache/p<P>``) and the app's in-memory state (the
    corrections job's grid, viewers): a new project must never meet what the deleted one left. Call inside
    the transaction that inserts the row.
    """
    assert table in _ID_TABLES
    held = int(db.execute(f"SELECT COALESCE(MAX(id), 0) FROM {table}").fetchone()[0])
    new = max(held, int(get_meta(db, _last_id_key(table)) or 0)) + 1
    set_meta(db, _last_id_key(table), str(new))
    return new


def _retire_ids(db: sqlite_utils.Database, table: str, highest: int) -> None:
    """Record that ids up to ``highest`` of ``table`` were handed out (before deleting rows that were
    created before ids were recorded)."""
    if highest > int(get_meta(db, _last_id_key(table)) or 0):
        set_meta(db, _last_id_key(table), str(highest))


# -------------------------------------------------------------------------------------------- projects
def create_project(
    db: sqlite_utils.Database,
    *,
    name: str,
    dataset_kind: DatasetKind,
    sequences: Sequence[tuple[str, str]],
    schema: dict[str, Any],
    pipeline: dict[str, Any],
    is_demo: bool = False,
    estimate_poses: bool = False,
) -> ProjectRow:
    """Insert a project and its ``sequences`` (name, dataset path), in order (at least one).

    Raises:
        ValueError: no sequence.
    """
    now = utcnow()
    seqs = list(sequences)
    if not seqs:
        raise ValueError("a project needs at least one sequence")
    with transaction(db):
        cursor = db.execute(
            "INSERT INTO projects (id, name, dataset_kind, dataset_path, schema_json, pipeline_json, "
            "is_demo, estimate_poses, created_at, updated_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            [
                _new_id(db, "projects"),
                name,
                dataset_kind,
                seqs[0][1],
                _dumps(schema),
                _dumps(pipeline),
                int(is_demo),
                int(estimate_poses),
                now,
                now,
            ],
        )
        project_id = _inserted_id(cursor)
        for position, (seq_name, seq_path) in enumerate(seqs):
            db.execute(
                "INSERT INTO project_sequences (project_id, name, dataset_path, position) "
                "VALUES (?, ?, ?, ?)",
                [project_id, seq_name, seq_path, position],
            )
    project = get_project(db, project_id)
    assert project is not None
    return project


def _project(row: dict[str, Any], sequences: Sequence[SequenceRow]) -> ProjectRow:
    return ProjectRow(
        id=int(row["id"]),
        name=str(row["name"]),
        dataset_kind=cast("DatasetKind", row["dataset_kind"]),
        schema=row["schema"],
        pipeline=row["pipeline"],
        is_demo=bool(row["is_demo"]),
        estimate_poses=bool(row["estimate_poses"]),
        created_at=str(row["created_at"]),
        updated_at=str(row["updated_at"]),
        sequences=tuple(sequences),
    )


def _sequence(row: dict[str, Any]) -> SequenceRow:
    return SequenceRow(str(row["name"]), str(row["dataset_path"]), int(row["position"]))


def _with_sequences(db: sqlite_utils.Database, row: dict[str, Any] | None) -> ProjectRow | None:
    return None if row is None else _project(row, list_sequences(db, int(row["id"])))


def get_project(db: sqlite_utils.Database, project_id: int) -> ProjectRow | None:
    """The project with its sequences (:func:`list_sequences`)."""
    return _with_sequences(db, _one(db, "SELECT * FROM projects WHERE id = ?", [project_id]))


def list_sequences(db: sqlite_utils.Database, project_id: int) -> list[SequenceRow]:
    """The project's current sequences in order (removed ones left out)."""
    return [
        _sequence(r)
        for r in _rows(
            db,
            "SELECT name, dataset_path, position FROM project_sequences WHERE project_id = ? "
            "AND removed_at IS NULL ORDER BY position",
            [project_id],
        )
    ]


def removed_sequence(db: sqlite_utils.Database, project_id: int, name: str) -> SequenceRow | None:
    """The removed sequence ``name`` of the project, if any: the folder its kept corrections and review
    marks belong to."""
    row = _one(
        db,
        "SELECT name, dataset_path, position FROM project_sequences WHERE project_id = ? AND name = ? "
        "AND removed_at IS NOT NULL",
        [project_id, name],
    )
    return None if row is None else _sequence(row)


def add_sequence(db: sqlite_utils.Database, project_id: int, *, name: str, dataset_path: str) -> None:
    """Append the sequence ``name`` on ``dataset_path`` to the project (a removed sequence of that name
    comes back, with its corrections and review marks; the caller checked it is the same folder). Call
    inside :func:`~app.core.db.transaction` with the checks it relies on.
    """
    position = db.execute(
        "SELECT COALESCE(MAX(position), -1) + 1 FROM project_sequences WHERE project_id = ?", [project_id]
    ).fetchone()[0]
    if removed_sequence(db, project_id, name) is not None:
        db.execute(
            "UPDATE project_sequences SET removed_at = NULL, position = ?, dataset_path = ? "
            "WHERE project_id = ? AND name = ?",
            [position, dataset_path, project_id, name],
        )
    else:
        db.execute(
            "INSERT INTO project_sequences (project_id, name, dataset_path, position) VALUES (?, ?, ?, ?)",
            [project_id, name, dataset_path, position],
        )
    db.execute("UPDATE projects SET updated_at = ? WHERE id = ?", [utcnow(), project_id])


def remove_sequence(db: sqlite_utils.Database, project_id: int, name: str) -> None:
    """Take the sequence ``name`` out of the project. Its row stays (``removed_at``), and so do its
    corrections, review marks and queues and every run; ``projects.dataset_path`` follows the new first
    sequence. Call inside :func:`~app.core.db.transaction` (the caller keeps one sequence)."""
    now = utcnow()
    db.execute(
        "UPDATE project_sequences SET removed_at = ? WHERE project_id = ? AND name = ?",
        [now, project_id, name],
    )
    after = list_sequences(db, project_id)
    db.execute(
        "UPDATE projects SET dataset_path = ?, updated_at = ? WHERE id = ?",
        [after[0].dataset_path, now, project_id],
    )


def sequence_name(
    db: sqlite_utils.Database, project_id: int, name: str | None, *, loc: Sequence[str | int] = ("sequence",)
) -> str:
    """The stored name of one of the project's sequences: ``name``, or the first sequence's when None
    (what single-sequence callers get).

    Raises:
        NotFound: unknown project.
        InvalidField: ``name`` is not one of the project's sequences (``loc`` names the field).
    """
    names = [s.name for s in list_sequences(db, project_id)]
    if not names:
        require_project(db, project_id)
        raise NotFound(f"Project {project_id} has no sequences")
    if name is None:
        return str(names[0])
    if name not in names:
        raise InvalidField(loc, f"project {project_id} has no sequence {name!r} (it has {', '.join(names)})")
    return name


def require_project(db: sqlite_utils.Database, project_id: int) -> ProjectRow:
    """The project row, or :class:`NotFound`."""
    project = get_project(db, project_id)
    if project is None:
        raise NotFound(f"Project {project_id} not found")
    return project


def list_projects(db: sqlite_utils.Database) -> list[ProjectRow]:
    by_project: dict[int, list[SequenceRow]] = {}
    for row in _rows(
        db,
        "SELECT project_id, name, dataset_path, position FROM project_sequences "
        "WHERE removed_at IS NULL ORDER BY project_id, position",
    ):
        by_project.setdefault(int(row["project_id"]), []).append(_sequence(row))
    return [
        _project(p, by_project.get(int(p["id"]), [])) for p in _rows(db, "SELECT * FROM projects ORDER BY id")
    ]


def update_project(
    db: sqlite_utils.Database,
    project_id: int,
    *,
    name: str | None = None,
    schema: dict[str, Any] | None = None,
    pipeline: dict[str, Any] | None = None,
    estimate_poses: bool | None = None,
) -> ProjectRow:
    sets: list[str] = []
    params: list[Any] = []
    for column, value in (("name", name), ("schema_json", schema), ("pipeline_json", pipeline)):
        if value is not None:
            sets.append(f"{column} = ?")
            params.append(value if column == "name" else _dumps(value))
    if estimate_poses is not None:
        sets.append("estimate_poses = ?")
        params.append(int(estimate_poses))
    sets.append("updated_at = ?")
    params.append(utcnow())
    db.execute(f"UPDATE projects SET {', '.join(sets)} WHERE id = ?", [*params, project_id])
    return require_project(db, project_id)


def delete_project(db: sqlite_utils.Database, project_id: int) -> None:
    """Delete the project and, by cascade, its runs, sequences, corrections and review marks; their ids are
    never handed out again (:func:`_new_id`)."""
    with transaction(db):
        last_run = db.execute("SELECT COALESCE(MAX(id), 0) FROM runs WHERE project_id = ?", [project_id])
        _retire_ids(db, "runs", int(last_run.fetchone()[0]))
        _retire_ids(db, "projects", project_id)
        db.execute("DELETE FROM projects WHERE id = ?", [project_id])


def find_demo_project(db: sqlite_utils.Database) -> ProjectRow | None:
    return _with_sequences(db, _one(db, "SELECT * FROM projects WHERE is_demo = 1 ORDER BY id LIMIT 1"))


# ------------------------------------------------------------------------------------------------ runs
def _run(row: dict[str, Any]) -> RunRow:
    return RunRow(
        id=int(row["id"]),
        project_id=int(row["project_id"]),
        number=int(row["number"]),
        status=cast("RunStatus", row["status"]),
        params=RunParams.from_dict(row["params"]),
        run_dir=Path(row["run_dir"]),
        created_at=str(row["created_at"]),
        started_at=row["started_at"],
        finished_at=row["finished_at"],
        error=row["error"],
        attempts=int(row["attempts"]),
        stages=row["stages"] or None,
        metrics=None if row["metrics"] is None else RunMetrics.from_dict(row["metrics"], f"run {row['id']}"),
        note=row.get("note"),
    )


def _runs(db: sqlite_utils.Database, sql: str, params: Sequence[Any] = ()) -> list[RunRow]:
    return [_run(r) for r in _rows(db, sql, params)]


def create_run(db: sqlite_utils.Database, *, project_id: int, params: RunParams, runs_dir: Path) -> RunRow:
    """Insert a queued run numbered after the project's earlier ones; its folder is ``runs_dir/p<P>/r<R>``."""
    with transaction(db):
        number = db.execute(
            "SELECT COALESCE(MAX(number), 0) + 1 FROM runs WHERE project_id = ?", [project_id]
        ).fetchone()[0]
        cursor = db.execute(
            "INSERT INTO runs (id, project_id, number, status, params_json, run_dir, created_at) "
            "VALUES (?, ?, ?, 'queued', ?, '', ?)",
            [_new_id(db, "runs"), project_id, number, _dumps(params.to_dict()), utcnow()],
        )
        run_id = _inserted_id(cursor)
        run_dir = runs_dir / f"p{project_id}" / f"r{run_id}"
        db.execute("UPDATE runs SET run_dir = ? WHERE id = ?", [str(run_dir), run_id])
    run = get_run(db, run_id)
    assert run is not None
    return run


def get_run(db: sqlite_utils.Database, run_id: int) -> RunRow | None:
    rows = _runs(db, "SELECT * FROM runs WHERE id = ?", [run_id])
    return rows[0] if rows else None


def require_run(db: sqlite_utils.Database, run_id: int) -> RunRow:
    """The run row, or :class:`NotFound`."""
    run = get_run(db, run_id)
    if run is None:
        raise NotFound(f"Run {run_id} not found")
    return run


def list_runs(db: sqlite_utils.Database, project_id: int) -> list[RunRow]:
    """Runs of a project, newest first."""
    return _runs(db, "SELECT * FROM runs WHERE project_id = ? ORDER BY id DESC", [project_id])


def runs_with_status(db: sqlite_utils.Database, statuses: Iterable[str]) -> list[RunRow]:
    statuses = list(statuses)
    marks = ", ".join("?" for _ in statuses)
    return _runs(db, f"SELECT * FROM runs WHERE status IN ({marks}) ORDER BY id", statuses)


def all_runs(db: sqlite_utils.Database) -> list[RunRow]:
    """Every run of every project, oldest first."""
    return _runs(db, "SELECT * FROM runs ORDER BY id")


def active_run(db: sqlite_utils.Database, project_id: int) -> RunRow | None:
    """The project's queued or running run, if any."""
    rows = _runs(
        db,
        "SELECT * FROM runs WHERE project_id = ? AND status IN ('queued', 'running') ORDER BY id LIMIT 1",
        [project_id],
    )
    return rows[0] if rows else None


def last_finished_run(db: sqlite_utils.Database, project_id: int) -> RunRow | None:
    rows = _runs(
        db,
        "SELECT * FROM runs WHERE project_id = ? AND status = 'done' ORDER BY id DESC LIMIT 1",
        [project_id],
    )
    return rows[0] if rows else None


def update_run(db: sqlite_utils.Database, run_id: int, **fields: Any) -> None:
    """Set columns of a run; ``stages``, ``metrics`` (a :class:`RunMetrics`) and ``params`` (a
    :class:`RunParams`) are stored as JSON."""
    sets: list[str] = []
    params: list[Any] = []
    for key, value in fields.items():
        column = f"{key}_json" if key in ("stages", "metrics", "params") else key
        stored = value.to_dict() if isinstance(value, (RunParams, RunMetrics)) else value
        sets.append(f"{column} = ?")
        params.append(_dumps(stored) if column.endswith("_json") and stored is not None else stored)
    if sets:
        db.execute(f"UPDATE runs SET {', '.join(sets)} WHERE id = ?", [*params, run_id])


def transition_run(db: sqlite_utils.Database, run_id: int, from_status: str, **fields: Any) -> bool:
    """Set ``fields`` only if the run is still ``from_status``; True when it was (an atomic check-and-set)."""
    sets = [f"{k} = ?" for k in fields]
    cursor = db.execute(
        f"UPDATE runs SET {', '.join(sets)} WHERE id = ? AND status = ?",
        [*fields.values(), run_id, from_status],
    )
    return cursor.rowcount == 1


def mark_stale_runs_interrupted(db: sqlite_utils.Database) -> list[int]:
    """After a crash or kill, runs left queued or running are marked ``interrupted``; returns their ids."""
    with transaction(db):
        ids = [
            r[0] for r in db.execute("SELECT id FROM runs WHERE status IN ('queued', 'running')").fetchall()
        ]
        if ids:
            marks = ", ".join("?" for _ in ids)
            db.execute(
                f"UPDATE runs SET status = 'interrupted', finished_at = ?, "
                f"error = 'the server stopped during this run; resume it to continue' WHERE id IN ({marks})",
                [utcnow(), *ids],
            )
    return ids


def count_runs(db: sqlite_utils.Database, project_id: int) -> int:
    return int(db.execute("SELECT COUNT(*) FROM runs WHERE project_id = ?", [project_id]).fetchone()[0])


# ----------------------------------------------------------------------------------------- corrections
ObjectAction = Literal["relabel", "merge", "split"]
"""What an object-scope correction does (:attr:`Correction.action`)."""


@dataclass(frozen=True)
class Correction:
    """Manual voxel class assignment made in the viewer; applied as an overriding observation by runs."""

    id: int
    """Row id."""
    project_id: int
    """Owning project."""
    created_at: str
    """ISO UTC time."""
    class_name: str
    """Class assigned (by name, so it survives reordering; dropped if the class is removed); ``""`` erases
    to unlabeled (export id 0)."""
    voxel_size: float
    """Voxel edge (m) the keys were computed with."""
    keys: npt.NDArray[np.int64]
    """(K,) packed voxel keys (``leap_core.fusion`` key packing): the voxels the correction covers (for a
    scan-scope correction, the voxels of its points, for display)."""
    active: bool
    """False once undone."""
    scope: Literal["map", "scan", "object"] = "map"
    """``"map"``: every point of every scan in ``keys``; ``"scan"``: only ``points`` of scan ``frame_id``;
    ``"object"``: every point of one object in every scan (``identity``)."""
    frame_id: str | None = None
    """Scan-scope: the scan's frame id (file stem)."""
    points: npt.NDArray[np.int64] | None = None
    """Scan-scope: (P,) indices into that scan's points."""
    author: str | None = None
    """Who made it ("viewer", "api"); None for corrections made before authors were recorded."""
    sequence: str | None = None
    """The project sequence whose scans it corrects (migration 6; voxel keys and frame ids are per
    sequence)."""
    reviewer: str | None = None
    """The reviewer's name the viewer tab was given (migration 9); None when none was given."""
    run_id: int | None = None
    """Object scope: the run whose tracks it was made on (migration 11)."""
    track_id: int | None = None
    """Object scope: the track of that run it relabels."""
    identity: str | None = None
    """Object scope: the file (relative to the work folder) holding the object's point rows per scan
    (:class:`leap_core.pipeline.object_corrections.ObjectIdentity`), matched to later runs' tracks."""
    action: ObjectAction = "relabel"
    """Object scope: ``relabel`` (``class_name``), ``merge`` (the object ``other_track_id`` into
    ``track_id``) or ``split`` (``track_id`` from scan ``split_frame`` on); migration 12, rows before it
    read as relabels."""
    other_track_id: int | None = None
    """Merge: the object of run ``run_id`` merged into ``track_id``."""
    other_identity: str | None = None
    """Merge: that object's identity file (as ``identity``)."""
    split_frame: str | None = None
    """Split: the frame id of the first scan of the new object."""


def _correction(row: dict[str, Any]) -> Correction:
    return Correction(
        id=int(row["id"]),
        project_id=int(row["project_id"]),
        created_at=row["created_at"],
        class_name=row["class_name"],
        voxel_size=float(row["voxel_size"]),
        keys=np.frombuffer(row["keys"], dtype=np.int64).copy(),
        active=bool(row["active"]),
        scope=row["scope"] if row.get("scope") in ("scan", "object") else "map",
        frame_id=row.get("frame_id"),
        points=None if row.get("points") is None else np.frombuffer(row["points"], dtype=np.int64).copy(),
        author=row.get("author"),
        sequence=row.get("sequence"),
        reviewer=row.get("reviewer"),
        run_id=row.get("run_id"),
        track_id=row.get("track_id"),
        identity=row.get("identity"),
        action=row["action"] if row.get("action") in ("merge", "split") else "relabel",
        other_track_id=row.get("other_track_id"),
        other_identity=row.get("other_identity"),
        split_frame=row.get("split_frame"),
    )


CORRECTION_SCOPES = ("map", "scan", "object")
"""Where a correction applies (:attr:`Correction.scope`)."""


@dataclass(frozen=True)
class ObjectRef:
    """What an object-scope correction stores beside its class: the run and track it was made on and its
    identity file (relative to the work folder; :attr:`Correction.identity`)."""

    run_id: int
    track_id: int
    identity: str
    action: ObjectAction = "relabel"
    other_track_id: int | None = None
    other_identity: str | None = None
    split_frame: str | None = None


def add_correction(  # noqa: PLR0913  one keyword per column of the row
    db: sqlite_utils.Database,
    *,
    project_id: int,
    class_name: str,
    voxel_size: float,
    keys: npt.ArrayLike,
    scope: str = "map",
    frame_id: str | None = None,
    points: npt.ArrayLike | None = None,
    author: str | None = None,
    sequence: str | None = None,
    reviewer: str | None = None,
    obj: ObjectRef | None = None,
) -> int:
    """Store a correction (active) of the project's sequence ``sequence`` (None: its first); returns its id.

    Raises:
        InvalidField: an unknown scope, a scan-scope correction without ``frame_id`` / ``points`` (or with
            negative point indices), or a map-scope one with them; an object-scope one without ``obj`` or
            another with it; an unknown ``sequence``.
    """
    arr = np.ascontiguousarray(np.asarray(keys, dtype=np.int64).reshape(-1))
    if scope not in CORRECTION_SCOPES:
        raise InvalidField(("scope",), f"scope must be one of {', '.join(CORRECTION_SCOPES)}, got {scope!r}")
    blob: bytes | None = None
    if scope == "scan":
        if not frame_id:
            raise InvalidField(("frame_id",), "a scan-scope correction needs the scan's frame_id")
        if points is None:
            raise InvalidField(("points",), "a scan-scope correction needs the indices of its points")
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.int64).reshape(-1))
        if pts.size and pts.min() < 0:
            raise InvalidField(("points",), "point indices must be >= 0")
        blob = pts.tobytes()
    elif frame_id is not None or points is not None:
        field = "frame_id" if frame_id is not None else "points"
        raise InvalidField((field,), f"{field} is only for scan-scope corrections")
    if (scope == "object") != (obj is not None):
        raise InvalidField(("track_id",), "an object-scope correction, and only one, names a run's track")
    require_project(db, project_id)
    seq = sequence_name(db, project_id, sequence)
    cursor = db.execute(
        "INSERT INTO corrections (project_id, created_at, class_name, voxel_size, keys, active, scope, "
        "frame_id, points, author, sequence, reviewer, run_id, track_id, identity, action, other_track_id, "
        "other_identity, split_frame) VALUES (?, ?, ?, ?, ?, 1, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        [
            project_id,
            utcnow(),
            class_name,
            float(voxel_size),
            arr.tobytes(),
            scope,
            frame_id,
            blob,
            author,
            seq,
            reviewer,
            None if obj is None else obj.run_id,
            None if obj is None else obj.track_id,
            None if obj is None else obj.identity,
            None if obj is None else obj.action,
            None if obj is None else obj.other_track_id,
            None if obj is None else obj.other_identity,
            None if obj is None else obj.split_frame,
        ],
    )
    return _inserted_id(cursor)


def get_correction(db: sqlite_utils.Database, correction_id: int) -> Correction:
    """One correction. Raises NotFound."""
    cursor = db.execute("SELECT * FROM corrections WHERE id = ?", [correction_id])
    row = cursor.fetchone()
    if row is None:
        raise NotFound(f"Correction {correction_id} not found")
    return _correction(dict(zip([d[0] for d in cursor.description], row, strict=True)))


def list_corrections(
    db: sqlite_utils.Database, project_id: int, *, active_only: bool = True, sequence: str | None = None
) -> list[Correction]:
    """Corrections of one sequence of a project (None: its first) in the order they were made (later ones
    win on overlap)."""
    where = " AND active = 1" if active_only else ""
    if sequence is None and not list_sequences(db, project_id):
        return []  # a deleted project has none (its corrections went with it)
    seq = sequence_name(db, project_id, sequence)
    cursor = db.execute(
        f"SELECT * FROM corrections WHERE project_id = ? AND sequence = ?{where} ORDER BY id",
        [project_id, seq],
    )
    names = [d[0] for d in cursor.description]
    return [_correction(dict(zip(names, r, strict=True))) for r in cursor.fetchall()]


def set_correction_active(db: sqlite_utils.Database, correction_id: int, active: bool) -> None:
    """Undo (``active=False``) or redo a correction."""
    cursor = db.execute("UPDATE corrections SET active = ? WHERE id = ?", [int(active), correction_id])
    if cursor.rowcount == 0:
        raise NotFound(f"Correction {correction_id} not found")


# ---------------------------------------------------------------------------------------- review marks
@dataclass(frozen=True)
class ReviewMark:
    """A reviewer's verdict on one review region (see :mod:`leap_core.review` for identity/signature)."""

    region: str
    """Stable region identity (:func:`leap_core.review.region_id`)."""
    signature: str
    """Content signature the verdict was made on; the mark counts only while the region still has it."""
    state: str
    """``accepted`` (reviewed) or ``skipped``."""
    run_id: int | None
    """Run shown when the mark was made."""
    updated_at: str
    """ISO UTC time."""


REVIEW_STATES = ("accepted", "skipped")
"""Values of :attr:`ReviewMark.state`."""


def set_review_mark(
    db: sqlite_utils.Database,
    project_id: int,
    *,
    region: str,
    signature: str,
    state: str,
    run_id: int | None = None,
    sequence: str | None = None,
    reviewer: str | None = None,
) -> None:
    """Record (or replace) the verdict on ``region`` of the sequence ``sequence`` (None: the first), by
    ``reviewer`` (None: unnamed)."""
    if state not in REVIEW_STATES:
        raise ValueError(f"state must be one of {', '.join(REVIEW_STATES)}, got {state!r}")
    require_project(db, project_id)
    key = review_key(db, project_id, sequence, region)
    db.execute(
        "INSERT INTO review_marks (project_id, region, signature, state, run_id, updated_at, reviewer) "
        "VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT(project_id, region) DO UPDATE SET "
        "signature = excluded.signature, state = excluded.state, run_id = excluded.run_id, "
        "updated_at = excluded.updated_at, reviewer = excluded.reviewer",
        [project_id, key, signature, state, run_id, utcnow(), reviewer],
    )


def review_key(db: sqlite_utils.Database, project_id: int, sequence: str | None, region: str) -> str:
    """How a mark on ``region`` of ``sequence`` (None: the first) is stored in ``review_marks.region``:
    ``<sequence>/<region>`` (sequence names hold no ``/``; a region's identity is a place in that
    sequence's world frame)."""
    return f"{sequence_name(db, project_id, sequence)}/{region}"


def list_review_marks(
    db: sqlite_utils.Database, project_id: int, sequence: str | None = None
) -> dict[str, ReviewMark]:
    """The review marks of one sequence of the project (None: its first) by region identity (a region's
    identity is a place in that sequence's world frame)."""
    prefix = review_key(db, project_id, sequence, "")
    rows = db.execute(
        "SELECT region, signature, state, run_id, updated_at FROM review_marks WHERE project_id = ?",
        [project_id],
    ).fetchall()
    out = {}
    for r in rows:
        if not r[0].startswith(prefix):
            continue
        region = r[0][len(prefix) :]
        out[region] = ReviewMark(region, r[1], r[2], None if r[3] is None else int(r[3]), r[4])
    return out


def save_review_queue(
    db: sqlite_utils.Database,
    project_id: int,
    kind: str,
    run_id: int | None,
    regions: Sequence[tuple[str, str]],
    sequence: str | None = None,
) -> None:
    """Remember the latest ranked queue of ``kind`` of the sequence ``sequence`` (None: the first):
    ``(region, signature)`` pairs, best first (the web UI counts review progress against it without
    starting a viewer)."""
    require_project(db, project_id)
    seq = sequence_name(db, project_id, sequence)
    db.execute(
        "INSERT INTO review_queues (project_id, sequence, kind, run_id, regions_json, updated_at) "
        "VALUES (?, ?, ?, ?, ?, ?) "
        "ON CONFLICT(project_id, sequence, kind) DO UPDATE SET run_id = excluded.run_id, "
        "regions_json = excluded.regions_json, updated_at = excluded.updated_at",
        [project_id, seq, kind, run_id, _dumps([list(r) for r in regions]), utcnow()],
    )


def review_progress(
    db: sqlite_utils.Database, project_id: int, sequence: str | None = None
) -> list[dict[str, Any]]:
    """Per saved queue of the sequence (None: the first): ``kind``, ``run_id``, ``total``, ``reviewed``
    (accepted with an unchanged signature), ``skipped`` (likewise) and ``updated_at``."""
    require_project(db, project_id)
    seq = sequence_name(db, project_id, sequence)
    marks = list_review_marks(db, project_id, seq)
    out = []
    for kind, run_id, regions_json, updated_at in db.execute(
        "SELECT kind, run_id, regions_json, updated_at FROM review_queues "
        "WHERE project_id = ? AND sequence = ? ORDER BY kind",
        [project_id, seq],
    ).fetchall():
        regions = json.loads(regions_json)
        states = [
            m.state for region, sig in regions if (m := marks.get(region)) is not None and m.signature == sig
        ]
        out.append(
            {
                "kind": kind,
                "run_id": run_id,
                "total": len(regions),
                "reviewed": states.count("accepted"),
                "skipped": states.count("skipped"),
                "updated_at": updated_at,
            }
        )
    return out


# ------------------------------------------------------------------------------------------------ meta
def get_meta(db: sqlite_utils.Database, key: str) -> str | None:
    row = db.execute("SELECT value FROM meta WHERE key = ?", [key]).fetchone()
    return None if row is None else str(row[0])


def set_meta(db: sqlite_utils.Database, key: str, value: str) -> None:
    db.execute(
        "INSERT INTO meta (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE SET value = ?",
        [key, value, value],
    )


# ------------------------------------------------------------------------------------------ model jobs
def _model_job(row: dict[str, Any]) -> ModelJobRow:
    return ModelJobRow(
        id=int(row["id"]),
        project_id=int(row["project_id"]),
        kind=cast("ModelJobKind", row["kind"]),
        status=cast("ModelJobStatus", row["status"]),
        name=str(row["name"]),
        model_id=None if row["model_id"] is None else int(row["model_id"]),
        params=dict(row["params"]),
        done=int(row["done"]),
        total=int(row["total"]),
        error=row["error"],
        created_at=str(row["created_at"]),
        started_at=row["started_at"],
        finished_at=row["finished_at"],
    )


def create_model_job(
    db: sqlite_utils.Database,
    *,
    project_id: int,
    kind: ModelJobKind,
    name: str,
    params: dict[str, Any],
    model_id: int | None = None,
) -> ModelJobRow:
    """Insert a queued model job."""
    with transaction(db):
        cursor = db.execute(
            "INSERT INTO model_jobs (project_id, kind, status, name, model_id, params_json, created_at) "
            "VALUES (?, ?, 'queued', ?, ?, ?, ?)",
            [project_id, kind, name, model_id, _dumps(params), utcnow()],
        )
        job_id = _inserted_id(cursor)
    return require_model_job(db, job_id)


def get_model_job(db: sqlite_utils.Database, job_id: int) -> ModelJobRow | None:
    row = _one(db, "SELECT * FROM model_jobs WHERE id = ?", [job_id])
    return None if row is None else _model_job(row)


def require_model_job(db: sqlite_utils.Database, job_id: int, project_id: int | None = None) -> ModelJobRow:
    """The job row, or :class:`NotFound` (also when it belongs to another project than ``project_id``)."""
    job = get_model_job(db, job_id)
    if job is None or (project_id is not None and job.project_id != project_id):
        raise NotFound(
            f"Model job {job_id} not found" + ("" if project_id is None else f" in project {project_id}")
        )
    return job


def list_model_jobs(
    db: sqlite_utils.Database, project_id: int | None = None, statuses: Sequence[str] = ()
) -> list[ModelJobRow]:
    """A project's model jobs (or every project's), newest first, optionally only in ``statuses``."""
    where: list[str] = []
    params: list[Any] = []
    if project_id is not None:
        where.append("project_id = ?")
        params.append(project_id)
    if statuses:
        where.append(f"status IN ({', '.join('?' for _ in statuses)})")
        params += list(statuses)
    sql = (
        "SELECT * FROM model_jobs" + (f" WHERE {' AND '.join(where)}" if where else "") + " ORDER BY id DESC"
    )
    return [_model_job(r) for r in _rows(db, sql, params)]


def update_model_job(db: sqlite_utils.Database, job_id: int, **fields: Any) -> None:
    """Set columns of a model job (``status``, ``done``, ``total``, ``error``, ``started_at``, ...)."""
    if not fields:
        return
    cols = ", ".join(f"{k} = ?" for k in fields)
    with transaction(db):
        db.execute(f"UPDATE model_jobs SET {cols} WHERE id = ?", [*fields.values(), job_id])
