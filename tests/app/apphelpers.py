"""Helpers shared by the app tests (imported as ``apphelpers``; the fixtures live in conftest.py)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx
from fastapi.testclient import TestClient

API = "/api/v1"
TERMINAL = ("done", "failed", "cancelled", "interrupted")


def create_project(client: TestClient, dataset: Path, name: str = "tiny") -> dict[str, Any]:
    r = client.post(
        f"{API}/projects", json={"name": name, "dataset": {"kind": "folder", "path": str(dataset)}}
    )
    assert r.status_code == 201, r.text
    return r.json()


def wait_run(
    client: httpx.Client,
    run_id: int,
    timeout: float = 90.0,
    until: tuple[str, ...] = TERMINAL,
    api: str = API,
) -> dict[str, Any]:
    """Poll the run until its status is in ``until``; ``api`` is the path prefix (empty when the client's
    base URL already ends in it)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        run = client.get(f"{api}/runs/{run_id}").json()
        if run["status"] in until:
            return run
        time.sleep(0.05)
    raise AssertionError(f"run {run_id} still {run['status']} after {timeout} s")


def loc_of(r: Any) -> list[Any]:
    """The ``loc`` of a 422 answer's first error."""
    assert r.status_code == 422, r.text
    return list(r.json()["detail"][0]["loc"])
