"""``GET /pipeline``: the stages, parameter form, labelers and run states the web UI is built from."""

from __future__ import annotations

from pathlib import Path

import appfixtures
from apphelpers import API, create_project
from fastapi.testclient import TestClient

from app.forms import FORM_FIELDS, stage_switches
from leap_core.labelers import LABELERS
from leap_core.pipeline import STAGE_TABLE
from leap_core.pipeline.steering import setting_scope

client, data_root, settings, tiny_dataset = (
    appfixtures.client,
    appfixtures.data_root,
    appfixtures.settings,
    appfixtures.tiny_dataset,
)


def test_stages_come_from_the_stage_table_after_the_demo_generation(client: TestClient) -> None:
    r = client.get(f"{API}/pipeline")
    assert r.status_code == 200, r.text
    stages = r.json()["stages"]
    assert stages[0] == {
        "name": "generate demo",
        "label": "Generate demo",
        "description": "generate the built-in demo sequence (before the first run of a demo project)",
        "per_frame": True,
        "switch": None,
    }
    # Then the app's pose estimation (projects with "Estimate poses" on a dataset without poses.txt).
    assert stages[1]["name"] == "estimate poses" and "KISS-ICP" in stages[1]["description"]
    switches = stage_switches()
    assert stages[2:] == [
        {
            "name": s.name,
            "label": s.label,
            "description": s.description,
            "per_frame": s.per_frame,
            "switch": switches.get(s.name),
        }
        for s in STAGE_TABLE
    ]
    # The 3D-CN is switched by the form's checkbox, whose field sets its stage's switch path.
    assert next(s for s in stages if s["name"] == "3dcn")["switch"] == "consistency"
    assert FORM_FIELDS["consistency"].path == next(s for s in STAGE_TABLE if s.name == "3dcn").switch
    assert len({s["label"] for s in stages}) == len(stages)  # every stage tells itself apart


def test_run_statuses_split_every_status_once(client: TestClient) -> None:
    statuses = client.get(f"{API}/pipeline").json()["run_statuses"]
    assert statuses == {
        "active": ["queued", "running"],
        "terminal": ["done", "failed", "cancelled", "interrupted"],
        "resumable": ["failed", "cancelled", "interrupted"],
    }


def test_the_form_fields_are_the_projects_form_values_and_its_limits_are_enforced(
    client: TestClient, tiny_dataset: Path
) -> None:
    body = client.get(f"{API}/pipeline").json()
    fields = body["form"]
    assert [f["name"] for f in fields] == list(FORM_FIELDS)
    for f in fields:
        spec = FORM_FIELDS[f["name"]]
        assert (f["path"], f["label"], f["kind"], f["help"]) == (spec.path, spec.label, spec.kind, spec.help)
        assert (f["minimum"], f["maximum"], f["step"]) == (spec.minimum, spec.maximum, spec.step)
        assert [(c["value"], c["label"]) for c in f["choices"]] == list(spec.choices)
        scope = setting_scope(spec.path)
        assert (f["labeler"], f["stage"]) == (scope.labeler, scope.stage)
    scoped = {f["name"]: (f["labeler"], f["stage"]) for f in fields if f["labeler"] or f["stage"]}
    assert scoped == {
        "threshold": ("grounded-sam", None),
        "sam3_threshold": ("sam3", None),
        "share": (None, "3dcn"),
        "temperature": (None, "3dcn"),
        "iterations": (None, "3dcn"),
    }
    labeler = next(f for f in fields if f["name"] == "labeler")
    assert [c["value"] for c in labeler["choices"]] == [lab["name"] for lab in body["labelers"]]
    assert [lab["name"] for lab in body["labelers"]] == list(LABELERS)

    # A project's form holds exactly these fields, and the server refuses what the form's limits exclude.
    project = create_project(client, tiny_dataset)
    assert set(project["form"]) == {f["name"] for f in fields}
    for f in fields:
        for bad in (
            None if f["minimum"] is None else f["minimum"] - 1,
            None if f["maximum"] is None else f["maximum"] + 1,
        ):
            if bad is None:
                continue
            r = client.patch(f"{API}/projects/{project['id']}", json={"form": {f["name"]: bad}})
            assert r.status_code == 422, (f["name"], bad, r.text)
            assert r.json()["detail"][0]["loc"] == ["body", "form", f["name"]]
    assert client.get(f"{API}/projects/{project['id']}").json()["form"] == project["form"]


def test_the_openapi_document_describes_the_answer(client: TestClient) -> None:
    spec = client.get(f"{API}/openapi.json").json()
    ok = spec["paths"]["/api/v1/pipeline"]["get"]["responses"]["200"]["content"]["application/json"]
    assert ok["schema"]["$ref"].endswith("/PipelinePublic")
    assert {"StageInfoPublic", "FormFieldPublic", "LabelerPublic"} <= set(spec["components"]["schemas"])
