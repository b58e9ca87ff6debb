"""The "Estimate poses (KISS-ICP)" checkbox in a real browser against a real server: a project on a
sequence without poses.txt, created with the box ticked, runs (the estimate stage shown first) and the
project page's switch saves the option."""

from __future__ import annotations

import sys
from pathlib import Path

import browserfixtures
import pytest

browser = browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]

FRAMES = 5


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    from serverproc import Server, make_small_street

    data = tmp_path_factory.mktemp("poses-ui") / "data"
    dataset = make_small_street(data / "street", FRAMES)
    (dataset / "poses.txt").unlink()
    srv = Server(data).start()
    yield srv, dataset
    srv.stop()


def test_create_with_estimate_poses_and_run(server, browser) -> None:
    import httpx
    from playwright.sync_api import expect

    srv, dataset = server
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(srv.base + "/")
    expect(page.locator("#create-form")).to_be_visible()
    page.fill("#new-name", "No poses")
    page.select_option("#new-dataset", str(dataset))
    box = page.get_by_label("Estimate poses (KISS-ICP)")
    expect(box).not_to_be_checked()
    box.check()
    page.click("#create-project")
    expect(page.locator("#project-name")).to_have_text("No poses")
    project_id = int(page.url.rsplit("/", 1)[-1])
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        assert api.get(f"/projects/{project_id}").json()["estimate_poses"] is True
    expect(page.locator("#estimate-poses")).to_be_checked()

    # The estimate comes first in the stage list (the default simulated labeler keeps the run short).
    page.click("#run-button")
    stage = page.locator('.stage[data-stage="00/estimate poses"]')
    expect(stage.locator(".stage-name")).to_have_text("Estimate poses")
    expect(page.locator(".stage").first).to_have_attribute("data-stage", "00/estimate poses")
    expect(page.locator("#run-status")).to_have_attribute("data-status", "done", timeout=120_000)
    expect(stage).to_have_attribute("data-status", "done")
    assert not (dataset / "poses.txt").exists()

    # The project page's switch saves the option at once.
    page.locator("#estimate-poses").uncheck()
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        browserfixtures.wait_until(
            lambda: api.get(f"/projects/{project_id}").json()["estimate_poses"] is False, 10, "option saved"
        )
    assert errors == []
