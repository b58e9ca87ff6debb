"""A dataset path typed into the create form is checked before *Create project*, in a real Chromium against
a real server: a sequence folder too deep for the picker's list shows its check summary, a folder outside
the data roots shows the refusal with the roots, and the project is then created on the typed folder."""

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
    from serverproc import Server, make_small_street

    data = tmp_path_factory.mktemp("typed") / "data"
    street = make_small_street(tmp_path_factory.mktemp("street"), 2)
    # Deeper than the picker looks (services.find_datasets' max_depth), so only typing reaches it.
    deep = data / "a" / "b" / "c" / "d" / "street" / "sequences" / "00"
    shutil.copytree(street, deep)
    (deep / "image_2" / "000001.png").unlink()
    srv = Server(data, extra_env={"LEAP_PREWARM_WORKERS": "false"}).start()
    yield srv, data, deep
    srv.stop()


def test_a_typed_path_is_checked_before_create(server, browser, artifacts: Path) -> None:
    from playwright.sync_api import expect

    srv, data, deep = server
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(srv.base + "/")
    expect(page.locator("#create-form")).to_be_visible()
    expect(page.locator(f'#new-dataset option[value="{deep}"]')).to_have_count(0)

    page.fill("#new-name", "typed")
    page.fill("#new-path", "/etc")
    refused = page.locator("#new-dataset-refused")
    expect(refused).to_contain_text("outside")
    expect(refused).to_contain_text(str(data))

    page.fill("#new-path", str(deep))
    summary = page.locator("#new-dataset-check")
    expect(summary).to_contain_text("2 frames")
    expect(summary.locator('.check-finding[data-code="images_partial"]')).to_contain_text("000001")
    expect(refused).to_have_count(0)
    page.screenshot(path=str(artifacts / "typed-path-check.png"))

    page.click("#create-project")
    expect(page.locator("#project-name")).to_have_text("typed")
    assert not errors, errors


def test_a_class_list_file_is_checked_on_pick_and_a_projects_list_downloads(
    server, browser, tmp_path: Path
) -> None:
    """Upload: a bad file is refused on pick naming its field; a good one shows its classes and the project
    gets them. Download: the project page's link gives a file the upload takes back."""
    import httpx
    from playwright.sync_api import expect

    srv, _data, deep = server
    bad = tmp_path / "bad.yaml"
    bad.write_text("classes:\n  - {name: car, color: [1, 2, 3], prompts: [], export_id: 10}\n")
    good = tmp_path / "good.yaml"
    good.write_text(
        "name: yard\nclasses:\n"
        "  - {name: crate, color: [200, 120, 40], prompts: [crate, wooden box], export_id: 1}\n"
        "  - {name: ground, color: [90, 90, 90], prompts: [ground], export_id: 2}\n"
    )
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(srv.base + "/")
    expect(page.locator("#create-form")).to_be_visible()
    page.fill("#new-name", "yard")
    page.fill("#new-path", str(deep))
    page.select_option("#new-preset", "__upload__")
    hint = page.locator("#new-preset-classes")
    page.set_input_files("#new-class-file", str(bad))
    expect(hint).to_contain_text("classes[0].prompts")
    page.set_input_files("#new-class-file", str(good))
    expect(hint).to_have_text("yard: crate, ground")
    page.click("#create-project")
    expect(page.locator("#project-name")).to_have_text("yard")

    link = page.locator("#download-classes")
    expect(link).to_be_visible()
    href = link.get_attribute("href")
    assert href is not None
    text = httpx.get(srv.base + href if href.startswith("/") else href, timeout=30).text
    assert "crate" in text and "wooden box" in text and "ground" in text
    again = tmp_path / "again.yaml"
    again.write_text(text)
    page.goto(srv.base + "/")
    page.select_option("#new-preset", "__upload__")
    page.set_input_files("#new-class-file", str(again))
    expect(page.locator("#new-preset-classes")).to_contain_text("crate, ground")
    assert not errors, errors
