"""Projects of several sequences (e.g. SemanticKITTI 00-10) with one class schema: creation and its checks,
the migration that gives every existing project its one sequence, runs over every sequence with metrics
per sequence and overall, exports in the ``sequences/<name>/predictions/`` layout, corrections and review
marks scoped to a sequence, and the viewer opening the sequence asked for."""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import appfixtures
import pytest
from apphelpers import API, create_project, loc_of, wait_run
from fastapi.testclient import TestClient

from app import crud
from app.core import db as dbmod
from app.core.config import Settings
from app.core.db import open_db
from app.jobs.apply import applier
from app.rows import SequenceRow
from leap_core.datasets.kitti import KittiSequence
from leap_core.fusion import voxel_keys
from leap_core.pipeline import STAGES, world_points

client = appfixtures.client
data_root = appfixtures.data_root
settings = appfixtures.settings
tiny_dataset = appfixtures.tiny_dataset


@pytest.fixture
def two_sequences(data_root: Path, make_tiny_sequence: Callable[..., Any], tmp_path: Path) -> list[Path]:
    """``data/kitti/sequences/00`` (4 frames) and ``.../01`` (3 frames, other points), both with images,
    labels and 2D ground truth."""
    return appfixtures.kitti_sequences(data_root, make_tiny_sequence, tmp_path, (4, 3))


def create_multi(
    client: TestClient, folders: list[Path], name: str = "multi", **extra: Any
) -> dict[str, Any]:
    r = client.post(
        f"{API}/projects",
        json={"name": name, "sequences": [{"path": str(f)} for f in folders], **extra},
    )
    assert r.status_code == 201, r.text
    return r.json()


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
    r = client.post(
        f"{API}/projects",
        json={
            "name": "m",
            "sequences": [
                {"path": str(two_sequences[0]), "name": "city"},
                {"path": str(two_sequences[1]), "name": "road"},
            ],
        },
    )
    assert r.status_code == 201, r.text
    assert [s["name"] for s in r.json()["sequences"]] == ["city", "road"]

    same = [{"path": str(two_sequences[0]), "name": "a"}, {"path": str(two_sequences[1]), "name": "a"}]
    r = client.post(f"{API}/projects", json={"name": "m", "sequences": same})
    assert loc_of(r) == ["body", "sequences", 1, "name"] and "taken" in r.text
    twice = [{"path": str(two_sequences[0])}, {"path": str(two_sequences[0]), "name": "b"}]
    assert loc_of(client.post(f"{API}/projects", json={"name": "m", "sequences": twice})) == [
        "body",
        "sequences",
        1,
        "path",
    ]
    for bad in ("../x", ".hidden", "a/b", "", "x" * 65):
        body = {"name": "m", "sequences": [{"path": str(two_sequences[0]), "name": bad}]}
        assert loc_of(client.post(f"{API}/projects", json=body))[:4] == ["body", "sequences", 0, "name"]


def test_each_folder_is_confined_and_checked(
    client: TestClient, two_sequences: list[Path], tmp_path: Path, data_root: Path
) -> None:
    outside = tmp_path / "outside" / "sequences" / "05"
    shutil.copytree(two_sequences[1], outside)
    r = client.post(
        f"{API}/projects",
        json={"name": "m", "sequences": [{"path": str(two_sequences[0])}, {"path": str(outside)}]},
    )
    assert r.status_code == 403, r.text
    assert "outside" in r.json()["detail"]
    not_kitti = data_root / "kitti" / "notes"
    not_kitti.mkdir()
    r = client.post(
        f"{API}/projects",
        json={"name": "m", "sequences": [{"path": str(two_sequences[0])}, {"path": str(not_kitti)}]},
    )
    assert loc_of(r) == ["body", "sequences", 1, "path"] and "velodyne" in r.text
    # A sequence the pipeline cannot run on (no calibration) is refused, naming it.
    (two_sequences[1] / "calib.txt").unlink()
    r = client.post(
        f"{API}/projects",
        json={"name": "m", "sequences": [{"path": str(two_sequences[0])}, {"path": str(two_sequences[1])}]},
    )
    assert loc_of(r) == ["body", "sequences", 1, "path"] and "'01'" in r.text
    assert client.get(f"{API}/projects").json()["count"] == 0  # nothing half-created


def test_dataset_or_sequences(client: TestClient, two_sequences: list[Path]) -> None:
    assert loc_of(client.post(f"{API}/projects", json={"name": "m"})) == ["body", "dataset"]
    both = {
        "name": "m",
        "dataset": {"kind": "folder", "path": str(two_sequences[0])},
        "sequences": [{"path": str(two_sequences[1])}],
    }
    assert loc_of(client.post(f"{API}/projects", json=both)) == ["body", "sequences"]
    assert loc_of(client.post(f"{API}/projects", json={"name": "m", "sequences": []}))[:2] == [
        "body",
        "sequences",
    ]
    r = client.post(
        f"{API}/projects", json={"name": "m", "sequences": [{"path": str(two_sequences[0]), "extra": 1}]}
    )
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
                "created_at, updated_at) VALUES (?, 'folder', ?, '{}', '{}', 'then', 'then')",
                [name, folder],
            )
        db.execute(
            "INSERT INTO corrections (project_id, created_at, class_name, voxel_size, keys) "
            "VALUES (1, 'then', 'car', 0.2, x'0500000000000000')"
        )
        db.execute("INSERT INTO review_marks VALUES (2, '4m:0,0,0', 'sig', 'accepted', NULL, 'then')")
        db.execute(
            "INSERT INTO review_queues VALUES (2, 'confidence', NULL, '[[\"4m:0,0,0\", \"sig\"]]', 'then')"
        )
    assert dbmod.init_db(path) == dbmod.SCHEMA_VERSION >= 6
    with dbmod.open_db(path) as db:
        assert crud.list_sequences(db, 1) == [SequenceRow("07", "/data/kitti/sequences/07", 0)]
        assert crud.list_sequences(db, 2)[0].name == "00"
        (c,) = crud.list_corrections(db, 1)
        assert c.class_name == "car" and c.sequence == "07" and c.keys.tolist() == [5]
        assert crud.list_corrections(db, 1, sequence="07") == [c]
        assert set(crud.list_review_marks(db, 2)) == {"4m:0,0,0"}
        # Marks carry their sequence in the table (migration 8), whatever the project's size.
        assert db.execute("SELECT region FROM review_marks").fetchall() == [("00/4m:0,0,0",)]
        assert crud.review_progress(db, 2) == [
            {
                "kind": "confidence",
                "run_id": None,
                "total": 1,
                "reviewed": 1,
                "skipped": 0,
                "updated_at": "then",
            }
        ]
        crud.delete_project(db, 2)  # sequences and queues go with their project
        assert db.execute("SELECT COUNT(*) FROM project_sequences WHERE project_id = 2").fetchone()[0] == 0
        assert db.execute("SELECT COUNT(*) FROM review_queues").fetchone()[0] == 0


def test_corrections_and_marks_are_per_sequence(tmp_path: Path) -> None:
    path = tmp_path / "s.db"
    dbmod.init_db(path)
    with dbmod.open_db(path) as db:
        p = crud.create_project(
            db,
            name="m",
            dataset_kind="folder",
            schema={},
            pipeline={},
            sequences=[("00", "/d/sequences/00"), ("01", "/d/sequences/01")],
        )
        pid = p.id
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


# ------------------------------------------------------------------------------------------------ runs
def test_run_labels_every_sequence(
    client: TestClient, two_sequences: list[Path], tiny_dataset: Path, tmp_path: Path, settings: Settings
) -> None:
    # Listed 01 first: run order is not name order (stored JSON sorts its keys; the API must not).
    two_sequences = two_sequences[::-1]
    project = create_multi(client, two_sequences)
    assert [s["name"] for s in project["sequences"]] == ["01", "00"]
    pid = project["id"]
    r = client.post(f"{API}/projects/{pid}/runs", json={"frames": {"start": 0, "stop": 2}})
    assert loc_of(r) == ["body", "frames"]
    r = client.post(f"{API}/projects/{pid}/runs", json={})
    assert r.status_code == 202, r.text
    run = r.json()
    assert run["params"]["sequences"] == [
        {"name": "01", "dataset": str(two_sequences[0]), "frames": None},
        {"name": "00", "dataset": str(two_sequences[1]), "frames": None},
    ]
    expected = [f"{n}/{s}" for n in ("01", "00") for s in STAGES]
    assert [s["name"] for s in run["progress"]["stages"]] == expected
    run = wait_run(client, run["id"], timeout=300)
    assert run["status"] == "done", run["error"]
    stages = {s["name"]: s for s in run["progress"]["stages"]}
    assert stages["00/labels2d"]["total"] == 4 and stages["01/labels2d"]["total"] == 3
    assert stages["01/export"]["status"] == "done" and stages["00/3dcn"]["status"] == "skipped"
    with open_db(settings.database) as db:
        run_dir = crud.require_run(db, run["id"]).run_dir
    for name, folder in zip(("01", "00"), two_sequences, strict=True):
        exported = sorted(p.name for p in (run_dir / "sequences" / name / "export").glob("*.label"))
        assert exported == sorted(f"{p.stem}.label" for p in (folder / "velodyne").glob("*.bin"))
    log = client.get(f"{API}/runs/{run['id']}/logs").json()["text"]
    assert "stage 00/fuse done" in log and "stage 01/export done" in log
    assert "stage 00/3dcn skipped (" in log  # the 3D-CN is off: the log says so, per sequence

    # Metrics: overall (the summed confusion matrices) by default, per sequence on request.
    overall = client.get(f"{API}/runs/{run['id']}/metrics").json()
    assert overall["sequences"] == ["01", "00"] and overall["sequence"] is None
    per = {
        n: client.get(f"{API}/runs/{run['id']}/metrics", params={"sequence": n}).json() for n in ("00", "01")
    }
    assert per["00"]["sequence"] == "00"
    stored = json.loads((run_dir / "metrics.json").read_text())
    for n in ("00", "01"):
        assert per[n]["metrics"]["protocols"]["camera"]["voxel"]["miou"] == pytest.approx(
            stored["sequences"][n]["camera"]["voxel"]["miou"]
        )
    assert overall["metrics"]["protocols"]["camera"]["voxel"]["miou"] == pytest.approx(
        stored["overall"]["camera"]["voxel"]["miou"]
    )
    assert per["00"]["metrics"] != per["01"]["metrics"]
    # Tracks do not span sequences: object scores per sequence only, none summed.
    assert overall["metrics"]["objects"] is None
    for n in ("00", "01"):
        assert per[n]["metrics"]["objects"] == stored["sequences"][n]["objects"] is not None
    assert loc_of(client.get(f"{API}/runs/{run['id']}/metrics", params={"sequence": "07"})) == [
        "query",
        "sequence",
    ]
    assert loc_of(client.get(f"{API}/runs/{run['id']}/metrics", params={"sequence": "../x"}))[:2] == [
        "query",
        "sequence",
    ]
    listed = client.get(f"{API}/projects/{pid}/runs").json()["data"][0]
    assert listed["has_export"] and listed["summary"]["camera"]["voxel"] == pytest.approx(
        stored["overall"]["camera"]["voxel"]["miou"]
    )

    # The zip: sequences/<name>/predictions/<frame>.label for every sequence.
    z = client.get(f"{API}/runs/{run['id']}/export.zip")
    assert z.status_code == 200
    names = set(zipfile.ZipFile(io.BytesIO(z.content)).namelist())
    for name, folder in zip(("01", "00"), two_sequences, strict=True):
        for scan in (folder / "velodyne").glob("*.bin"):
            member = f"sequences/{name}/predictions/{scan.stem}.label"
            assert member in names
            assert (
                zipfile.ZipFile(io.BytesIO(z.content)).read(member)
                == (run_dir / "sequences" / name / "export" / f"{scan.stem}.label").read_bytes()
            )

    # The folder export: by default into each dataset's predictions/.
    info = client.get(f"{API}/runs/{run['id']}/export").json()
    assert info["targets"] == [
        {"sequence": name, "path": str(folder / "predictions"), "existing": 0}
        for name, folder in zip(("01", "00"), two_sequences, strict=True)
    ]
    assert info["frames"] == 7 and info["predictions_allowed"]
    w = client.post(f"{API}/runs/{run['id']}/export", json={})
    assert w.status_code == 200, w.text
    assert w.json()["files"] == 7
    for name, folder in zip(("01", "00"), two_sequences, strict=True):
        assert sorted(p.name for p in (folder / "predictions").iterdir()) == sorted(
            p.name for p in (run_dir / "sequences" / name / "export").glob("*.label")
        )
    again = client.post(f"{API}/runs/{run['id']}/export", json={})
    assert again.status_code == 409
    assert client.post(f"{API}/runs/{run['id']}/export", json={"overwrite": True}).json()["replaced"] == 7
    # Into the app's export folder: sequences/<name>/predictions/ under the folder named.
    own = settings.work_dir / "exports" / "kitti-out"
    w = client.post(f"{API}/runs/{run['id']}/export", json={"path": str(own)})
    assert w.status_code == 200, w.text
    assert {p.relative_to(own).parts[:3] for p in own.rglob("*.label")} == {
        ("sequences", "00", "predictions"),
        ("sequences", "01", "predictions"),
    }
    # Anywhere else in a data root is refused (not a dataset's predictions/ folder).
    bad = client.post(f"{API}/runs/{run['id']}/export", json={"path": str(tiny_dataset.parent)})
    assert bad.status_code == 403

    # The next run's preview starts from this run, over every sequence.
    preview = client.get(f"{API}/projects/{pid}/runs/preview").json()
    assert preview["base_run"]["id"] == run["id"] and "fuse" not in preview["recompute"], preview

    # Corrections are per sequence: one in 00 changes 00's export only.
    before = {
        n: {p.name: p.read_bytes() for p in (run_dir / "sequences" / n / "export").glob("*.label")}
        for n in ("01", "00")
    }
    keys = _voxel_keys_of(two_sequences[1], "000000", run["params"]["pipeline"])
    c = client.post(
        f"{API}/projects/{pid}/corrections",
        json={"class_name": "building", "voxel_size": 0.2, "keys": keys, "sequence": "00"},
    )
    assert c.status_code == 201, c.text
    assert c.json()["sequence"] == "00"
    assert client.get(f"{API}/projects/{pid}/corrections").json()["corrections"] == []
    assert (
        len(client.get(f"{API}/projects/{pid}/corrections", params={"sequence": "00"}).json()["corrections"])
        == 1
    )
    assert loc_of(
        client.post(
            f"{API}/projects/{pid}/corrections",
            json={"class_name": "car", "voxel_size": 0.2, "keys": [1], "sequence": "09"},
        )
    ) == ["body", "sequence"]
    preview = client.get(f"{API}/projects/{pid}/runs/preview").json()
    fuse = next(st for st in preview["stages"] if st["name"] == "fuse")
    assert fuse["action"] == "recompute" and fuse["reason"].startswith("sequence 00: "), fuse
    state = applier(settings).wait(pid)
    assert state.status == "done" and state.frames >= 1, state
    after = {
        n: {p.name: p.read_bytes() for p in (run_dir / "sequences" / n / "export").glob("*.label")}
        for n in ("01", "00")
    }
    assert after["01"] == before["01"] and after["00"] != before["00"]

    # The viewer opens the sequence asked for: its run folder, its dataset, its corrections.
    v = client.post(f"{API}/projects/{pid}/viewer", json={"sequence": "00"})
    assert v.status_code == 200, v.text
    assert v.json()["sequence"] == "00" and v.json()["run_id"] == run["id"]
    session = client.app.state.viewers.get(pid)
    assert session.run.run_dir == run_dir / "sequences" / "00"
    assert session.backend.dataset_path() == two_sequences[1]
    assert [c.class_name for c in session.backend.corrections()] == ["building"]
    v = client.post(f"{API}/projects/{pid}/viewer", json={"sequence": "01"})
    assert v.json()["sequence"] == "01"
    assert client.app.state.viewers.get(pid).run.run_dir == run_dir / "sequences" / "01"
    assert client.app.state.viewers.get(pid).backend.corrections() == []
    bad_sequence = client.post(f"{API}/projects/{pid}/viewer", json={"sequence": "05"})
    assert loc_of(bad_sequence) == ["body", "sequence"]
    assert client.get(f"{API}/projects/{pid}/viewer").json()["sequence"] == "01"


def _voxel_keys_of(folder: Path, frame_id: str, pipeline: dict[str, Any]) -> list[int]:
    """The voxel keys of one scan's points (what a map correction covering the scan lists)."""
    seq = KittiSequence(folder)
    frame = seq.frame(seq.frame_ids.index(frame_id))
    return sorted({int(k) for k in voxel_keys(world_points(frame.points, frame.pose), 0.2)})


@pytest.mark.slow
def test_joint_3dcn_run_reports_its_rounds_between_the_sequences(
    client: TestClient, two_sequences: list[Path]
) -> None:
    tiny_3dcn = {
        "enabled": True,
        "iterations": 1,
        "points_per_scan": 512,
        "num_threads": 1,
        "min_steps": 0,
        "device": "cpu",
        "backbone": {"channels": 8, "layers": 1, "knn": 4},
    }
    project = create_multi(client, two_sequences, pipeline={"consistency": tiny_3dcn})
    run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    # Every sequence up to smoothing, the rounds trained on both, then each sequence from its 3D-CN on.
    cut = STAGES.index("3dcn")
    expected = (
        [f"{n}/{s}" for n in ("00", "01") for s in STAGES[:cut]]
        + ["*/3dcn"]
        + [f"{n}/{s}" for n in ("00", "01") for s in STAGES[cut:]]
    )
    assert [s["name"] for s in run["progress"]["stages"]] == expected
    run = wait_run(client, run["id"], timeout=600)
    assert run["status"] == "done", run["error"]
    stages = {s["name"]: s for s in run["progress"]["stages"]}
    assert stages["*/3dcn"]["status"] == "done" and stages["*/3dcn"]["total"] >= 1
    assert all(stages[f"{n}/export"]["status"] == "done" for n in ("00", "01"))
    assert all(s["status"] in ("done", "skipped") for s in stages.values()), stages
    rows = client.get(f"{API}/runs/{run['id']}/metrics", params={"sequence": "01"}).json()["metrics"]["rows"]
    # The last labels are the 3D-CN's; the objects row (the export: its tracks on top) follows them.
    assert rows[-1] == "objects" and rows[-2].startswith("+3D-CN"), rows
    # Nothing changed since: the next run reuses every stage, the joint 3D-CN included.
    preview = client.get(f"{API}/projects/{project['id']}/runs/preview").json()
    assert preview["base_run"]["id"] == run["id"] and "3dcn" not in preview["recompute"], preview
