"""The app on a work folder an earlier version wrote (``tests/formerruns.py``): its database of schema
version 7 and its run folders move into today's shape when the server starts, and the runs keep their
results, metrics, exports and corrections."""

from __future__ import annotations

import io
import sqlite3
import zipfile
from pathlib import Path

import formerruns
import numpy as np
import pytest
from apphelpers import API, wait_run
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.core.db import SCHEMA_VERSION
from app.main import create_app
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.run_layout import RunLayout, former_layout

former = formerruns.former


def _files(folder: Path) -> dict[Path, bytes]:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_the_app_moves_its_database_and_run_folders_and_carries_on(former: Path) -> None:
    studio = former / "studio"
    old_export = _files(studio / "runs/p1/r2/export")
    settings = Settings(
        data_roots=[former / "data"],
        work_dir=studio,
        seed_demo=False,
        progress_interval_s=0.02,
        prewarm_workers=False,
    )
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
        with sqlite3.connect(settings.database) as db:
            assert db.execute("SELECT MAX(version) FROM schema_version").fetchone()[0] == SCHEMA_VERSION
        for run_dir in ("p1/r1", "p1/r2", "p2/r3"):
            assert RunLayout.is_run(studio / "runs" / run_dir), run_dir
            assert former_layout(studio / "runs" / run_dir) is None

        runs = client.get(f"{API}/projects/1/runs").json()["data"]
        assert [r["number"] for r in runs] == [2, 1]
        assert runs[0]["params"]["sequences"] == [
            {"name": "00", "dataset": str(former / "data/street/sequences/00"), "frames": None}
        ]
        stages = [s["name"] for s in runs[0]["progress"]["stages"]]
        assert stages[0] == "00/labels2d" and all(s.startswith("00/") for s in stages)
        assert all(s["status"] in ("done", "skipped") for s in runs[0]["progress"]["stages"])
        assert runs[0]["has_export"] and runs[0]["has_metrics"]

        metrics = client.get(f"{API}/runs/2/metrics").json()
        assert metrics["sequences"] == ["00"] and metrics["metrics"]["protocols"]["camera"]
        both = client.get(f"{API}/runs/3/metrics", params={"sequence": "01"})
        assert both.status_code == 200 and both.json()["sequence"] == "01"

        zipped = client.get(f"{API}/runs/2/export.zip")
        assert zipped.status_code == 200
        with zipfile.ZipFile(io.BytesIO(zipped.content)) as zf:
            for rel, data in old_export.items():
                if rel.suffix == ".label":
                    assert zf.read(f"sequences/00/predictions/{rel.name}") == data

        corrections = client.get(f"{API}/projects/1/corrections").json()["corrections"]
        assert len(corrections) == 1

        # A new run (seeded from the moved run 2; the data moved, so it recomputes) writes run 2's labels,
        # the correction made after run 1 included.
        started = client.post(f"{API}/projects/1/runs", json={}).json()
        run = wait_run(client, started["id"], timeout=120)
        assert run["status"] == "done", run["error"]
        seq = RunLayout(studio / f"runs/p1/r{started['id']}").sequence("00")
        new_files = _files(seq.export_dir)
        assert new_files.keys() == old_export.keys()
        # The runs before objects had no tracks stage: a tracked point now carries its track (and a mover
        # its moving id); every other point keeps the label the earlier version wrote.
        tracks = SequenceTracks.load(seq.tracks)
        for rel, data in old_export.items():
            if rel.suffix != ".label":
                continue
            new_label = np.frombuffer(new_files[rel], "<u4")
            untracked = np.ones(new_label.size, bool)
            untracked[tracks.scan(rel.stem).rows] = False
            assert (new_label[untracked] == np.frombuffer(data, "<u4")[untracked]).all(), rel
        assert all(new_files[rel] == data for rel, data in old_export.items() if rel.suffix == ".conf")
