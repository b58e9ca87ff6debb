"""The project's LiDAR-only models through the API on a real app (real SQLite, the pipeline's worker, the
model thread): train on the latest finished run's labels, the card, label a sequence, download the zip;
bad input names its field; one project never reaches another's models or labels; cancel then resume gives
the checkpoint an uninterrupted training gives."""

from __future__ import annotations

import io
import json
import shutil
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from appfixtures import add_gt2d
from apphelpers import API, loc_of, wait_run
from conftest import build_tiny_sequence
from fastapi.testclient import TestClient

from app import crud
from app.core.config import Settings
from app.core.db import open_db
from app.jobs.models import label_folder, model_file
from app.main import create_app

pytestmark = pytest.mark.slow

FRAMES = 4
TINY = {"steps": 3, "points_per_scan": 256, "val_block": 1, "val_every": 2}
"""A few steps on 400-point scans; blocks of one frame, every second one validates (frames 1 and 3)."""


class Studio:
    def __init__(self, client: TestClient, settings: Settings, dataset: Path) -> None:
        self.c, self.settings, self.dataset = client, settings, dataset
        self.projects: dict[str, int] = {}
        self.runs: dict[str, dict[str, Any]] = {}


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Studio]:
    data = tmp_path_factory.mktemp("models") / "data"
    seq = build_tiny_sequence(data / "kitti", n_frames=FRAMES, n_points=400)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    settings = Settings(
        data_roots=[data],
        work_dir=data / "studio",
        seed_demo=False,
        progress_interval_s=0.02,
        prewarm_workers=False,
    )
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as c:
        st = Studio(c, settings, seq.root)
        for name in ("A", "B"):
            p = c.post(
                f"{API}/projects", json={"name": name, "dataset": {"kind": "folder", "path": str(seq.root)}}
            )
            assert p.status_code == 201, p.text
            st.projects[name] = p.json()["id"]
            run = c.post(f"{API}/projects/{p.json()['id']}/runs", json={}).json()
            st.runs[name] = wait_run(c, run["id"])
            assert st.runs[name]["status"] == "done", st.runs[name]
        yield st


def wait_job(
    st: Studio, project: str, job_id: int, until: tuple[str, ...] = ("done", "failed", "cancelled")
) -> dict[str, Any]:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        jobs = st.c.get(f"{API}/projects/{st.projects[project]}/model-jobs").json()["data"]
        job = next(j for j in jobs if j["id"] == job_id)
        if job["status"] in until:
            return job
        time.sleep(0.05)
    raise AssertionError(f"model job {job_id} still {job['status']}")


def train(st: Studio, project: str, **body: Any) -> dict[str, Any]:
    r = st.c.post(f"{API}/projects/{st.projects[project]}/models", json={**TINY, **body})
    assert r.status_code == 202, r.text
    return wait_job(st, project, r.json()["id"])


def a_model(st: Studio) -> int:
    """Project A's first model (trained here when no earlier test trained one)."""
    found = st.c.get(f"{API}/projects/{st.projects['A']}/models").json()["data"]
    return int(found[-1]["id"]) if found else int(train(st, "A")["id"])


def a_labeling(st: Studio) -> dict[str, Any]:
    """A finished labeling of project A (made here when no earlier test made one)."""
    jobs = st.c.get(f"{API}/projects/{st.projects['A']}/model-jobs").json()["data"]
    done = [j for j in jobs if j["kind"] == "label" and j["status"] == "done"]
    if done:
        return done[0]
    r = st.c.post(f"{API}/projects/{st.projects['A']}/models/{a_model(st)}/label", json={"sequence": "00"})
    return wait_job(st, "A", r.json()["id"])


def test_train_then_label_a_sequence_and_download_its_labels(studio: Studio) -> None:
    st = studio
    pid = st.projects["A"]
    job = train(st, "A", name="first")
    assert job["status"] == "done", job
    assert (job["done"], job["total"]) == (3, 3)
    models = st.c.get(f"{API}/projects/{pid}/models").json()
    assert models["count"] == 1
    model = models["data"][0]
    assert (model["id"], model["name"]) == (job["id"], "first")
    card = model["card"]
    run_dir = st.settings.work_dir / "runs" / f"p{pid}" / f"r{st.runs['A']['id']}"
    assert card["data"]["runs"] == [str(run_dir)]
    # Frames 1 and 3 were held apart (blocks of one frame, every second one), never trained on.
    assert [d["frames"] for d in card["data"]["train"]] == [["000000", "000002"]]
    assert card["data"]["train"][0]["scans"] == 2
    assert card["validation"]["scans"] == 2
    assert set(card["validation"]["iou"]) == {c["name"] for c in card["classes"]}
    assert card["settings"]["steps"] == 3
    # Trained on the run's final point labels (points/*.npz, where the corrections are applied).
    counts = np.zeros(len(card["classes"]), np.int64)
    for fid in ("000000", "000002"):
        label = np.load(run_dir / "sequences" / "00" / "points" / f"{fid}.npz")["label"]
        counts += np.bincount(label[label >= 0], minlength=counts.size)
    assert [c["training_points"] for c in card["classes"]] == counts.tolist()
    path = model_file(st.settings, pid, job["id"])
    assert path.is_file() and path.with_suffix(".card.json").is_file()
    assert path.is_relative_to(st.settings.work_dir)

    r = st.c.post(f"{API}/projects/{pid}/models/{job['id']}/label", json={"sequence": "00"})
    assert r.status_code == 202, r.text
    done = wait_job(st, "A", r.json()["id"])
    assert done["status"] == "done", done
    assert done["download"] == f"/projects/{pid}/model-jobs/{done['id']}/labels.zip"
    z = st.c.get(f"{API}{done['download']}")
    assert z.status_code == 200, z.text
    with zipfile.ZipFile(io.BytesIO(z.content)) as zf:
        names = zf.namelist()
        labels = sorted(n for n in names if n.endswith(".label"))
        assert labels == [f"sequences/00/predictions/{i:06d}.label" for i in range(FRAMES)]
        assert json.loads(zf.read("model-card.json"))["settings"]["steps"] == 3
        lmap = yaml.safe_load(zf.read("label-map.yaml"))
        export_ids = {c["export_id"] for c in card["classes"]}
        for name in labels:
            raw = np.frombuffer(zf.read(name), np.uint32) & 0xFFFF
            assert raw.size == 400
            assert set(raw.tolist()) <= export_ids  # every point labeled: no camera needed
            assert set(raw.tolist()) <= set(lmap["labels"])
    # The dataset got nothing: the labels are in the project's own folder.
    assert not (st.dataset / "predictions").exists()
    assert label_folder(st.settings, pid, done["id"]).is_relative_to(st.settings.work_dir)


def test_label_a_sequence_folder_without_a_camera(studio: Studio) -> None:
    """A dataset path inside a data root, LiDAR only (no images, no labels, no poses): every point labeled."""
    st = studio
    pid = st.projects["A"]
    folder = st.dataset.parents[2] / "lidar-only" / "sequences" / "05"
    (folder / "velodyne").mkdir(parents=True)
    for scan in sorted((st.dataset / "velodyne").glob("*.bin")):
        shutil.copy(scan, folder / "velodyne" / scan.name)
    shutil.copy(st.dataset / "calib.txt", folder / "calib.txt")
    model = a_model(st)
    r = st.c.post(f"{API}/projects/{pid}/models/{model}/label", json={"dataset": str(folder)})
    assert r.status_code == 202, r.text
    done = wait_job(st, "A", r.json()["id"])
    assert (done["status"], done["name"]) == ("done", "05"), done
    with zipfile.ZipFile(io.BytesIO(st.c.get(f"{API}{done['download']}").content)) as zf:
        labels = sorted(n for n in zf.namelist() if n.endswith(".label"))
        assert labels == [f"sequences/05/predictions/{i:06d}.label" for i in range(FRAMES)]
        assert all((np.frombuffer(zf.read(n), np.uint32) & 0xFFFF).min() > 0 for n in labels)
    assert sorted(p.name for p in folder.iterdir()) == ["calib.txt", "velodyne"]


def test_bad_input_names_the_field(studio: Studio) -> None:
    st = studio
    pid = st.projects["A"]
    base = f"{API}/projects/{pid}/models"
    assert loc_of(st.c.post(base, json={"steps": 0})) == ["body", "steps"]
    assert loc_of(st.c.post(base, json={"steps": 10**6})) == ["body", "steps"]
    assert loc_of(st.c.post(base, json={"points_per_scan": 10})) == ["body", "points_per_scan"]
    assert loc_of(st.c.post(base, json={"name": "a/b"})) == ["body", "name"]
    assert loc_of(st.c.post(base, json={"validation": "random"})) == ["body", "validation"]
    r = st.c.post(base, json={"validation": "sequence", "validation_sequence": "07"})
    assert loc_of(r) == ["body", "validation_sequence"]
    assert "00" in r.json()["detail"][0]["msg"]
    assert loc_of(st.c.post(base, json={"validation": "sequence", "validation_sequence": "00"})) == [
        "body",
        "validation",
    ]
    model = a_model(st)
    r = st.c.post(f"{base}/{model}/label", json={"sequence": "../00"})
    assert loc_of(r) == ["body", "sequence"]
    assert st.c.post(f"{base}/{model}/label", json={}).status_code == 422
    both = st.c.post(f"{base}/{model}/label", json={"sequence": "00", "dataset": str(st.dataset)})
    assert both.status_code == 422 and "give one of" in both.text
    assert loc_of(st.c.post(f"{base}/{model}/label", json={"dataset": "kitti"})) == ["body", "dataset"]
    outside = st.c.post(f"{base}/{model}/label", json={"dataset": str(Path(__file__).parent)})
    assert outside.status_code == 403, outside.text
    assert st.c.post(f"{API}/projects/999/models", json={}).status_code == 404


def test_one_project_never_reaches_another_projects_models(studio: Studio) -> None:
    st = studio
    a, b = st.projects["A"], st.projects["B"]
    model = a_model(st)
    label_job = a_labeling(st)
    a_ids = {model, label_job["id"]}
    assert not a_ids & {m["id"] for m in st.c.get(f"{API}/projects/{b}/models").json()["data"]}
    b_jobs = {j["id"] for j in st.c.get(f"{API}/projects/{b}/model-jobs").json()["data"]}
    assert not a_ids & b_jobs
    r = st.c.post(f"{API}/projects/{b}/models/{model}/label", json={"sequence": "00"})
    assert r.status_code == 404, r.text
    assert st.c.get(f"{API}/projects/{b}/model-jobs/{label_job['id']}/labels.zip").status_code == 404
    assert st.c.post(f"{API}/projects/{b}/model-jobs/{model}/resume").status_code == 404
    assert st.c.post(f"{API}/projects/{b}/model-jobs/{model}/cancel").status_code == 404
    # A training is no labeling: nothing to download, and a labeling is no model to label with.
    assert st.c.get(f"{API}/projects/{a}/model-jobs/{model}/labels.zip").status_code == 404
    r = st.c.post(f"{API}/projects/{a}/models/{label_job['id']}/label", json={"sequence": "00"})
    assert r.status_code == 404
    assert {j["id"] for j in st.c.get(f"{API}/projects/{b}/model-jobs").json()["data"]} == b_jobs


def test_cancel_then_resume_ends_with_the_uninterrupted_checkpoint(studio: Studio) -> None:
    st = studio
    pid = st.projects["B"]
    steps = 12
    body = {**TINY, "steps": steps, "seed": 3}
    whole = train(st, "B", **body)
    assert whole["status"] == "done", whole
    r = st.c.post(f"{API}/projects/{pid}/models", json=body)
    job_id = r.json()["id"]
    wait_job(st, "B", job_id, until=("running",))
    deadline = time.monotonic() + 30
    while st.c.get(f"{API}/projects/{pid}/model-jobs").json()["data"][0]["done"] < 2:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    busy = st.c.delete(f"{API}/projects/{pid}")
    r = st.c.post(f"{API}/projects/{pid}/model-jobs/{job_id}/cancel")
    assert r.status_code == 200, r.text
    assert busy.status_code == 409 and f"model job {job_id}" in busy.text, busy.text
    cancelled = wait_job(st, "B", job_id)
    assert cancelled["status"] == "cancelled", cancelled
    assert 0 < cancelled["done"] < steps
    path = model_file(st.settings, pid, job_id)
    assert not path.exists() and path.with_suffix(".state.pt").is_file()
    assert st.c.post(f"{API}/projects/{pid}/model-jobs/{job_id}/cancel").status_code == 409
    r = st.c.post(f"{API}/projects/{pid}/model-jobs/{job_id}/resume")
    assert r.status_code == 200, r.text
    resumed = wait_job(st, "B", job_id)
    assert resumed["status"] == "done", resumed
    card = st.c.get(f"{API}/projects/{pid}/models").json()["data"][0]["card"]
    assert card["training"]["resumed_from"] > 0
    assert st.c.post(f"{API}/projects/{pid}/model-jobs/{job_id}/resume").status_code == 409
    one = torch.load(model_file(st.settings, pid, whole["id"]), weights_only=True)["state_dict"]
    two = torch.load(path, weights_only=True)["state_dict"]
    assert one.keys() == two.keys()
    for key in one:
        assert torch.equal(one[key], two[key]), key
    # The models go with their project.
    assert st.c.delete(f"{API}/projects/{pid}").status_code == 200
    assert not path.parent.exists()


def test_a_job_the_server_left_working_is_interrupted_and_resumable(tmp_path: Path) -> None:
    """What a restart finds: the job row says running (the server stopped mid-training)."""
    settings = Settings(
        data_roots=[tmp_path], work_dir=tmp_path / "studio", seed_demo=False, prewarm_workers=False
    )
    dataset = build_tiny_sequence(tmp_path / "kitti", n_frames=2, n_points=50).root
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as c:
        p = c.post(
            f"{API}/projects", json={"name": "R", "dataset": {"kind": "folder", "path": str(dataset)}}
        ).json()
    with open_db(settings.database) as db:
        job = crud.create_model_job(db, project_id=p["id"], kind="train", name="m", params={"run_id": 1})
        crud.update_model_job(db, job.id, status="running")
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as c:
        jobs = c.get(f"{API}/projects/{p['id']}/model-jobs").json()["data"]
        assert [(j["id"], j["status"]) for j in jobs] == [(job.id, "interrupted")]
        assert c.post(f"{API}/projects/{p['id']}/model-jobs/{job.id}/resume").status_code == 200
        c.app.state.model_jobs.wait_idle(30)
        jobs = c.get(f"{API}/projects/{p['id']}/model-jobs").json()["data"]
        # Its run is gone (the project never ran): the resumed job fails with the reason.
        assert jobs[0]["status"] == "failed" and "run 1" in jobs[0]["error"]
