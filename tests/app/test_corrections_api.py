"""Manual corrections on a real server (``python -m app.main``, real SQLite, HTTP on 127.0.0.1) with a tiny
generated sequence: the corrections routes, the immediate "apply corrections" job
(the export changes without a run; undo reverts it), and scan scope + erase through a real pipeline run.
Also migration 3 on a version-2 database file.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from appfixtures import add_gt2d
from apphelpers import wait_run
from conftest import build_tiny_sequence
from serverproc import Server

from app.core import db as dbmod
from leap_core.datasets.kitti import KittiSequence, read_label
from leap_core.fusion import voxel_keys, world_points

FRAMES = 4


class Studio:
    def __init__(
        self, data: Path, c: httpx.Client, dataset: Path, project: dict[str, Any], run: dict[str, Any]
    ) -> None:
        self.data, self.c, self.dataset, self.project, self.run = data, c, dataset, project, run

    @property
    def pid(self) -> int:
        return int(self.project["id"])

    def run_dir(self, run: dict[str, Any]) -> Path:
        """The run's folder of the project's one sequence."""
        name = self.project["sequences"][0]["name"]
        return self.data / "studio" / "runs" / f"p{self.pid}" / f"r{run['id']}" / "sequences" / name

    def labels(self, run: dict[str, Any]) -> dict[str, np.ndarray]:
        export = self.run_dir(run) / "export"
        return {p.stem: read_label(p) & 0xFFFF for p in sorted(export.glob("*.label"))}

    def runs(self) -> list[dict[str, Any]]:
        r = self.c.get(f"/projects/{self.pid}/runs")
        assert r.status_code == 200, r.text
        body = r.json()
        return list(body["data"])

    def wait_apply(self, timeout: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            body = self.c.get(f"/projects/{self.pid}/corrections").json()
            if body["apply"]["status"] != "running":
                return body
            time.sleep(0.05)
        raise AssertionError("the apply-corrections job did not finish")

    def class_id(self, name: str) -> int:
        return next(int(c["export_id"]) for c in self.run["params"]["schema"]["classes"] if c["name"] == name)


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Studio]:
    data = tmp_path_factory.mktemp("corrections") / "data"
    seq = build_tiny_sequence(data / "kitti", n_frames=FRAMES, n_points=400)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    server = Server(data).start()
    try:
        with server.client() as c:
            dataset = {"kind": "folder", "path": str(seq.root)}
            p = c.post("/projects", json={"name": "corr", "dataset": dataset})
            assert p.status_code == 201, p.text
            run = c.post(f"/projects/{p.json()['id']}/runs", json={}).json()
            run = wait_run(c, run["id"], api="")
            assert run["status"] == "done", run
            yield Studio(data, c, seq.root, c.get(f"/projects/{p.json()['id']}").json(), run)
    finally:
        server.stop()


def _voxel_size(st: Studio) -> float:
    return float(st.run["params"]["pipeline"]["fusion"]["voxel_size"])


def point_keys(st: Studio, frame: int) -> np.ndarray:
    seq = KittiSequence(st.dataset)
    f = seq.frame(frame)
    return voxel_keys(world_points(f.points, f.pose), _voxel_size(st))


def in_keys(st: Studio, keys: np.ndarray) -> dict[str, np.ndarray]:
    """Per frame id: mask of the points whose voxel is in ``keys``."""
    seq = KittiSequence(st.dataset)
    return {seq.frame_ids[i]: np.isin(point_keys(st, i), keys) for i in range(len(seq))}


def test_a_correction_reaches_the_export_without_a_run_and_undo_reverts_it(studio: Studio) -> None:
    st = studio
    before = st.labels(st.run)
    runs_before = len(st.runs())
    names = [c["name"] for c in st.run["params"]["schema"]["classes"]]
    # A class the points of frame 0's first 30 voxels do not have everywhere already.
    keys = np.unique(point_keys(st, 0)[:30])
    target = next(
        n
        for n in names
        if not all((before[f][m] == st.class_id(n)).all() for f, m in in_keys(st, keys).items() if m.any())
    )
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={"class_name": target, "voxel_size": _voxel_size(st), "keys": keys.tolist()},
    )
    assert r.status_code == 201, r.text
    corr = r.json()
    assert corr["author"] == "api" and corr["scope"] == "map" and corr["voxels"] == keys.size
    body = st.wait_apply()
    assert body["apply"]["status"] == "done", body
    assert body["apply"]["run_id"] == st.run["id"]
    assert {"class_name": target, "corrections": 1, "voxels": int(keys.size)} in body["per_class"]
    after = st.labels(st.run)
    touched = in_keys(st, keys)
    assert body["apply"]["frames"] == sum(1 for m in touched.values() if m.any())
    for fid, mask in touched.items():
        assert (after[fid][mask] == st.class_id(target)).all(), fid
        assert (after[fid][~mask] == before[fid][~mask]).all(), fid  # nothing else moved
    assert len(st.runs()) == runs_before  # no run was started
    # The run's cached counts follow the new export.
    info = st.c.get(f"/runs/{st.run['id']}/export").json()
    counted = next(c["points"] for c in info["classes"] if c["name"] == target)
    assert counted == sum(int((lab == st.class_id(target)).sum()) for lab in after.values())
    # Its metrics were measured before the correction: they say so (and stop saying so once undone).
    assert st.c.get(f"/runs/{st.run['id']}/metrics").json()["before_corrections"] is True

    r = st.c.patch(f"/projects/{st.pid}/corrections/{corr['id']}", json={"active": False})
    assert r.status_code == 200 and r.json()["active"] is False, r.text
    st.wait_apply()
    reverted = st.labels(st.run)
    for fid in before:
        assert (reverted[fid] == before[fid]).all(), fid
    assert len(st.runs()) == runs_before
    assert st.c.get(f"/runs/{st.run['id']}/metrics").json()["before_corrections"] is False


def test_routes_refuse_bad_input_with_the_field_named(studio: Studio) -> None:
    st = studio
    vs = _voxel_size(st)
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={"class_name": "car", "voxel_size": vs, "keys": [1], "scope": "scan"},
    )
    assert r.status_code == 422 and "frame_id" in r.text, r.text
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={"class_name": "car", "voxel_size": vs, "keys": [1], "colour": 1},
    )
    assert r.status_code == 422 and "colour" in r.text, r.text
    r = st.c.post(f"/projects/{st.pid}/corrections", json={"class_name": "a/b", "voxel_size": vs, "keys": []})
    assert r.status_code == 422 and "class_name" in r.text, r.text
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={"class_name": "car", "voxel_size": vs, "scope": "scan", "frame_id": "000000", "points": [-1]},
    )
    assert r.status_code == 422 and "points" in r.text, r.text
    r = st.c.post(
        f"/projects/{st.pid}/corrections", json={"class_name": "car", "voxel_size": vs, "keys": [2**63]}
    )
    assert r.status_code == 422 and "keys" in r.text, r.text
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={"class_name": "car", "voxel_size": vs, "scope": "scan", "frame_id": "999999", "points": [1]},
    )
    assert r.status_code == 422 and "frame_id" in r.text and "999999" in r.text, r.text
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={"class_name": "car", "voxel_size": vs, "scope": "scan", "frame_id": "000000", "points": [400]},
    )  # the scans have 400 points
    assert r.status_code == 422 and "points" in r.text and "past scan 000000" in r.text, r.text
    r = st.c.patch(f"/projects/{st.pid}/corrections/999999", json={"active": True})
    assert r.status_code == 404, r.text
    r = st.c.patch(f"/projects/{st.pid}/corrections/1", json={"active": "maybe"})
    assert r.status_code == 422 and "active" in r.text, r.text
    r = st.c.get("/projects/999999/corrections")
    assert r.status_code == 404, r.text


def test_scan_scope_and_erase_survive_and_win_in_a_real_run(studio: Studio) -> None:
    st = studio
    names = [c["name"] for c in st.run["params"]["schema"]["classes"]]
    target = names[-1]
    scan_points = list(range(0, 40, 2))
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={
            "class_name": target,
            "voxel_size": _voxel_size(st),
            "keys": [],
            "scope": "scan",
            "frame_id": "000001",
            "points": scan_points,
        },
    )
    assert r.status_code == 201, r.text
    assert r.json()["scope"] == "scan" and r.json()["points"] == len(scan_points)
    erase = np.unique(point_keys(st, 2)[100:160])
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={"class_name": "", "voxel_size": _voxel_size(st), "keys": erase.tolist()},
    )
    assert r.status_code == 201, r.text
    st.wait_apply()
    # Applied at once to the finished run...
    now = st.labels(st.run)
    assert (now["000001"][scan_points] == st.class_id(target)).all()
    for fid, mask in in_keys(st, erase).items():
        assert (now[fid][mask] == 0).all(), fid
    # ... and a full run, which fuses them, keeps them.
    run = st.c.post(f"/projects/{st.pid}/runs", json={}).json()
    run = wait_run(st.c, run["id"], api="")
    assert run["status"] == "done", run
    labels = st.labels(run)
    assert (labels["000001"][scan_points] == st.class_id(target)).all()
    others = np.setdiff1d(np.arange(labels["000001"].size), scan_points)
    assert (labels["000001"][others] != st.class_id(target)).any()  # only the listed points of that scan
    for fid, mask in in_keys(st, erase).items():
        assert mask.any() or fid != "000002"
        assert (labels[fid][mask] == 0).all(), fid
    conf = np.fromfile(st.run_dir(run) / "export" / "000001.conf", dtype="<f4")
    assert np.allclose(conf[scan_points], 1.0)
    # Only the scan-scope change next: the run after reruns label_points and export but not the fusion.
    r = st.c.post(
        f"/projects/{st.pid}/corrections",
        json={
            "class_name": target,
            "voxel_size": _voxel_size(st),
            "keys": [],
            "scope": "scan",
            "frame_id": "000003",
            "points": [5],
        },
    )
    assert r.status_code == 201
    preview = st.c.get(f"/projects/{st.pid}/runs/preview").json()
    text = repr(preview)
    assert "label_points" in text


def test_a_correction_made_while_a_run_works_reaches_that_runs_export_when_it_ends(studio: Studio) -> None:
    from app import crud
    from app.core.config import Settings

    st = studio
    names = [c["name"] for c in st.run["params"]["schema"]["classes"]]
    target = names[0]
    run = st.c.post(f"/projects/{st.pid}/runs", json={}).json()
    # Straight into the database (as the viewer's request would land while the run works): the run's
    # corrections were written when it was created, and no apply pass is asked for here, so only the
    # run-done hook can bring this one into the run's export.
    database = Settings(work_dir=st.data / "studio", data_roots=[st.data]).database
    points = list(range(1, 30, 3))
    with dbmod.open_db(database) as db:
        crud.add_correction(
            db,
            project_id=st.pid,
            class_name=target,
            voxel_size=_voxel_size(st),
            keys=[],
            scope="scan",
            frame_id="000000",
            points=points,
            author="api",
        )
    assert st.c.get(f"/runs/{run['id']}").json()["status"] in ("queued", "running")
    run = wait_run(st.c, run["id"], api="")
    assert run["status"] == "done", run
    deadline = time.monotonic() + 30
    while (body := st.wait_apply())["apply"]["run_id"] != run["id"] and time.monotonic() < deadline:
        time.sleep(0.1)
    assert body["apply"]["run_id"] == run["id"], body
    assert (st.labels(run)["000000"][points] == st.class_id(target)).all()


def test_an_object_correction_relabels_its_track_in_every_scan_and_undo_reverts_it(studio: Studio) -> None:
    from leap_core.pipeline.apply import RunCorrections, frame_keys
    from leap_core.pipeline.tracks_file import SequenceTracks
    from leap_core.run_layout import SequenceLayout

    st = studio
    run = next(r for r in st.runs() if r["status"] == "done")  # the latest: the apply job's run
    folder = st.run_dir(run)
    tracks = SequenceTracks.load(folder / "tracks.npz")
    assert tracks.table.label.size >= 1, "the tiny sequence's run has no objects"
    track = int(np.argmax(tracks.table.scans)) + 1
    names = [c["name"] for c in run["params"]["schema"]["classes"]]
    target = next(n for n in names if n not in ("", names[int(tracks.table.label[track - 1])]))
    before = st.labels(run)
    url = f"/projects/{st.pid}/corrections"
    body = {"class_name": target, "voxel_size": _voxel_size(st), "scope": "object", "run_id": run["id"]}
    # Refused with the field named: no such track, another project's run, an object without a track.
    for bad, field in (
        ({**body, "track_id": int(tracks.table.label.size) + 1}, "track_id"),
        ({**body, "run_id": 10**6, "track_id": track}, "run_id"),
    ):
        r = st.c.post(url, json=bad)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", field], r.text
    assert st.c.post(url, json=body).status_code == 422
    r = st.c.post(url, json={**body, "track_id": track})
    assert r.status_code == 201, r.text
    corr = r.json()
    assert corr["scope"] == "object" and corr["track_id"] == track and corr["run_id"] == run["id"]
    assert (st.data / "studio" / "objects" / f"p{st.pid}").is_dir()
    # The next run would redo the evaluation and the export for it, not the fusion: an object correction is
    # never fused (an earlier test's scan correction, made during the latest run, reruns label_points here).
    preview = st.c.get(f"/projects/{st.pid}/runs/preview").json()
    assert {"evaluate", "export"} <= set(preview["recompute"]), preview
    assert "fuse" not in preview["recompute"], preview
    assert any(f"object {track} of run id {run['id']}" in c["text"] for c in preview["changes"]), preview
    listed = st.wait_apply()
    assert listed["apply"]["status"] == "done", listed
    mine = next(c for c in listed["corrections"] if c["id"] == corr["id"])
    assert mine["match"] == {
        "run_id": run["id"],
        "run_number": run["number"],
        "track": track,
        "iou": 1.0,
        "applied": True,
        "other_track": None,
        "other_iou": None,
        "new_track": None,
    }
    assert listed["latest_run_objects"] is True
    # A latest run without tracks (tracking off) is said so: the list does not say "not applied yet".
    (folder / "tracks.npz").rename(folder / "tracks.off")
    try:
        assert st.c.get(f"/projects/{st.pid}/corrections").json()["latest_run_objects"] is False
    finally:
        (folder / "tracks.off").rename(folder / "tracks.npz")
    # Every scan's points of the track take the class, but those a map or scan correction labels (those
    # win); nothing else moves.
    applied = RunCorrections.applied(SequenceLayout(folder), len(names))
    seq = KittiSequence(st.dataset)
    after = st.labels(run)
    relabeled = 0
    for i, fid in enumerate(seq.frame_ids):
        obj = tracks.scan(fid)
        rows = obj.rows[obj.track == track].astype(np.int64)
        scan_points, _ = applied.scan.of(fid)
        kept = np.isin(frame_keys(seq.frame(i), _voxel_size(st)), applied.map_keys)[rows] | np.isin(
            rows, scan_points
        )
        assert (after[fid][rows[~kept]] == st.class_id(target)).all(), fid
        assert (after[fid][rows[kept]] == before[fid][rows[kept]]).all(), fid
        rest = np.setdiff1d(np.arange(after[fid].size), rows)
        assert (after[fid][rest] == before[fid][rest]).all(), fid
        relabeled += int((~kept).sum())
    assert relabeled > 0
    r = st.c.patch(f"{url}/{corr['id']}", json={"active": False})
    assert r.status_code == 200, r.text
    st.wait_apply()
    reverted = st.labels(run)
    for fid in before:
        assert (reverted[fid] == before[fid]).all(), fid
    # A track without a point in the export (a static one whose points all keep a stuff class) is refused.
    original = (folder / "tracks.npz").read_bytes()
    t = tracks.table
    # One more track, a copy of the first's fields (its vote evidence dropped: the file then reads as
    # unanimous votes), with no point in any scan.
    empty = dataclasses.replace(
        t,
        evidence=None,
        **{
            f.name: np.concatenate([getattr(t, f.name), getattr(t, f.name)[:1]])
            for f in dataclasses.fields(t)
            if f.name != "evidence"
        },
    )
    dataclasses.replace(tracks, table=empty).save(folder / "tracks.npz")
    try:
        r = st.c.post(url, json={**body, "track_id": int(t.label.size) + 1})
        assert r.status_code == 422 and "has no points" in r.text, r.text
    finally:
        (folder / "tracks.npz").write_bytes(original)


def test_merge_and_split_give_the_exports_instance_ids_and_undo_reverts_them(studio: Studio) -> None:
    from leap_core.pipeline.tracks_file import SequenceTracks

    st = studio
    run = next(r for r in st.runs() if r["status"] == "done")
    export = st.run_dir(run) / "export"

    def ids() -> dict[str, np.ndarray]:
        return {p.stem: read_label(p) >> 16 for p in sorted(export.glob("*.label"))}

    before = ids()
    sizes = np.bincount(np.concatenate(list(before.values())).astype(np.int64))
    sizes[0] = 0
    assert np.count_nonzero(sizes) >= 2, "the tiny sequence's export has fewer than two objects"
    a, b = (int(x) for x in np.argsort(-sizes, kind="stable")[:2])
    scans = [f for f, v in before.items() if (v == a).any()]
    url = f"/projects/{st.pid}/corrections"
    body = {"voxel_size": _voxel_size(st), "scope": "object", "run_id": run["id"], "track_id": a}
    # Refused with the field named: a merge of an object with itself, a split at the object's first scan.
    for bad, field in (
        ({**body, "action": "merge", "other_track_id": a}, "other_track_id"),
        ({**body, "action": "split", "frame": scans[0]}, "frame"),
    ):
        r = st.c.post(url, json=bad)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", field], r.text
    merge = st.c.post(url, json={**body, "action": "merge", "other_track_id": b})
    assert merge.status_code == 201, merge.text
    listed = st.wait_apply()
    mine = next(c for c in listed["corrections"] if c["id"] == merge.json()["id"])
    assert (mine["action"], mine["other_track_id"], mine["class_name"]) == ("merge", b, ""), mine
    assert mine["match"]["applied"] and mine["match"]["other_track"] == b, mine
    merged = ids()
    for fid, v in before.items():
        assert (merged[fid][(v == a) | (v == b)] == a).all(), fid
        assert (merged[fid][(v != a) & (v != b)] == v[(v != a) & (v != b)]).all(), fid
    # The merged object is split at a later scan: its points from there on take a new id beyond the run's.
    both = [f for f, v in merged.items() if (v == a).any()]
    assert len(both) >= 2, both
    split = st.c.post(url, json={**body, "action": "split", "frame": both[1]})
    assert split.status_code == 201, split.text
    listed = st.wait_apply()
    new = next(c for c in listed["corrections"] if c["id"] == split.json()["id"])["match"]["new_track"]
    assert new == SequenceTracks.load(st.run_dir(run) / "tracks.npz").table.label.size + 1, new
    cut = ids()
    for fid in before:
        later = fid >= both[1]
        assert (cut[fid][merged[fid] == a] == (new if later else a)).all(), fid
    preview = st.c.get(f"/projects/{st.pid}/runs/preview").json()
    texts = [c["text"] for c in preview["changes"]]
    assert any(f"merge of objects {a} and {b}" in t for t in texts), texts
    assert any(f"split of object {a} of run id {run['id']} at scan {both[1]}" in t for t in texts), texts
    for c in (split, merge):
        assert st.c.patch(f"{url}/{c.json()['id']}", json={"active": False}).status_code == 200
    st.wait_apply()
    for fid, v in ids().items():
        assert (v == before[fid]).all(), fid


def test_migration_3_upgrades_a_version_2_database(tmp_path: Path) -> None:
    path = tmp_path / "old.db"
    db = dbmod.connect(path)
    try:
        db.execute(
            "CREATE TABLE schema_version (version INTEGER PRIMARY KEY, description TEXT NOT NULL, "
            "applied_at TEXT NOT NULL)"
        )
        for number, description, apply in dbmod.MIGRATIONS[:2]:
            with dbmod.transaction(db):
                apply(db)
                db.execute("INSERT INTO schema_version VALUES (?, ?, ?)", [number, description, "x"])
        db.execute(
            "INSERT INTO projects (name, dataset_kind, dataset_path, schema_json, pipeline_json, "
            "created_at, updated_at) VALUES ('p', 'folder', '/x', '{}', '{}', 'x', 'x')"
        )
        db.execute(
            "INSERT INTO corrections (project_id, created_at, class_name, voxel_size, keys) "
            "VALUES (1, 'x', 'car', 0.2, ?)",
            [np.array([7], np.int64).tobytes()],
        )
    finally:
        db.close()
    assert dbmod.init_db(path) >= 3
    from app import crud

    with dbmod.open_db(path) as db:
        (old,) = crud.list_corrections(db, 1)
        assert (old.scope, old.frame_id, old.points, old.author) == ("map", None, None, None)
        cid = crud.add_correction(
            db,
            project_id=1,
            class_name="",
            voxel_size=0.2,
            keys=[1],
            scope="scan",
            frame_id="000004",
            points=[3, 4],
            author="viewer",
        )
        new = crud.get_correction(db, cid)
        assert new.scope == "scan" and new.frame_id == "000004" and new.points is not None
        assert new.points.tolist() == [3, 4] and new.author == "viewer" and new.class_name == ""
        with pytest.raises(Exception, match="CHECK"):
            db.execute("UPDATE corrections SET scope = 'world' WHERE id = ?", [cid])


def _wait_apply(c: httpx.Client, pid: int, timeout: float = 60.0) -> dict[str, Any]:
    """The project's corrections once its apply job is not running (its last pass done)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body = c.get(f"/projects/{pid}/corrections").json()
        if body["apply"]["status"] != "running":
            return dict(body)
        time.sleep(0.05)
    raise AssertionError(f"the apply-corrections job of project {pid} did not finish")


def _labeled_project(c: httpx.Client, dataset: Path, name: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """A project on ``dataset`` with one finished run: (project, run)."""
    p = c.post("/projects", json={"name": name, "dataset": {"kind": "folder", "path": str(dataset)}})
    assert p.status_code == 201, p.text
    run = wait_run(c, c.post(f"/projects/{p.json()['id']}/runs", json={}).json()["id"], api="")
    assert run["status"] == "done", run
    return p.json(), run


def _export_labels(data: Path, run: dict[str, Any]) -> dict[str, np.ndarray]:
    run_dir = data / "studio" / "runs" / f"p{run['project_id']}" / f"r{run['id']}"
    export = run_dir / "sequences" / "00" / "export"
    return {p.stem: read_label(p) for p in sorted(export.glob("*.label"))}


def _frame_keys(dataset: Path, frame: int, voxel_size: float) -> np.ndarray:
    f = KittiSequence(dataset).frame(frame)
    return np.unique(voxel_keys(world_points(f.points, f.pose), voxel_size))


@pytest.mark.slow
def test_a_deleted_projects_grid_never_relabels_a_new_projects_export(tmp_path: Path) -> None:
    """The corrections job keeps a run's grid in memory. A project deleted and another created after it
    (which SQLite alone would give the same ids, hence the same run folder) must get its own: undoing a
    correction of the new project restores exactly its run's export, as a freshly started server does."""
    data = tmp_path / "data"
    first = build_tiny_sequence(data / "first", n_frames=FRAMES, n_points=400, seed=0)
    second = build_tiny_sequence(data / "second", n_frames=FRAMES, n_points=400, seed=1)
    for seq in (first, second):
        add_gt2d(seq.root, seq.frame_ids, (48, 64))
    server = Server(data).start()
    try:
        with server.client() as c:
            old, old_run = _labeled_project(c, first.root, "deleted")
            vs = float(old_run["params"]["pipeline"]["fusion"]["voxel_size"])
            target = old_run["params"]["schema"]["classes"][0]["name"]
            keys = _frame_keys(first.root, 0, vs)[:40]
            body = {"class_name": target, "voxel_size": vs, "keys": keys.tolist()}
            assert c.post(f"/projects/{old['id']}/corrections", json=body).status_code == 201
            assert _wait_apply(c, old["id"])["apply"]["status"] == "done"  # the job holds its grid now
            assert c.delete(f"/projects/{old['id']}").status_code == 200

            new, new_run = _labeled_project(c, second.root, "created after")
            own = _export_labels(data, new_run)
            keys = _frame_keys(second.root, 0, vs)[:40]
            body = {"class_name": target, "voxel_size": vs, "keys": keys.tolist()}
            r = c.post(f"/projects/{new['id']}/corrections", json=body)
            assert r.status_code == 201, r.text
            assert _wait_apply(c, new["id"])["apply"]["frames"] > 0
            r = c.patch(f"/projects/{new['id']}/corrections/{r.json()['id']}", json={"active": False})
            assert r.status_code == 200, r.text
            assert _wait_apply(c, new["id"])["apply"]["status"] == "done"
            undone = _export_labels(data, new_run)
        assert undone.keys() == own.keys()
        wrong = [f for f in own if not np.array_equal(undone[f], own[f])]
        assert not wrong, f"undo did not restore the run's labels in {wrong}"

        # A freshly started server (no grid in memory) gives the same export for redo then undo.
        server.stop()
        server.start()
        with server.client() as c:
            correction = c.get(f"/projects/{new['id']}/corrections").json()["corrections"][0]
            for active in (True, False):
                r = c.patch(f"/projects/{new['id']}/corrections/{correction['id']}", json={"active": active})
                assert r.status_code == 200, r.text
                assert _wait_apply(c, new["id"])["apply"]["status"] == "done"
            fresh = _export_labels(data, new_run)
        assert all(np.array_equal(fresh[f], undone[f]) for f in own)
    finally:
        server.stop()
