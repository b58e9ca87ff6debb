"""Pages of other origins cannot change state, and viser's own port streams only to the
app's relay.

Each test runs the real server (``python -m app.main``, real SQLite, real HTTP on 127.0.0.1) and speaks to
it with the headers a browser sends: a page served from ``http://127.0.0.2:8769`` sends
``Origin: http://127.0.0.2:8769`` and ``Sec-Fetch-Site: cross-site`` even on a ``no-cors`` POST.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import httpx
import pytest
import viser
from appfixtures import add_gt2d
from apphelpers import wait_run
from serverproc import Server
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from app.core.security import cross_origin_reason
from app.viewer.scene import SECRET_HEADER

EVIL_PAGE = "http://127.0.0.2:8769"
TOKEN = "correct-horse-battery"
PROTOCOL = f"viser-v{viser.__version__}"


@pytest.mark.parametrize(
    ("headers", "refused"),
    [
        ({"host": "127.0.0.1:8000"}, False),  # curl, scripts, the CLI: not a page
        ({"host": "127.0.0.1:8000", "origin": "http://127.0.0.1:8000"}, False),
        ({"host": "127.0.0.1:80", "origin": "http://127.0.0.1", "sec-fetch-site": "same-origin"}, False),
        ({"host": "127.0.0.1:8000", "sec-fetch-site": "none"}, False),  # typed into the address bar
        ({"host": "[::1]:8000", "origin": "http://[::1]:8000"}, False),
        ({"host": "127.0.0.1", "origin": "http://127.0.0.1:80"}, False),  # default ports
        ({"host": "studio.example", "origin": "https://studio.example"}, False),  # behind a TLS proxy
        ({"host": "Studio.Example:443", "origin": "https://studio.example"}, False),
        ({"host": "127.0.0.1:8000", "origin": "http://127.0.0.2:8000"}, True),  # loopback alias
        ({"host": "127.0.0.1:8000", "origin": "http://localhost:8000"}, True),
        ({"host": "127.0.0.1:8000", "origin": "http://127.0.0.1:8001"}, True),
        ({"host": "studio.example:80", "origin": "https://studio.example"}, True),  # scheme → port 443
        ({"host": "127.0.0.1:8000", "origin": "null"}, True),
        ({"host": "127.0.0.1:8000", "origin": "chrome-extension://abc"}, True),
        ({"origin": "http://127.0.0.1:8000"}, True),  # no Host to compare with
        ({"host": "127.0.0.1:80", "origin": "http://127.0.0.1", "sec-fetch-site": "same-site"}, True),
        ({"host": "127.0.0.1:8000", "sec-fetch-site": "cross-site"}, True),
    ],
)
def test_what_counts_as_another_origin(headers: dict[str, str], refused: bool) -> None:
    assert (cross_origin_reason(headers) is not None) is refused


@pytest.fixture
def tiny_data(tmp_path: Path, make_tiny_sequence: Any) -> tuple[Path, Path]:
    """(data root, a 3-frame sequence inside it with images and 2D ground truth)."""
    data = tmp_path / "data"
    seq = make_tiny_sequence(data / "tiny", n_frames=3, n_points=300)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    return data, seq.root


@pytest.mark.slow
def test_state_changes_from_other_origins_are_refused_without_a_token(tiny_data: tuple[Path, Path]) -> None:
    data, seq = tiny_data
    server = Server(data, extra_env={"LEAP_PREWARM_WORKERS": "false"}).start()
    own = f"http://127.0.0.1:{server.port}"
    cross_site = {"Origin": EVIL_PAGE, "Sec-Fetch-Site": "cross-site"}
    foreign: list[dict[str, str]] = [
        cross_site,
        {"Origin": EVIL_PAGE},  # browsers without Fetch Metadata
        {"Origin": f"http://localhost:{server.port}"},  # another loopback name is another origin
        {"Origin": f"http://127.0.0.1:{server.port + 1}"},  # another port too
        {"Origin": "null"},  # sandboxed iframes, file: pages
        {"Sec-Fetch-Site": "same-site"},
    ]
    try:
        with server.client() as c:
            for headers in foreign:
                r = c.post("/projects", json={"name": "x", "dataset": {"path": str(seq)}}, headers=headers)
                assert r.status_code == 403 and "Cross-origin" in r.json()["detail"], (headers, r.text)
            assert c.get("/projects").json()["count"] == 0
            # The web UI's own requests (same origin), and clients that are not browsers, pass.
            same = {"Origin": own, "Sec-Fetch-Site": "same-origin"}
            project = c.post("/projects", json={"name": "ok", "dataset": {"path": str(seq)}}, headers=same)
            assert project.status_code == 201, project.text
            pid = project.json()["id"]
            for headers in foreign:
                assert c.post(f"/projects/{pid}/runs", headers=headers).status_code == 403
                assert c.post(f"/projects/{pid}/viewer", headers=headers).status_code == 403
                assert c.patch(f"/projects/{pid}", json={"name": "pwned"}, headers=headers).status_code == 403
                assert c.delete(f"/projects/{pid}", headers=headers).status_code == 403
            assert c.get(f"/projects/{pid}/runs").json()["count"] == 0
            assert c.get(f"/projects/{pid}/viewer").status_code == 404  # no viewer was started
            assert c.get(f"/projects/{pid}").json()["name"] == "ok"
            # Reading stays open (the browser's CORS rule keeps other pages from reading the answer).
            assert c.get("/projects", headers=cross_site).status_code == 200
            run = c.post(f"/projects/{pid}/runs", json={}, headers=same)
            assert run.status_code == 202, run.text
            assert c.post(f"/runs/{run.json()['id']}/cancel").status_code == 200  # curl-like: no headers
    finally:
        server.stop()


async def _first_message(url: str, **kwargs: Any) -> bytes | str:
    """The first message a websocket at ``url`` sends; raises if it closes first."""
    async with connect(url, subprotocols=[PROTOCOL], open_timeout=10, max_size=None, **kwargs) as ws:
        return await asyncio.wait_for(ws.recv(), timeout=20)


async def _closed_before_any_message(url: str, **kwargs: Any) -> int:
    """Connect and expect the server to close without sending anything; returns the close code."""
    try:
        message = await _first_message(url, **kwargs)
    except ConnectionClosed as exc:
        assert exc.rcvd is not None
        return exc.rcvd.code
    raise AssertionError(f"the websocket streamed {len(message)} bytes")


@pytest.mark.slow
def test_the_viewer_port_streams_only_to_the_relay(tiny_data: tuple[Path, Path]) -> None:
    data, seq = tiny_data
    server = Server(data, extra_env={"LEAP_ACCESS_TOKEN": TOKEN}).start_with_token(TOKEN)
    own = f"http://127.0.0.1:{server.port}"
    auth = {"X-Leap-Token": TOKEN}
    try:
        with httpx.Client(base_url=f"{own}/api/v1", timeout=30.0, headers=auth) as c:
            project = c.post("/projects", json={"name": "v", "dataset": {"path": str(seq)}}).json()
            run = c.post(f"/projects/{project['id']}/runs", json={}).json()
            assert wait_run(c, run["id"], timeout=240, api="")["status"] == "done"
            r = c.post(f"/projects/{project['id']}/viewer", headers={"Origin": own})
            assert r.status_code == 200, r.text
            viewer = r.json()
            assert "direct_url" not in viewer
        port = viewer["port"]
        direct = f"ws://127.0.0.1:{port}"
        relay = f"ws://127.0.0.1:{server.port}{viewer['url'].rstrip('/')}?token={TOKEN}"

        async def probe() -> None:
            # viser's own port: a page of another site, and a local process without the secret or with a
            # guessed one, are all closed before the scene is sent.
            assert await _closed_before_any_message(direct, origin="http://evil.example") == 1008
            assert await _closed_before_any_message(direct) == 1008
            guessed = {SECRET_HEADER: "guess"}
            assert await _closed_before_any_message(direct, additional_headers=guessed) == 1008
            # The relay: refused at the handshake for another origin, streams for the app's own pages.
            for origin in ("http://evil.example", EVIL_PAGE):
                with pytest.raises(InvalidStatus) as refused:
                    await _first_message(relay, origin=origin)
                assert refused.value.response.status_code == 403
            first = await _first_message(relay, origin=own)
            assert isinstance(first, bytes) and len(first) > 1000  # the scene backlog

        asyncio.run(probe())
    finally:
        server.stop()
