"""The project page's LiDAR-only models in a real browser against a real server: train a model from the page
(a few steps on a 4-frame sequence's finished run), see it listed with its card, label the sequence with
it and download the labels."""

from __future__ import annotations

import io
import sys
import zipfile
from pathlib import Path

import browserfixtures
import numpy as np
import pytest

browser = browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]

FRAMES = 4


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    import httpx
    from appfixtures import add_gt2d
    from apphelpers import wait_run
    from conftest import build_tiny_sequence
    from serverproc import Server

    data = tmp_path_factory.mktemp("models-ui") / "data"
    seq = build_tiny_sequence(data / "kitti", n_frames=FRAMES, n_points=400)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    srv = Server(data).start()
    try:
        with httpx.Client(base_url=f"{srv.base}/api/v1", timeout=30) as c:
            p = c.post(
                "/projects", json={"name": "Models <b>", "dataset": {"kind": "folder", "path": str(seq.root)}}
            )
            assert p.status_code == 201, p.text
            run = c.post(f"/projects/{p.json()['id']}/runs", json={}).json()
            assert wait_run(c, run["id"], api="")["status"] == "done"
        yield srv, p.json()["id"]
    finally:
        srv.stop()


def test_train_from_the_project_page_then_label_a_sequence_with_the_model(server, browser, tmp_path) -> None:
    import httpx
    from playwright.sync_api import expect

    srv, project_id = server
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{srv.base}/#/projects/{project_id}")
    card = page.locator("#lidar-models")
    expect(card).to_be_visible()
    card.locator("#model-name").fill("tiny <i>model")
    card.locator("#model-steps").fill("3")
    card.locator("#model-points").fill("256")
    card.locator("#model-val-block").fill("1")
    card.locator("#model-val-every").fill("2")
    card.locator("#train-model").click()

    job = card.locator('.model-job[data-kind="train"]')
    expect(job).to_have_attribute("data-status", "done", timeout=60_000)
    expect(job.locator(".job-count")).to_have_text(" 3/3")
    model = card.locator(".model-card")
    expect(model).to_have_count(1)
    # The user's text is shown as text, never parsed as HTML.
    expect(model.locator(".model-title")).to_have_text("tiny <i>model")
    expect(model.locator(".model-title i")).to_have_count(0)
    with httpx.Client(base_url=f"{srv.base}/api/v1") as api:
        classes = api.get(f"/projects/{project_id}/classes").json()["data"]
        card_data = api.get(f"/projects/{project_id}/models").json()["data"][0]["card"]
    rows = model.locator(".model-classes tbody tr")
    expect(rows).to_have_count(len(classes))
    first = classes[0]
    row = model.locator(f'.model-classes tr[data-cls="{first["name"]}"] td')
    expect(row.nth(1)).to_have_text(str(first["export_id"]))
    iou = card_data["validation"]["iou"][first["name"]]
    expect(row.nth(3)).to_have_text("\u2013" if iou is None else f"{100 * iou:.1f}")
    expect(model.locator(".model-miou")).to_contain_text("Validation mIoU")
    expect(model.locator(".model-data")).to_contain_text("Trained on 2 scans, validated on 2")

    model.locator(".label-sequence").select_option("00")
    model.locator(".label-with-model").click()
    labeling = card.locator('.model-job[data-kind="label"]')
    expect(labeling).to_have_attribute("data-status", "done", timeout=60_000)
    with page.expect_download() as info:
        labeling.locator(".download-labels").click()
    target = tmp_path / "labels.zip"
    info.value.save_as(target)
    export_ids = {c["export_id"] for c in classes}
    with zipfile.ZipFile(io.BytesIO(target.read_bytes())) as zf:
        labels = sorted(n for n in zf.namelist() if n.endswith(".label"))
        assert labels == [f"sequences/00/predictions/{i:06d}.label" for i in range(FRAMES)]
        raw = np.frombuffer(zf.read(labels[0]), np.uint32) & 0xFFFF
        assert raw.size == 400 and set(raw.tolist()) <= export_ids
        assert "model-card.json" in zf.namelist()
    assert errors == []
