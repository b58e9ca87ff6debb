"""Runs through the real app: worker processes running the real pipeline on a tiny dataset."""

from __future__ import annotations

import dataclasses
import io
import json
import threading
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import appfixtures
import numpy as np
import pytest
import yaml
from apphelpers import API, create_project, wait_run
from fastapi import FastAPI
from fastapi.testclient import TestClient

import leap_core
from app import crud
from app.core.config import Settings
from app.core.db import open_db
from app.jobs.apply import applier
from leap_core.datasets.kitti import KittiSequence
from leap_core.eval_view import PAPER_VIEW
from leap_core.fusion import voxel_keys
from leap_core.object_review import ObjectQueueConfig
from leap_core.pipeline import STAGES, world_points
from leap_core.pipeline import apply as core_apply
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.tracking import VoteEvidence

# The app tests' fixtures (this folder has no conftest.py; see appfixtures), found by name here.
client, data_root, settings, tiny_dataset = (
    appfixtures.client,
    appfixtures.data_root,
    appfixtures.settings,
    appfixtures.tiny_dataset,
)


def read_events(client: TestClient, run_id: int) -> list[tuple[str, dict]]:
    events: list[tuple[str, dict]] = []
    kind = None
    with client.stream("GET", f"{API}/runs/{run_id}/events") as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        for line in stream.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: ") and kind is not None:
                events.append((kind, json.loads(line[6:])))
                if kind == "end":
                    break
    return events


def test_run_progress_metrics_and_exports(client: TestClient, tiny_dataset: Path) -> None:
    project = create_project(client, tiny_dataset)
    r = client.post(f"{API}/projects/{project['id']}/runs", json={})
    assert r.status_code == 202, r.text
    run = r.json()
    assert run["status"] in ("queued", "running") and run["number"] == 1
    assert [s["name"] for s in run["progress"]["stages"]] == [f"00/{s}" for s in STAGES]
    # One active run per project.
    again = client.post(f"{API}/projects/{project['id']}/runs", json={})
    assert again.status_code == 409 and f"already has run 1 (id {run['id']})" in again.json()["detail"]

    events = read_events(client, run["id"])
    assert events[-1][0] == "end"
    progress = [e for k, e in events if k == "progress"]
    assert progress[-1]["status"] == "done" and progress[-1]["percent"] == 100.0
    assert [e["version"] for e in progress] == sorted(e["version"] for e in progress)
    assert any(e["status"] == "running" for e in progress)

    run = client.get(f"{API}/runs/{run['id']}").json()
    assert run["status"] == "done" and run["error"] is None and run["attempts"] == 1
    # The tiny dataset's 2D ground truth has no sidewalk, its 3D ground truth has: the run says so.
    assert any(
        "class 'sidewalk' got no pixels from the 2D labeler" in w and "try other prompts" in w
        for w in run["progress"]["warnings"]
    ), run["progress"]["warnings"]
    stages = {s["name"].removeprefix("00/"): s for s in run["progress"]["stages"]}
    assert stages["3dcn"]["status"] == "skipped"  # 3D-CN is off by default
    for name in ("labels2d", "project", "label_points", "export"):
        assert stages[name]["status"] == "done" and stages[name]["done"] == stages[name]["total"] == 4
        assert stages[name]["seconds"] is not None
    assert run["params"]["schema"]["name"] == "semantickitti"
    assert run["params"]["sequences"] == [{"name": "00", "dataset": str(tiny_dataset), "frames": None}]
    assert run["has_metrics"] and run["has_export"] and not run["resumable"]
    assert set(run["summary"]) == {"camera", "common", "all", "paper"}
    assert set(run["summary"]["camera"]) == {"point", "voxel", "objects"}

    metrics = client.get(f"{API}/runs/{run['id']}/metrics").json()
    voxel = metrics["metrics"]["protocols"]["camera"]["voxel"]
    assert set(voxel["iou"]) == set(metrics["class_names"]) and "confusion" not in voxel
    assert 0.0 <= voxel["miou"] <= 1.0 and metrics["metrics"]["rows"] == ["point", "voxel", "objects"]
    # The paper's protocol: Table 1's 11 merged classes, named in views, with the merge and a description.
    view = metrics["metrics"]["views"]["paper"]
    paper = metrics["metrics"]["protocols"]["paper"]["voxel"]
    assert view["class_names"] == PAPER_VIEW.names and len(view["class_names"]) == 11
    assert set(paper["iou"]) == set(view["class_names"])  # stored JSON sorts keys: the order is the view's
    assert view["merge"]["manmade"] == ["building", "fence", "pole", "traffic-sign"]
    assert "confusion" not in paper
    assert "Table 1" in metrics["metrics"]["descriptions"]["paper"] and metrics["metrics"]["notes"] == {}
    stored = json.loads((Path(crud_run_dir(client, run["id"])) / "metrics.json").read_text())
    assert paper["miou"] == stored["paper"]["voxel"]["miou"] == run["summary"]["paper"]["voxel"]
    # Object scores are a sequence's; a run of one sequence shows them as its own.
    objects = metrics["metrics"]["objects"]
    assert objects == stored["objects"] and set(objects) >= {"camera", "all", "motion"}
    assert 0.0 <= objects["camera"]["PQ"] <= 1.0 and "s_assoc" in objects["motion"]

    logs = client.get(f"{API}/runs/{run['id']}/logs").json()
    assert "stage 00/export done" in logs["text"] and "run finished" in logs["text"]

    seq = KittiSequence(tiny_dataset)
    z = client.get(f"{API}/runs/{run['id']}/export.zip")
    assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(z.content)) as zf:
        labels = [f"sequences/00/predictions/{f}.label" for f in seq.frame_ids]
        assert sorted(zf.namelist()) == sorted([*labels, "label-map.yaml", "summary.yaml"])
        for i, fid in enumerate(seq.frame_ids):
            data = zf.read(f"sequences/00/predictions/{fid}.label")
            assert len(data) == 4 * seq.frame(i).points.shape[0]
            run_dir = Path(crud_run_dir(client, run["id"]))
            assert data == (run_dir / "export" / f"{fid}.label").read_bytes()
    with zipfile.ZipFile(
        io.BytesIO(client.get(f"{API}/runs/{run['id']}/export.zip?confidence=true").content)
    ) as zf:
        confs = [n for n in zf.namelist() if n.startswith("sequences/00/confidences/")]
        assert len(confs) == len(seq.frame_ids)

    written = client.post(f"{API}/runs/{run['id']}/export", json={})
    assert written.status_code == 200, written.text
    assert written.json() == {
        "run_id": run["id"],
        "path": str(tiny_dataset / "predictions"),
        "files": 4,
        "replaced": 0,
    }
    for fid in seq.frame_ids:
        assert (tiny_dataset / "predictions" / f"{fid}.label").is_file()
    outside = client.post(f"{API}/runs/{run['id']}/export", json={"path": "/tmp/leap-export-elsewhere"})
    assert outside.status_code == 403

    project = client.get(f"{API}/projects/{project['id']}").json()
    assert project["last_run"]["status"] == "done" and project["active_run"] is None
    _check_objects(client, run, crud_run_dir(client, run["id"]) / "tracks.npz")


def _check_objects(client: TestClient, run: dict[str, Any], path: Path) -> None:
    """``GET /runs/{id}/objects`` lists tracks.npz's tracks, and with ``queued`` the review queue in order.
    The file's first track gets a close vote first (car 50 % vs truck 45 %), so the queue holds it."""
    found = SequenceTracks.load(path)
    k = found.table.label.size
    assert k >= 2, "the tiny run has too few objects"
    ev = found.table.vote_evidence()
    names = [c["name"] for c in run["params"]["schema"]["classes"]]
    close = VoteEvidence(
        np.r_[0.5, ev.share[1:]],
        np.r_[names.index("truck"), ev.runner_up[1:]].astype(np.int16),
        np.r_[0.45, ev.runner_share[1:]],
    )
    label = found.table.label.copy()
    label[0] = names.index("car")
    table = dataclasses.replace(found.table, label=label, evidence=close)
    dataclasses.replace(found, table=table, life=None).save(path)
    url = f"{API}/runs/{run['id']}/objects"
    every = client.get(url, params={"limit": 1000}).json()
    assert every["count"] == k and [o["id"] for o in every["data"]] == list(range(1, k + 1))
    life = found.track_life()
    first = every["data"][0]
    assert (
        first["class_name"] == "car" and first["runner_up"] == "truck" and first["queued"][0] == "close_vote"
    )
    assert first["vote_share"] == pytest.approx(0.5) and first["runner_up_share"] == pytest.approx(0.45)
    assert first["reason"].startswith("car 50 % vs truck 45 %")
    assert [o["scans"] for o in every["data"]] == life.present.tolist()
    assert [o["gaps"] for o in every["data"]] == life.gaps.tolist()
    assert [o["moving"] for o in every["data"]] == found.table.moving.tolist()
    things = np.array([c["thing"] for c in run["params"]["schema"]["classes"]], bool)
    ids, _ = SequenceTracks.load(path).review_queue(things, ObjectQueueConfig())
    queued = client.get(url, params={"queued": True, "limit": 1}).json()
    assert queued["count"] == ids.size and [o["id"] for o in queued["data"]] == [1]
    page = client.get(url, params={"queued": True, "offset": 1, "limit": 1000}).json()
    assert [o["id"] for o in page["data"]] == ids[1:].tolist()
    assert all(o["queued"] and o["reason"] for o in page["data"])
    for bad, field in (
        ({"limit": 1001}, "limit"),
        ({"offset": -1}, "offset"),
        ({"sequence": "01"}, "sequence"),
    ):
        r = client.get(url, params=bad)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", field], r.text
    assert client.get(f"{API}/runs/999999/objects").status_code == 404


def app_settings(client: TestClient) -> Settings:
    """The settings the test client's app was created with."""
    app = client.app
    assert isinstance(app, FastAPI)
    settings: Settings = app.state.settings
    return settings


def crud_run_dir(client: TestClient, run_id: int) -> Path:
    """The run's folder of its first sequence."""
    with open_db(app_settings(client).database) as db:
        run = crud.require_run(db, run_id)
    return run.sequence_layout(run.params.names[0]).folder


def test_first_run_progress_weighs_stages_by_cost_and_has_an_eta(
    client: TestClient, data_root: Path, make_tiny_sequence: Callable[..., Any]
) -> None:
    """A project's first run (no earlier times to go by): its percent weighs each stage by its expected
    seconds, and once a stage has a rate it has an ETA for the rest (the stages' own rates and the costs
    of those to come), where it used to stay empty until the last stage."""
    seq = make_tiny_sequence(data_root / "longer", n_frames=24, n_points=400)
    appfixtures.add_gt2d(seq.root, seq.frame_ids, (48, 64))
    project = create_project(client, seq.root)
    run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    progress = [e for k, e in read_events(client, run["id"]) if k == "progress"]
    assert progress[-1]["status"] == "done" and progress[-1]["percent"] == 100.0
    running = [e for e in progress if e["status"] == "running"]
    measured = [
        e
        for e in running
        if any(s["status"] == "done" or (s["status"] == "running" and s["done"] > 0) for s in e["stages"])
        and any(s["status"] == "pending" for s in e["stages"])
    ]
    assert measured, progress  # the stream saw the run between its first rate and its last stage
    for e in measured:
        assert e["eta_s"] is not None, e
    for e in running:
        weights = [s["expected_s"] for s in e["stages"]]
        assert all(w is not None and w >= 0 for w in weights), e
        if sum(weights) > 0:
            weighted = sum(w * s["percent"] for w, s in zip(weights, e["stages"], strict=True)) / sum(weights)
            assert e["percent"] == pytest.approx(weighted, abs=0.2), e
        pending = {s["name"]: s["expected_s"] for s in e["stages"] if s["status"] == "pending"}
        if "00/project" in pending and "00/export" in pending:
            # Before they run, stages weigh their cost: projection costs more per frame than the export.
            assert pending["00/project"] > pending["00/export"] > 0, e


def test_deleting_a_project_removes_its_folders_and_its_ids_are_never_reused(
    client: TestClient, tiny_dataset: Path
) -> None:
    project = create_project(client, tiny_dataset, name="doomed")
    run = client.post(f"{API}/projects/{project['id']}/runs", json={"frames": {"start": 0, "stop": 2}}).json()
    assert wait_run(client, run["id"])["status"] == "done"
    run_dir = Path(crud_run_dir(client, run["id"]))
    assert (run_dir / "export" / "000000.label").is_file()
    run_root = run_dir.parents[1]  # the run folder, p<P>/r<R>
    cache = app_settings(client).cache_dir / f"p{project['id']}"
    assert any(cache.rglob("*")), "the run keeps its 2D labels in the project's cache folder"

    assert client.delete(f"{API}/projects/{project['id']}").status_code == 200
    assert not run_root.parent.exists()
    assert list(run_root.parent.parent.iterdir()) == []  # nothing half-deleted left beside it
    assert not cache.exists()
    assert (tiny_dataset / "velodyne" / "000000.bin").is_file()  # the user's dataset stays

    # The next project and its run get ids of their own (SQLite alone would hand the deleted ones out
    # again), so nothing keyed by an id (folders, the corrections job's grid, viewers) is shared.
    again = create_project(client, tiny_dataset, name="reborn")
    assert again["id"] == project["id"] + 1
    # Files already at a new run's folder (a database restored from a backup may hand out an id whose
    # folder is in use) must not leak into it: the new run starts from an empty folder.
    new_root = run_root.parent.parent / f"p{again['id']}" / f"r{run['id'] + 1}"
    new_dir = new_root / run_dir.relative_to(run_root)
    new_dir.mkdir(parents=True)
    (new_dir / "left-by-a-deleted-project.txt").write_text("stale")
    (new_root / "left-by-a-deleted-project.txt").write_text("stale")
    rerun = client.post(f"{API}/projects/{again['id']}/runs", json={"frames": {"start": 0, "stop": 2}})
    rerun = rerun.json()
    assert rerun["id"] == run["id"] + 1
    assert wait_run(client, rerun["id"])["status"] == "done"
    assert Path(crud_run_dir(client, rerun["id"])) == new_dir
    assert not (new_dir / "left-by-a-deleted-project.txt").exists()
    assert not (new_root / "left-by-a-deleted-project.txt").exists()
    assert sorted(p.name for p in (new_dir / "export").glob("*.label")) == ["000000.label", "000001.label"]
    assert client.delete(f"{API}/projects/{again['id']}").status_code == 200
    assert create_project(client, tiny_dataset, name="third")["id"] == again["id"] + 1


def test_a_corrections_pass_in_flight_at_a_delete_leaves_no_folder_behind(
    client: TestClient, tiny_dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The first corrections pass after a run reads every scan (the voxel → frames index) before it writes
    into the run folder. A project deleted meanwhile must not get its run folder back from that pass,
    and nothing is applied for it afterwards.

    The pass is held at a gate in front of its real reading of the scans, after it has loaded the run's
    grid (the dataset reader refuses a pipe in place of a scan, so the gate cannot live in the dataset
    folder)."""
    reading, release = threading.Event(), threading.Event()
    real_index = core_apply.build_frame_index

    def gated_index(*args: Any, **kwargs: Any) -> Any:
        reading.set()
        assert release.wait(60), "the test never released the pass"
        return real_index(*args, **kwargs)

    settings = app_settings(client)
    project = create_project(client, tiny_dataset)
    run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    run = wait_run(client, run["id"])
    assert run["status"] == "done", run["error"]
    applier(settings).wait(project["id"])  # the run-done pass (nothing to apply yet)
    run_root = settings.runs_dir / f"p{project['id']}"
    assert run_root.is_dir()

    voxel_size = float(run["params"]["pipeline"]["fusion"]["voxel_size"])
    first = KittiSequence(tiny_dataset).frame(0)
    keys = np.unique(voxel_keys(world_points(first.points, first.pose), voxel_size))[:30]
    monkeypatch.setattr(core_apply, "build_frame_index", gated_index)
    try:
        body = {"class_name": "car", "voxel_size": voxel_size, "keys": keys.tolist()}
        assert client.post(f"{API}/projects/{project['id']}/corrections", json=body).status_code == 201
        assert reading.wait(60), "the corrections pass never started reading the scans"
        assert client.delete(f"{API}/projects/{project['id']}").status_code == 200
        assert not run_root.exists()
    finally:
        release.set()
    applier(settings).wait(project["id"])
    assert not run_root.exists(), sorted(str(p.relative_to(run_root)) for p in run_root.rglob("*"))
    # Asked again (a viewer left open on the deleted project): nothing runs, nothing is written.
    applier(settings).request(project["id"])
    applier(settings).warm(project["id"])
    assert applier(settings).wait(project["id"]).status == "idle"
    assert not run_root.exists()


def test_unknown_runs_are_404(client: TestClient) -> None:
    for method, path in [
        ("get", "/runs/77"),
        ("post", "/runs/77/cancel"),
        ("post", "/runs/77/resume"),
        ("get", "/runs/77/progress"),
        ("get", "/runs/77/events"),
        ("get", "/runs/77/metrics"),
        ("get", "/runs/77/logs"),
        ("get", "/runs/77/export.zip"),
        ("post", "/runs/77/export"),
    ]:
        r = getattr(client, method)(API + path, **({"json": {}} if method == "post" else {}))
        assert r.status_code == 404, (method, path, r.text)
        assert r.json()["detail"] == "Run 77 not found"


def test_invalid_run_payload_is_422(client: TestClient, tiny_dataset: Path) -> None:
    project = create_project(client, tiny_dataset)
    r = client.post(f"{API}/projects/{project['id']}/runs", json={"frames": {"start": 3, "stop": 1}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:2] == ["body", "frames"]
    r = client.post(f"{API}/projects/{project['id']}/runs", json={"frames": {"start": -1, "stop": 2}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "frames", "start"]


@pytest.mark.slow
def test_cancel_then_resume_finishes(client: TestClient, tiny_dataset: Path) -> None:
    project = create_project(client, tiny_dataset)
    run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    cancelled = client.post(f"{API}/runs/{run['id']}/cancel")
    assert cancelled.status_code == 200
    run = wait_run(client, run["id"])
    assert run["status"] == "cancelled" and run["resumable"]
    assert client.post(f"{API}/runs/{run['id']}/cancel").status_code == 409  # already ended
    resumed = client.post(f"{API}/runs/{run['id']}/resume")
    assert resumed.status_code == 202 and resumed.json()["status"] in ("queued", "running")
    run = wait_run(client, run["id"])
    assert run["status"] == "done" and run["number"] == 1
    assert client.post(f"{API}/runs/{run['id']}/resume").status_code == 409  # done runs do not resume


@pytest.mark.slow
def test_rerun_reuses_unchanged_stages(client: TestClient, tiny_dataset: Path) -> None:
    project = create_project(client, tiny_dataset)
    first = wait_run(client, client.post(f"{API}/projects/{project['id']}/runs", json={}).json()["id"])
    # A colour edit changes no computation: every stage output is reused from run 1.
    assert (
        client.patch(f"{API}/projects/{project['id']}/classes/car", json={"color": "#ff0000"}).status_code
        == 200
    )
    second = wait_run(client, client.post(f"{API}/projects/{project['id']}/runs", json={}).json()["id"])
    # A smoothing edit reruns smoothing and what follows, and still reuses the 2D labels and projection.
    assert client.patch(f"{API}/projects/{project['id']}", json={"form": {"k": 4}}).status_code == 200
    third = wait_run(client, client.post(f"{API}/projects/{project['id']}/runs", json={}).json()["id"])
    assert [r["status"] for r in (first, second, third)] == ["done"] * 3
    d1, d2, d3 = (Path(crud_run_dir(client, r["id"])) for r in (first, second, third))

    def inode(p: Path) -> int:
        return p.stat().st_ino

    fid = "000000"
    for folder, name in [
        ("labels2d", f"{fid}.npz"),
        ("observations", f"{fid}.npz"),
        ("export", f"{fid}.label"),
    ]:
        assert inode(d2 / folder / name) == inode(d1 / folder / name)
    assert inode(d2 / "grid_smooth.npz") == inode(d1 / "grid_smooth.npz")
    assert inode(d3 / "labels2d" / f"{fid}.npz") == inode(d1 / "labels2d" / f"{fid}.npz")
    assert inode(d3 / "observations" / f"{fid}.npz") == inode(d1 / "observations" / f"{fid}.npz")
    assert inode(d3 / "grid_smooth.npz") != inode(d1 / "grid_smooth.npz")
    # The earlier runs' outputs were not touched by the reruns.
    assert (
        json.loads((d1 / "stages.json").read_text())["smooth"]["fingerprint"]
        != json.loads((d3 / "stages.json").read_text())["smooth"]["fingerprint"]
    )
    with np.load(d1 / "grid_smooth.npz") as z1, np.load(d2 / "grid_smooth.npz") as z2:
        assert np.array_equal(z1["probs"], z2["probs"])


@pytest.mark.slow
def test_corrupt_dataset_fails_readably_and_keeps_earlier_outputs(
    client: TestClient, tiny_dataset: Path
) -> None:

    project = create_project(client, tiny_dataset)
    first = wait_run(client, client.post(f"{API}/projects/{project['id']}/runs", json={}).json()["id"])
    before = client.get(f"{API}/runs/{first['id']}/export.zip").content
    d1 = Path(crud_run_dir(client, first["id"]))
    labels_before = {p.name: p.read_bytes() for p in (d1 / "export").iterdir()}

    scan = tiny_dataset / "velodyne" / "000002.bin"
    scan.write_bytes(scan.read_bytes()[:-5])  # no longer a multiple of 16 bytes
    second = wait_run(client, client.post(f"{API}/projects/{project['id']}/runs", json={}).json()["id"])
    assert second["status"] == "failed" and second["resumable"]
    assert "000002.bin" in second["error"] and "multiple of 16" in second["error"]
    assert "\n" not in second["error"]
    assert client.get(f"{API}/runs/{second['id']}/export.zip").status_code == 409

    assert client.get(f"{API}/runs/{first['id']}/export.zip").content == before
    assert {p.name: p.read_bytes() for p in (d1 / "export").iterdir()} == labels_before


@pytest.mark.slow
def test_runs_of_different_projects_queue(data_root: Path, tiny_dataset: Path) -> None:
    from app.core.config import Settings
    from app.main import create_app

    settings = Settings(
        data_roots=[data_root], work_dir=data_root / "studio", seed_demo=False, max_parallel_runs=1
    )
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        a = create_project(client, tiny_dataset, "a")
        b = create_project(client, tiny_dataset, "b")
        ra = client.post(f"{API}/projects/{a['id']}/runs", json={}).json()
        rb = client.post(f"{API}/projects/{b['id']}/runs", json={}).json()
        assert client.get(f"{API}/runs/{rb['id']}").json()["status"] == "queued"
        assert (
            client.get(f"{API}/health").json()["queued"] + client.get(f"{API}/health").json()["running"] == 2
        )
        ra = wait_run(client, ra["id"])
        rb = wait_run(client, rb["id"])
        assert ra["status"] == rb["status"] == "done"
        assert rb["started_at"] >= ra["finished_at"]


def test_corrections_reach_the_exported_labels(client: TestClient, tiny_dataset: Path) -> None:
    project = create_project(client, tiny_dataset)
    seq = KittiSequence(tiny_dataset)
    frame = seq.frame(0)
    keys = voxel_keys(world_points(frame.points, frame.pose), 0.2)
    chosen = np.unique(keys)[:25]
    settings = app_settings(client)
    with open_db(settings.database) as db:
        undone = crud.add_correction(
            db, project_id=project["id"], class_name="vegetation", voxel_size=0.2, keys=chosen
        )
        crud.set_correction_active(db, undone, False)
        crud.add_correction(db, project_id=project["id"], class_name="pole", voxel_size=0.2, keys=chosen)
        crud.add_correction(db, project_id=project["id"], class_name="pole", voxel_size=0.5, keys=chosen[:3])
        assert [c.class_name for c in crud.list_corrections(db, project["id"])] == ["pole", "pole"]
        assert len(crud.list_corrections(db, project["id"], active_only=False)) == 3
    run = wait_run(client, client.post(f"{API}/projects/{project['id']}/runs", json={}).json()["id"])
    assert run["status"] == "done", run["error"]
    run_dir = Path(crud_run_dir(client, run["id"]))
    with np.load(run_dir / "corrections.npz") as z:
        assert np.array_equal(z["keys"], chosen) and z["keys"].dtype == np.int64
        assert (
            z["class_idx"].dtype == np.int16 and (z["class_idx"] == 17).all()
        )  # pole; the 0.5 m one dropped
    raw = np.fromfile(run_dir / "export" / "000000.label", dtype=np.uint32)
    in_chosen = np.isin(keys, chosen)
    assert in_chosen.any() and (raw[in_chosen] & 0xFFFF == 80).all()  # pole's export id

    # The export says which corrections its labels carry, and where the rest came from.
    info = client.get(f"{API}/runs/{run['id']}/export").json()
    prov = info["provenance"]
    (corr,) = prov["corrections"]
    assert corr["map_voxels"] == len(chosen) and corr["scan_points"] == 0 and len(corr["digest"]) == 16
    assert prov["labeler"] == {
        "name": "simulated",
        "description": "simulated (from 2D ground truth)",
        "weights": "none",
        "seed": 0,
    }
    assert prov["poses"] == [{"sequence": "00", "source": "file", "file": str(tiny_dataset / "poses.txt")}]
    assert prov["code"]["package"] == leap_core.__version__
    assert (
        f"corrections: {len(chosen)} voxels and 0 scan points in 0 frames (digest {corr['digest']})"
        in (info["provenance_lines"])
    )
    archive = client.get(f"{API}/runs/{run['id']}/export.zip")
    with zipfile.ZipFile(io.BytesIO(archive.content)) as zf:
        summary = yaml.safe_load(zf.read("summary.yaml"))
    assert summary["provenance"]["corrections"] == prov["corrections"]
    assert summary["provenance"]["labeler"]["weights"] == "none"


@pytest.mark.slow
def test_graceful_shutdown_interrupts_and_restart_resumes(settings, tiny_dataset: Path) -> None:
    from app.main import create_app

    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        project = create_project(client, tiny_dataset)
        run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    # Leaving the block shut the app down while the worker was still importing the pipeline.
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        stopped = client.get(f"{API}/runs/{run['id']}").json()
        assert stopped["status"] == "interrupted" and stopped["resumable"]
        assert client.post(f"{API}/runs/{run['id']}/resume").status_code == 202
        assert wait_run(client, run["id"])["status"] == "done"
