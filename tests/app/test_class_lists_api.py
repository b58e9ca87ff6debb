"""Class-list files through the real API: an uploaded file is validated with problems named by their field
in the file (422), its size is bounded, and a project's exported class list uploads back into the same
classes."""

from __future__ import annotations

from pathlib import Path

import appfixtures
from apphelpers import API
from fastapi.testclient import TestClient

from leap_core.schema import MAX_CLASS_LIST_BYTES

client, data_root, settings, tiny_dataset = (
    appfixtures.client,
    appfixtures.data_root,
    appfixtures.settings,
    appfixtures.tiny_dataset,
)

YAML = {"content-type": "application/yaml"}

GOOD = """\
name: orchard
classes:
  - {name: tree, color: [20, 160, 40], prompts: [tree, fruit tree], export_id: 1}
  - {name: ground, color: "#8b5a2b", prompts: [ground, soil], export_id: 2, category: flat}
  - {name: person, color: [250, 30, 30], prompts: [person], export_id: 3, gt_ids: [30, 31]}
  - {name: tractor, color: [230, 230, 0], prompts: [tractor], export_id: 4}
"""


def _upload(client: TestClient, text: str | bytes) -> tuple[int, dict]:
    r = client.post(f"{API}/class-lists", content=text, headers=YAML)
    return r.status_code, r.json()


def test_an_uploaded_class_list_is_validated_naming_the_field(client: TestClient) -> None:
    status, body = _upload(client, GOOD)
    assert status == 200, body
    assert body["name"] == "orchard" and body["count"] == 4
    assert body["classes"][1]["color"] == [139, 90, 43] and body["classes"][1]["category"] == "flat"

    cases = {
        GOOD.replace("prompts: [tractor]", "prompts: []"): (
            "classes[3].prompts",
            "classes[3].prompts: must list at least one prompt",
        ),
        GOOD.replace("prompts: [tractor]", "prompts: [tree]"): (
            "classes[3].prompts",
            "classes[3].prompts: prompt 'tree' is also a prompt of classes[0] 'tree'",
        ),
        GOOD.replace("color: [250, 30, 30]", "colour: [250, 30, 30]"): (
            "classes[2].colour",
            "classes[2].colour: unknown key (did you mean 'color'?)",
        ),
        GOOD.replace("export_id: 4", "export_id: 0"): ("classes[3].export_id", None),
        GOOD.replace("fruit tree", "fruit. tree"): ("classes[0].prompts[1]", None),
        "classes: [\n": (None, None),
        GOOD + "pipeline: {labeler: simulated}\n": ("pipeline", None),
    }
    for text, (where, message) in cases.items():
        status, body = _upload(client, text)
        assert status == 422, (text, body)
        detail = body["detail"][0]
        if where is None:
            assert detail["loc"] == ["body"] and detail["msg"].startswith("invalid YAML at line 2")
            continue
        assert detail["loc"] == ["body", where]
        assert detail["msg"].startswith(f"{where}: "), detail
        # Worded for people: no pydantic error text.
        assert "validation error" not in detail["msg"] and "type=" not in detail["msg"]
        if message is not None:
            assert detail["msg"] == message

    status, body = _upload(client, "é".encode("latin-1"))
    assert status == 422 and "UTF-8" in body["detail"][0]["msg"]
    status, body = _upload(client, GOOD + "#" * MAX_CLASS_LIST_BYTES)
    assert status == 422 and "larger than" in body["detail"][0]["msg"]


def test_an_exported_class_list_creates_a_project_with_the_same_classes(
    client: TestClient, tiny_dataset: Path
) -> None:
    dataset = {"kind": "folder", "path": str(tiny_dataset)}
    r = client.post(f"{API}/projects", json={"name": "a", "dataset": dataset, "schema_name": "agri_uav"})
    assert r.status_code == 201, r.text
    first = r.json()["id"]
    # An edited class (a prompt of its own, a ground-truth id) must travel too, not only the preset's.
    r = client.post(
        f"{API}/projects/{first}/classes",
        json={"name": "scare-crow", "prompts": ["scarecrow"], "export_id": 900, "gt_ids": [77]},
    )
    assert r.status_code == 201, r.text

    r = client.get(f"{API}/projects/{first}/classes.yaml")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/yaml")
    assert "attachment" in r.headers["content-disposition"]
    status, class_list = _upload(client, r.content)
    assert status == 200, class_list

    r = client.post(
        f"{API}/projects",
        json={
            "name": "b",
            "dataset": dataset,
            "class_list": {k: class_list[k] for k in ("name", "description", "classes")},
        },
    )
    assert r.status_code == 201, r.text
    second = r.json()
    assert second["schema_name"] == "agri_uav"
    # The preset's pipeline section stays behind: a class list holds classes only.
    assert second["pipeline"]["grounded_sam"]["box_threshold"] != 0.2

    def classes(project_id: int) -> list[dict]:
        return client.get(f"{API}/projects/{project_id}/classes").json()["data"]

    assert classes(second["id"]) == classes(first) and len(classes(first)) == 8


def test_a_class_list_in_the_create_payload_is_checked_as_a_whole(client: TestClient) -> None:
    one = {"name": "a", "color": [1, 2, 3], "prompts": ["thing"], "export_id": 5}
    body = {"name": "p", "dataset": {"kind": "demo"}, "class_list": {"classes": [one, {**one, "name": "b"}]}}
    r = client.post(f"{API}/projects", json=body)
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "class_list", "classes", 1, "export_id"]
    r = client.post(f"{API}/projects", json={**body, "schema_name": "demo"})
    assert r.status_code == 422 and "not both" in r.text
