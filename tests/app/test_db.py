"""SQLite schema versioning and the corrections table used by the viewer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app import crud
from app.core import db as dbmod
from app.core.errors import NotFound


def test_fresh_database_is_migrated_once(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    assert dbmod.init_db(path) == dbmod.SCHEMA_VERSION
    assert dbmod.init_db(path) == dbmod.SCHEMA_VERSION  # idempotent
    with dbmod.open_db(path) as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        rows = db.execute("SELECT version FROM schema_version").fetchall()
        assert [r[0] for r in rows] == [m[0] for m in dbmod.MIGRATIONS]
        assert {"projects", "runs", "corrections", "meta"} <= set(db.table_names())


def test_newer_database_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    dbmod.init_db(path)
    with dbmod.open_db(path) as db:
        db.execute("INSERT INTO schema_version VALUES (?, 'future', 'now')", [dbmod.SCHEMA_VERSION + 1])
    with pytest.raises(dbmod.DatabaseVersionError, match="newer"):
        dbmod.init_db(path)


def test_failed_migration_rolls_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(db) -> None:
        db.execute("CREATE TABLE half_done (x)")
        raise RuntimeError("boom")

    path = tmp_path / "s.db"
    released = dbmod.init_db(path)
    monkeypatch.setattr(dbmod, "MIGRATIONS", [*dbmod.MIGRATIONS, (99, "broken", broken)])
    monkeypatch.setattr(dbmod, "SCHEMA_VERSION", 99)
    with pytest.raises(RuntimeError, match="boom"):
        dbmod.init_db(path)
    with dbmod.open_db(path) as db:
        assert "half_done" not in db.table_names() and dbmod.current_version(db) == released


def test_corrections_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    dbmod.init_db(path)
    with dbmod.open_db(path) as db:
        p = crud.create_project(
            db, name="p", dataset_kind="demo", sequences=[("x", "/x")], schema={}, pipeline={}
        )
        keys = np.array([5, -3, 1 << 40], dtype=np.int64)
        cid = crud.add_correction(db, project_id=p.id, class_name="car", voxel_size=0.2, keys=keys)
        crud.add_correction(db, project_id=p.id, class_name="road", voxel_size=0.2, keys=[7])
        got = crud.list_corrections(db, p.id)
        assert [c.class_name for c in got] == ["car", "road"]
        assert got[0].keys.dtype == np.int64 and np.array_equal(got[0].keys, keys) and got[0].active
        crud.set_correction_active(db, cid, False)
        assert [c.class_name for c in crud.list_corrections(db, p.id)] == ["road"]
        assert [c.active for c in crud.list_corrections(db, p.id, active_only=False)] == [False, True]
        crud.set_correction_active(db, cid, True)
        assert len(crud.list_corrections(db, p.id)) == 2
        with pytest.raises(NotFound):
            crud.set_correction_active(db, 999, False)
        with pytest.raises(NotFound):
            crud.add_correction(db, project_id=999, class_name="car", voxel_size=0.2, keys=[1])
        crud.delete_project(db, p.id)
        assert crud.list_corrections(db, p.id, active_only=False) == []  # cascade
