"""Projects created from a built-in preset through the real API keep the preset's ``pipeline:`` section;
pipeline errors come back with the field's path as their 422 ``loc``; the server's models folder reaches
the labeler as a run-time value."""

from __future__ import annotations

from pathlib import Path

import appfixtures
import pytest
from apphelpers import API, wait_run
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


def _create(client: TestClient, dataset: Path, **fields: object) -> dict:
    r = client.post(
        f"{API}/projects", json={"name": "p", "dataset": {"kind": "folder", "path": str(dataset)}, **fields}
    )
    assert r.status_code == 201, r.text
    return r.json()


def test_a_project_from_a_preset_keeps_its_pipeline_section(client: TestClient, tiny_dataset: Path) -> None:
    project = _create(client, tiny_dataset, schema_name="agri_uav")
    assert project["schema_name"] == "agri_uav" and project["num_classes"] == 7
    assert project["form"]["labeler"] == "grounded-sam" and project["form"]["threshold"] == 0.2
    stored = client.get(f"{API}/projects/{project['id']}").json()["pipeline"]
    assert stored["labeler"] == "grounded-sam" and stored["grounded_sam"]["box_threshold"] == 0.2


def test_payload_overrides_apply_on_top_of_the_preset(client: TestClient, tiny_dataset: Path) -> None:
    project = _create(
        client, tiny_dataset, schema_name="agri_uav", pipeline={"grounded_sam": {"mode": "per-class"}}
    )
    gs = project["pipeline"]["grounded_sam"]
    assert gs["mode"] == "per-class" and gs["box_threshold"] == 0.2  # the preset's, not the default 0.25
    assert project["pipeline"]["labeler"] == "grounded-sam"
    simulated = _create(client, tiny_dataset, schema_name="agri_uav", pipeline={"labeler": "simulated"})
    assert simulated["form"]["labeler"] == "simulated" and simulated["form"]["threshold"] == 0.2


def test_pipeline_errors_locate_the_field(client: TestClient, tiny_dataset: Path) -> None:
    def error(pipeline: dict) -> dict:
        r = client.post(
            f"{API}/projects",
            json={"name": "x", "dataset": {"kind": "demo"}, "schema_name": "agri_uav", "pipeline": pipeline},
        )
        assert r.status_code == 422, r.text
        return r.json()["detail"][0]

    nested = error({"consistency": {"backbone": {"channels": 2}}})
    assert nested["loc"] == ["body", "pipeline", "consistency", "backbone", "channels"]
    assert nested["msg"] == "pipeline.consistency.backbone.channels: must be in [4, 1024], got 2"
    retired = error({"grounded_sam": {"models_dir": "/models"}})
    assert retired["loc"] == ["body", "pipeline", "grounded_sam", "models_dir"]
    assert "LEAP_MODELS_DIR" in retired["msg"]
    assert error({"labeler": "magic"})["loc"] == ["body", "pipeline", "labeler"]
    assert client.get(f"{API}/projects").json()["count"] == 0

    project = _create(client, tiny_dataset, schema_name="agri_uav")
    r = client.patch(f"{API}/projects/{project['id']}", json={"pipeline": {"fusion": {"voxel_size": 0}}})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "pipeline", "fusion", "voxel_size"]
    r = client.patch(f"{API}/projects/{project['id']}", json={"form": {"threshold": 1.5}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "form", "threshold"]
    assert r.json()["detail"][0]["msg"].startswith("pipeline.grounded_sam.box_threshold: must be in (0, 1)")


@pytest.mark.slow
def test_the_servers_models_folder_reaches_a_grounded_sam_run(data_root: Path, tiny_dataset: Path) -> None:
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
        project = _create(
            client, tiny_dataset, schema_name="agri_uav", pipeline={"grounded_sam": {"box_threshold": 0.01}}
        )
        run = client.post(f"{API}/projects/{project['id']}/runs", json={}).json()
        run = wait_run(client, run["id"], timeout=240)
        assert run["status"] == "done", run["error"]
        logs = client.get(f"{API}/runs/{run['id']}/logs").json()["text"]
        assert "stage 00/labels2d done" in logs
    # Per-pass results went to the project's shared 2D cache, under the server's cache folder.
    assert list((settings.cache_dir / f"p{project['id']}" / "passes").rglob("*"))
