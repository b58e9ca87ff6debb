"""Cross-site writes as a browser meets them: a page served from another origin (``127.0.0.2``) tries to start
a run and open a viewer with ``no-cors`` POSTs, and to read viser's own port with a websocket.

Real Chromium (Debian's, driven by Playwright), the real server in a subprocess on 127.0.0.1 (real SQLite,
no access token: the same-origin rule must hold without one), and the hostile page on its own HTTP server.
"""

from __future__ import annotations

import json
import sys
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import browserfixtures
import pytest

browser = browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]

EVIL_HOST = "127.0.0.2"  # another loopback alias: another origin, and another site, to the browser


def _serve_pages(pages: dict[str, str]) -> tuple[ThreadingHTTPServer, str]:
    """Serve ``pages`` (path → HTML) on ``EVIL_HOST``; returns the server and its base URL."""

    class Page(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = pages.get(self.path, "").encode()
            self.send_response(200 if body else 404)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:
            pass

    try:
        httpd = ThreadingHTTPServer((EVIL_HOST, 0), Page)
    except OSError as exc:  # pragma: no cover - every Linux routes 127.0.0.0/8 to lo
        pytest.skip(f"cannot bind {EVIL_HOST}: {exc}")
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd, f"http://{EVIL_HOST}:{httpd.server_address[1]}"


@pytest.fixture
def server(tmp_path: Path, make_tiny_sequence: Any) -> Iterator[tuple[Any, Path]]:
    from appfixtures import add_gt2d
    from serverproc import Server

    data = tmp_path / "data"
    seq = make_tiny_sequence(data / "tiny", n_frames=3, n_points=300)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    srv = Server(data, extra_env={"LEAP_PREWARM_WORKERS": "false"}).start()
    try:
        yield srv, seq.root
    finally:
        srv.stop()


POSTS = """<!doctype html><script>
window.done = (async () => {
  const report = {};
  for (const url of %(urls)s) {
    try { await fetch(url, {method: "POST", mode: "no-cors"}); report[url] = "sent"; }
    catch (e) { report[url] = String(e); }
  }
  return report;
})();
</script>"""
"""What the hostile page of the issue did: ``no-cors`` POSTs (the browser sends them, hiding the answer)."""

WEBSOCKET = """<!doctype html><script>
window.done = new Promise((resolve) => {
  const ws = new WebSocket(%(url)s, [%(protocol)s]);
  let bytes = 0;
  ws.binaryType = "arraybuffer";
  ws.onmessage = (e) => { bytes += e.data.byteLength || e.data.length; };
  ws.onclose = (e) => resolve({bytes, code: e.code});
  setTimeout(() => { ws.close(); resolve({bytes, code: "still open after 10 s"}); }, 10000);
});
</script>"""
"""A page reading a websocket: how many bytes it got before the close, and the close code."""


def test_a_page_of_another_origin_cannot_start_runs_open_viewers_or_read_the_viewer_port(
    server: tuple[Any, Path], browser: Any
) -> None:
    import viser

    srv, seq = server
    api = f"{srv.base}/api/v1"
    with srv.client() as c:
        pid = c.post("/projects", json={"name": "target", "dataset": {"path": str(seq)}}).json()["id"]
        targets = [f"{api}/projects/{pid}/runs", f"{api}/projects/{pid}/viewer"]
        pages = {"/posts": POSTS % {"urls": json.dumps(targets)}}
        httpd, base = _serve_pages(pages)
        try:
            page = browser.new_page()
            browserfixtures.echo_console(page)
            page.goto(f"{base}/posts")
            sent = page.evaluate("window.done")
            assert set(sent.values()) == {"sent"}, sent  # the browser did send both
            assert c.get(f"/projects/{pid}/runs").json()["count"] == 0, "the page started a run"
            assert c.get(f"/projects/{pid}/viewer").status_code == 404, "the page opened a viewer"

            # The project's user opens the viewer; the page then tries viser's own port and the relay.
            opened = c.post(f"/projects/{pid}/viewer")
            assert opened.status_code == 200, opened.text
            protocol = json.dumps(f"viser-v{viser.__version__}")
            relay = srv.base.replace("http://", "ws://") + opened.json()["url"].rstrip("/")
            pages["/viser"] = WEBSOCKET % {
                "url": json.dumps(f"ws://127.0.0.1:{opened.json()['port']}"),
                "protocol": protocol,
            }
            pages["/relay"] = WEBSOCKET % {"url": json.dumps(relay), "protocol": protocol}
            page.goto(f"{base}/viser")
            direct = page.evaluate("window.done")
            page.goto(f"{base}/relay")
            relayed = page.evaluate("window.done")
            page.close()
        finally:
            httpd.shutdown()
            httpd.server_close()
    assert direct == {"bytes": 0, "code": 1008}, direct
    assert relayed["bytes"] == 0 and relayed["code"] != "still open after 10 s", relayed
