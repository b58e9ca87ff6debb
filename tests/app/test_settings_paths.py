"""A project's settings cannot send a run outside the data roots or trigger downloads.

Each test runs the real server (``python -m app.main``, real SQLite, real HTTP on 127.0.0.1). Where models
are, where 2D caches live and whether models may be downloaded are the server's settings; a project can
name model ids, never folders, and cannot allow downloads.
"""

from __future__ import annotations

import shutil
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest
from appfixtures import add_gt2d
from apphelpers import wait_run
from serverproc import Server

from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models

ESCAPES: list[tuple[dict[str, Any], list[str]]] = [
    ({"grounded_sam": {"cache_dir": "{outside}"}}, ["grounded_sam", "cache_dir"]),
    ({"grounded_sam": {"models_dir": "{outside}"}}, ["grounded_sam", "models_dir"]),
    ({"grounded_sam": {"allow_download": True}}, ["grounded_sam", "allow_download"]),
    ({"grounded_sam": {"device": "cuda"}}, ["grounded_sam", "device"]),
    # The last part of a model id names a subfolder of the models folder: these would leave it.
    ({"grounded_sam": {"detector_id": "IDEA-Research/.."}}, ["grounded_sam", "detector_id"]),
    ({"grounded_sam": {"segmenter_id": "{outside}"}}, ["grounded_sam", "segmenter_id"]),
    ({"grounded_sam": {"segmenter_id": "../outside"}}, ["grounded_sam", "segmenter_id"]),
]
"""Pipeline overrides that used to point a run at another folder or at the network, and the field the
refusal names (below ``pipeline``)."""


def _fill(value: Any, outside: Path) -> Any:
    if isinstance(value, dict):
        return {k: _fill(v, outside) for k, v in value.items()}
    return value.replace("{outside}", str(outside)) if isinstance(value, str) else value


@pytest.fixture
def tiny_data(tmp_path: Path, make_tiny_sequence: Any) -> tuple[Path, Path]:
    """(data root, a 3-frame sequence inside it with images and 2D ground truth)."""
    data = tmp_path / "data"
    seq = make_tiny_sequence(data / "tiny", n_frames=3, n_points=300)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    return data, seq.root


def test_project_settings_cannot_name_folders_or_allow_downloads(
    tmp_path: Path, tiny_data: tuple[Path, Path]
) -> None:
    data, seq = tiny_data
    outside = tmp_path / "outside"
    outside.mkdir()
    server = Server(data, extra_env={"LEAP_PREWARM_WORKERS": "false"}).start()
    try:
        with server.client() as c:
            for overrides, field in ESCAPES:
                body = _fill(overrides, outside)
                r = c.post("/projects", json={"name": "x", "dataset": {"path": str(seq)}, "pipeline": body})
                assert r.status_code == 422, (body, r.text[:300])
                assert r.json()["detail"][0]["loc"] == ["body", "pipeline", *field], r.text
            assert c.get("/projects").json()["count"] == 0
            project = c.post("/projects", json={"name": "ok", "dataset": {"path": str(seq)}}).json()
            stored = c.get(f"/projects/{project['id']}").json()["pipeline"]
            for overrides, field in ESCAPES:
                body = _fill(overrides, outside)
                r = c.patch(f"/projects/{project['id']}", json={"pipeline": body})
                assert r.status_code == 422, (body, r.text[:300])
                assert r.json()["detail"][0]["loc"] == ["body", "pipeline", *field], r.text
            assert c.get(f"/projects/{project['id']}").json()["pipeline"] == stored
            # A preset is a name, never a path.
            r = c.post("/projects", json={"name": "x", "dataset": {"path": str(seq)}, "schema_name": "../x"})
            assert r.status_code == 422
    finally:
        server.stop()
    assert not list(outside.iterdir())


@pytest.mark.slow
def test_a_grounded_sam_run_writes_and_loads_only_inside_the_servers_folders(
    tmp_path: Path, tiny_data: tuple[Path, Path]
) -> None:
    """The worker's 2D cache (``.npz`` and pass files) lands in the server's work folder, models load from
    the server's models folder, and a dataset path stored before the roots narrowed is refused."""
    data, seq = tiny_data
    models = make_tiny_models(tmp_path / "models", TinyModelsConfig(num_queries=8)).models_dir
    env = {"LEAP_MODELS_DIR": str(models), "LEAP_PREWARM_WORKERS": "false"}
    server = Server(data, extra_env=env).start()
    try:
        with server.client() as c:
            pipeline = {"labeler": "grounded-sam", "grounded_sam": {"box_threshold": 0.01}}
            project = c.post(
                "/projects", json={"name": "gs", "dataset": {"path": str(seq)}, "pipeline": pipeline}
            ).json()
            run = c.post(f"/projects/{project['id']}/runs", json={}).json()
            run = wait_run(c, run["id"], timeout=240, api="")
            assert run["status"] == "done", run["error"]
    finally:
        server.stop()
    written = [p for p in tmp_path.rglob("*") if p.is_file() and p.suffix in (".npz", ".bin")]
    cache = data / "studio" / "cache" / f"p{project['id']}"
    assert any(p.is_relative_to(cache) for p in written), "no 2D cache entry in the project's cache folder"
    stray = [p for p in written if not p.is_relative_to(data) and not p.is_relative_to(models)]
    assert not stray, f"files written outside the data root: {stray[:5]}"

    # The server restarts with a narrower data root: the project's stored dataset is now outside it.
    narrow = data / "narrow"
    narrow.mkdir()
    server = Server(data, port=server.port, extra_env={**env, "LEAP_DATA_ROOTS": f'["{narrow}"]'}).start()
    try:
        with server.client() as c:
            r = c.post(f"/projects/{project['id']}/runs", json={})
            assert r.status_code == 403 and "outside the allowed data roots" in r.json()["detail"], r.text
    finally:
        server.stop()


class _Recorder(BaseHTTPRequestHandler):
    """A stand-in Hugging Face Hub: records each request's path and answers 404."""

    seen: list[str]

    def do_GET(self) -> None:
        self.seen.append(self.path)
        self.send_error(404)

    do_HEAD = do_GET

    def log_message(self, *args: Any) -> None:
        pass


@pytest.fixture
def hub() -> Iterator[tuple[str, list[str]]]:
    """(endpoint URL, paths requested so far) of a local stand-in for the Hugging Face Hub."""
    seen: list[str] = []
    handler = type("Handler", (_Recorder,), {"seen": seen})
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", seen
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.mark.slow
def test_downloads_happen_only_when_the_servers_settings_allow_them(
    tmp_path: Path, tiny_data: tuple[Path, Path], hub: tuple[str, list[str]]
) -> None:
    """Without a models folder the ids are looked up in the Hugging Face cache; the hub (a local stand-in
    here) is asked only when the server runs with ``allow_download``."""
    data, seq = tiny_data
    endpoint, seen = hub
    env = {"HF_HOME": str(tmp_path / "hf"), "HF_ENDPOINT": endpoint, "LEAP_PREWARM_WORKERS": "false"}
    for key in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "LEAP_MODELS_DIR", "LEAP_ALLOW_DOWNLOAD"):
        env[key] = ""  # LEAP_* ignore empty values; huggingface_hub reads "" as false
    pipeline = {"labeler": "grounded-sam"}
    outcomes = []
    for allow in ("false", "true"):
        shutil.rmtree(data / "studio", ignore_errors=True)
        server = Server(data, extra_env={**env, "LEAP_ALLOW_DOWNLOAD": allow}).start()
        try:
            with server.client() as c:
                project = c.post(
                    "/projects", json={"name": "gs", "dataset": {"path": str(seq)}, "pipeline": pipeline}
                ).json()
                run = c.post(f"/projects/{project['id']}/runs", json={}).json()
                run = wait_run(c, run["id"], timeout=240, api="")
                outcomes.append((run["status"], run["error"], list(seen)))
                health = httpx.get(f"{server.base}/api/v1/health").status_code
                assert health == 200
        finally:
            server.stop()
    (status_off, error_off, seen_off), (status_on, _error_on, seen_on) = outcomes
    assert status_off == "failed" and "not in the Hugging Face cache" in (error_off or "")
    assert seen_off == [], f"the hub was asked without the server's permission: {seen_off}"
    assert status_on == "failed"  # the stand-in hub has no models
    assert any("grounding-dino-tiny" in p for p in seen_on), seen_on
