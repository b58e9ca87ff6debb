"""kill -9 of the server in the middle of a run, restart, resume: labels identical to an uninterrupted run."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest
from apphelpers import wait_run
from serverproc import Server, make_small_street, process_gone

PER_FRAME_STAGES = ("00/labels2d", "00/project", "00/label_points", "00/export")
"""The run's per-frame stages of its one sequence (``00``), as its progress names them."""
FRAMES = 16


@pytest.mark.slow
def test_kill_9_mid_run_then_resume_is_byte_identical(tmp_path: Path) -> None:
    data = tmp_path / "data"
    dataset = make_small_street(data / "street", FRAMES)
    server = Server(data).start()
    try:
        with server.client() as c:
            a = c.post(
                "/projects", json={"name": "killed", "dataset": {"kind": "folder", "path": str(dataset)}}
            ).json()
            run = c.post(f"/projects/{a['id']}/runs", json={}).json()
            # Wait until a per-frame stage is part-way through, then kill the server without warning.
            killed_in = None
            deadline = time.monotonic() + 120
            while killed_in is None and time.monotonic() < deadline:
                progress = c.get(f"/runs/{run['id']}/progress").json()
                assert progress["status"] in ("queued", "running"), progress
                for stage in progress["stages"]:
                    if (
                        stage["name"] in PER_FRAME_STAGES
                        and stage["status"] == "running"
                        and 2 <= stage["done"] < stage["total"] - 2
                    ):
                        killed_in = (stage["name"], stage["done"])
                        break
                else:
                    time.sleep(0.01)
            assert killed_in is not None, "never saw a per-frame stage part-way through"
        run_dir = data / "studio" / "runs" / f"p{a['id']}" / f"r{run['id']}"
        started = re.search(r"\(pid (\d+)\)", (run_dir / "run.log").read_text())
        assert started is not None, "run.log names no worker pid"
        worker_pid = int(started.group(1))
        server.kill9()
        # The worker dies with the server: nothing keeps writing into the run folder.
        assert process_gone(worker_pid), "the worker process outlived the killed server"
        sequence_dir = run_dir / "sequences" / "00"
        stage = killed_in[0].split("/")[1]
        stages_at_kill = json.loads((sequence_dir / "stages.json").read_text())
        assert stages_at_kill[stage]["status"] == "running"

        server = Server(data, port=server.port).start()
        with server.client() as c:
            run = c.get(f"/runs/{run['id']}").json()
            assert run["status"] == "interrupted" and run["resumable"]
            assert "server stopped" in run["error"]
            # The stage states stored before the kill survive it: earlier stages done, this one cut short.
            stored = [(s["name"], s["status"]) for s in run["progress"]["stages"]]
            cut = [n for n, _ in stored].index(killed_in[0])
            assert all(st in ("done", "skipped") for _, st in stored[:cut]) and stored[cut][1] == "cancelled"
            assert c.post(f"/runs/{run['id']}/resume").status_code == 202
            run = wait_run(c, run["id"], 180.0, ("done", "failed"), api="")
            assert run["status"] == "done", run["error"]
            assert run["attempts"] == 2 and run["number"] == 1

            b = c.post(
                "/projects", json={"name": "clean", "dataset": {"kind": "folder", "path": str(dataset)}}
            ).json()
            clean = c.post(f"/projects/{b['id']}/runs", json={}).json()
            clean = wait_run(c, clean["id"], 180.0, ("done", "failed"), api="")
            assert clean["status"] == "done", clean["error"]
        clean_dir = data / "studio" / "runs" / f"p{b['id']}" / f"r{clean['id']}" / "sequences" / "00"
        run_dir = sequence_dir

        # The resumed stage computed only the frames the killed attempt had not finished.
        resumed = json.loads((run_dir / "stages.json").read_text())[stage]
        assert resumed["status"] == "done" and 0 < resumed["frames_computed"] < FRAMES

        names = sorted(p.name for p in (clean_dir / "export").iterdir())
        assert len(names) == 2 * FRAMES
        assert sorted(p.name for p in (run_dir / "export").iterdir()) == names
        for name in names:
            assert (run_dir / "export" / name).read_bytes() == (clean_dir / "export" / name).read_bytes(), (
                name
            )
        assert (
            json.loads((run_dir / "metrics.json").read_text())["camera"]
            == json.loads((clean_dir / "metrics.json").read_text())["camera"]
        )
    finally:
        server.stop()
