"""Safe by default: loopback binding, the access token on every API call, host-header guard."""

from __future__ import annotations

from pathlib import Path

import appfixtures
import pytest
from apphelpers import API
from fastapi.testclient import TestClient
from pydantic import ValidationError

from app.core.config import Settings, is_loopback
from app.core.db import SCHEMA_VERSION
from app.core.errors import Forbidden
from app.core.security import resolve_in_roots, token_matches
from app.main import create_app

# The app tests' fixtures (this folder has no conftest.py; see appfixtures), found by name here.
client, data_root, settings, tiny_dataset = (
    appfixtures.client,
    appfixtures.data_root,
    appfixtures.settings,
    appfixtures.tiny_dataset,
)

TOKEN = "correct-horse-battery"


def test_settings_defaults_and_validation(tmp_path: Path) -> None:
    s = Settings(data_roots=[tmp_path], work_dir=tmp_path / "w")
    assert s.host == "127.0.0.1" and s.port == 8000 and s.token is None
    assert s.database == tmp_path / "w" / "studio.db"
    with pytest.raises(ValidationError, match="not a loopback address"):
        Settings(host="0.0.0.0", data_roots=[tmp_path])
    with pytest.raises(ValidationError, match="at least 16 characters"):
        Settings(host="0.0.0.0", access_token="short", data_roots=[tmp_path])
    with pytest.raises(ValidationError, match="port"):
        Settings(port=70000, data_roots=[tmp_path])
    with pytest.raises(ValidationError, match="at least one data root"):
        Settings(data_roots=[])
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValidationError, match="is a file"):
        Settings(data_roots=[tmp_path / "file"])
    assert Settings(host="0.0.0.0", access_token=TOKEN, data_roots=[tmp_path]).token == TOKEN
    assert (
        is_loopback("127.0.0.1")
        and is_loopback("::1")
        and is_loopback("localhost")
        and is_loopback("127.3.4.5")
    )
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.2") and not is_loopback("example.com")


def test_settings_come_from_the_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("LEAP_PORT", "8123")
    monkeypatch.setenv("LEAP_DATA_ROOTS", f'["{tmp_path}"]')
    s = Settings()
    assert s.port == 8123 and s.data_roots == [tmp_path.resolve()]


def test_path_confinement(tmp_path: Path) -> None:
    root = tmp_path / "root"
    (root / "a").mkdir(parents=True)
    assert resolve_in_roots("a", [root]) == root / "a"
    assert resolve_in_roots(root / "a" / ".." / "a", [root]) == root / "a"
    for bad in ["..", "../x", "/etc/passwd", str(tmp_path)]:
        with pytest.raises(Forbidden):
            resolve_in_roots(bad, [root])
    assert token_matches(None, None) and token_matches(TOKEN, TOKEN)
    assert not token_matches(TOKEN, None) and not token_matches(TOKEN, TOKEN + "x")


def test_every_api_call_needs_the_token_off_loopback(tmp_path: Path) -> None:
    settings = Settings(
        host="0.0.0.0",
        access_token=TOKEN,
        data_roots=[tmp_path],
        work_dir=tmp_path / "w",
        seed_demo=False,
        prewarm_workers=False,
    )
    with TestClient(create_app(settings), base_url="http://10.0.0.5:8000") as client:
        for path in ["/health", "/projects", "/datasets", "/projects/1", "/runs/1", "/runs/1/events"]:
            r = client.get(API + path)
            assert r.status_code == 403, path
            assert r.json()["detail"] == "Access token missing or wrong"
        assert (
            client.post(f"{API}/projects", json={"name": "x", "dataset": {"kind": "demo"}}).status_code == 403
        )
        assert client.get(f"{API}/health", headers={"X-Leap-Token": "wrong-token-value"}).status_code == 403
        assert client.get(f"{API}/health", headers={"X-Leap-Token": TOKEN}).status_code == 200
        assert client.get(f"{API}/health", headers={"Authorization": f"Bearer {TOKEN}"}).json()[
            "auth_required"
        ]
        assert client.get(f"{API}/projects?token={TOKEN}").status_code == 200
        client.cookies.set("leap_token", TOKEN)
        assert client.get(f"{API}/projects").status_code == 200
        # The static UI itself carries no data and loads without the token (it asks for one).
        client.cookies.clear()
        assert client.get("/").status_code == 200 and "LeAP Studio" in client.get("/").text


def test_loopback_server_refuses_foreign_host_headers(client: TestClient) -> None:
    assert client.get(f"{API}/health").status_code == 200
    for host in ["evil.example.com", "evil.example.com:8000", "192.168.0.10:8000"]:
        r = client.get(f"{API}/health", headers={"host": host})
        assert r.status_code == 403 and "is not allowed" in r.json()["detail"]
    assert client.get(f"{API}/health", headers={"host": "localhost:8000"}).status_code == 200
    assert client.get(f"{API}/health", headers={"host": "[::1]:8000"}).status_code == 200


def test_health(client: TestClient) -> None:
    body = client.get(f"{API}/health").json()
    assert body["status"] == "ok" and body["db_schema_version"] == SCHEMA_VERSION
    assert body["queued"] == body["running"] == 0 and body["auth_required"] is False


def test_the_web_folder_serves_only_the_ui(client: TestClient) -> None:
    """The web UI's folder is also a Python package (how it ships); only its pages, modules and styles
    are served."""
    assert client.get("/").status_code == 200
    assert client.get("/app.js").status_code == 200 and client.get("/style.css").status_code == 200
    assert client.get("/viewer/viewer-api.js").status_code == 200
    for path in ("/__init__.py", "/viewer/../__init__.py", "/__pycache__/"):
        assert client.get(path).status_code == 404, path
