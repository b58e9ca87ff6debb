"""Classes and prompts API: every edit is checked against the whole schema and stored in SQLite."""

from __future__ import annotations

from pathlib import Path

import appfixtures
import pytest
from apphelpers import API, create_project
from fastapi.testclient import TestClient

# The app tests' fixtures (this folder has no conftest.py; see appfixtures), found by name here.
client, data_root, settings, tiny_dataset = (
    appfixtures.client,
    appfixtures.data_root,
    appfixtures.settings,
    appfixtures.tiny_dataset,
)


@pytest.fixture
def project(client: TestClient, tiny_dataset: Path) -> dict:
    return create_project(client, tiny_dataset)


def names(body: dict) -> list[str]:
    return [c["name"] for c in body["data"]]


def test_class_crud_round_trip(client: TestClient, project: dict) -> None:
    base = f"{API}/projects/{project['id']}/classes"
    body = client.get(base).json()
    assert body["count"] == 19 and body["data"][0]["name"] == "car" and body["data"][0]["hex"] == "#6496f5"
    car, road = body["data"][0], body["data"][8]
    assert (car["thing"], car["moving_id"], road["thing"], road["moving_id"]) == (True, 252, False, None)

    r = client.post(
        base,
        json={
            "name": "bus stop",
            "color": "#12ab34",
            "prompts": ["bus stop", "bus shelter"],
            "export_id": 99,
            "position": 1,
        },
    )
    assert r.status_code == 201, r.text
    assert names(r.json())[:3] == ["car", "bus stop", "bicycle"]
    assert r.json()["data"][1]["color"] == [0x12, 0xAB, 0x34]

    r = client.patch(f"{base}/bus stop", json={"thing": True, "moving_id": 300})
    assert r.status_code == 200 and r.json()["data"][1]["moving_id"] == 300, r.text
    r = client.patch(f"{base}/bus stop", json={"moving_id": None})  # null removes it
    assert r.json()["data"][1]["moving_id"] is None and r.json()["data"][1]["thing"] is True
    r = client.patch(f"{base}/bus stop", json={"moving_id": 40})  # road's export id
    assert r.status_code == 422 and "moving_id" in r.text
    r = client.patch(f"{base}/bus stop", json={"name": "shelter", "color": [1, 2, 3], "position": 0})
    assert r.status_code == 200, r.text
    assert names(r.json())[:2] == ["shelter", "car"] and r.json()["data"][0]["hex"] == "#010203"

    r = client.put(f"{base}/shelter/prompts", json={"prompts": ["shelter", "canopy"]})
    assert r.json()["data"][0]["prompts"] == ["shelter", "canopy"]
    r = client.post(f"{base}/shelter/prompts", json={"prompt": "  awning "})
    assert r.status_code == 201 and r.json()["data"][0]["prompts"] == ["shelter", "canopy", "awning"]
    r = client.delete(f"{base}/shelter/prompts/1")
    assert r.json()["data"][0]["prompts"] == ["shelter", "awning"]

    r = client.delete(f"{base}/shelter")
    assert r.status_code == 200 and r.json()["count"] == 19 and "shelter" not in names(r.json())

    # The stored schema is what the next run snapshots.
    classes = [c for c in client.get(base).json()["data"]][:2]
    r = client.put(
        base,
        json={"classes": [{k: c[k] for k in ("name", "color", "prompts", "export_id")} for c in classes]},
    )
    assert r.status_code == 200 and names(r.json()) == ["car", "bicycle"]
    assert client.get(f"{API}/projects/{project['id']}").json()["num_classes"] == 2


def test_user_text_is_kept_literally(client: TestClient, project: dict) -> None:
    base = f"{API}/projects/{project['id']}/classes"
    evil = "<img src=x onerror=alert(1)>"
    r = client.post(
        base, json={"name": evil, "color": "#000000", "prompts": [evil + " thing"], "export_id": 200}
    )
    assert r.status_code == 201, r.text
    assert r.json()["data"][-1]["name"] == evil and r.json()["data"][-1]["prompts"] == [evil + " thing"]


def test_unknown_class_or_prompt_is_404(client: TestClient, project: dict) -> None:
    base = f"{API}/projects/{project['id']}/classes"
    for method, path, body in [
        ("patch", "/nope", {"color": "#000000"}),
        ("delete", "/nope", None),
        ("put", "/nope/prompts", {"prompts": ["x"]}),
        ("post", "/nope/prompts", {"prompt": "x"}),
        ("delete", "/car/prompts/17", None),
    ]:
        r = getattr(client, method)(base + path, **({"json": body} if body is not None else {}))
        assert r.status_code == 404, (method, path, r.text)
    assert client.get(f"{API}/projects/404/classes").status_code == 404


@pytest.mark.parametrize(
    ("method", "path", "body", "loc"),
    [
        ("post", "", {"name": "x", "color": "#12345", "prompts": ["x"], "export_id": 5}, ["body", "color"]),
        ("post", "", {"name": "x", "color": "#123456", "prompts": [], "export_id": 5}, ["body", "prompts"]),
        (
            "post",
            "",
            {"name": "x", "color": "#123456", "prompts": ["x"], "export_id": 0},
            ["body", "export_id"],
        ),
        ("post", "", {"name": "a/b", "color": "#123456", "prompts": ["x"], "export_id": 5}, ["body", "name"]),
        (
            "post",
            "",
            {"name": "car", "color": "#123456", "prompts": ["x"], "export_id": 5},
            ["body", "classes", 19, "name"],
        ),
        (
            "post",
            "",
            {"name": "x", "color": "#123456", "prompts": ["road"], "export_id": 5},
            ["body", "classes", 19, "prompts"],
        ),
        (
            "post",
            "",
            {"name": "x", "color": "#123456", "prompts": ["x"], "export_id": 10},
            ["body", "classes", 19, "export_id"],
        ),
        ("patch", "/car", {"prompts": ["car. truck"]}, ["body", "classes", 0, "prompts"]),
        ("patch", "/car", {"moving_id": 10}, ["body", "classes", 0, "moving_id"]),
        ("patch", "/road", {"moving_id": 300}, ["body", "classes", 8, "moving_id"]),
        ("patch", "/car", {"color": None}, ["body", "color"]),
        ("post", "/car/prompts", {"prompt": ""}, ["body", "prompt"]),
    ],
)
def test_invalid_class_edits_are_422_with_the_field(
    client: TestClient, project: dict, method: str, path: str, body: dict, loc: list
) -> None:
    base = f"{API}/projects/{project['id']}/classes"
    r = getattr(client, method)(base + path, json=body)
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == loc
    assert client.get(base).json()["count"] == 19  # unchanged


def test_last_class_and_last_prompt_cannot_be_removed(client: TestClient, project: dict) -> None:
    base = f"{API}/projects/{project['id']}/classes"
    client.put(
        base, json={"classes": [{"name": "thing", "color": "#ffffff", "prompts": ["thing"], "export_id": 1}]}
    )
    assert client.delete(f"{base}/thing").status_code == 409
    assert client.delete(f"{base}/thing/prompts/0").status_code == 409
