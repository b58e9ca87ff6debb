"""Projects of several sequences (e.g. SemanticKITTI 00-10) with one class schema: creation and its checks,
the migration that gives every existing project its one sequence, runs over every sequence with metrics
per sequence and overall, exports in the ``sequences/<name>/predictions/`` layout, corrections and review
marks scoped to a sequence, and the viewer opening the sequence asked for."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app import crud
from app.core import db as dbmod
import appfixtures
from apphelpers import API, create_project

client = appfixtures.client
data_root = appfixtures.data_root
settings = appfixtures.settings
tiny_dataset = appfixtures.tiny_dataset


@pytest.fixture
def two_sequences(data_root: Path, make_tiny_sequence: Callable[..., Any], tmp_path: Path) -> list[Path]:
    """``data/kitti/sequences/00`` (4 frames) and ``.../01`` (3 frames, other points), both with images,
    labels and 2D ground truth."""
    out = []
    for i, n_frames in enumerate((4, 3)):
        seq = make_tiny_sequence(tmp_path / f"build{i}", n_frames=n_frames, n_points=400, seed=i)
        appfixtures.add_gt2d(seq.root, seq.frame_ids, (48, 64))
        target = data_root / "kitti" / "sequences" / f"{i:02d}"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(seq.root, target)
        out.append(target)
    return out


def create_multi(client: TestClient, folders: list[Path], name: str = "multi", **extra: Any) -> dict[str, Any]:
    r = client.post(
        f"{API}/projects",
        json={"name": name, "sequences": [{"path": str(f)} for f in folders], **extra},
    )
    assert r.status_code == 201, r.text
    return r.json()


def loc_of(r: Any) -> list[Any]:
    assert r.status_code == 422, r.text
    return list(r.json()["detail"][0]["loc"])


# ------------------------------------------------------------------------------------------- creation
def test_create_lists_every_sequence_in_order(client: TestClient, two_sequences: list[Path]) -> None:
    project = create_multi(client, two_sequences)
    assert [s["name"] for s in project["sequences"]] == ["00", "01"]
    assert [s["dataset"]["path"] for s in project["sequences"]] == [str(p) for p in two_sequences]
    assert [s["dataset"]["frames"] for s in project["sequences"]] == [4, 3]
    # The project's own dataset is its first sequence (what single-sequence code reads).
    assert project["dataset"]["path"] == str(two_sequences[0])
    again = client.get(f"{API}/projects/{project['id']}").json()
    assert again["sequences"] == project["sequences"]
    listed = client.get(f"{API}/projects").json()["data"]
    assert [s["name"] for s in listed[0]["sequences"]] == ["00", "01"]


def test_single_sequence_project_has_one_sequence(client: TestClient, tiny_dataset: Path) -> None:
    project = create_project(client, tiny_dataset)
    assert [(s["name"], s["dataset"]["path"]) for s in project["sequences"]] == [("00", str(tiny_dataset))]


def test_names_given_and_refused(client: TestClient, two_sequences: list[Path], data_root: Path) -> None:
    r = client.post(f"{API}/projects", json={"name": "m", "sequences": [
        {"path": str(two_sequences[0]), "name": "city"}, {"path": str(two_sequences[1]), "name": "road"}]})
    assert r.status_code == 201, r.text
    assert [s["name"] for s in r.json()["sequences"]] == ["city", "road"]

    same = [{"path": str(two_sequences[0]), "name": "a"}, {"path": str(two_sequences[1]), "name": "a"}]
    r = client.post(f"{API}/projects", json={"name": "m", "sequences": same})
    assert loc_of(r) == ["body", "sequences", 1, "name"] and "taken" in r.text
    twice = [{"path": str(two_sequences[0])}, {"path": str(two_sequences[0]), "name": "b"}]
    assert loc_of(client.post(f"{API}/projects", json={"name": "m", "sequences": twice})) == [
        "body", "sequences", 1, "path"]
    for bad in ("../x", ".hidden", "a/b", "", "x" * 65):
        body = {"name": "m", "sequences": [{"path": str(two_sequences[0]), "name": bad}]}
        assert loc_of(client.post(f"{API}/projects", json=body))[:4] == ["body", "sequences", 0, "name"]


def test_each_folder_is_confined_and_checked(client: TestClient, two_sequences: list[Path], tmp_path: Path,
                                             data_root: Path) -> None:
    outside = tmp_path / "outside" / "sequences" / "05"
    shutil.copytree(two_sequences[1], outside)
    r = client.post(f"{API}/projects", json={"name": "m", "sequences": [
        {"path": str(two_sequences[0])}, {"path": str(outside)}]})
    assert r.status_code == 403, r.text
    assert "outside" in r.json()["detail"]
    not_kitti = data_root / "kitti" / "notes"
    not_kitti.mkdir()
    r = client.post(f"{API}/projects", json={"name": "m", "sequences": [
        {"path": str(two_sequences[0])}, {"path": str(not_kitti)}]})
    assert loc_of(r) == ["body", "sequences", 1, "path"] and "velodyne" in r.text
    # A sequence the pipeline cannot run on (no calibration) is refused, naming it.
    (two_sequences[1] / "calib.txt").unlink()
    r = client.post(f"{API}/projects", json={"name": "m", "sequences": [
        {"path": str(two_sequences[0])}, {"path": str(two_sequences[1])}]})
    assert loc_of(r) == ["body", "sequences", 1, "path"] and "'01'" in r.text
    assert client.get(f"{API}/projects").json()["count"] == 0  # nothing half-created


def test_dataset_or_sequences(client: TestClient, two_sequences: list[Path]) -> None:
    assert loc_of(client.post(f"{API}/projects", json={"name": "m"})) == ["body", "dataset"]
    both = {"name": "m", "dataset": {"kind": "folder", "path": str(two_sequences[0])},
            "sequences": [{"path": str(two_sequences[1])}]}
    assert loc_of(client.post(f"{API}/projects", json=both)) == ["body", "sequences"]
    assert loc_of(client.post(f"{API}/projects", json={"name": "m", "sequences": []}))[:2] == [
        "body", "sequences"]
    r = client.post(f"{API}/projects", json={"name": "m", "sequences": [{"path": str(two_sequences[0]),
                                                                          "extra": 1}]})
    assert loc_of(r)[:3] == ["body", "sequences", 0]


# ------------------------------------------------------------------------------------------ migration
def test_migration_6_gives_existing_projects_their_sequence(tmp_path: Path) -> None:
    path = tmp_path / "old.db"
    with dbmod.open_db(path) as db:
        db.execute(
            "CREATE TABLE schema_version (version INTEGER PRIMARY KEY, description TEXT NOT NULL, "
            "applied_at TEXT NOT NULL)"
        )
        for number, description, apply in dbmod.MIGRATIONS:
            if number <= 5:
                apply(db)
                db.execute("INSERT INTO schema_version VALUES (?, ?, 'then')", [number, description])
        for name, folder in (("a", "/data/kitti/sequences/07"), ("b", "/data/other/sequences/00")):
            db.execute(
                "INSERT INTO projects (name, dataset_kind, dataset_path, schema_json, pipeline_json, "
                "created_at, updated_at) VALUES (?, 'folder', ?, '{}', '{}', 'then', 'then')", [name, folder])
        db.execute("INSERT INTO corrections (project_id, created_at, class_name, voxel_size, keys) "
                   "VALUES (1, 'then', 'car', 0.2, x'0500000000000000')")
        db.execute("INSERT INTO review_marks VALUES (2, '4m:0,0,0', 'sig', 'accepted', NULL, 'then')")
        db.execute("INSERT INTO review_queues VALUES (2, 'confidence', NULL, '[[\"4m:0,0,0\", \"sig\"]]', "
                   "'then')")
    assert dbmod.init_db(path) == dbmod.SCHEMA_VERSION >= 6
    with dbmod.open_db(path) as db:
        assert crud.list_sequences(db, 1) == [
            {"name": "07", "dataset_path": "/data/kitti/sequences/07", "position": 0}]
        assert crud.list_sequences(db, 2)[0]["name"] == "00"
        (c,) = crud.list_corrections(db, 1)
        assert c.class_name == "car" and c.sequence == "07" and c.keys.tolist() == [5]
        assert crud.list_corrections(db, 1, sequence="07") == [c]
        assert set(crud.list_review_marks(db, 2)) == {"4m:0,0,0"}
        assert crud.review_progress(db, 2) == [{"kind": "confidence", "run_id": None, "total": 1,
                                                "reviewed": 1, "skipped": 0, "updated_at": "then"}]
        crud.delete_project(db, 2)  # sequences and queues go with their project
        assert db.execute("SELECT COUNT(*) FROM project_sequences WHERE project_id = 2").fetchone()[0] == 0
        assert db.execute("SELECT COUNT(*) FROM review_queues").fetchone()[0] == 0


def test_corrections_and_marks_are_per_sequence(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    dbmod.init_db(path)
    with dbmod.open_db(path) as db:
        p = crud.create_project(db, name="m", dataset_kind="folder", dataset_path="/d/sequences/00",
                                schema={}, pipeline={},
                                sequences=[("00", "/d/sequences/00"), ("01", "/d/sequences/01")])
        pid = int(p["id"])
        crud.add_correction(db, project_id=pid, class_name="car", voxel_size=0.2, keys=[1])
        crud.add_correction(db, project_id=pid, class_name="road", voxel_size=0.2, keys=[1], sequence="01")
        assert [c.class_name for c in crud.list_corrections(db, pid)] == ["car"]
        assert [c.class_name for c in crud.list_corrections(db, pid, sequence="01")] == ["road"]
        with pytest.raises(Exception, match="no sequence '02'"):
            crud.add_correction(db, project_id=pid, class_name="x", voxel_size=0.2, keys=[1], sequence="02")
        # One region identity in two sequences is two places: marked apart.
        crud.set_review_mark(db, pid, region="4m:0,0,0", signature="s", state="accepted", sequence="00")
        crud.set_review_mark(db, pid, region="4m:0,0,0", signature="s", state="skipped", sequence="01")
        assert crud.list_review_marks(db, pid)["4m:0,0,0"].state == "accepted"
        assert crud.list_review_marks(db, pid, "01")["4m:0,0,0"].state == "skipped"
        crud.save_review_queue(db, pid, "confidence", None, [("4m:0,0,0", "s")], sequence="01")
        assert crud.review_progress(db, pid) == []
        (q,) = crud.review_progress(db, pid, "01")
        assert (q["total"], q["reviewed"], q["skipped"]) == (1, 0, 1)
