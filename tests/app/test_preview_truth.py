"""The *Next run* preview says what the run then does: for every kind of edit the preview's recomputed
stages are exactly the stages whose ``stages.json`` record the run rewrote, on a project whose poses are
estimated (real app, SQLite and worker processes); and what changed lists corrections and pose
estimation, in the preview and in the comparison of the two runs."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import appfixtures
import numpy as np
import pytest
from apphelpers import API, wait_run
from fastapi.testclient import TestClient

from app.core.config import Settings
from leap_core.fusion import voxel_keys, world_points
from leap_core.run_layout import RunLayout
from leap_core.synth import CameraConfig, LidarConfig, SceneConfig, SynthConfig, generate_sequence

client, data_root, settings = appfixtures.client, appfixtures.data_root, appfixtures.settings

DRIVE = SynthConfig(
    frames=4,
    seed=3,
    lidar=LidarConfig(beams=32, azimuth_step_deg=0.6),
    camera=CameraConfig().scaled(0.2),
    scene=SceneConfig(margin=90.0),
)


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_sequence(tmp_path_factory.mktemp("drive"), DRIVE, workers=1).path


@pytest.fixture
def no_poses(drive: Path, data_root: Path) -> Path:
    seq = data_root / "drive" / "sequences" / "00"
    shutil.copytree(drive, seq)
    (seq / "poses.txt").unlink()
    return seq


def _stages_json(settings: Settings, project_id: int, run_id: int) -> dict[str, Any]:
    lay = RunLayout(settings.runs_dir / f"p{project_id}" / f"r{run_id}").sequence("00")
    data: dict[str, Any] = json.loads((lay.folder / "stages.json").read_text())
    return data


def _rewritten(before: dict[str, Any], after: dict[str, Any]) -> set[str]:
    """Stages the later run computed: a record the earlier run did not leave (a reused stage keeps the
    record, its ``finished`` time included, of the run that computed it)."""
    return {
        name
        for name, rec in after.items()
        if rec.get("status") == "done" and rec.get("finished") != (before.get(name) or {}).get("finished")
    }


def _map_keys(dataset: Path, voxel_size: float, n: int) -> list[int]:
    """``n`` voxel keys of frame 0's first points, in the world the run's estimated poses place them."""
    from leap_core.datasets.kitti import read_scan

    points = read_scan(dataset / "velodyne" / "000000.bin")[:2000, :3]
    keys = np.unique(voxel_keys(world_points(points, np.eye(4)), voxel_size))
    return [int(k) for k in keys[:n]]


@pytest.mark.slow
def test_the_preview_matches_the_run_for_every_kind_of_edit(
    client: TestClient, no_poses: Path, settings: Settings
) -> None:
    body = {
        "name": "truth",
        "dataset": {"kind": "folder", "path": str(no_poses)},
        "pipeline": {"labeler": "simulated"},
        "estimate_poses": True,
    }
    r = client.post(f"{API}/projects", json=body)
    assert r.status_code == 201, r.text
    pid = r.json()["id"]

    def run() -> dict[str, Any]:
        started = client.post(f"{API}/projects/{pid}/runs", json={})
        assert started.status_code == 202, started.text
        done = wait_run(client, started.json()["id"], timeout=180)
        assert done["status"] == "done", done["error"]
        return done

    last = run()
    voxel = float(last["params"]["pipeline"]["fusion"]["voxel_size"])
    made: list[int] = []

    def add_correction() -> None:
        keys = _map_keys(no_poses, voxel, 40)
        r = client.post(
            f"{API}/projects/{pid}/corrections",
            json={"class_name": "building", "voxel_size": voxel, "keys": keys},
        )
        assert r.status_code == 201, r.text
        made.append(r.json()["id"])

    def switch_off() -> None:
        r = client.patch(f"{API}/projects/{pid}/corrections/{made[-1]}", json={"active": False})
        assert r.status_code == 200, r.text

    def patch(path: str, payload: dict[str, Any]) -> Callable[[], None]:
        def edit() -> None:
            r = client.patch(f"{API}/projects/{pid}{path}", json=payload)
            assert r.status_code == 200, r.text

        return edit

    edits: list[tuple[str, Callable[[], None], str | None]] = [
        # Nothing but the estimated poses, which the next run reuses from the cache.
        ("poses estimated", lambda: None, None),
        ("class edit", patch("/classes/car", {"gt_ids": [10]}), "class"),
        ("prompt edit", patch("/classes/car", {"prompts": ["car", "parked car"]}), "class"),
        ("setting change", patch("", {"form": {"k": 4}}), "parameter"),
        # Read by the object stages only: the export (and what the evaluation scores of it), the tracks.
        ("moving id", patch("/classes/car", {"moving_id": None}), "class"),
        ("thing flag", patch("/classes/car", {"thing": False}), "class"),
        ("correction added", add_correction, "correction"),
        ("correction removed", switch_off, "correction"),
    ]
    for what, edit, kind in edits:
        edit()
        preview = client.get(f"{API}/projects/{pid}/runs/preview").json()
        assert preview["base_run"]["id"] == last["id"], what
        kinds = {c["kind"] for c in preview["changes"]}
        assert kinds == (set() if kind is None else {kind}), (what, preview["changes"])
        done = run()
        truth = _rewritten(_stages_json(settings, pid, last["id"]), _stages_json(settings, pid, done["id"]))
        assert set(preview["recompute"]) == truth, (what, preview["stages"])
        if what in ("moving id", "thing flag"):
            stages = {p["name"]: p for p in preview["stages"]}
            first = "tracks" if what == "thing flag" else "export"
            assert {first, "evaluate", "export"} <= set(preview["recompute"]), (what, preview["stages"])
            assert stages[first]["reason"] == "a class's thing flag or moving id changed", stages[first]
            assert [c["field"] for c in preview["changes"]] == [what.replace(" flag", "").replace(" ", "_")]
        if kind == "correction":
            assert preview["recompute"], what  # a correction is fused: never "no changes" beside a recompute
            cmp = client.get(f"{API}/runs/{done['id']}/compare/{last['id']}").json()
            assert [c["text"] for c in cmp["changes"]] == [c["text"] for c in preview["changes"]], what
        if what == "correction removed":
            assert [c["text"] for c in preview["changes"]] == [
                f"correction {made[-1]} (building, map, 40 voxels) switched off"
            ]
        last = done
