"""The export dialog in a real Chromium against a real server: it states how many points stay unlabeled and
why, and writes into the dataset's predictions/ only after a confirmation, a second one (naming how many
files) when the folder already holds files."""

from __future__ import annotations

import sys
from pathlib import Path

import browserfixtures
import numpy as np
import pytest

FRAMES = 4

artifacts, browser = browserfixtures.artifacts, browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory):
    from appfixtures import add_gt2d
    from apphelpers import wait_run
    from conftest import build_tiny_sequence
    from serverproc import Server

    data = tmp_path_factory.mktemp("export-ui") / "data"
    seq = build_tiny_sequence(data / "kitti", n_frames=FRAMES, n_points=400)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    srv = Server(data).start()
    try:
        with srv.client() as c:
            project = c.post(
                "/projects", json={"name": "tiny", "dataset": {"kind": "folder", "path": str(seq.root)}}
            )
            run = c.post(f"/projects/{project.json()['id']}/runs", json={}).json()
            assert wait_run(c, run["id"], api="")["status"] == "done"
            info = c.get(f"/runs/{run['id']}/export").json()
        yield srv, seq.root, project.json()["id"], info
    finally:
        srv.stop()


def test_export_dialog_counts_and_confirmations(finished_run, browser, artifacts: Path) -> None:
    from playwright.sync_api import expect

    srv, dataset, project_id, info = finished_run
    predictions = dataset / "predictions"
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("dialog", lambda d: errors.append(f"unexpected native dialog: {d.message}"))
    page.goto(f"{srv.base}/#/projects/{project_id}")

    page.locator('button[data-action="export"]').first.click()
    dialog = page.locator("dialog.export-dialog")
    expect(dialog).to_be_visible()
    # The counts and reasons come from the run: the same numbers the API reports.
    expect(dialog.locator(".unlabeled-count")).to_have_text(f"{info['unlabeled']:,}")
    expect(dialog.locator(".labeled-count")).to_have_text(f"{info['labeled']:,}")
    for reason in info["reasons"]:
        expect(dialog.locator(f'li[data-reason="{reason["key"]}"] .reason-count')).to_have_text(
            f"{reason['points']:,}"
        )
    assert info["reasons"][0]["points"] > 0
    expect(dialog.locator('li[data-reason="outside_view"]')).to_contain_text("outside every camera view")
    expect(dialog.locator(".threshold-note")).to_contain_text("No confidence threshold")
    # Where the labels came from, as the zip's summary.yaml records it.
    provenance = dialog.locator("details.provenance")
    provenance.locator("summary").click()
    expect(provenance.locator("li").first).to_have_text(info["provenance_lines"][0])
    expect(provenance).to_contain_text("labels: simulated labeler")
    expect(provenance).to_contain_text("corrections: none applied")

    # Writing asks first; Cancel writes nothing.
    dialog.locator('button[data-action="predictions"]').click()
    expect(dialog.locator(".confirm-text")).to_have_text(f"Write {FRAMES} files into {predictions}?")
    dialog.locator('button[data-action="cancel-write"]').click()
    assert not predictions.exists()
    dialog.locator('button[data-action="predictions"]').click()
    dialog.locator('button[data-action="confirm-write"]').click()
    expect(dialog.locator(".write-result")).to_contain_text(f"Wrote {FRAMES} files to {predictions}")
    assert sorted(p.name for p in predictions.iterdir()) == [f"{i:06d}.label" for i in range(FRAMES)]

    # Someone edits a prediction; a second write names how many files it would replace and keeps them
    # until that is confirmed.
    edited = predictions / "000000.label"
    edited.write_bytes(np.zeros(400, "<u4").tobytes())
    dialog.locator('button[data-action="close"]').click()
    expect(dialog).to_have_count(0)
    page.locator('button[data-action="export"]').first.click()
    dialog.locator('button[data-action="predictions"]').click()
    expect(dialog.locator(".confirm-text")).to_contain_text(f"already holds {FRAMES} files")
    expect(dialog.locator('button[data-action="confirm-write"]')).to_have_text(f"Replace {FRAMES} files")
    dialog.screenshot(path=str(artifacts / "export_dialog.png"))
    dialog.locator('button[data-action="cancel-write"]').click()
    assert edited.read_bytes() == np.zeros(400, "<u4").tobytes()
    dialog.locator('button[data-action="predictions"]').click()
    dialog.locator('button[data-action="confirm-write"]').click()
    expect(dialog.locator(".write-result")).to_contain_text(f"(replaced {FRAMES})")
    assert edited.read_bytes() != np.zeros(400, "<u4").tobytes()
    assert errors == []
    page.close()
