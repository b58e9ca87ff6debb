"""The web UI in a real Chromium (Debian's, driven by Playwright) against a real server on 127.0.0.1.

Creates a project on a small generated street, edits a class's prompts, runs the pipeline while watching
the live progress, reads the metrics and downloads the exported labels. Screenshots go to test-artifacts/.
The stage labels and the parameter form come from ``GET /api/v1/pipeline``: the test relabels a stage and
a parameter in that answer and finds the new labels on the page.
"""

from __future__ import annotations

import io
import json
import re
import sys
import zipfile
from pathlib import Path

import browserfixtures
import numpy as np
import pytest
import yaml

FRAMES = 4

# The browser fixtures (this folder has no conftest.py; see browserfixtures), found by name here.
artifacts, browser = browserfixtures.artifacts, browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    from serverproc import Server, make_small_street

    data = tmp_path_factory.mktemp("ui") / "data"
    dataset = make_small_street(data / "street", FRAMES)
    srv = Server(data).start()
    yield srv, dataset
    srv.stop()


def test_create_edit_run_compare_and_download(server, browser, artifacts: Path, tmp_path: Path) -> None:
    import httpx
    from playwright.sync_api import expect

    srv, dataset = server
    page = browser.new_page(viewport={"width": 1440, "height": 1000}, accept_downloads=True)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))

    # The page must show the server's stage and parameter labels: change two in the answer it gets.
    served: list[dict] = []

    def relabel(route) -> None:
        body = route.fetch().json()
        for stage in body["stages"]:
            if stage["name"] == "smooth":
                stage["label"] = "Smoothing (served label)"
        for field in body["form"]:
            if field["name"] == "k":
                field["label"] = "Neighbours k (served label)"
        served.append(body)
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    page.route("**/api/v1/pipeline", relabel)
    page.goto(srv.base + "/")

    # ---- create a project on the dataset folder found in the data root
    expect(page.locator("#create-form")).to_be_visible()
    page.fill("#new-name", "Street <i>test</i>")
    page.select_option("#new-dataset", str(dataset))
    page.click("#create-project")
    expect(page.locator("#project-name")).to_have_text("Street <i>test</i>")  # shown literally
    assert page.locator("#project-name i").count() == 0

    # ---- edit the car class's prompts: add one, remove one
    car = page.locator('.class-row[data-class="car"]')
    car.locator(".prompt-add").fill("sedan")
    # A redraw of the list (the ground-truth ids arriving, another class's editor opening) keeps a prompt
    # being typed: it used to drop it, so a prompt typed while the page loaded was lost.
    gt_bicycle = page.locator('button[aria-label="Edit ground-truth ids of bicycle"]')
    gt_bicycle.click()
    expect(car.locator(".prompt-add")).to_have_value("sedan")
    gt_bicycle.click()
    car.locator(".prompt-add").press("Enter")
    expect(page.locator('.class-row[data-class="car"] .prompt-text', has_text="sedan")).to_be_visible()
    page.locator('.class-row[data-class="car"] button[aria-label="Remove prompt jeep"]').click()
    expect(page.locator('.class-row[data-class="car"] .prompt-text')).to_have_text(
        ["car", "automobile", "van", "sedan"]
    )
    project_id = int(page.url.rsplit("/", 1)[-1])
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        car_api = api.get(f"/projects/{project_id}/classes").json()["data"][0]
    assert car_api["name"] == "car" and car_api["prompts"] == ["car", "automobile", "van", "sedan"]

    # ---- user text with markup stays text
    page.fill("#new-class-name", "<img src=x onerror=window.__pwned=1>")
    page.fill("#new-class-prompts", "odd thing")
    page.locator("form.add-class button[type=submit]").click()
    expect(page.locator(".class-row .cls-name").last).to_have_value("<img src=x onerror=window.__pwned=1>")
    assert page.evaluate("window.__pwned") is None and page.locator(".class-list img").count() == 0

    # ---- run with live per-stage progress
    page.click("#run-button")
    expect(page.locator("#run-status")).to_have_attribute("data-status", "running", timeout=60_000)
    expect(page.locator(".stage")).to_have_count(10)
    expect(page.locator('.stage[data-stage="00/smooth"] .stage-name')).to_have_text(
        "Smoothing (served label)"
    )
    labels2d = next(s for s in served[0]["stages"] if s["name"] == "labels2d")
    expect(page.locator('.stage[data-stage="00/labels2d"] .stage-name')).to_have_text(labels2d["label"])
    expect(page.locator('.stage[data-stage="00/labels2d"] .stage-name')).to_have_attribute(
        "title", labels2d["description"]
    )
    expect(page.locator("#run-status")).to_have_attribute("data-status", "done", timeout=180_000)
    statuses = page.locator(".stage").evaluate_all("els => els.map(e => e.dataset.status)")
    assert set(statuses) <= {"done", "skipped"} and statuses.count("done") >= 6
    expect(page.locator("#run-percent")).to_have_text("100 %")

    # ---- metrics table and per-class IoU chart
    expect(page.locator("#metrics-table tbody tr")).to_have_count(3)  # point, voxel, objects
    one_run_bars = page.locator("#iou-chart svg rect[fill]:not(.swatch)").count()
    assert one_run_bars == 20  # one bar per class
    miou = page.locator('#metrics-table tr[data-row="voxel"] td.strong').inner_text()
    assert 0 < float(miou) <= 100
    # The object scores: PQ, MOS IoU and S_assoc as the run's metrics.json has them, in %.
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        run1 = max(api.get(f"/projects/{project_id}/runs").json()["data"], key=lambda r: r["id"])
        objects1 = api.get(f"/runs/{run1['id']}/metrics").json()["metrics"]["objects"]
    expect(page.locator("#object-table tbody tr")).to_have_count(7)
    # One sequence: its figures are the run's own, not an "overall" of several.
    expect(page.locator("#metrics-headline")).not_to_contain_text("overall")
    expect(page.locator("#object-scores-note")).to_have_count(0)
    expect(page.locator('#object-table tr[data-score="pq-camera"] td.score')).to_have_text(
        f"{100 * objects1['camera']['PQ']:.1f}"
    )
    s_assoc = objects1["motion"]["s_assoc"]
    expect(page.locator('#object-table tr[data-score="s-assoc"] td.score')).to_have_text(
        "\u2013" if s_assoc is None else f"{100 * s_assoc:.1f}"
    )

    # ---- a class's object fields: the thing flag and the moving id, saved at once; the preview follows
    def class_api(name: str) -> dict:
        with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
            return next(
                c for c in api.get(f"/projects/{project_id}/classes").json()["data"] if c["name"] == name
            )

    def saving(action) -> None:
        """Do ``action`` and wait for the class PATCH it sends to be answered."""
        with page.expect_response(lambda r: r.request.method == "PATCH" and "/classes/" in r.url):
            action()

    truck = page.locator('.class-row[data-class="truck"]')
    assert truck.locator(".cls-thing").is_checked() and truck.locator(".cls-moving").input_value() == "258"
    saving(truck.locator(".cls-thing").uncheck)
    expect(truck.locator(".cls-moving")).to_be_disabled()  # a stuff class has no moving id
    expect(page.locator(".editor-status")).to_have_text("Saved")
    assert (class_api("truck")["thing"], class_api("truck")["moving_id"]) == (False, None)
    plan = page.locator('#recompute-plan .plan-stage[data-stage="tracks"]')
    expect(plan).to_have_attribute("data-action", "recompute")
    expect(plan.locator(".plan-reason")).to_have_text("a class's thing flag or moving id changed")
    saving(truck.locator(".cls-thing").check)
    expect(truck.locator(".cls-moving")).to_be_enabled()
    truck.locator(".cls-moving").fill("258")
    saving(lambda: truck.locator(".cls-moving").press("Tab"))
    assert (class_api("truck")["thing"], class_api("truck")["moving_id"]) == (True, 258)
    # A moving id equal to the class's export id is refused: the message beside the field, the value kept.
    car = page.locator('.class-row[data-class="car"]')
    car.locator(".cls-moving").fill("10")
    saving(lambda: car.locator(".cls-moving").press("Tab"))
    expect(car.locator(".cls-object-error")).to_contain_text("equals export_id")
    expect(car.locator(".cls-moving")).to_have_class(re.compile("invalid"))
    expect(car.locator(".cls-moving")).to_have_value("10")
    assert class_api("car")["moving_id"] == 252
    car.locator(".cls-moving").fill("")
    saving(lambda: car.locator(".cls-moving").press("Tab"))
    expect(car.locator(".cls-object-error")).to_be_empty()
    expect(car.locator(".cls-moving")).to_have_value("")
    assert class_api("car")["moving_id"] is None

    # ---- change a parameter, run again, compare both runs side by side
    expect(page.locator('#params label[data-param="k"] > span')).to_have_text("Neighbours k (served label)")
    expect(page.locator("#params label[data-param]")).to_have_count(len(served[0]["form"]))
    page.fill('#params input[name="k"]', "0")
    page.click("#save-params")
    expect(page.locator('#params input[name="k"]')).to_have_class(re.compile("invalid"))
    expect(page.locator("#params .error")).to_contain_text("smoothing.k")
    page.fill('#params input[name="k"]', "4")
    page.click("#save-params")
    expect(page.locator("#params .error")).to_be_empty()
    page.click("#run-button")
    expect(page.locator("#run-panel h2")).to_have_text("Run 2")
    expect(page.locator("#run-status")).to_have_attribute("data-status", "done", timeout=180_000)
    expect(page.locator(".runs-table tbody tr[data-run-id]")).to_have_count(2)
    expect(page.locator("#metrics-table tbody tr")).to_have_count(6)  # 2 runs x (point, voxel, objects)
    # The object scores of both runs with their Δ, as the per-class IoU table.
    expect(page.locator("#object-table thead th")).to_have_count(4)
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        run2 = max(api.get(f"/projects/{project_id}/runs").json()["data"], key=lambda r: r["id"])
        objects2 = api.get(f"/runs/{run2['id']}/metrics").json()["metrics"]["objects"]
    delta = 100 * (objects2["camera"]["PQ"] - objects1["camera"]["PQ"])
    sign = "+" if delta > 0 else "−" if delta < 0 else "±"
    expect(page.locator('#object-table tr[data-score="pq-camera"] td.delta')).to_have_text(
        f"{sign}{abs(delta):.1f}"
    )
    expect(page.locator(".legend > span")).to_have_count(2)
    assert page.locator("#iou-chart svg rect[fill]:not(.swatch)").count() == 2 * one_run_bars
    page.screenshot(path=str(artifacts / "web_ui_project.png"), full_page=True)

    # ---- export download, from the export dialog
    page.locator('button[data-action="export"]').first.click()
    expect(page.locator("dialog.export-dialog .unlabeled-count")).to_be_visible()
    with page.expect_download() as info:
        page.locator('dialog.export-dialog a[data-action="zip"]').click()
    target = tmp_path / "labels.zip"
    info.value.save_as(target)
    frame_ids = sorted(p.stem for p in (dataset / "velodyne").glob("*.bin"))
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        classes = api.get(f"/projects/{project_id}/classes").json()["data"]
        # A moving thing's points carry its class's moving id.
        export_ids = {c["export_id"] for c in classes} | {c["moving_id"] for c in classes if c["moving_id"]}
    with zipfile.ZipFile(io.BytesIO(target.read_bytes())) as zf:
        members = [f"sequences/00/predictions/{f}.label" for f in frame_ids]
        assert sorted(zf.namelist()) == sorted([*members, "label-map.yaml", "summary.yaml"])
        labeled = 0
        for fid, member in zip(frame_ids, members, strict=True):
            labels = np.frombuffer(zf.read(member), dtype=np.uint32)
            n_points = (dataset / "velodyne" / f"{fid}.bin").stat().st_size // 16
            assert labels.shape == (n_points,)
            semantic = labels & 0xFFFF
            # Most points of a scan lie outside the camera view, and the simulated detector may miss the
            # road of a whole block of frames: a few per cent labeled is a real export, none is not.
            # The upper 16 bits hold a thing's track id; an unlabeled point belongs to no object.
            assert (labels[semantic == 0] >> 16 == 0).all() and (semantic > 0).mean() > 0.05
            assert set(np.unique(semantic).tolist()) <= export_ids | {0}
            labeled += int((semantic > 0).sum())
        summary = yaml.safe_load(zf.read("summary.yaml"))
    # The zip holds exactly the labels whose counts the export dialog showed.
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        info = api.get(f"/runs/{summary['run']['id']}/export").json()
    assert labeled == info["labeled"] == summary["counts"]["labeled"] > 0

    page.locator('dialog.export-dialog button[data-action="close"]').click()

    # ---- the project list shows the finished run
    page.goto(srv.base + "/#/")
    card = page.locator(f'.project-card[data-project-id="{project_id}"]')
    expect(card.locator(".chip.status-done")).to_be_visible()
    page.screenshot(path=str(artifacts / "web_ui_projects.png"), full_page=True)
    # Back to the project: the page is built again from the pipeline description it already has.
    card.click()
    expect(page.locator('.stage[data-stage="00/smooth"] .stage-name')).to_have_text(
        "Smoothing (served label)"
    )
    assert len(served) == 1  # fetched once per page load
    assert errors == []
    page.close()


def test_token_protected_server_asks_for_the_token(browser, tmp_path: Path) -> None:
    from playwright.sync_api import expect
    from serverproc import Server

    token = "browser-test-token-123"
    data = tmp_path / "data"
    data.mkdir()
    srv = Server(
        data, extra_env={"LEAP_ACCESS_TOKEN": token, "LEAP_PREWARM_WORKERS": "false"}
    ).start_with_token(token)
    try:
        page = browser.new_page()
        page.goto(srv.base + "/")
        expect(page.locator("#token-input")).to_be_visible()
        page.fill("#token-input", "not-the-token-at-all")
        page.locator("button[type=submit]").click()
        # Refused: asked again, and told so (waiting for the message also waits for the new form).
        expect(page.locator("#token-refused")).to_contain_text("refused that token")
        expect(page.locator("#token-input")).to_have_value("")
        page.fill("#token-input", token)
        page.locator("button[type=submit]").click()
        expect(page.locator("#create-form")).to_be_visible()
        # A link that carries the token works directly and the token leaves the address bar.
        fresh = browser.new_page()
        fresh.goto(f"{srv.base}/?token={token}#/")
        expect(fresh.locator("#create-form")).to_be_visible()
        assert "token=" not in fresh.url
        page.close()
        fresh.close()
    finally:
        srv.stop()


def test_create_form_offers_the_class_presets(server, browser) -> None:
    """The create form lists the shipped class presets (default: the SemanticKITTI classes); a project
    created with the farm drone preset has its classes, as many as the preset file holds."""
    import httpx
    from playwright.sync_api import expect

    from leap_core.presets import builtin_preset

    srv, dataset = server
    agri = builtin_preset("agri_uav").schema.names
    assert len(agri) == 7
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(srv.base + "/")
    picker = page.locator("#new-preset")
    expect(picker).to_have_value("semantickitti")
    expect(picker.locator("option")).to_contain_text(["agri_uav (7 classes)", "nuscenes (16 classes)"])
    page.fill("#new-name", "Farm")
    page.select_option("#new-dataset", str(dataset))
    picker.select_option("agri_uav")
    expect(page.locator("#new-preset-classes")).to_have_text(", ".join(agri))
    page.click("#create-project")
    expect(page.locator("#project-name")).to_have_text("Farm")
    expect(page.locator(".class-row")).to_have_count(len(agri))
    assert page.locator(".class-row").evaluate_all("rows => rows.map((r) => r.dataset.class)") == agri
    pid = int(page.url.rsplit("/", 1)[-1])
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        project = api.get(f"/projects/{pid}").json()
    assert project["schema_name"] == "agri_uav" and project["num_classes"] == len(agri)
    assert errors == []
