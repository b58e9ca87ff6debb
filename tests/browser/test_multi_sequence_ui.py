"""A project of several sequences in a real Chromium against a real server on 127.0.0.1: created from the
form's "several sequence folders" list (one named there), its sequences listed on its page, a run over
both, the metrics card's sequence picker showing each sequence's figures, and the picker beside "Open 3D
viewer" opening the viewer on the sequence chosen."""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import browserfixtures
import pytest

artifacts, browser = browserfixtures.artifacts, browserfixtures.browser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    from appfixtures import add_gt2d
    from conftest import build_tiny_sequence
    from serverproc import Server

    base = tmp_path_factory.mktemp("multi-ui")
    data = base / "data"
    folders = []
    for i, n_frames in enumerate((4, 3)):
        seq = build_tiny_sequence(base / f"build{i}", n_frames=n_frames, n_points=400, seed=i)
        add_gt2d(seq.root, seq.frame_ids, (48, 64))
        target = data / "kitti" / "sequences" / f"{i:02d}"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(seq.root, target)
        folders.append(target)
    srv = Server(data).start()
    yield srv, folders
    srv.stop()


def test_sequences_in_the_form_metrics_and_viewer(server, browser, artifacts: Path) -> None:
    import httpx
    from playwright.sync_api import expect

    srv, folders = server
    api = f"{srv.base}/api/v1"
    page = browser.new_page(viewport={"width": 1440, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(srv.base + "/")

    # ---- create: the picker adds folders to the list while "several" is chosen; "name = folder" names one
    browserfixtures.echo_console(page)
    expect(page.locator("#create-form")).to_be_visible(timeout=60_000)
    page.fill("#new-name", "Two <b>streets</b>")
    page.check("#kind-several")
    page.fill("#new-paths", f"city = {folders[0]}")
    page.select_option("#new-dataset", str(folders[1]))
    assert page.input_value("#new-paths").splitlines() == [f"city = {folders[0]}", str(folders[1])]
    page.click("#create-project")
    expect(page.locator("#project-name")).to_have_text("Two <b>streets</b>")  # shown literally
    items = page.locator("#sequence-list li")
    expect(items).to_have_count(2)
    assert [items.nth(i).get_attribute("data-sequence") for i in range(2)] == ["city", "01"]
    expect(items.nth(1)).to_contain_text("3 frames")
    pid = int(page.url.rsplit("/", 1)[-1])

    # ---- a run over both sequences: the run panel shows each sequence's stages
    page.click("#run-button")
    deadline = time.monotonic() + 300
    while True:
        runs = httpx.get(f"{api}/projects/{pid}/runs").json()["data"]
        if runs and runs[0]["status"] not in ("queued", "running"):
            break
        assert time.monotonic() < deadline, "the run did not end"
        time.sleep(0.5)
    run = runs[0]
    assert run["status"] == "done", run["error"]
    fuse = page.locator('#run-panel li.stage[data-stage="01/fuse"] .stage-name')
    expect(fuse).to_have_text("01 · Voxel fusion", timeout=30_000)

    # ---- metrics: overall by default, one sequence's figures through the picker
    picker = page.locator("#metrics-sequence")
    expect(picker).to_be_visible(timeout=30_000)
    assert picker.locator("option").all_inner_texts() == ["overall", "city", "01"]
    expect(page.locator("#metrics-headline")).to_contain_text("overall")
    for name in ("01", "city"):
        miou = httpx.get(f"{api}/runs/{run['id']}/metrics", params={"sequence": name}).json()["metrics"][
            "protocols"
        ]["camera"]["voxel"]["miou"]
        picker.select_option(name)
        expect(page.locator("#metrics-headline")).to_contain_text(f"sequence {name}")
        expect(page.locator("#metrics-headline")).to_contain_text(f"camera view mIoU {100 * miou:.1f} %")
    overall = httpx.get(f"{api}/runs/{run['id']}/metrics").json()["metrics"]["protocols"]["camera"]["voxel"]
    page.locator("#metrics-sequence").select_option("")
    headline = page.locator("#metrics-headline")
    expect(headline).to_contain_text(f"camera view mIoU {100 * overall['miou']:.1f} %")

    page.screenshot(path=str(artifacts / "web_ui_multi_sequence.png"), full_page=True)

    # ---- the viewer opens the sequence picked beside its button
    seq_select = page.locator("#viewer-sequence")
    assert seq_select.locator("option").all_inner_texts() == ["city", "01"]
    seq_select.select_option("01")
    # The review progress shown is the picked sequence's (marks are per sequence).
    expect(page.locator("#review-progress h2")).to_have_text("Review progress · 01")
    with page.context.expect_page() as popup_info:
        page.click("#viewer-button")
    popup = popup_info.value
    viewer = browserfixtures.wait_until(
        lambda: (r := httpx.get(f"{api}/projects/{pid}/viewer")).status_code == 200 and r.json(),
        60,
        "the viewer to start",
    )
    assert viewer["sequence"] == "01" and viewer["run_id"] == run["id"]
    popup.close()
    assert errors == []
    page.close()
