"""Steering through the API of a real server on 127.0.0.1: the dataset's raw ground-truth ids, a new class's
colour, the preview of what the next run recomputes, run notes, and the comparison of two runs."""

from __future__ import annotations

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

from leap_core.colors import UNLABELED_RGB, srgb_to_lab
from leap_core.datasets.kitti import write_label
from leap_core.pipeline import STAGES


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[httpx.Client, Path]]:
    data = tmp_path_factory.mktemp("steer") / "data"
    seq = build_tiny_sequence(data / "tiny", n_frames=4, n_points=400)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    build_tiny_sequence(data / "nolabels", n_frames=2, n_points=50, with_labels=False)
    srv = Server(data).start()
    try:
        with srv.client() as client:
            yield client, data
    finally:
        srv.stop()


def _project(client: httpx.Client, path: Path, name: str = "p") -> dict[str, Any]:
    r = client.post("/projects", json={"name": name, "dataset": {"kind": "folder", "path": str(path)}})
    assert r.status_code == 201, r.text
    return r.json()


def _run(client: httpx.Client, project_id: int, **body: Any) -> dict[str, Any]:
    r = client.post(f"/projects/{project_id}/runs", json=body)
    assert r.status_code == 202, r.text
    run = wait_run(client, r.json()["id"], timeout=120, api="")
    assert run["status"] == "done", run
    return run


def test_gt_ids_list_the_datasets_raw_ids_with_names_and_classes(env) -> None:
    client, data = env
    seq = data / "tiny" / "sequences" / "00"
    p = _project(client, seq, "ids")
    body = client.get(f"/projects/{p['id']}/gt-ids").json()
    assert body["has_ground_truth"] and body["frames_read"] == body["frames_total"] == 4
    by_id = {r["id"]: r for r in body["data"]}
    assert sorted(by_id) == [0, 1, 10, 40, 48, 50, 60, 70, 99, 252]  # the tiny sequence's raw ids
    assert by_id[252]["name"] == "moving-car" and by_id[252]["classes"] == ["car"]
    assert by_id[99]["name"] == "other-object" and by_id[99]["classes"] == []
    assert all(r["points"] > 0 for r in body["data"]) and sum(r["points"] for r in body["data"]) == 4 * 400
    assert body["names"]["300"] == "traffic-cone" and body["names"]["81"] == "traffic-sign"

    # A label file that changes is read again (the scan is cached per folder state).
    labels = seq / "labels" / "000003.label"
    original = labels.read_bytes()
    try:
        write_label(labels, np.full(400, 300, np.uint32))
        again = {r["id"]: r for r in client.get(f"/projects/{p['id']}/gt-ids").json()["data"]}
        assert again[300] == {"id": 300, "name": "traffic-cone", "points": 400, "classes": []}
    finally:
        labels.write_bytes(original)
    assert 300 not in {r["id"] for r in client.get(f"/projects/{p['id']}/gt-ids").json()["data"]}

    q = _project(client, data / "nolabels" / "sequences" / "00", "no labels")
    empty = client.get(f"/projects/{q['id']}/gt-ids").json()
    assert empty["has_ground_truth"] is False and empty["data"] == [] and empty["names"]["10"] == "car"
    assert client.get("/projects/9999/gt-ids").status_code == 404


def test_a_new_class_without_colour_gets_the_most_distinct_one(env) -> None:
    client, data = env
    p = _project(client, data / "tiny" / "sequences" / "00", "colours")
    before = client.get(f"/projects/{p['id']}/classes").json()
    suggested = before["next_color"]
    r = client.post(
        f"/projects/{p['id']}/classes",
        json={"name": "traffic-cone", "prompts": ["traffic cone"], "export_id": 300, "gt_ids": [300]},
    )
    assert r.status_code == 201, r.text
    cone = r.json()["data"][-1]
    assert cone["hex"] == suggested and cone["gt_ids"] == [300]
    others = [c["color"] for c in before["data"]]
    lab = srgb_to_lab(np.asarray(cone["color"], float))
    assert np.linalg.norm(srgb_to_lab(np.asarray(others, float)) - lab, axis=-1).min() > 10
    assert np.linalg.norm(srgb_to_lab(np.asarray(UNLABELED_RGB, float)) - lab) > 30
    # The next suggestion moves on, and an explicit colour is kept.
    assert r.json()["next_color"] != suggested
    r2 = client.post(
        f"/projects/{p['id']}/classes",
        json={"name": "bench", "prompts": ["bench"], "export_id": 301, "color": "#123456"},
    )
    assert r2.json()["data"][-1]["hex"] == "#123456"
    bad = client.post(
        f"/projects/{p['id']}/classes",
        json={"name": "x", "prompts": ["x"], "export_id": 302, "color": "grey"},
    )
    assert bad.status_code == 422 and bad.json()["detail"][0]["loc"][-1] == "color"


@pytest.mark.slow
def test_preview_note_and_comparison(env) -> None:
    client, data = env
    p = _project(client, data / "tiny" / "sequences" / "00", "steer")
    pid = p["id"]

    fresh = client.get(f"/projects/{pid}/runs/preview").json()
    assert fresh["base_run"] is None and fresh["changes"] == []
    assert [s["name"] for s in fresh["stages"]] == list(STAGES)
    assert fresh["recompute"] == [s for s in STAGES if s not in ("motion", "3dcn")]
    assert {s["reason"] for s in fresh["stages"] if s["action"] == "recompute"} == {"no earlier run to reuse"}

    run1 = _run(client, pid, note="baseline")
    assert run1["note"] == "baseline"

    same = client.get(f"/projects/{pid}/runs/preview").json()
    assert same["base_run"] == {"id": run1["id"], "number": 1}
    assert same["recompute"] == [] and same["changes"] == []

    # A setting the simulated labeler ignores recomputes nothing and is listed as having no effect.
    client.patch(f"/projects/{pid}", json={"form": {"threshold": 0.4}})
    ignored = client.get(f"/projects/{pid}/runs/preview").json()
    assert ignored["recompute"] == []
    assert [(c["subject"], c["ignored"] is not None) for c in ignored["changes"]] == [
        ("grounded_sam.box_threshold", True)
    ]

    # k: smoothing and what follows.
    client.patch(f"/projects/{pid}", json={"form": {"k": 4}})
    k = client.get(f"/projects/{pid}/runs/preview").json()
    assert k["recompute"] == ["smooth", "label_points", "tracks", "evaluate", "export"]
    reasons = {s["name"]: s["reason"] for s in k["stages"]}
    assert reasons["smooth"] == "settings changed: smoothing"
    assert reasons["export"] == "after Point labels, Objects"

    # A class evaluated against id 99 (other-object): the 2D labels and everything after them.
    client.post(
        f"/projects/{pid}/classes",
        json={"name": "thing", "prompts": ["odd thing"], "export_id": 99, "gt_ids": [99]},
    )
    added = client.get(f"/projects/{pid}/runs/preview").json()
    assert added["recompute"] == [s for s in STAGES if s not in ("motion", "3dcn")]
    assert {s["name"]: s["reason"] for s in added["stages"]}["labels2d"] == "the classes or prompts changed"
    assert any(c["text"].startswith("class thing added") for c in added["changes"])

    run2 = _run(client, pid)
    assert run2["note"] is None
    assert client.get(f"/projects/{pid}/runs/preview").json()["recompute"] == []

    # Notes: set, cleared, too long.
    r = client.patch(f"/runs/{run2['id']}", json={"note": "k 4 and a thing class"})
    assert r.status_code == 200 and r.json()["note"] == "k 4 and a thing class"
    listed = {x["id"]: x for x in client.get(f"/projects/{pid}/runs").json()["data"]}
    assert listed[run2["id"]]["note"] == "k 4 and a thing class" and listed[run1["id"]]["note"] == "baseline"
    assert client.patch(f"/runs/{run1['id']}", json={"note": ""}).json()["note"] is None
    long = client.patch(f"/runs/{run1['id']}", json={"note": "x" * 501})
    assert long.status_code == 422 and long.json()["detail"][0]["loc"][-1] == "note"
    assert client.post(f"/projects/{pid}/runs", json={"note": "y" * 501}).status_code == 422
    assert client.patch("/runs/9999", json={"note": "a"}).status_code == 404

    # The comparison: what changed, and Δ per class and result row.
    cmp = client.get(f"/runs/{run2['id']}/compare/{run1['id']}").json()
    texts = [c["text"] for c in cmp["changes"]]
    assert "kNN smoothing k (smoothing.k): 9 → 4" in texts
    assert any(t.startswith("class thing added") for t in texts)
    assert {(r["protocol"], r["row"]) for r in cmp["rows"]} == {
        (p_, r_) for p_ in ("camera", "common", "all") for r_ in ("point", "voxel", "objects")
    }
    m1 = client.get(f"/runs/{run1['id']}/metrics").json()["metrics"]["protocols"]
    m2 = client.get(f"/runs/{run2['id']}/metrics").json()["metrics"]["protocols"]
    for row in cmp["rows"]:
        a, b = m2[row["protocol"]][row["row"]], m1[row["protocol"]][row["row"]]
        assert row["miou"] == a["miou"] and row["base_miou"] == b["miou"]
        assert row["delta"] == pytest.approx(a["miou"] - b["miou"])
        classes = {c["name"]: c for c in row["classes"]}
        assert classes["thing"]["base_iou"] is None and classes["thing"]["delta"] is None
        for name, c in classes.items():
            if name == "thing" or c["iou"] is None or c["base_iou"] is None:
                continue
            assert c["iou"] == a["iou"][name] and c["base_iou"] == b["iou"][name]
            assert c["delta"] == pytest.approx(a["iou"][name] - b["iou"][name])
    # k 9 → 4 and the new class moved some class's IoU: the deltas above were not all zero.
    assert any(c["delta"] for row in cmp["rows"] for c in row["classes"] if c["delta"] is not None)
    assert client.get(f"/runs/{run2['id']}/compare/9999").status_code == 404
    other = _project(client, data / "tiny" / "sequences" / "00", "other")
    run3 = _run(client, other["id"])
    foreign = client.get(f"/runs/{run3['id']}/compare/{run1['id']}")
    assert foreign.status_code == 422 and "another project" in foreign.text


def test_comparison_of_the_paper_protocol_lists_its_merged_classes(env) -> None:
    client, data = env
    pid = _project(client, data / "tiny" / "sequences" / "00", "paper")["id"]
    run1 = _run(client, pid)
    client.patch(f"/projects/{pid}", json={"form": {"k": 4}})
    run2 = _run(client, pid)
    cmp = client.get(f"/runs/{run2['id']}/compare/{run1['id']}").json()
    rows = [r for r in cmp["rows"] if r["protocol"] == "paper"]
    assert [r["row"] for r in rows] == ["objects", "point", "voxel"]
    m1 = client.get(f"/runs/{run1['id']}/metrics").json()["metrics"]
    m2 = client.get(f"/runs/{run2['id']}/metrics").json()["metrics"]
    for row in rows:
        # The view's classes in its order, not the schema's 19 (none of which but car ... terrain exist).
        assert [c["name"] for c in row["classes"]] == m2["views"]["paper"]["class_names"]
        for c in row["classes"]:
            assert c["iou"] == m2["protocols"]["paper"][row["row"]]["iou"][c["name"]]
            assert c["base_iou"] == m1["protocols"]["paper"][row["row"]]["iou"][c["name"]]


def test_metrics_carry_the_share_of_all_points_labeled(env) -> None:
    client, data = env
    p = _project(client, data / "tiny" / "sequences" / "00", "share")
    run = _run(client, p["id"])
    m = client.get(f"/runs/{run['id']}/metrics").json()["metrics"]
    n = m["n_points"]
    assert set(m["labeled_share_all_points"]) == {"point", "voxel", "objects"}
    for row, share in m["labeled_share_all_points"].items():
        assert share == pytest.approx(m["labeled_points"][row] / n)
    assert m["labeled_share_all_points"]["point"] < m["labeled_share_all_points"]["voxel"] <= 1.0
