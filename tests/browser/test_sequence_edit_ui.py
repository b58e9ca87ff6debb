"""Editing a project's sequences in a real Chromium against a real server on 127.0.0.1: the Sequences card
adds a folder (a refused one shows the server's reason), the dataset check card then reports each
sequence, and a sequence is removed after a confirmation (dismissing it keeps the sequence). Folder
names are shown literally."""

from __future__ import annotations

import shutil
import sys
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

    base = tmp_path_factory.mktemp("seqedit-ui")
    data = base / "data"
    folders = []
    # The second folder's path holds markup and has no poses.txt (a warning of its own dataset check).
    for i, parent in enumerate(("kitti", "<i>odd</i>")):
        seq = build_tiny_sequence(base / f"build{i}", n_frames=4 - i, n_points=400, seed=i)
        add_gt2d(seq.root, seq.frame_ids, (48, 64))
        target = data / parent / "sequences" / f"{i:02d}"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(seq.root, target)
        folders.append(target)
    (folders[1] / "poses.txt").unlink()
    srv = Server(data).start()
    yield srv, data, folders
    srv.stop()


def test_add_and_remove_a_sequence(server, browser, artifacts: Path) -> None:
    import httpx
    from playwright.sync_api import expect

    srv, data, folders = server
    api = f"{srv.base}/api/v1"
    body = {"name": "edit", "dataset": {"kind": "folder", "path": str(folders[0])}}
    r = httpx.post(f"{api}/projects", json=body)
    assert r.status_code == 201, r.text
    pid = r.json()["id"]
    page = browser.new_page(viewport={"width": 1440, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    browserfixtures.echo_console(page)
    page.goto(f"{srv.base}/#/projects/{pid}")

    card = page.locator("#sequences")
    items = card.locator("#sequence-list li")
    expect(items).to_have_count(1, timeout=60_000)
    expect(card.locator("button.sequence-remove")).to_be_disabled()  # the last sequence stays
    expect(page.locator("#dataset-check")).to_be_hidden()

    # A folder outside the data roots: the server's reason shows, nothing is added.
    page.fill("#sequence-path", str(data.parent))
    page.click("#sequence-add")
    expect(page.locator("#sequence-error")).to_contain_text("outside the allowed data roots")
    expect(items).to_have_count(1)

    page.fill("#sequence-path", str(folders[1]))
    page.fill("#sequence-name", "odd")
    page.click("#sequence-add")
    expect(items).to_have_count(2)
    assert [items.nth(i).get_attribute("data-sequence") for i in range(2)] == ["00", "odd"]
    expect(items.nth(1).locator("code")).to_have_text(str(folders[1]))  # the markup shown literally
    expect(items.nth(1)).to_contain_text("3 frames")
    assert page.locator("#sequence-list i").count() == 0
    # The dataset check card reports each sequence: 01's missing poses, 00's frames.
    checks = page.locator("#sequence-checks li.sequence-check")
    expect(checks).to_have_count(2)
    expect(checks.nth(0)).to_contain_text("4 frames")
    expect(checks.nth(1).locator('.check-finding[data-code="poses_missing"]')).to_contain_text("poses.txt")
    expect(page.locator("#sequences-line")).to_contain_text("2 sequences: 00, odd")
    assert [s["name"] for s in httpx.get(f"{api}/projects/{pid}").json()["sequences"]] == ["00", "odd"]
    page.screenshot(path=str(artifacts / "web_ui_sequence_edit.png"), full_page=True)

    # Remove 00: dismissing the confirmation keeps it, accepting removes it (its folder stays).
    page.once("dialog", lambda d: d.dismiss())
    card.locator('button.sequence-remove[data-sequence="00"]').click()
    expect(items).to_have_count(2)
    messages: list[str] = []
    page.once("dialog", lambda d: (messages.append(d.message), d.accept()))
    card.locator('button.sequence-remove[data-sequence="00"]').click()
    expect(items).to_have_count(1)
    assert "00" in messages[0] and "stay" in messages[0]
    assert items.nth(0).get_attribute("data-sequence") == "odd"
    expect(page.locator("#dataset-check")).to_contain_text("poses.txt")
    assert [s["name"] for s in httpx.get(f"{api}/projects/{pid}").json()["sequences"]] == ["odd"]
    assert (folders[0] / "velodyne").is_dir()
    assert errors == []
    page.close()
