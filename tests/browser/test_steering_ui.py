"""Steering in a real Chromium against a real server: the parameters panel greys out what the chosen labeler
or a switched-off stage ignores, the next-run card says which stages the edits recompute, a class added for
the demo street's traffic cones (prompt "traffic cone", ground-truth id 300) gets a distinct colour and, after
a re-run, an IoU and a Δ in the metrics, and the comparison lists what changed. Screenshot in test-artifacts/.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import browserfixtures
import pytest

FRAMES = 4
CONE_ID = 300
NO_VALUE = "\u2013"  # the en dash the UI shows for a missing figure

artifacts, browser = browserfixtures.artifacts, browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    from serverproc import Server, make_small_street

    from leap_core.datasets.raw_ids import scan_raw_ids

    data = tmp_path_factory.mktemp("steer-ui") / "data"
    dataset = make_small_street(data / "street", FRAMES)
    # The demo street has traffic cones: raw id 300 in its 3D labels.
    assert scan_raw_ids(dataset).counts.get(CONE_ID, 0) > 0
    srv = Server(data).start()
    yield srv, dataset
    srv.stop()


def _wait_done(page, number: int) -> None:
    from playwright.sync_api import expect

    expect(page.locator("#run-panel h2")).to_have_text(f"Run {number}", timeout=60_000)
    expect(page.locator("#run-status")).to_have_attribute("data-status", "done", timeout=240_000)


def test_traffic_cones_get_an_iou_and_ignored_settings_are_greyed(server, browser, artifacts: Path) -> None:
    import httpx
    from playwright.sync_api import expect

    srv, dataset = server
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        r = api.post("/projects", json={"name": "Cones", "dataset": {"kind": "folder", "path": str(dataset)}})
        assert r.status_code == 201, r.text
        project = r.json()
    assert project["form"]["labeler"] == "simulated" and project["form"]["consistency"] is False
    page = browser.new_page(viewport={"width": 1440, "height": 1100})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("dialog", lambda d: d.accept())
    page.goto(f"{srv.base}/#/projects/{project['id']}")

    # ---- the parameters panel: the box threshold does nothing for the simulated labeler
    threshold = page.locator('#params [name="threshold"]')
    share = page.locator('#params [name="share"]')
    expect(threshold).to_be_disabled()
    expect(page.locator('#params label[data-param="threshold"] .param-note')).to_contain_text(
        "the simulated (from 2D ground truth) labeler ignores it"
    )
    expect(share).to_be_disabled()
    share_note = page.locator('#params label[data-param="share"] .param-note')
    expect(share_note).to_contain_text("3D-CN stage is off")
    for name in ("voxel_size", "k", "cluster_gap", "consistency", "labeler"):
        expect(page.locator(f'#params [name="{name}"]')).to_be_enabled()
    # Choices take effect before saving: another labeler or the 3D-CN ticked enables their settings.
    page.select_option('#params [name="labeler"]', "grounded-sam")
    expect(threshold).to_be_enabled()
    page.select_option('#params [name="labeler"]', "simulated")
    expect(threshold).to_be_disabled()
    page.check('#params [name="consistency"]')
    expect(share).to_be_enabled()
    page.uncheck('#params [name="consistency"]')
    expect(share).to_be_disabled()

    # ---- before the first run everything is computed; the run carries a note
    labels2d = page.locator('#recompute-plan li[data-stage="labels2d"]')
    expect(labels2d).to_have_attribute("data-action", "recompute")
    expect(page.locator('#recompute-plan li[data-stage="3dcn"]')).to_have_attribute("data-action", "off")
    page.fill("#run-note", "before cones")
    page.click("#run-button")
    _wait_done(page, 1)
    expect(page.locator("#next-summary")).to_contain_text("reuses every stage")
    expect(page.locator("#all-points-labeled")).to_contain_text("% of all points labeled")
    expect(page.locator('#class-table tr[data-class="traffic-cone"]')).to_have_count(0)

    # ---- the traffic cones are in the ground truth but no class maps them: offered
    expect(page.locator(f'.suggestion[data-raw-id="{CONE_ID}"]')).to_contain_text("traffic-cone")
    others = page.locator(".class-row .cls-color").evaluate_all("els => els.map(e => e.value)")
    suggested = page.locator("#new-class-color").input_value()
    assert suggested not in others and suggested != "#808080"

    # ---- add the class by hand: name, prompt, ground-truth id picked from the dataset's ids
    page.fill("#new-class-name", "traffic-cone")
    page.fill("#new-class-prompts", "traffic cone")
    expect(page.locator("#new-class-gt-summary")).to_have_text("Ground truth: none: not evaluated")
    page.select_option("#new-class-gt", [str(CONE_ID)])
    expect(page.locator("#new-class-gt-summary")).to_have_text("Ground truth: 300 traffic-cone")
    # The object fields: the API's field error beside them (a moving id equal to the export id), the typed
    # values kept; a stuff class sends no moving id.
    page.locator("#new-class-thing").check()
    page.fill("#new-class-moving", page.locator("#new-class-export").input_value())
    page.locator("form.add-class button[type=submit]").click()
    expect(page.locator("#new-class-object-error")).to_contain_text("equals export_id")
    expect(page.locator("#new-class-moving")).to_have_class(re.compile("invalid"))
    expect(page.locator("#new-class-name")).to_have_value("traffic-cone")
    page.locator("#new-class-thing").uncheck()
    expect(page.locator("#new-class-moving")).to_be_disabled()
    with page.expect_request(lambda r: r.method == "POST" and r.url.endswith("/classes")) as sent:
        page.locator("form.add-class button[type=submit]").click()
    body = sent.value.post_data_json
    assert body["thing"] is False and "moving_id" not in body, body
    cone = page.locator('.class-row[data-class="traffic-cone"]')
    expect(cone.locator(".gt-summary")).to_have_text("300 traffic-cone")
    expect(cone.locator(".prompt-text")).to_have_text(["traffic cone"])
    assert not cone.locator(".cls-thing").is_checked() and cone.locator(".cls-moving").input_value() == ""
    colour = cone.locator(".cls-color").input_value()
    assert colour == suggested  # the distinct colour it was offered, never the unlabeled grey
    expect(page.locator(f'.suggestion[data-raw-id="{CONE_ID}"]')).to_have_count(0)

    # ---- its ground-truth ids can be changed in place: "not evaluated", then 300 again
    cone.locator(".gt-edit").click()
    expect(cone.locator(".gt-select option:checked")).to_have_count(1)
    cone.locator(".gt-clear").click()
    expect(cone.locator(".gt-summary")).to_have_text("none: not evaluated")
    cone.locator(".gt-edit").click()
    cone.locator(".gt-select").select_option([str(CONE_ID)])
    cone.locator(".gt-save").click()
    expect(cone.locator(".gt-summary")).to_have_text("300 traffic-cone")

    # ---- the next run recomputes from the 2D labels on, and says what changed
    expect(labels2d).to_have_attribute("data-action", "recompute")
    expect(labels2d.locator(".plan-reason")).to_have_text("the classes or prompts changed")
    expect(page.locator("#pending-changes")).to_contain_text("class traffic-cone added")
    page.fill("#run-note", "traffic cones")
    page.click("#run-button")
    _wait_done(page, 2)
    expect(page.locator("#run-note")).to_have_value("")  # the started run took the note

    # ---- the cones have an IoU now; Δ against run 1 (where the class did not exist) is blank
    cell = page.locator('#class-table tr[data-class="traffic-cone"] td.iou')
    expect(cell).not_to_have_text(NO_VALUE)
    assert float(cell.inner_text()) > 0
    expect(page.locator('#class-table tr[data-class="traffic-cone"] td.delta')).to_have_text(NO_VALUE)
    expect(page.locator("#class-table thead th")).to_have_text(["Class", "#1 IoU", "#2 IoU", "Δ"])
    expect(page.locator("#run-changes")).to_contain_text(
        'class traffic-cone added (prompts "traffic cone"; ground-truth ids 300)'
    )
    expect(page.locator(".run-note-row")).to_have_count(2)
    expect(page.locator(".legend")).to_contain_text("“traffic cones”")
    expect(page.locator("#metrics-headline")).to_contain_text("Run 2")
    page.screenshot(path=str(artifacts / "web_ui_steering.png"), full_page=True)

    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        runs = api.get(f"/projects/{project['id']}/runs").json()["data"]
        metrics = api.get(f"/runs/{runs[0]['id']}/metrics").json()["metrics"]
    iou = metrics["protocols"]["camera"]["voxel"]["iou"]["traffic-cone"]
    assert iou is not None and iou > 0
    assert f"{100 * iou:.1f}" == cell.inner_text()
    assert [r["note"] for r in runs] == ["traffic cones", "before cones"]

    # ---- the paper's protocol: run 1 (SemanticKITTI's 19 classes) has it over Table 1's 11 classes; run 2
    # (with traffic-cone, a class the merge does not know) has a note instead
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        first = api.get(f"/runs/{runs[1]['id']}/metrics").json()["metrics"]
    manmade = first["protocols"]["paper"]["voxel"]["iou"]["manmade"]
    assert manmade is not None and "paper" not in metrics["protocols"]
    page.select_option("#protocol-select", "paper")
    expect(page.locator("#protocol-notes")).to_contain_text("does not know (traffic-cone)")
    expect(page.locator("#class-table tbody tr")).to_have_count(11)
    row = page.locator('#class-table tr[data-class="manmade"] td')
    expect(row.nth(1)).to_have_text(f"{100 * manmade:.1f}")  # run 1's column
    expect(row.nth(2)).to_have_text(NO_VALUE)  # run 2 has no paper protocol
    assert errors == []
    page.close()
