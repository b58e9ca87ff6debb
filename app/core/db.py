"""SQLite storage (sqlite-utils) with a versioned schema.

One database file holds projects, runs, manual corrections and a small key/value ``meta`` table. The
schema version lives in ``schema_version``; :data:`MIGRATIONS` are applied in order, each in its own
transaction, so an older database is upgraded on start-up and a newer one is refused.

Connections are cheap (WAL mode, no shared cache): every request and every job thread opens its own.
"""

from __future__ import annotations

import datetime as dt
import functools
import json
import sqlite3
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import sqlite_utils


def utcnow() -> str:
    """Current UTC time as an ISO-8601 string with a ``Z`` suffix (sortable, unambiguous)."""
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _execute_script(db: sqlite_utils.Database, script: str) -> None:
    # sqlite3's executescript() commits any open transaction first; run statement by statement instead.
    for statement in script.split(";"):
        if statement.strip():
            db.execute(statement)


def _v1_initial(db: sqlite_utils.Database) -> None:
    _execute_script(
        db,
        """
        CREATE TABLE projects (
            id INTEGER PRIMARY KEY,
            name TEXT NOT NULL,
            dataset_kind TEXT NOT NULL CHECK (dataset_kind IN ('demo', 'folder')),
            dataset_path TEXT NOT NULL,
            schema_json TEXT NOT NULL,
            pipeline_json TEXT NOT NULL,
            is_demo INTEGER NOT NULL DEFAULT 0,
            created_at TEXT NOT NULL,
            updated_at TEXT NOT NULL
        );
        CREATE TABLE runs (
            id INTEGER PRIMARY KEY,
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            number INTEGER NOT NULL,
            status TEXT NOT NULL CHECK (status IN
                ('queued', 'running', 'done', 'failed', 'cancelled', 'interrupted')),
            params_json TEXT NOT NULL,
            run_dir TEXT NOT NULL,
            stages_json TEXT NOT NULL DEFAULT '{}',
            metrics_json TEXT,
            error TEXT,
            attempts INTEGER NOT NULL DEFAULT 0,
            created_at TEXT NOT NULL,
            started_at TEXT,
            finished_at TEXT
        );
        CREATE INDEX runs_project ON runs(project_id, id);
        CREATE INDEX runs_status ON runs(status);
        CREATE TABLE corrections (
            id INTEGER PRIMARY KEY,
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            created_at TEXT NOT NULL,
            class_name TEXT NOT NULL,
            voxel_size REAL NOT NULL,
            keys BLOB NOT NULL,
            active INTEGER NOT NULL DEFAULT 1
        );
        CREATE INDEX corrections_project ON corrections(project_id, id);
        CREATE TABLE meta (
            key TEXT PRIMARY KEY,
            value TEXT NOT NULL
        );
        """,
    )


def _v2_run_note(db: sqlite_utils.Database) -> None:
    db.execute("ALTER TABLE runs ADD COLUMN note TEXT")


def _v3_correction_scope(db: sqlite_utils.Database) -> None:
    # Existing rows are map-scope corrections made before authors were recorded (author stays NULL).
    _execute_script(
        db,
        """
        ALTER TABLE corrections ADD COLUMN scope TEXT NOT NULL DEFAULT 'map' CHECK (scope IN ('map', 'scan'));
        ALTER TABLE corrections ADD COLUMN frame_id TEXT;
        ALTER TABLE corrections ADD COLUMN points BLOB;
        ALTER TABLE corrections ADD COLUMN author TEXT
        """,
    )


def _v4_review_marks(db: sqlite_utils.Database) -> None:
    _execute_script(
        db,
        """
        CREATE TABLE review_marks (
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            region TEXT NOT NULL,
            signature TEXT NOT NULL,
            state TEXT NOT NULL CHECK (state IN ('accepted', 'skipped')),
            run_id INTEGER,
            updated_at TEXT NOT NULL,
            PRIMARY KEY (project_id, region)
        );
        CREATE TABLE review_queues (
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            kind TEXT NOT NULL CHECK (kind IN ('confidence', 'disagreement')),
            run_id INTEGER,
            regions_json TEXT NOT NULL,
            updated_at TEXT NOT NULL,
            PRIMARY KEY (project_id, kind)
        );
        """,
    )


def _v5_estimate_poses(db: sqlite_utils.Database) -> None:
    # Existing projects read their dataset's poses.txt as before.
    db.execute("ALTER TABLE projects ADD COLUMN estimate_poses INTEGER NOT NULL DEFAULT 0")


def _v6_project_sequences(db: sqlite_utils.Database) -> None:
    # A project labels one or more sequences with one class schema. Every existing project gets its one
    # sequence, named after its folder (".../sequences/00" -> "00"), and its corrections and saved review
    # queues are scoped to it, so single-sequence projects read exactly what they did. review_queues gains
    # the sequence in its primary key (SQLite cannot alter a key: the table is rebuilt). review_marks keeps
    # its columns: in a project with several sequences a mark's region is stored as "<sequence>/<region>"
    # (app.crud.review_key), so a single-sequence project's marks are unchanged.
    _execute_script(
        db,
        """
        CREATE TABLE project_sequences (
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            name TEXT NOT NULL,
            dataset_path TEXT NOT NULL,
            position INTEGER NOT NULL,
            PRIMARY KEY (project_id, name),
            UNIQUE (project_id, position)
        );
        ALTER TABLE corrections ADD COLUMN sequence TEXT;
        CREATE TABLE review_queues_v6 (
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            sequence TEXT NOT NULL,
            kind TEXT NOT NULL CHECK (kind IN ('confidence', 'disagreement')),
            run_id INTEGER,
            regions_json TEXT NOT NULL,
            updated_at TEXT NOT NULL,
            PRIMARY KEY (project_id, sequence, kind)
        )
        """,
    )
    for project_id, dataset_path in db.execute("SELECT id, dataset_path FROM projects").fetchall():
        db.execute(
            "INSERT INTO project_sequences (project_id, name, dataset_path, position) VALUES (?, ?, ?, 0)",
            [project_id, default_sequence_name(dataset_path), dataset_path],
        )
    _execute_script(
        db,
        """
        UPDATE corrections SET sequence =
            (SELECT s.name FROM project_sequences s WHERE s.project_id = corrections.project_id);
        INSERT INTO review_queues_v6 (project_id, sequence, kind, run_id, regions_json, updated_at)
            SELECT q.project_id, s.name, q.kind, q.run_id, q.regions_json, q.updated_at
            FROM review_queues q JOIN project_sequences s ON s.project_id = q.project_id;
        DROP TABLE review_queues;
        ALTER TABLE review_queues_v6 RENAME TO review_queues;
        CREATE INDEX corrections_sequence ON corrections(project_id, sequence, id)
        """,
    )


def _v7_sequence_removal(db: sqlite_utils.Database) -> None:
    # Sequences can be added to and removed from an existing project. A removed sequence keeps its row
    # (removed_at set) so its name stays bound to its folder: its corrections, review marks and queues are
    # the user's and stay, and come back when the same folder is added again under that name; the name
    # cannot be given to another folder, whose world frame those voxel keys do not describe.
    db.execute("ALTER TABLE project_sequences ADD COLUMN removed_at TEXT")


def _v8_one_run_shape(db: sqlite_utils.Database) -> None:
    # Every run labels a list of sequences (often one). Runs of one sequence stored their dataset and
    # frames at the top of their parameters and plain stage names; they get the list (the sequence named
    # as the project calls the sequence on that folder), "<sequence>/<stage>" progress stages and
    # metrics of the run's shape ({"overall", "sequences"}). Review marks always carry their sequence
    # ("<sequence>/<region>"); a project of one sequence stored bare regions. Run folders move to the
    # same shape when the server starts (app.jobs.folders).
    names: dict[tuple[int, str], str] = {}
    for project_id, name, path in db.execute(
        "SELECT project_id, name, dataset_path FROM project_sequences "
        "ORDER BY removed_at IS NOT NULL, position"
    ).fetchall():
        names.setdefault((int(project_id), str(path)), str(name))
    for run_id, project_id, params_json, stages_json, metrics_json in db.execute(
        "SELECT id, project_id, params_json, stages_json, metrics_json FROM runs"
    ).fetchall():
        params = json.loads(params_json)
        if "sequences" in params and "dataset" not in params:
            continue
        updates = one_run_shape(
            params,
            None if stages_json is None else json.loads(stages_json),
            None if metrics_json is None else json.loads(metrics_json),
            functools.partial(_name_of, names, int(project_id)),
        )
        db.execute(
            "UPDATE runs SET params_json = ?, stages_json = ?, metrics_json = ? WHERE id = ?",
            [*(None if u is None else _dumps(u) for u in updates), run_id],
        )
    db.execute(
        "UPDATE review_marks SET region = (SELECT s.name FROM project_sequences s WHERE "
        "s.project_id = review_marks.project_id AND s.removed_at IS NULL ORDER BY s.position LIMIT 1) "
        "|| '/' || region WHERE instr(region, '/') = 0"
    )


def _v9_reviewers(db: sqlite_utils.Database) -> None:
    # Several people review one project: every correction and review mark records the reviewer's name
    # (NULL for those made before names were asked, or through the API without one), and a reviewer claims
    # regions of a saved review queue so the others skip them until the claim expires or is released.
    _execute_script(
        db,
        """
        ALTER TABLE corrections ADD COLUMN reviewer TEXT;
        ALTER TABLE review_marks ADD COLUMN reviewer TEXT;
        CREATE TABLE review_claims (
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            sequence TEXT NOT NULL,
            region TEXT NOT NULL,
            reviewer TEXT NOT NULL,
            claimed_at TEXT NOT NULL,
            expires_at TEXT NOT NULL,
            PRIMARY KEY (project_id, sequence, region)
        );
        """,
    )


def _v10_model_jobs(db: sqlite_utils.Database) -> None:
    # LiDAR-only models trained on a project's labels and the labelings made with them: both are background
    # jobs with progress, cancel and resume. AUTOINCREMENT: a job's id names its folder, never handed out
    # again after a project (and its jobs) is deleted.
    _execute_script(
        db,
        """
        CREATE TABLE model_jobs (
            id INTEGER PRIMARY KEY AUTOINCREMENT,
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            kind TEXT NOT NULL,
            status TEXT NOT NULL,
            name TEXT NOT NULL,
            model_id INTEGER,
            params_json TEXT NOT NULL,
            done INTEGER NOT NULL DEFAULT 0,
            total INTEGER NOT NULL DEFAULT 0,
            error TEXT,
            created_at TEXT NOT NULL,
            started_at TEXT,
            finished_at TEXT
        );
        CREATE INDEX model_jobs_project ON model_jobs (project_id, id);
        """,
    )


def _v11_object_corrections(db: sqlite_utils.Database) -> None:
    # A correction may name one object (scope 'object'): the run and track it was made on, and the file
    # under the work folder that keeps the object's point rows per scan (its identity, matched to later
    # runs' tracks). SQLite cannot widen a CHECK in place: the table is rebuilt with its rows and indexes.
    _execute_script(
        db,
        """
        CREATE TABLE corrections_v11 (
            id INTEGER PRIMARY KEY,
            project_id INTEGER NOT NULL REFERENCES projects(id) ON DELETE CASCADE,
            created_at TEXT NOT NULL,
            class_name TEXT NOT NULL,
            voxel_size REAL NOT NULL,
            keys BLOB NOT NULL,
            active INTEGER NOT NULL DEFAULT 1,
            scope TEXT NOT NULL DEFAULT 'map' CHECK (scope IN ('map', 'scan', 'object')),
            frame_id TEXT,
            points BLOB,
            author TEXT,
            sequence TEXT,
            reviewer TEXT,
            run_id INTEGER,
            track_id INTEGER,
            identity TEXT
        );
        INSERT INTO corrections_v11 (id, project_id, created_at, class_name, voxel_size, keys, active, scope,
            frame_id, points, author, sequence, reviewer)
            SELECT id, project_id, created_at, class_name, voxel_size, keys, active, scope, frame_id, points,
            author, sequence, reviewer FROM corrections;
        DROP TABLE corrections;
        ALTER TABLE corrections_v11 RENAME TO corrections;
        CREATE INDEX corrections_project ON corrections(project_id, id);
        CREATE INDEX corrections_sequence ON corrections(project_id, sequence, id)
        """,
    )


def _v12_object_edits(db: sqlite_utils.Database) -> None:
    # An object correction may merge two objects or split one at a scan: what it does (NULL: a relabel, as
    # every row before), the second object of a merge (its track and identity file) and a split's scan.
    _execute_script(
        db,
        """
        ALTER TABLE corrections ADD COLUMN action TEXT;
        ALTER TABLE corrections ADD COLUMN other_track_id INTEGER;
        ALTER TABLE corrections ADD COLUMN other_identity TEXT;
        ALTER TABLE corrections ADD COLUMN split_frame TEXT
        """,
    )


def _name_of(names: dict[tuple[int, str], str], project_id: int, path: str) -> str | None:
    return names.get((project_id, path))


def one_run_shape(
    params: dict[str, Any],
    stages: dict[str, Any] | None,
    metrics: dict[str, Any] | None,
    name_of: Callable[[str], str | None],
) -> tuple[dict[str, Any], dict[str, Any] | None, dict[str, Any] | None]:
    """A run's stored parameters, progress record and metrics of an earlier shape in today's (see
    :func:`_v8_one_run_shape`); ``name_of(dataset_path)`` is the project's name of the sequence on that
    folder (None: the folder's own name)."""
    from leap_core.pipeline.evaluation import overall_metrics  # noqa: PLC0415  loads numpy: only here
    from leap_core.pipeline.metrics_file import SequenceMetrics  # noqa: PLC0415

    params = dict(params)
    dataset, frames = params.pop("dataset", None), params.pop("frames", None)
    if "sequences" in params:
        params["sequences"] = [{**s, "frames": s.get("frames")} for s in params["sequences"]]
        return params, stages, metrics
    name = name_of(str(dataset)) or default_sequence_name(str(dataset))
    params = {"sequences": [{"name": name, "dataset": str(dataset), "frames": frames}], **params}

    def staged(stage: str) -> str:
        return f"{name}/{stage}"

    params["stages"] = [staged(s) for s in params.get("stages") or []]
    if stages:
        stages = {
            **stages,
            "order": [staged(s) for s in stages.get("order") or []],
            "stages": {staged(k): v for k, v in (stages.get("stages") or {}).items()},
        }
    if metrics is not None and "overall" not in metrics:
        summed = overall_metrics({name: SequenceMetrics.from_dict(metrics, f"run metrics of {dataset}")})
        metrics = {"overall": None if summed is None else summed.to_dict(), "sequences": {name: metrics}}
    return params, stages, metrics


def _dumps(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"))


def default_sequence_name(dataset_path: str) -> str:
    """The name a sequence gets from its folder when none is given: the folder's own name (``00`` for
    ``.../sequences/00``), or ``"00"`` for a path without one."""
    name = Path(dataset_path).name
    return name if name not in ("", ".", "..") else "00"


Migration = tuple[int, str, Callable[[sqlite_utils.Database], None]]

MIGRATIONS: list[Migration] = [
    (1, "projects, runs, corrections, meta", _v1_initial),
    (2, "runs.note", _v2_run_note),
    (3, "corrections.scope, frame_id, points, author", _v3_correction_scope),
    (4, "review_marks, review_queues", _v4_review_marks),
    (5, "projects.estimate_poses", _v5_estimate_poses),
    (6, "project_sequences; corrections and review queues per sequence", _v6_project_sequences),
    (7, "project_sequences.removed_at", _v7_sequence_removal),
    (8, "runs of one shape: a list of sequences; review marks per sequence", _v8_one_run_shape),
    (9, "reviewer names on corrections and review marks; review_claims", _v9_reviewers),
    (
        10,
        "model_jobs: LiDAR-only models trained on a project's labels and labelings with them",
        _v10_model_jobs,
    ),
    (11, "object-scope corrections: corrections.run_id, track_id, identity", _v11_object_corrections),
    (
        12,
        "merge and split of objects: corrections.action, other_track_id, other_identity, split_frame",
        _v12_object_edits,
    ),
]
"""Ordered schema migrations: (version, description, apply). Append only; never edit a released one."""

SCHEMA_VERSION = MIGRATIONS[-1][0]


class DatabaseVersionError(RuntimeError):
    """The database was written by a newer LeAP Studio."""


_size_caps: dict[Path, int] = {}
"""Largest size in bytes per database file (``Settings.db_max_mb``), applied to every connection."""


def set_size_cap(path: Path, max_bytes: int | None) -> None:
    """Cap the database at ``path`` to ``max_bytes`` (None removes the cap) for connections opened from
    now on. SQLite then fails a write that needs more pages with ``database or disk is full``, exactly
    as on a full disk (``PRAGMA max_page_count`` is a per-connection setting, hence this registry)."""
    if max_bytes is None:
        _size_caps.pop(path, None)
    else:
        _size_caps[path] = max_bytes


def connect(path: Path, *, set_wal: bool = True) -> sqlite_utils.Database:
    """Open ``path`` (created if missing) in WAL mode with foreign keys on.

    WAL mode is stored in the file: connections to a database :func:`init_db` prepared may skip setting it
    (``set_wal=False``), which keeps opening a connection free of any lock.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    conn = sqlite3.connect(str(path), timeout=30.0, check_same_thread=False, isolation_level=None)
    if set_wal:
        conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA synchronous=NORMAL")
    conn.execute("PRAGMA foreign_keys=ON")
    conn.execute("PRAGMA busy_timeout=30000")
    cap = _size_caps.get(path)
    if cap is not None:
        page_size = int(conn.execute("PRAGMA page_size").fetchone()[0])
        conn.execute(f"PRAGMA max_page_count = {max(1, cap // page_size)}")
    return sqlite_utils.Database(conn)


def current_version(db: sqlite_utils.Database) -> int:
    if not db["schema_version"].exists():
        return 0
    row = db.execute("SELECT MAX(version) FROM schema_version").fetchone()
    return int(row[0] or 0)


def migrate(db: sqlite_utils.Database) -> int:
    """Apply pending migrations in order; return the resulting version."""
    db.execute(
        "CREATE TABLE IF NOT EXISTS schema_version "
        "(version INTEGER PRIMARY KEY, description TEXT NOT NULL, applied_at TEXT NOT NULL)"
    )
    version = current_version(db)
    if version > SCHEMA_VERSION:
        raise DatabaseVersionError(
            f"database schema version {version} is newer than this program's {SCHEMA_VERSION}; "
            "upgrade LeAP Studio"
        )
    for number, description, apply in MIGRATIONS:
        if number <= version:
            continue
        with transaction(db):
            apply(db)
            db.execute(
                "INSERT INTO schema_version (version, description, applied_at) VALUES (?, ?, ?)",
                [number, description, utcnow()],
            )
        version = number
    return version


@contextmanager
def transaction(db: sqlite_utils.Database) -> Iterator[None]:
    """``BEGIN IMMEDIATE`` … ``COMMIT`` (rollback on error); writers never interleave inside one.

    Nested use joins the outer transaction, so crud functions can be composed atomically by a caller.
    """
    conn = db.conn
    if conn.in_transaction:
        yield
        return
    conn.execute("BEGIN IMMEDIATE")
    try:
        yield
    except BaseException:
        # SQLite ends the transaction itself after some errors (a full disk); a ROLLBACK then would
        # raise "no transaction is active" and hide the error that matters.
        if conn.in_transaction:
            conn.execute("ROLLBACK")
        raise
    conn.execute("COMMIT")


def init_db(path: Path) -> int:
    """Create or upgrade the database at ``path``; return its schema version."""
    db = connect(path)
    try:
        return migrate(db)
    finally:
        db.close()


class ConnectionPool:
    """Idle connections to one database, reused across requests (opening one costs about a millisecond).

    A connection is used by one request at a time: :meth:`connection` takes it from the pool and puts it
    back afterwards, rolled back if the request left a transaction open.
    """

    def __init__(self, path: Path, max_idle: int = 16, *, prefill: int = 4) -> None:
        self.path = path
        self.max_idle = max_idle
        self._lock = threading.Lock()
        self._idle: list[sqlite_utils.Database] = [connect(path) for _ in range(min(prefill, max_idle))]

    @contextmanager
    def connection(self) -> Iterator[sqlite_utils.Database]:
        with self._lock:
            db = self._idle.pop() if self._idle else None
        if db is None:
            db = connect(self.path, set_wal=False)
        try:
            yield db
        finally:
            if db.conn.in_transaction:
                db.conn.execute("ROLLBACK")
            with self._lock:
                if len(self._idle) < self.max_idle:
                    self._idle.append(db)
                    db = None
            if db is not None:
                db.close()

    def close(self) -> None:
        with self._lock:
            idle, self._idle = self._idle, []
        for db in idle:
            db.close()


@contextmanager
def open_db(path: Path) -> Iterator[sqlite_utils.Database]:
    """A connection for one unit of work, closed afterwards."""
    db = connect(path)
    try:
        yield db
    finally:
        db.close()
