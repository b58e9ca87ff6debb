"""Review marks: migration 4, the crud rules of review progress, and the review routes' answers."""

from __future__ import annotations

from pathlib import Path

import appfixtures
import pytest
from fastapi.testclient import TestClient

from app import crud
from app.core import db as dbmod
from app.core.config import Settings

settings = appfixtures.settings
data_root = appfixtures.data_root
client = appfixtures.client

SCHEMA = {"name": "s", "classes": [{"name": "car", "color": [1, 2, 3], "prompts": ["car"], "export_id": 10}]}


def _project(db, name: str = "p") -> int:  # type: ignore[no-untyped-def]
    p = crud.create_project(
        db, name=name, dataset_kind="folder", sequences=[("x", "/x")], schema=SCHEMA, pipeline={}
    )
    return p.id


def test_migration_4_upgrades_a_version_2_database(tmp_path: Path) -> None:
    path = tmp_path / "old.db"
    with dbmod.open_db(path) as db:
        db.execute(
            "CREATE TABLE schema_version (version INTEGER PRIMARY KEY, description TEXT NOT NULL, "
            "applied_at TEXT NOT NULL)"
        )
        for number, description, apply in dbmod.MIGRATIONS:
            if number <= 2:
                apply(db)
                db.execute("INSERT INTO schema_version VALUES (?, ?, 'then')", [number, description])
        assert "review_marks" not in db.table_names()
    assert dbmod.init_db(path) == dbmod.SCHEMA_VERSION >= 4
    with dbmod.open_db(path) as db:
        assert {"review_marks", "review_queues"} <= set(db.table_names())
        pid = _project(db)
        crud.set_review_mark(db, pid, region="4m:0,0,0", signature="ab", state="accepted", run_id=None)
        with pytest.raises(Exception, match="CHECK"):
            db.execute(
                "INSERT INTO review_marks (project_id, region, signature, state, run_id, updated_at) "
                "VALUES (?, 'r', 's', 'maybe', NULL, 'now')",
                [pid],
            )
        # Marks go with their project.
        crud.delete_project(db, pid)
        assert db.execute("SELECT COUNT(*) FROM review_marks").fetchone()[0] == 0


def test_progress_counts_marks_on_unchanged_content_only(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    dbmod.init_db(path)
    with dbmod.open_db(path) as db:
        pid = _project(db)
        other = _project(db, "other")
        assert crud.review_progress(db, pid) == []
        crud.save_review_queue(db, pid, "confidence", 7, [("a", "s1"), ("b", "s2"), ("c", "s3")])
        crud.set_review_mark(db, pid, region="a", signature="s1", state="accepted")
        crud.set_review_mark(db, pid, region="b", signature="old", state="accepted")  # b changed since
        crud.set_review_mark(db, pid, region="c", signature="s3", state="skipped")
        crud.set_review_mark(db, other, region="a", signature="s1", state="skipped")  # other project
        (row,) = crud.review_progress(db, pid)
        assert (row["kind"], row["run_id"], row["total"], row["reviewed"], row["skipped"]) == (
            "confidence",
            7,
            3,
            1,
            1,
        )
        # Re-marking replaces; a re-ranked queue replaces the saved one.
        crud.set_review_mark(db, pid, region="b", signature="s2", state="accepted")
        crud.save_review_queue(db, pid, "confidence", 8, [("b", "s2"), ("d", "s4")])
        (row,) = crud.review_progress(db, pid)
        assert (row["run_id"], row["total"], row["reviewed"], row["skipped"]) == (8, 2, 1, 0)
        with pytest.raises(ValueError, match="state must be one of"):
            crud.set_review_mark(db, pid, region="a", signature="s", state="maybe")


def test_review_routes(client: TestClient, settings: Settings) -> None:
    with dbmod.open_db(settings.database) as db:
        pid = _project(db)
    assert client.get(f"/api/v1/projects/{pid}/review").json() == {"data": []}
    with dbmod.open_db(settings.database) as db:
        crud.save_review_queue(db, pid, "disagreement", None, [("a", "s1"), ("b", "s2")])
        crud.set_review_mark(db, pid, region="b", signature="s2", state="accepted")
    (row,) = client.get(f"/api/v1/projects/{pid}/review").json()["data"]
    assert (row["kind"], row["total"], row["reviewed"], row["skipped"]) == ("disagreement", 2, 1, 0)
    assert client.get("/api/v1/projects/999999/review").status_code == 404

    # Viewer routes need a running viewer; bodies are checked first, naming the field.
    assert client.get(f"/api/v1/projects/{pid}/viewer/review").status_code == 404
    bad = client.post(f"/api/v1/projects/{pid}/viewer/review/mark", json={"state": "maybe"})
    assert bad.status_code == 422 and "state" in bad.text
    extra = client.post(f"/api/v1/projects/{pid}/viewer/review/step", json={"step": 1, "evil": 1})
    assert extra.status_code == 422 and "evil" in extra.text
    assert client.post(f"/api/v1/projects/{pid}/viewer/review/step", json={"step": 2}).status_code == 422
    long = client.post(f"/api/v1/projects/{pid}/viewer/review/relabel", json={"class_name": "x" * 65})
    assert long.status_code == 422 and "class_name" in long.text
    missing = client.post(f"/api/v1/projects/{pid}/viewer/review/mark", json={"state": "accepted"})
    assert missing.status_code == 404 and "No viewer" in missing.text
