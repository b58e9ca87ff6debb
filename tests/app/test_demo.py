"""First start seeds the demo project and its run; ``leap demo`` labels the demo and would then serve it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import appfixtures
import pytest
from apphelpers import API, wait_run
from fastapi.testclient import TestClient
from serverproc import SMALL_DEMO

from app.core.config import Settings
from app.main import create_app

# The app tests' fixtures (this folder has no conftest.py; see appfixtures), found by name here.
client, data_root, settings, tiny_dataset = (
    appfixtures.client,
    appfixtures.data_root,
    appfixtures.settings,
    appfixtures.tiny_dataset,
)

TINY_DEMO = {**SMALL_DEMO, "frames": 3}


@pytest.mark.slow
def test_first_start_seeds_a_demo_project_with_a_finished_run(data_root: Path) -> None:
    settings = Settings(
        data_roots=[data_root],
        work_dir=data_root / "studio",
        seed_demo=True,
        seed_agri_demo=False,
        demo_synth=TINY_DEMO,
    )
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        projects = client.get(f"{API}/projects").json()
        assert projects["count"] == 1
        demo = projects["data"][0]
        assert (
            demo["is_demo"] and demo["dataset"]["kind"] == "demo" and demo["schema_name"] == "semantickitti"
        )
        assert demo["form"]["labeler"] == "simulated"
        run = client.get(f"{API}/projects/{demo['id']}/runs").json()["data"][0]
        run = wait_run(client, run["id"], timeout=180)
        assert run["status"] == "done", run["error"]
        stages = [s["name"] for s in run["progress"]["stages"]]
        assert stages[0] == "00/generate demo" and stages[1] == "00/labels2d"
        assert run["has_metrics"] and run["summary"]["camera"]["voxel"] > 0.3
        assert (settings.demo_dataset / "velodyne" / "000002.bin").is_file()
        assert client.get(f"{API}/projects/{demo['id']}").json()["last_run"]["miou"] > 0.3
    # A restart (or a deleted demo project) does not seed again.
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        assert client.get(f"{API}/projects").json()["count"] == 1
        client.delete(f"{API}/projects/{demo['id']}")
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        assert client.get(f"{API}/projects").json()["count"] == 0


@pytest.mark.slow
def test_first_start_also_seeds_the_farm_drone_demo(data_root: Path) -> None:
    """The second demo project: the agri_uav preset with the simulated labeler, on a farm sequence its
    first run generates (under work_dir/demo-agri), queued after the street's; it labels and evaluates."""
    from app.demo import AGRI_DEMO_PROJECT_NAME, demo_exists
    from leap_core.synth.agri import AGRI_SYNTH_STAMP
    from leap_core.synth.generator import synth_stamp

    settings = Settings(
        data_roots=[data_root],
        work_dir=data_root / "studio",
        seed_demo=True,
        demo_synth={**TINY_DEMO, "frames": 2},
    )
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        projects = client.get(f"{API}/projects").json()
        assert projects["count"] == 2
        farm = next(p for p in projects["data"] if p["name"] == AGRI_DEMO_PROJECT_NAME)
        assert farm["is_demo"] and farm["dataset"]["kind"] == "demo" and farm["schema_name"] == "agri_uav"
        assert farm["form"]["labeler"] == "simulated"
        run = client.get(f"{API}/projects/{farm['id']}/runs").json()["data"][0]
        run = wait_run(client, run["id"], timeout=300)
        assert run["status"] == "done", run["error"]
        assert [s["name"] for s in run["progress"]["stages"]][:2] == ["00/generate demo", "00/labels2d"]
        assert run["has_metrics"] and run["summary"]["camera"]["voxel"] > 0.3
        assert synth_stamp(settings.demo_agri_dataset) == AGRI_SYNTH_STAMP
        assert demo_exists(settings.demo_agri_dataset) and not demo_exists(settings.demo_dataset.parent / "x")
        assert (settings.demo_agri_dataset / "velodyne" / "000001.bin").is_file()


def test_bad_demo_settings_are_refused(data_root: Path) -> None:
    with pytest.raises(ValueError, match=r"demo_synth\.lidar\.beemz: unknown setting"):
        Settings(data_roots=[data_root], demo_synth={"lidar": {"beemz": 3}})


@pytest.mark.slow
def test_leap_demo_command_labels_the_demo(tmp_path: Path) -> None:
    env = {**os.environ, "LEAP_DEMO_SYNTH": json.dumps(TINY_DEMO)}

    def demo() -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "app.cli", "demo", "--no-serve"],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )

    out = demo()
    assert out.returncode == 0, out.stderr[-2000:]
    assert "camera view" in out.stdout and "voxel" in out.stdout
    from app import crud
    from app.core.db import open_db

    with open_db(tmp_path / "data" / "studio" / "studio.db") as db:
        project = crud.find_demo_project(db)
        assert project is not None
        runs = crud.list_runs(db, project.id)
        assert [r.status for r in runs] == ["done"] and runs[0].metrics is not None
    # Run again: nothing to do, the finished run is reused and its table printed.
    again = demo()
    assert again.returncode == 0 and "labeling the demo" not in again.stdout and "voxel" in again.stdout


@pytest.mark.slow
def test_a_demo_from_an_older_generator_is_generated_again(tmp_path: Path) -> None:
    """A demo folder without the current ``synth_version.txt`` (written before the demo world had names) is
    stale: ``ensure_demo_sequence`` replaces it, so the simulated labeler finds ``gt2d/name``."""
    from app.demo import demo_exists, ensure_demo_sequence
    from leap_core.synth import SYNTH_VERSION

    dataset = tmp_path / "demo" / "sequences" / "00"
    ensure_demo_sequence(dataset, TINY_DEMO)
    assert demo_exists(dataset) and (dataset / "gt2d" / "name" / "000002.png").is_file()
    (dataset / "synth_version.txt").write_text(f"{SYNTH_VERSION - 1}\n")
    (dataset / "gt2d" / "name" / "000002.png").unlink()
    assert not demo_exists(dataset)
    ensure_demo_sequence(dataset, TINY_DEMO)
    assert demo_exists(dataset) and (dataset / "gt2d" / "name" / "000002.png").is_file()
