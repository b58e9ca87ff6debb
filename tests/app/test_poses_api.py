"""The project option "Estimate poses (KISS-ICP)" through the real app (real SQLite, real worker processes)
on a generated drive whose poses.txt was removed."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import appfixtures
import pytest
from apphelpers import API, wait_run
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.jobs.poses import cache_folder
from app.jobs.stages import POSES
from leap_core.datasets.kitti import POSES_NOTE, KittiSequence
from leap_core.pipeline import STAGES
from leap_core.run_layout import RunLayout
from leap_core.synth import CameraConfig, LidarConfig, SceneConfig, SynthConfig, generate_sequence

client, data_root, settings = appfixtures.client, appfixtures.data_root, appfixtures.settings

DRIVE = SynthConfig(
    frames=6,
    seed=3,
    lidar=LidarConfig(beams=48, azimuth_step_deg=0.4),
    camera=CameraConfig().scaled(0.25),
    scene=SceneConfig(margin=90.0),
)


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_sequence(tmp_path_factory.mktemp("drive"), DRIVE, workers=1).path


@pytest.fixture
def no_poses(drive: Path, data_root: Path) -> Path:
    """``data/drive/sequences/00``: the drive without poses.txt, inside the data root."""
    seq = data_root / "drive" / "sequences" / "00"
    shutil.copytree(drive, seq)
    (seq / "poses.txt").unlink()
    return seq


def _create(client: TestClient, dataset: Path, **extra: object) -> dict:
    body = {
        "name": "drive",
        "dataset": {"kind": "folder", "path": str(dataset)},
        "pipeline": {"labeler": "simulated"},
        **extra,
    }
    r = client.post(f"{API}/projects", json=body)
    assert r.status_code == 201, r.text
    return r.json()


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _stages(project: dict[str, Any], *before: str) -> list[str]:
    """A run's progress stages on the project's one sequence: ``before`` (e.g. the pose estimation), then
    the pipeline's."""
    name = project["sequences"][0]["name"]
    return [f"{name}/{stage}" for stage in (*before, *STAGES)]


def test_a_run_without_poses_is_refused_with_app_advice(
    client: TestClient, no_poses: Path, drive: Path
) -> None:
    """As ``leap run`` refuses a sequence without poses before any work, the app refuses the run when it is
    started (no run row, no failed run): 409 naming the poses file and the fixes in the app's words."""
    project = _create(client, no_poses)
    assert project["estimate_poses"] is False
    r = client.post(f"{API}/projects/{project['id']}/runs", json={})
    assert r.status_code == 409, r.text[:300]
    error = r.json()["detail"]
    assert f"{no_poses / 'poses.txt'}: no poses" in error, error
    assert "Estimate poses (KISS-ICP)" in error and '"estimate_poses": true' in error, error
    assert "--estimate-poses" not in error and "leap poses" not in error  # no CLI advice in the app
    assert client.get(f"{API}/projects/{project['id']}/runs").json()["count"] == 0

    # Either fix lets the run start: the option (through the API here) ...
    r = client.patch(f"{API}/projects/{project['id']}", json={"estimate_poses": True})
    assert r.status_code == 200, r.text
    run = client.post(f"{API}/projects/{project['id']}/runs", json={})
    assert run.status_code == 202, run.text
    assert client.post(f"{API}/runs/{run.json()['id']}/cancel").status_code == 200
    wait_run(client, run.json()["id"], timeout=120)
    # ... or a poses file in the dataset.
    r = client.patch(f"{API}/projects/{project['id']}", json={"estimate_poses": False})
    assert r.status_code == 200, r.text
    assert client.post(f"{API}/projects/{project['id']}/runs", json={}).status_code == 409
    shutil.copyfile(drive / "poses.txt", no_poses / "poses.txt")
    run = client.post(f"{API}/projects/{project['id']}/runs", json={})
    assert run.status_code == 202, run.text
    assert client.post(f"{API}/runs/{run.json()['id']}/cancel").status_code == 200
    wait_run(client, run.json()["id"], timeout=120)


def test_estimated_poses_go_to_the_work_folder_and_are_reused(
    client: TestClient, no_poses: Path, settings: Settings
) -> None:
    before = _files(no_poses)
    project = _create(client, no_poses, estimate_poses=True)
    assert project["estimate_poses"] is True
    run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    assert [s["name"] for s in run["progress"]["stages"]] == _stages(project, POSES)
    done = wait_run(client, run["id"], timeout=180)
    assert done["status"] == "done", done["error"]
    assert _files(no_poses) == before  # the dataset is never written

    cached = cache_folder(settings.cache_dir, no_poses) / "poses.txt"
    assert cached.is_file() and (cached.parent / POSES_NOTE).is_file()
    run_layout = RunLayout(settings.runs_dir / f"p{project['id']}" / f"r{done['id']}")
    layout = run_layout.sequence(project["sequences"][0]["name"])
    assert layout.poses.read_bytes() == cached.read_bytes()
    assert layout.open_sequence(no_poses).pose_source == "estimated"
    warnings = done["progress"]["warnings"]
    assert any(
        "poses: the dataset has no poses.txt; KISS-ICP" in w and "estimated them" in w for w in warnings
    ), warnings
    assert "KISS-ICP" in run_layout.log.read_text()
    stages = {s["name"]: s for s in done["progress"]["stages"]}
    assert stages[_stages(project, POSES)[0]]["status"] == "done"

    second = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    done2 = wait_run(client, second["id"], timeout=180)
    assert done2["status"] == "done", done2["error"]
    assert any("reused the estimate cached" in w for w in done2["progress"]["warnings"])


def test_the_option_can_be_switched_and_is_validated(client: TestClient, no_poses: Path) -> None:
    project = _create(client, no_poses)
    r = client.patch(f"{API}/projects/{project['id']}", json={"estimate_poses": True})
    assert r.status_code == 200 and r.json()["estimate_poses"] is True
    assert client.get(f"{API}/projects/{project['id']}").json()["estimate_poses"] is True
    body = {"name": "x", "dataset": {"kind": "folder", "path": str(no_poses)}, "estimate_poses": "perhaps"}
    bad = client.post(f"{API}/projects", json=body)
    assert bad.status_code == 422
    assert bad.json()["detail"][0]["loc"] == ["body", "estimate_poses"]


def test_a_dataset_with_poses_keeps_its_own(client: TestClient, drive: Path, data_root: Path) -> None:
    seq = data_root / "own" / "sequences" / "00"
    shutil.copytree(drive, seq)
    project = _create(client, seq, estimate_poses=True)
    run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
    assert [s["name"] for s in run["progress"]["stages"]] == _stages(project)  # nothing to estimate
    done = wait_run(client, run["id"], timeout=180)
    assert done["status"] == "done", done["error"]
    assert KittiSequence(seq).pose_source == "file"
    assert not any("KISS-ICP" in w for w in done["progress"]["warnings"])
