"""Editing a project's sequences after creation: ``POST /projects/{id}/sequences`` and
``DELETE /projects/{id}/sequences/{name}`` against the real app, real SQLite and real sequence folders.

Adding confines and checks a folder as creation does; names are unique; edits wait for a queued or
running run (409); the last sequence stays; removing deletes no data, run or correction; afterwards the
latest run's results are marked stale (``stale``) and are never shown, measured or corrected as a sequence
they did not label. The dataset check is reported per sequence.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import appfixtures
import pytest
from apphelpers import API, TERMINAL, create_project, loc_of, wait_run
from fastapi.testclient import TestClient

from app import crud
from app.core.config import Settings
from app.core.db import open_db
from app.core.errors import Conflict
from app.jobs.apply import applier
from app.viewer.manager import AppBackend
from leap_core.datasets.kitti import KittiSequence
from leap_core.fusion import voxel_keys
from leap_core.pipeline import world_points

client = appfixtures.client
data_root = appfixtures.data_root
settings = appfixtures.settings


@pytest.fixture
def folders(data_root: Path, make_tiny_sequence: Callable[..., Any], tmp_path: Path) -> list[Path]:
    """``data/kitti/sequences/00`` (4 frames), ``01`` (3 frames) and ``02`` (3 frames), each with images,
    labels and 2D ground truth."""
    return appfixtures.kitti_sequences(data_root, make_tiny_sequence, tmp_path, (4, 3, 3))


def add(client: TestClient, pid: int, path: Path | str, name: str | None = None, **headers: str) -> Any:
    body = {"path": str(path)} | ({"name": name} if name is not None else {})
    return client.post(f"{API}/projects/{pid}/sequences", json=body, headers=headers)


def remove(client: TestClient, pid: int, name: str) -> Any:
    return client.delete(f"{API}/projects/{pid}/sequences/{name}")


def names_of(project: dict[str, Any]) -> list[str]:
    return [s["name"] for s in project["sequences"]]


def tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------- add and remove
def test_add_and_remove_keep_every_sequence_checked(client: TestClient, folders: list[Path]) -> None:
    (folders[1] / "poses.txt").unlink()  # 01 opens, but without poses: a warning of its own check
    project = create_project(client, folders[0])
    pid = project["id"]
    r = add(client, pid, folders[1])
    assert r.status_code == 201, r.text
    project = r.json()
    assert names_of(project) == ["00", "01"]
    assert [s["dataset"]["path"] for s in project["sequences"]] == [str(folders[0]), str(folders[1])]
    # The dataset check is each sequence's own: frames, poses, ground truth and problems.
    checks = [s["dataset"]["check"] for s in project["sequences"]]
    assert [c["root"] for c in checks] == [str(folders[0]), str(folders[1])]
    assert [c["frames"] for c in checks] == [4, 3]
    assert [c["poses"]["source"] for c in checks] == ["file", "missing"]
    assert [c["verdict"] for c in checks] == ["full", "partial"]
    assert not [f for f in checks[0]["findings"] if f["severity"] != "info"]
    assert [f["path"] for f in checks[1]["findings"] if f["code"] == "poses_missing"] == [
        str(folders[1] / "poses.txt")
    ]
    assert project["dataset"]["check"] == checks[0]  # the project's own stays its first sequence's
    listed = client.get(f"{API}/projects/{pid}/sequences").json()
    assert [s["name"] for s in listed["data"]] == ["00", "01"] and listed["count"] == 2
    assert listed["data"] == project["sequences"] and listed["stale"] is None

    r = add(client, pid, folders[2], name="city")
    assert r.status_code == 201, r.text
    assert names_of(r.json()) == ["00", "01", "city"]

    before = {f.name: tree(f) for f in folders}
    r = remove(client, pid, "00")
    assert r.status_code == 200, r.text
    project = r.json()
    assert names_of(project) == ["01", "city"]
    # The project's dataset follows its new first sequence; no folder lost a byte.
    assert project["dataset"]["path"] == str(folders[1])
    assert {f.name: tree(f) for f in folders} == before
    assert names_of(client.get(f"{API}/projects/{pid}").json()) == ["01", "city"]
    assert names_of(client.get(f"{API}/projects").json()["data"][0]) == ["01", "city"]

    assert remove(client, pid, "city").status_code == 200
    last = remove(client, pid, "01")
    assert last.status_code == 409 and "last" in last.json()["detail"], last.text
    assert names_of(client.get(f"{API}/projects/{pid}").json()) == ["01"]
    gone = remove(client, pid, "00")
    assert gone.status_code == 404 and "no sequence '00'" in gone.json()["detail"]
    assert remove(client, 999, "01").status_code == 404
    assert add(client, 999, folders[0]).status_code == 404
    assert loc_of(remove(client, pid, ".hidden"))[:2] == ["path", "name"]


def test_added_folders_are_confined_and_checked(
    client: TestClient, folders: list[Path], tmp_path: Path, data_root: Path
) -> None:
    pid = create_project(client, folders[0])["id"]
    outside = tmp_path / "outside" / "sequences" / "05"
    shutil.copytree(folders[1], outside)
    r = add(client, pid, outside)
    assert r.status_code == 403 and "outside the allowed data roots" in r.json()["detail"], r.text
    # A folder inside the roots whose velodyne/ is a link out of them is refused too.
    linked = data_root / "kitti" / "sequences" / "06"
    linked.mkdir()
    shutil.copy(folders[1] / "calib.txt", linked / "calib.txt")
    os.symlink(outside / "velodyne", linked / "velodyne")
    r = add(client, pid, linked)
    assert r.status_code == 403 and "velodyne is a symlink to" in r.json()["detail"], r.text
    # A link inside the roots leading out of them is resolved, then refused.
    os.symlink(outside, data_root / "kitti" / "sequences" / "07")
    assert add(client, pid, data_root / "kitti" / "sequences" / "07").status_code == 403

    not_kitti = data_root / "kitti" / "notes"
    not_kitti.mkdir()
    r = add(client, pid, not_kitti)
    assert loc_of(r) == ["body", "path"] and "velodyne" in r.text
    assert loc_of(add(client, pid, data_root / "kitti" / "none")) == ["body", "path"]
    (folders[2] / "calib.txt").unlink()  # nothing can run on it
    r = add(client, pid, folders[2])
    assert loc_of(r) == ["body", "path"] and "calib.txt" in r.text
    r = add(client, pid, folders[0], name="again")
    assert loc_of(r) == ["body", "path"] and "sequence '00'" in r.text
    r = add(client, pid, folders[1], name="00")
    assert loc_of(r) == ["body", "name"] and "taken" in r.text
    for bad in ("../x", ".hidden", "a/b", "x" * 65):
        assert loc_of(add(client, pid, folders[1], name=bad))[:2] == ["body", "name"]
    assert loc_of(client.post(f"{API}/projects/{pid}/sequences", json={"path": str(folders[1]), "x": 1}))[
        :2
    ] == ["body", "x"]
    assert names_of(client.get(f"{API}/projects/{pid}").json()) == ["00"]  # nothing was added


def test_symlink_loops_are_refused_naming_the_field(
    client: TestClient, folders: list[Path], data_root: Path
) -> None:
    pid = create_project(client, folders[0])["id"]
    loop = data_root / "kitti" / "sequences" / "loop"
    loop.symlink_to(loop)
    for path in (loop, loop / "inner"):
        r = add(client, pid, path)
        assert loc_of(r) == ["body", "path"] and "symlink loop" in r.json()["detail"][0]["msg"], r.text
    # A sequence folder of the project that has become a loop since does not break the next add.
    folders[0].rename(data_root / "kitti" / "moved")
    folders[0].symlink_to(folders[0])
    r = add(client, pid, folders[1])
    assert r.status_code == 201, r.text[:500]
    assert names_of(r.json()) == ["00", "01"]


def test_a_cross_site_page_cannot_edit_sequences(client: TestClient, folders: list[Path]) -> None:
    pid = create_project(client, folders[0])["id"]
    evil = {"origin": "http://127.0.0.2:8769", "sec-fetch-site": "cross-site"}
    r = add(client, pid, folders[1], **evil)
    assert r.status_code == 403 and "Cross-origin" in r.text, r.text
    assert add(client, pid, folders[1]).status_code == 201
    r = client.delete(f"{API}/projects/{pid}/sequences/01", headers=evil)
    assert r.status_code == 403
    assert names_of(client.get(f"{API}/projects/{pid}").json()) == ["00", "01"]


def test_edits_wait_for_the_projects_run(client: TestClient, folders: list[Path]) -> None:
    pid = create_project(client, folders[0])["id"]
    assert add(client, pid, folders[1]).status_code == 201
    run = client.post(f"{API}/projects/{pid}/runs", json={}).json()
    # The worker process starts on demand (pipeline imports take seconds): the run is queued or running.
    r, d = add(client, pid, folders[2]), remove(client, pid, "01")
    status = client.get(f"{API}/runs/{run['id']}").json()["status"]
    assert status in ("queued", "running"), status
    for answer in (r, d):
        assert answer.status_code == 409 and f"run {run['id']}" in answer.json()["detail"], answer.text
    assert names_of(client.get(f"{API}/projects/{pid}").json()) == ["00", "01"]
    assert client.post(f"{API}/runs/{run['id']}/cancel").status_code in (200, 202)
    assert wait_run(client, run["id"], timeout=120)["status"] in TERMINAL
    assert add(client, pid, folders[2]).status_code == 201
    assert remove(client, pid, "01").status_code == 200


def test_the_demo_project_keeps_its_one_sequence(client: TestClient, folders: list[Path]) -> None:
    r = client.post(f"{API}/projects", json={"name": "d", "dataset": {"kind": "demo"}})
    assert r.status_code == 201, r.text
    r = add(client, r.json()["id"], folders[0])
    assert r.status_code == 409 and "demo" in r.json()["detail"]


# ---------------------------------------------------------------------------- stale results, no mixing
def test_results_go_stale_and_are_never_mixed(
    client: TestClient, folders: list[Path], settings: Settings
) -> None:
    project = create_project(client, folders[0])
    pid = project["id"]
    with open_db(settings.database) as db:  # a reviewer's mark in the one-sequence project
        crud.set_review_mark(db, pid, region="4m:0,0,0", signature="s", state="accepted")
    run = wait_run(client, client.post(f"{API}/projects/{pid}/runs", json={}).json()["id"], timeout=300)
    assert run["status"] == "done", run["error"]
    assert client.get(f"{API}/projects/{pid}").json()["stale"] is None
    with open_db(settings.database) as db:
        run_dir = crud.require_run(db, run["id"]).sequence_layout("00").folder
    export = {p.name: p.read_bytes() for p in (run_dir / "export").glob("*.label")}
    assert export

    v = client.post(f"{API}/projects/{pid}/viewer", json={})
    assert v.status_code == 200 and v.json()["run_id"] == run["id"], v.text
    project = add(client, pid, folders[1]).json()
    # The viewer opened on the one sequence is closed: the next one opens on the sequences as they are.
    assert client.app.state.viewers.get(pid) is None
    stale = project["stale"]
    assert stale is not None
    assert (stale["run_id"], stale["added"], stale["removed"]) == (run["id"], ["01"], [])
    assert "run 1" in stale["message"]
    preview = client.get(f"{API}/projects/{pid}/runs/preview").json()
    assert preview["stale"] == stale and preview["base_run"] is None
    assert client.get(f"{API}/projects/{pid}/sequences").json()["stale"] == stale
    assert all(
        s["reason"] == "the sequences changed since run 1"
        for s in preview["stages"]
        if s["action"] == "recompute"
    ), preview
    # The one-sequence run labeled 00 only: no figures of it are 01's.
    assert client.get(f"{API}/runs/{run['id']}/metrics", params={"sequence": "00"}).status_code == 200
    assert loc_of(client.get(f"{API}/runs/{run['id']}/metrics", params={"sequence": "01"})) == [
        "query",
        "sequence",
    ]
    # The viewer shows a sequence only the runs that labeled it.
    assert AppBackend(settings, pid, sequence="01").latest_finished_run() is None
    assert AppBackend(settings, pid, sequence="00").latest_finished_run().run_id == run["id"]
    with pytest.raises(Conflict, match="did not label sequence '01'"):
        AppBackend(settings, pid, sequence="01").run_info(run["id"])
    # The mark made before is still 00's, now that marks are kept per sequence.
    with open_db(settings.database) as db:
        assert set(crud.list_review_marks(db, pid, "00")) == {"4m:0,0,0"}
        assert crud.list_review_marks(db, pid, "01") == {}
    # A correction of 01 (on keys that are 00's voxels too) never reaches the run's export, which
    # labeled 00: neither now nor once 00 is removed and 01 is the project's first sequence.
    c = client.post(
        f"{API}/projects/{pid}/corrections",
        json={"class_name": "building", "voxel_size": 0.2, "keys": _voxel_keys(folders[0]), "sequence": "01"},
    )
    assert c.status_code == 201, c.text
    assert applier(settings).wait(pid).frames == 0

    # Removing 00 (the one the run labeled) is stale the other way; its run, correction and mark stay.
    project = remove(client, pid, "00").json()
    assert (project["stale"]["added"], project["stale"]["removed"]) == (["01"], ["00"])
    assert loc_of(client.get(f"{API}/runs/{run['id']}/metrics", params={"sequence": "01"})) == [
        "query",
        "sequence",
    ]
    applier(settings).request(pid)
    assert applier(settings).wait(pid).frames == 0
    assert {p.name: p.read_bytes() for p in (run_dir / "export").glob("*.label")} == export
    assert client.get(f"{API}/runs/{run['id']}").json()["status"] == "done"
    assert {p.name: p.read_bytes() for p in (run_dir / "export").glob("*.label")} == export
    assert (
        len(client.get(f"{API}/projects/{pid}/corrections", params={"sequence": "01"}).json()["corrections"])
        == 1
    )
    # 00's name stays bound to its folder: another folder cannot take it over ...
    r = add(client, pid, folders[2], name="00")
    assert loc_of(r) == ["body", "name"] and "removed sequence" in r.text
    # ... and adding 00's folder back under it brings back its mark; removing 01 leaves exactly what the
    # run labeled, so nothing is stale any more.
    assert add(client, pid, folders[0]).status_code == 201
    project = remove(client, pid, "01").json()
    assert names_of(project) == ["00"] and project["stale"] is None
    with open_db(settings.database) as db:
        assert set(crud.list_review_marks(db, pid)) == {"4m:0,0,0"}
    assert client.get(f"{API}/projects/{pid}/runs/preview").json()["base_run"]["id"] == run["id"]


def _voxel_keys(folder: Path) -> list[int]:
    """The voxel keys (0.2 m) of a sequence's first scan: what a map correction covering it lists."""
    seq = KittiSequence(folder)
    frame = seq.frame(0)
    return sorted({int(k) for k in voxel_keys(world_points(frame.points, frame.pose), 0.2)})
