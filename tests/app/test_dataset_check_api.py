"""The dataset check in the app (real app, real SQLite): project creation refuses a folder the pipeline
cannot run on (422 naming the file), creates one where only some stages can run and shows the check with
app-worded fixes on the project, and ``/datasets`` lists the check of every dataset. A run's page shows
skipped stages with their reason and the labeler's warnings."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import appfixtures
import pytest
from apphelpers import API, create_project, wait_run
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app
from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models

client, data_root, settings, tiny_dataset = (
    appfixtures.client,
    appfixtures.data_root,
    appfixtures.settings,
    appfixtures.tiny_dataset,
)


def _post(client: TestClient, path: Path) -> Any:
    body = {"name": "x", "dataset": {"kind": "folder", "path": str(path)}}
    return client.post(f"{API}/projects", json=body)


def _copy(src: Path, dst: Path, drop: tuple[str, ...] = ()) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(*drop) if drop else None)
    return dst


def _no_cli_words(check: dict[str, Any]) -> None:
    """The app never tells a browser user to pass a command-line flag or run a leap command."""
    texts = [f["fix"] for f in check["findings"]] + [s["reason"] for s in check["stages"]]
    texts += [lab["reason"] for lab in check["labelers"]] + [check["summary"]]
    for text in texts:
        assert "--" not in text and "leap " not in text, text


def test_creation_refuses_a_folder_nothing_can_run_on(client: TestClient, tiny_dataset: Path) -> None:
    root = tiny_dataset.parents[2]
    no_calib = _copy(tiny_dataset, root / "nocalib" / "sequences" / "00")
    (no_calib / "calib.txt").unlink()
    r = _post(client, no_calib)
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "dataset", "path"]
    assert str(no_calib / "calib.txt") in err["msg"] and "'P2:'" in err["msg"], err["msg"]

    bad_calib = _copy(tiny_dataset, root / "badcalib" / "sequences" / "00")
    (bad_calib / "calib.txt").write_text("P2: 1 2 3\nTr: nonsense\n")
    r = _post(client, bad_calib)
    assert r.status_code == 422 and "calib.txt" in r.text and "has 3 values, expected 12" in r.text, r.text

    # Scans only: neither camera images nor 2D ground truth, so no 2D labeler has anything to label.
    no_images = _copy(tiny_dataset, root / "noimg" / "sequences" / "00", drop=("image_2", "gt2d"))
    r = _post(client, no_images)
    assert r.status_code == 422 and "image_2" in r.text and "Grounding DINO + SAM" in r.text, r.text
    assert "--" not in r.json()["detail"][0]["msg"].replace(str(root), "")

    r = _post(client, root / "tiny")  # a dataset root, not its sequence folder
    assert r.status_code == 422 and "velodyne" in r.text, r.text
    assert client.get(f"{API}/projects").json()["count"] == 0


def test_a_dataset_without_poses_is_created_with_the_warning_and_its_fix(
    client: TestClient, tiny_dataset: Path
) -> None:
    no_poses = _copy(tiny_dataset, tiny_dataset.parents[2] / "noposes" / "sequences" / "00")
    (no_poses / "poses.txt").unlink()
    project = create_project(client, no_poses)
    check = project["dataset"]["check"]
    assert check["verdict"] == "partial" and check["poses"]["source"] == "missing"
    (finding,) = [f for f in check["findings"] if f["code"] == "poses_missing"]
    assert finding["severity"] == "warning" and finding["path"] == str(no_poses / "poses.txt")
    assert "Estimate poses (KISS-ICP)" in finding["fix"]
    stages = {s["name"]: s for s in check["stages"]}
    assert stages["labels2d"]["state"] == "runs" and stages["project"]["state"] == "runs"
    assert stages["fuse"]["state"] == "blocked" and stages["fuse"]["reason"] == "no poses"
    assert stages["export"]["state"] == "blocked"
    _no_cli_words(check)
    # The project page reads the same check.
    assert client.get(f"{API}/projects/{project['id']}").json()["dataset"]["check"] == check

    # /datasets lists the check of every dataset; the poses file put back is seen at once (the cache
    # follows the folder's state).
    listed = {d["path"]: d["check"] for d in client.get(f"{API}/datasets").json()["data"]}
    assert listed[str(no_poses)]["verdict"] == "partial" and listed[str(tiny_dataset)]["verdict"] == "full"
    shutil.copy(tiny_dataset / "poses.txt", no_poses / "poses.txt")
    listed = {d["path"]: d["check"] for d in client.get(f"{API}/datasets").json()["data"]}
    assert listed[str(no_poses)]["verdict"] == "full"


def test_labeler_and_images_warnings_use_the_apps_words(client: TestClient, tiny_dataset: Path) -> None:
    root = tiny_dataset.parents[2]
    # Images but no 2D ground truth: the project's simulated labeler cannot run, Grounding DINO + SAM could.
    real = _copy(tiny_dataset, root / "real" / "sequences" / "00", drop=("gt2d",))
    check = create_project(client, real)["dataset"]["check"]
    assert check["verdict"] == "partial" and check["labeler"] == "simulated"
    (finding,) = [f for f in check["findings"] if f["code"] == "labeler_cannot_run"]
    assert finding["fix"] == 'choose "Grounding DINO + SAM" as the 2D labeler under Parameters'
    # ... but without a models folder on this server it cannot run either: the fix is the server's.
    (models,) = [f for f in check["findings"] if f["code"] == "models_missing" and f["severity"] != "info"]
    assert "LEAP_MODELS_DIR" in models["fix"]
    _no_cli_words(check)

    # One image missing: created; the check names the frame.
    gap = _copy(tiny_dataset, root / "gap" / "sequences" / "00")
    (gap / "image_2" / "000002.png").unlink()
    check = create_project(client, gap)["dataset"]["check"]
    (finding,) = [f for f in check["findings"] if f["code"] == "images_partial"]
    assert finding["frames"] == ["000002"] and finding["count"] == 1 and "000002" in finding["message"]
    assert check["images"] == {"present": 3, "total": 4, "kind": "some"}
    _no_cli_words(check)


def test_a_single_scan_copied_out_with_the_full_poses(client: TestClient, tiny_dataset: Path) -> None:
    """Frame 000002 alone, with the sequence's 4-line poses.txt and times.txt: the reader takes a frame's
    pose by its file number, so the project is created with a full check."""
    single = tiny_dataset.parents[2] / "single" / "sequences" / "00"
    for sub, suffix in (
        ("velodyne", ".bin"),
        ("image_2", ".png"),
        ("labels", ".label"),
        ("gt2d/semantic", ".png"),
        ("gt2d/instance", ".png"),
    ):
        (single / sub).mkdir(parents=True)
        shutil.copy(tiny_dataset / sub / f"000002{suffix}", single / sub)
    for name in ("calib.txt", "poses.txt", "times.txt"):
        shutil.copy(tiny_dataset / name, single / name)
    r = _post(client, single)
    assert r.status_code == 201, r.text
    check = r.json()["dataset"]["check"]
    assert check["verdict"] == "full" and check["frames"] == 1 and check["poses"]["lines"] == 4


@pytest.mark.slow
def test_the_run_shows_skipped_stages_with_their_reason(client: TestClient, tiny_dataset: Path) -> None:
    project = create_project(client, tiny_dataset)
    run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    run = wait_run(client, run["id"])
    assert run["status"] == "done", run["error"]
    stages = {s["name"]: s for s in run["progress"]["stages"]}
    assert stages["00/3dcn"]["status"] == "skipped" and stages["00/3dcn"]["note"] == "3D-CN disabled"
    assert stages["00/fuse"]["status"] == "done" and stages["00/fuse"]["note"] is None
    log = client.get(f"{API}/runs/{run['id']}/logs").json()["text"]
    assert "stage 00/3dcn skipped (3D-CN disabled)" in log and "stage 00/3dcn done" not in log, log

    # A second run reuses every stage: each says so instead of "done in 0.00 s".
    again = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    again = wait_run(client, again["id"])
    assert again["status"] == "done", again["error"]
    stages = {s["name"]: s for s in again["progress"]["stages"]}
    for name in ("labels2d", "project", "fuse", "smooth", "label_points", "tracks", "evaluate", "export"):
        assert stages[f"00/{name}"]["status"] == "skipped", stages[f"00/{name}"]
        assert stages[f"00/{name}"]["note"] == "unchanged since the last run", stages[f"00/{name}"]
    log = client.get(f"{API}/runs/{again['id']}/logs").json()["text"]
    assert (
        "stage 00/fuse skipped (unchanged since the last run)" in log and "stage 00/fuse done" not in log
    ), log


@pytest.mark.slow
def test_random_weight_models_warn_in_the_run_log_and_on_the_run(data_root: Path, tiny_dataset: Path) -> None:
    models = make_tiny_models(data_root.parent / "models", TinyModelsConfig(num_queries=8)).models_dir
    settings = Settings(
        data_roots=[data_root],
        work_dir=data_root / "studio",
        seed_demo=False,
        progress_interval_s=0.02,
        prewarm_workers=False,
        models_dir=models,
    )
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        r = client.post(
            f"{API}/projects",
            json={
                "name": "p",
                "dataset": {"kind": "folder", "path": str(tiny_dataset)},
                "schema_name": "agri_uav",
            },
        )
        assert r.status_code == 201, r.text
        check = r.json()["dataset"]["check"]
        assert check["labeler"] == "grounded-sam"
        assert [f["code"] for f in check["findings"] if f["severity"] == "warning"] == ["models_random"] * 2
        run = client.post(f"{API}/projects/{r.json()['id']}/runs", json={}).json()
        run = wait_run(client, run["id"], timeout=240)
        assert run["status"] == "done", run["error"]
        warnings = run["progress"]["warnings"]
        assert any("RANDOM-weight" in w for w in warnings), warnings
        log = client.get(f"{API}/runs/{run['id']}/logs").json()["text"]
        assert "RANDOM-weight test model" in log, log


def test_a_run_without_models_fails_with_the_servers_side_of_the_fix(
    client: TestClient, tiny_dataset: Path
) -> None:
    r = client.post(
        f"{API}/projects",
        json={
            "name": "p",
            "dataset": {"kind": "folder", "path": str(tiny_dataset)},
            "schema_name": "agri_uav",
        },
    )
    assert r.status_code == 201, r.text
    assert r.json()["dataset"]["check"]["verdict"] == "partial"  # warned at creation: no models folder
    run = client.post(f"{API}/projects/{r.json()['id']}/runs", json={}).json()
    run = wait_run(client, run["id"])
    assert run["status"] == "failed" and "LEAP_MODELS_DIR" in run["error"], run["error"]
    assert "--" not in run["error"] and "grounding-dino-tiny" in run["error"], run["error"]
