"""The dataset check and the run log in a real Chromium against a real server.

A 3-frame street with one camera image deleted: the create form shows the check of the picked folder, a
folder without calib.txt is refused with the file named, the created project's page shows the warning
with its fix, and after a run the stage list says "skipped (3D-CN disabled)" and the run's log holds the
labeler's warning about the frame without an image and the skipped stage.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import browserfixtures
import pytest

FRAMES = 3

artifacts, browser = browserfixtures.artifacts, browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    from serverproc import Server, make_small_street

    data = tmp_path_factory.mktemp("check") / "data"
    dataset = make_small_street(data / "street", FRAMES)
    (dataset / "image_2" / "000001.png").unlink()
    no_calib = data / "nocalib" / "sequences" / "00"
    shutil.copytree(dataset, no_calib)
    (no_calib / "calib.txt").unlink()
    srv = Server(data, extra_env={"LEAP_PREWARM_WORKERS": "false"}).start()
    yield srv, dataset, no_calib
    srv.stop()


def test_check_at_creation_and_the_run_log(server, browser, artifacts: Path) -> None:
    from playwright.sync_api import expect

    srv, dataset, no_calib = server
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(srv.base + "/")
    expect(page.locator("#create-form")).to_be_visible()

    # A folder the pipeline cannot run on: the form shows why before and after "Create project".
    page.fill("#new-name", "broken")
    page.select_option("#new-dataset", str(no_calib))
    summary = page.locator("#new-dataset-check")
    expect(summary).to_have_attribute("data-verdict", "none")
    expect(summary.locator('.check-finding[data-code="calib_missing"]')).to_contain_text("calib.txt")
    page.click("#create-project")
    expect(page.locator("#create-form .error")).to_contain_text(f"{no_calib / 'calib.txt'}")
    expect(page.locator("#create-form .error")).to_contain_text("cannot run on this dataset")

    # The street with a frame without its camera image: created, with the warning and its fix.
    page.fill("#new-name", "street")
    page.select_option("#new-dataset", str(dataset))
    expect(summary.locator('.check-finding[data-code="images_partial"]')).to_contain_text("000001")
    page.click("#create-project")
    expect(page.locator("#project-name")).to_have_text("street")
    card = page.locator("#dataset-check")
    expect(card).to_be_visible()
    finding = card.locator('.check-finding[data-code="images_partial"]')
    expect(finding).to_contain_text("000001")
    expect(finding.locator(".check-fix")).to_contain_text("add the missing images")
    assert "--" not in finding.inner_text()
    page.screenshot(path=str(artifacts / "dataset-check-project.png"))

    # Run: the skipped stage says why; the run's log has the labeler's warning and the skip.
    page.click("#run-button")
    expect(page.locator("#run-status")).to_have_attribute("data-status", "done", timeout=180_000)
    skipped = page.locator('.stage[data-stage="00/3dcn"]')
    expect(skipped).to_have_attribute("data-status", "skipped")
    expect(skipped.locator(".stage-detail")).to_have_text("skipped (3D-CN disabled)")
    expect(page.locator("#run-panel .run-warnings")).to_contain_text("have no camera image")
    page.locator("#runs button", has_text="Log").first.click()
    log = page.locator("#runs pre.log")
    expect(log).to_contain_text("stage 00/3dcn skipped (3D-CN disabled)")
    expect(log).to_contain_text("1 of 3 frames have no camera image")
    page.screenshot(path=str(artifacts / "dataset-check-run.png"))
    assert not errors, errors
