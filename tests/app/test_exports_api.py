"""Exports on a real server (``python -m app.main``, real SQLite, HTTP on 127.0.0.1) in the default layout:
the work folder inside the data root, a dataset copy with ground-truth labels in the same root.

An export could replace a dataset's ground-truth ``labels/`` and another project's run
folder. The export dialog's counts, the confirmation before writing into ``predictions/``, and
a zip that stands alone (read with its label-map YAML only).
"""

from __future__ import annotations

import hashlib
import io
import resource
import shutil
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml
from appfixtures import add_gt2d
from apphelpers import wait_run
from conftest import build_tiny_sequence
from serverproc import Server

from leap_core.schema import builtin_schema

FRAMES = 4


def tree_digest(folder: Path) -> dict[str, str]:
    """Relative path → sha256 of every file under ``folder``."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


class Studio:
    """The server and what the tests share: two projects on one dataset copy, each with a finished run."""

    def __init__(self, data: Path, server: Server, c: httpx.Client, dataset: Path) -> None:
        self.data, self.server, self.c, self.dataset = data, server, c, dataset
        self.runs: dict[str, dict[str, Any]] = {}


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Studio]:
    data = tmp_path_factory.mktemp("exports") / "data"
    seq = build_tiny_sequence(data / "kitti", n_frames=FRAMES, n_points=400)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    server = Server(data).start()
    try:
        with server.client() as c:
            st = Studio(data, server, c, seq.root)
            for name in ("A", "B"):
                p = c.post(
                    "/projects", json={"name": name, "dataset": {"kind": "folder", "path": str(seq.root)}}
                )
                assert p.status_code == 201, p.text
                run = c.post(f"/projects/{p.json()['id']}/runs", json={}).json()
                st.runs[name] = wait_run(c, run["id"], api="")
                assert st.runs[name]["status"] == "done", st.runs[name]
            yield st
    finally:
        server.stop()


@pytest.fixture
def clean_predictions(studio: Studio) -> Path:
    target = studio.dataset / "predictions"
    shutil.rmtree(target, ignore_errors=True)
    return target


def run_dir(studio: Studio, name: str) -> Path:
    """The run folder of the run of project ``name``."""
    run = studio.runs[name]
    return studio.data / "studio" / "runs" / f"p{run['project_id']}" / f"r{run['id']}"


def sequence_dir(studio: Studio, name: str) -> Path:
    """That run's folder of its one sequence (``00``)."""
    return run_dir(studio, name) / "sequences" / "00"


def export(studio: Studio, name: str, **body: Any) -> httpx.Response:
    return studio.c.post(f"/runs/{studio.runs[name]['id']}/export", json=body)


def test_export_never_writes_into_a_datasets_ground_truth_or_inputs(studio: Studio) -> None:
    before = tree_digest(studio.dataset)
    assert sum(k.startswith("labels/") for k in before) == FRAMES
    for rel in ("labels", "velodyne", "image_2", "labels/sub", "", "gt2d/semantic"):
        target = studio.dataset / rel
        r = export(studio, "B", path=str(target), overwrite=True)
        assert r.status_code == 403, (rel, r.text)
        assert "dataset" in r.json()["detail"], r.text
    # The relative spelling of the same folder (taken inside the data root) is refused as well.
    r = export(studio, "B", path="kitti/sequences/00/labels", overwrite=True)
    assert r.status_code == 403, r.text
    assert tree_digest(studio.dataset) == before


def test_export_never_writes_into_another_run_or_the_work_folder(studio: Studio) -> None:
    a_dir = run_dir(studio, "A")
    before = tree_digest(a_dir)
    assert sum(k.startswith("sequences/00/export/") for k in before) == 2 * FRAMES
    work = studio.data / "studio"
    for target in (
        sequence_dir(studio, "A") / "export",
        sequence_dir(studio, "A"),
        a_dir,
        "studio/runs/p1/r1",
        work,
        work / "runs",
        work / "somewhere-new",
        run_dir(studio, "B"),
        studio.data / "not-a-dataset",
    ):
        r = export(studio, "B", path=str(target), overwrite=True)
        assert r.status_code == 403, (target, r.text)
    assert tree_digest(a_dir) == before
    assert not (work / "somewhere-new").exists() and not (studio.data / "not-a-dataset").exists()


def test_existing_predictions_are_replaced_only_with_overwrite(
    studio: Studio, clean_predictions: Path
) -> None:
    b_export = sequence_dir(studio, "B") / "export"
    first = export(studio, "A")
    assert first.status_code == 200, first.text
    assert first.json()["files"] == FRAMES and first.json()["replaced"] == 0
    # Someone's earlier predictions: a refused write must leave every byte of them in place.
    mine = clean_predictions / "000000.label"
    mine.write_bytes(b"\x07\x00\x00\x00" * 400)
    before = tree_digest(clean_predictions)

    refused = export(studio, "B", include_confidence=True)
    assert refused.status_code == 409, refused.text
    assert "already holds 4 files" in refused.json()["detail"] and "overwrite" in refused.json()["detail"]
    assert tree_digest(clean_predictions) == before

    done = export(studio, "B", include_confidence=True, overwrite=True)
    assert done.status_code == 200, done.text
    assert done.json() == {
        "run_id": studio.runs["B"]["id"],
        "path": str(clean_predictions),
        "files": 2 * FRAMES,
        "replaced": FRAMES,
    }
    # The labels go to predictions/, their confidences to confidences/ beside it (as in the zip).
    exported = tree_digest(b_export)
    assert tree_digest(clean_predictions) == {k: v for k, v in exported.items() if k.endswith(".label")}
    confidences = clean_predictions.parent / "confidences"
    assert tree_digest(confidences) == {k: v for k, v in exported.items() if k.endswith(".conf")}
    shutil.rmtree(confidences)
    # No temp or backup folder is left beside it.
    assert sorted(p.name for p in clean_predictions.parent.iterdir() if p.name.startswith(".")) == []

    # A file an export never writes is not deleted, even with overwrite.
    (clean_predictions / "notes.txt").write_text("mine")
    before = tree_digest(clean_predictions)
    foreign = export(studio, "A", overwrite=True)
    assert foreign.status_code == 409 and "notes.txt" in foreign.json()["detail"], foreign.text
    assert tree_digest(clean_predictions) == before


def test_app_export_folder_takes_new_folders(studio: Studio) -> None:
    target = studio.data / "studio" / "exports" / "b-run"
    r = export(studio, "B", path=str(target))
    assert r.status_code == 200, r.text
    assert r.json()["path"] == str(target)
    # SemanticKITTI's layout: the folder holds sequences/<name>/predictions/.
    assert tree_digest(target) == {
        f"sequences/00/predictions/{k}": v
        for k, v in tree_digest(sequence_dir(studio, "B") / "export").items()
        if k.endswith(".label")
    }
    again = export(studio, "B", path=str(target))
    assert again.status_code == 409


def test_dialog_counts_and_confirmation_state(studio: Studio, clean_predictions: Path) -> None:
    run = studio.runs["B"]
    info = studio.c.get(f"/runs/{run['id']}/export").json()
    assert info["targets"] == [{"sequence": "00", "path": str(clean_predictions), "existing": 0}]
    assert info["predictions_allowed"]
    assert info["frames"] == FRAMES and info["points"] == FRAMES * 400
    assert info["labeled"] + info["unlabeled"] == info["points"]
    reasons = {r["key"]: r["points"] for r in info["reasons"]}
    assert sum(reasons.values()) == info["unlabeled"]
    # The tiny sequence puts points 4-20 m ahead, ±6 m to the sides: some are outside the narrow camera.
    assert reasons["outside_view"] > 0 and info["labeled"] > 0

    # The same counts from the run's own files: labels per point and the camera mask per scan.
    rd = sequence_dir(studio, "B")
    labels = [np.load(rd / "points" / f"{i:06d}.npz")["label"] for i in range(FRAMES)]
    assert info["labeled"] == sum(int((lab >= 0).sum()) for lab in labels)
    raw = np.concatenate([np.fromfile(rd / "export" / f"{i:06d}.label", "<u4") for i in range(FRAMES)])
    moving = {c.name: c.moving_id for c in builtin_schema("semantickitti").classes}
    assert {c["name"]: c["points"] for c in info["classes"]} == {
        c["name"]: int(np.isin(raw & 0xFFFF, [c["export_id"], moving.get(c["name"]) or c["export_id"]]).sum())
        for c in info["classes"]
    }

    # The UI asks before writing and says when files would be replaced: it reads each target's count.
    assert export(studio, "B").status_code == 200
    assert studio.c.get(f"/runs/{run['id']}/export").json()["targets"][0]["existing"] == FRAMES


def test_zip_stands_alone_with_its_label_map(studio: Studio, tmp_path: Path) -> None:
    run = studio.runs["B"]
    info = studio.c.get(f"/runs/{run['id']}/export").json()
    r = studio.c.get(f"/runs/{run['id']}/export.zip", params={"confidence": "true"})
    assert r.status_code == 200
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        zf.extractall(tmp_path)
    # Only the unpacked files from here on, read the way semantic-kitti-api's scripts read theirs.
    cfg = yaml.safe_load((tmp_path / "label-map.yaml").read_text())
    preds = sorted((tmp_path / "sequences" / "00" / "predictions").glob("*.label"))
    assert [p.stem for p in preds] == [f"{i:06d}" for i in range(FRAMES)]
    assert len(list((tmp_path / "sequences" / "00" / "confidences").glob("*.conf"))) == FRAMES
    raw = np.concatenate([np.fromfile(p, dtype=np.uint32) & 0xFFFF for p in preds])
    ids, n = np.unique(raw, return_counts=True)
    assert set(ids.tolist()) <= set(cfg["labels"]) and set(ids.tolist()) <= set(cfg["color_map"])
    counted = dict(zip(ids.tolist(), n.tolist(), strict=True))
    assert {k: v for k, v in cfg["counts"].items() if v} == counted
    assert sum(cfg["content"].values()) == pytest.approx(1.0)
    lut = np.zeros(max(cfg["learning_map"]) + 1, np.int64)
    for k, v in cfg["learning_map"].items():
        lut[k] = v
    learned = lut[raw]
    assert int((learned == 0).sum()) == info["unlabeled"] == cfg["counts"][0]
    # Names, colours (BGR in the file) and counts match what the run reports for its classes.
    for k, cls in enumerate(info["classes"], start=1):
        raw_id = cfg["learning_map_inv"][k]
        assert raw_id == cls["export_id"] and cfg["labels"][raw_id] == cls["name"]
        b, g, red = cfg["color_map"][raw_id]
        assert f"#{red:02x}{g:02x}{b:02x}" == cls["color"]
        assert int((learned == k).sum()) == cls["points"] == cfg["counts"][raw_id]
        assert cfg["learning_ignore"][k] is False
    assert cfg["learning_ignore"][0] is True
    assert cfg["split"]["valid"] == [0]  # semantic-kitti-api's evaluate_semantics.py --split valid
    summary = yaml.safe_load((tmp_path / "summary.yaml").read_text())
    assert summary["project"]["name"] == "B" and summary["run"]["id"] == run["id"]
    assert summary["counts"]["unlabeled"] == info["unlabeled"]
    assert summary["settings"]["pipeline"]["fusion"]["voxel_size"] == pytest.approx(0.2)


def test_a_full_disk_is_507_on_every_route_that_writes_files(studio: Studio) -> None:
    """Reads write files too: the export's counts and its zip are built on first use, a run preview
    fingerprints in a scratch folder. With the server unable to write more than one byte to any file
    (``RLIMIT_FSIZE`` set on its process: every larger write fails with EFBIG, as on a full disk), each of
    them and a folder export answer 507 saying the disk is full; the server lives on and, with the
    limit lifted, each works."""
    run = studio.runs["A"]
    for cached in run_dir(studio, "A").rglob("*"):
        if cached.name == "export-coverage.json" or cached.suffix == ".zip":
            cached.unlink()
    requests = {
        "export counts": lambda: studio.c.get(f"/runs/{run['id']}/export"),
        "export zip": lambda: studio.c.get(f"/runs/{run['id']}/export.zip"),
        "folder export": lambda: export(studio, "A", path=str(studio.data / "studio" / "exports" / "full")),
        "run preview": lambda: studio.c.get(f"/projects/{run['project_id']}/runs/preview"),
    }
    assert studio.server.proc is not None
    pid = studio.server.proc.pid
    limits = resource.prlimit(pid, resource.RLIMIT_FSIZE)
    resource.prlimit(pid, resource.RLIMIT_FSIZE, (1, limits[1]))
    try:
        answers = {what: send() for what, send in requests.items()}
    finally:
        resource.prlimit(pid, resource.RLIMIT_FSIZE, limits)
    for what, r in answers.items():
        assert r.status_code == 507, (what, r.status_code, r.text)
        assert "the disk is full" in r.json()["detail"] and "free some space" in r.json()["detail"], r.text
    full = studio.data / "studio" / "exports" / "full"
    assert not [p for p in full.rglob("*") if p.is_file()]  # nothing half-written is left
    for what, send in requests.items():
        assert send().status_code == 200, what

    # The API declares the answer on each of them.
    paths = studio.c.get("/openapi.json").json()["paths"]
    for path, method in (
        ("/api/v1/runs/{run_id}/export", "get"),
        ("/api/v1/runs/{run_id}/export.zip", "get"),
        ("/api/v1/runs/{run_id}/export", "post"),
        ("/api/v1/projects/{project_id}/runs/preview", "get"),
    ):
        assert "507" in paths[path][method]["responses"], (path, method)


def test_a_symlink_loop_as_export_path_is_refused_naming_the_field(studio: Studio) -> None:
    exports_dir = studio.data / "studio" / "exports"
    exports_dir.mkdir(parents=True, exist_ok=True)
    loop = exports_dir / "loop"
    loop.symlink_to(loop)
    try:
        for path in (loop, loop / "below"):
            r = export(studio, "A", path=str(path))
            assert r.status_code == 422, r.text
            (error,) = r.json()["detail"]
            assert error["loc"] == ["body", "path"] and "symlink loop" in error["msg"], error
    finally:
        loop.unlink()
