"""``/api/docs`` in a real Chromium with every request off 127.0.0.1 blocked: the API reference renders
from the server alone (FastAPI's default page loads Swagger UI from a CDN and stays blank offline)."""

from __future__ import annotations

import sys
from pathlib import Path

import browserfixtures
import pytest

browser = browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_api_docs_render_with_no_external_request(browser, tmp_path: Path) -> None:
    from serverproc import Server

    data = tmp_path / "data"
    data.mkdir()
    server = Server(data).start()
    try:
        page = browser.new_page()
        browserfixtures.echo_console(page)
        external: list[str] = []

        def route(r) -> None:
            if r.request.url.startswith(server.base):
                r.continue_()
            else:
                external.append(r.request.url)
                r.abort()

        page.route("**/*", route)
        page.goto(f"{server.base}/api/docs")
        page.get_by_text("/api/v1/projects/{project_id}/runs", exact=True).first.wait_for(timeout=15000)
        assert page.locator("#schema-ProjectPublic").count() == 1
        assert "LeAP Studio API" in page.title()
        # Opening an operation shows its parameters and responses.
        page.locator("details.op summary", has_text="/api/v1/runs/{run_id}/cancel").first.click()
        assert page.locator("details.op[open] td", has_text="run_id").count() >= 1
        assert external == [], external
        page.close()
    finally:
        server.stop()
