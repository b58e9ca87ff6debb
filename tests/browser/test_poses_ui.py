"""The "Estimate poses (KISS-ICP)" checkbox in a real browser against a real server: a project on a
sequence without poses.txt, created with the box ticked, runs (the estimate stage shown first) and the
project page's switch saves the option."""

from __future__ import annotations

import re
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


def test_a_run_that_failed_on_a_setting_offers_a_new_run_with_the_new_settings(server, browser) -> None:
    """The Resume trap: a run whose dataset lost its poses fails with "turn on Estimate poses"; after the
    user ticks it, Resume fails the same way (a resumed run keeps its own settings). The run panel says so
    and offers a new run with the project's current settings, which estimates the poses and finishes."""
    import httpx
    from playwright.sync_api import expect
    from serverproc import make_small_street

    srv, dataset = server
    trap = make_small_street(dataset.parents[2] / "trap", FRAMES)
    api = httpx.Client(base_url=f"{srv.base}/api/v1", timeout=30)
    body = {"name": "Trap", "dataset": {"kind": "folder", "path": str(trap)}}
    project = api.post("/projects", json=body).json()
    pid = project["id"]
    assert project["estimate_poses"] is False
    # The run starts while the dataset has its poses (a run without them is refused up front), is
    # cancelled, and the poses file goes away before it is resumed.
    first = api.post(f"/projects/{pid}/runs", json={}).json()
    assert api.post(f"/runs/{first['id']}/cancel").status_code == 200
    browserfixtures.wait_until(
        lambda: api.get(f"/runs/{first['id']}").json()["status"] == "cancelled", 60, "the run cancelled"
    )
    (trap / "poses.txt").unlink()

    def failed_attempt(after: int) -> dict:
        return browserfixtures.wait_until(
            lambda: (
                (r := api.get(f"/runs/{first['id']}").json())["status"] == "failed"
                and r["attempts"] > after
                and r
            ),
            120,
            "the resumed run to fail",
        )

    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{srv.base}/#/projects/{pid}")
    resume = page.locator("#resume-button")
    expect(resume).to_have_attribute("title", re.compile("with the settings it was started with"))
    attempts = api.get(f"/runs/{first['id']}").json()["attempts"]
    resume.click()
    run = failed_attempt(attempts)
    assert "Estimate poses (KISS-ICP)" in run["error"] and run["fix_setting"] == "Estimate poses (KISS-ICP)"
    expect(page.locator("#run-status")).to_have_attribute("data-status", "failed", timeout=30_000)
    expect(page.locator(".run-error")).to_contain_text('turn on "Estimate poses (KISS-ICP)"')
    expect(page.locator("#run-fix")).to_contain_text("Resume keeps this run's own settings")

    # The trap: the setting changed, Resume still runs the old settings and fails with the same advice.
    page.locator("#estimate-poses").check()
    browserfixtures.wait_until(
        lambda: api.get(f"/projects/{pid}").json()["estimate_poses"] is True, 10, "the option saved"
    )
    resume.click()
    again = failed_attempt(run["attempts"])
    assert again["params"]["estimate_poses"] is False and "Estimate poses (KISS-ICP)" in again["error"]

    # The way out: a new run with the project's current settings.
    expect(page.locator("#run-status")).to_have_attribute("data-status", "failed", timeout=30_000)
    page.get_by_role("button", name="Run again with the new settings").click()
    expect(page.locator("h2", has_text="Run 2")).to_be_visible(timeout=30_000)
    expect(page.locator("#run-status")).to_have_attribute("data-status", "done", timeout=180_000)
    runs = api.get(f"/projects/{pid}/runs").json()["data"]
    newest = max(runs, key=lambda r: r["number"])
    assert newest["id"] != first["id"] and newest["params"]["estimate_poses"] is True
    assert newest["status"] == "done" and newest["fix_setting"] is None
    expect(page.locator("#run-again-button")).to_have_count(0)
    assert errors == []
