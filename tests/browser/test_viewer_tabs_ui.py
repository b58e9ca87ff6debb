"""A viewer per browser tab and reviewers who split the queue, in real Chromium pages against the real app.

One small street project (6 frames) serves the three tests: two viewer tabs browse scans apart while a
correction made in one shows in the other within 2 s, and a tab left alone then polls the server rarely
until it is used; a run started from the project page shows its progress in an open viewer, which loads it
when it ends; two reviewers (two browser profiles, so two localStorages) claim disjoint batches of the
review queue from the project page.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import browserfixtures
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

from test_viewer_review import LiveApp, _settings, _street_project

wait_until = browserfixtures.wait_until
FRAMES = 6

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """The app with one street project whose first run finished, and a headless Chromium."""
    import httpx
    from serverproc import make_small_street

    root = tmp_path_factory.mktemp("tabs-e2e")
    dataset = make_small_street(root / "data" / "street", FRAMES)
    live = LiveApp(_settings(root))
    try:
        api = httpx.Client(base_url=f"{live.base}/api/v1", timeout=30)
        pid = _street_project(api, dataset)
        with browserfixtures.launch_chromium() as browser:
            yield {"live": live, "api": api, "pid": pid, "browser": browser}
    finally:
        live.stop()


def _open_tab(street: dict[str, Any], context: Any = None, reviewer: str | None = None) -> tuple[Any, Any]:
    """A new viewer tab (its own session) in a new page; (page, session)."""
    live, api, pid = street["live"], street["api"], street["pid"]
    opened = api.post(f"/projects/{pid}/viewer", json={"reviewer": reviewer} if reviewer else {})
    assert opened.status_code == 200, opened.text
    body = opened.json()
    page = (context or street["browser"]).new_page(viewport={"width": 1280, "height": 800})
    browserfixtures.echo_console(page)
    page.goto(live.base + body["url"])
    page.get_by_text("Color by", exact=True).wait_for(timeout=60_000)
    alert = page.get_by_role("alert")
    if alert.count():
        alert.get_by_role("button").first.click()
    session = live.app.state.viewers.get(pid, body["tab"])
    assert session is not None
    wait_until(session.scene.clients, 30, "the tab's viser client")
    assert session.renderer.wait_drawn(30)
    page.locator("#leap-review").wait_for(state="attached", timeout=30_000)  # the page's keys are bound
    return page, session


def _polls_rarely_when_idle(page: Any) -> None:
    """The page, left alone, asks the server for its scan and tool state rarely (it polled every 0.8 s and
    0.4 s, for every open tab); a key brings the fast polling back."""
    polls: list[str] = []

    def on_request(request: Any) -> None:
        path = request.url.split("?")[0]
        if path.endswith(("/viewer/nav", "/viewer/tools")):
            polls.append(path.rsplit("/", 1)[1])

    page.wait_for_timeout(3_500)  # fast for 3 s after the last input (web/viewer/viewer-api.js)
    page.on("request", on_request)
    page.wait_for_timeout(2_000)  # polled every 0.8 s and 0.4 s: 7 requests
    idle = list(polls)
    assert len(idle) <= 2, idle
    page.bring_to_front()
    page.keyboard.press("Shift")
    page.wait_for_timeout(1_500)
    assert polls.count("tools") - idle.count("tools") >= 2, polls
    assert polls.count("nav") - idle.count("nav") >= 1, polls


def test_two_tabs_browse_apart_and_see_each_others_corrections(street: dict[str, Any]) -> None:
    from playwright.sync_api import expect

    from app import crud
    from app.core.db import open_db

    page_a, a = _open_tab(street, reviewer="ana")
    page_b, b = _open_tab(street)
    try:
        assert a is not b and a.grid is b.grid  # one copy of the run for both tabs
        start = a.player.frame_pos
        # Tab A steps forward two scans with its keys; tab B stays where it was.
        page_a.bring_to_front()
        page_a.evaluate("document.activeElement && document.activeElement.blur()")
        page_a.keyboard.press("ArrowRight")
        wait_until(lambda: a.player.frame_pos == start + 1, 20, "tab A's next scan")
        page_a.keyboard.press("ArrowRight")
        wait_until(lambda: a.player.frame_pos == start + 2, 20, "tab A's second step")
        page_b.bring_to_front()
        page_b.evaluate("document.activeElement && document.activeElement.blur()")
        page_b.keyboard.press("ArrowLeft")
        wait_until(lambda: b.player.frame_pos == start - 1, 20, "tab B's previous scan")
        assert a.player.frame_pos == start + 2

        # A correction in tab A (box select + Apply in its panel) shows in tab B's page within 2 s.
        page_b.get_by_text("Corrections", exact=True).click()
        expect(page_b.get_by_text("0 active corrections", exact=False)).to_be_visible(timeout=20_000)
        page_a.get_by_text("Corrections", exact=True).click()
        browserfixtures.pick(page_a, "Assign class", a.class_names()[0])
        selected = browserfixtures.box_select_centre(page_a, a)
        assert selected > 0
        page_a.get_by_text(f"{selected:,} voxels selected.").wait_for(timeout=20_000)
        page_a.get_by_role("button", name="Apply to selection").click()
        wait_until(lambda: a.corrections.correction_count() == 1, 20, "the correction in tab A")
        t0 = time.monotonic()
        expect(page_b.get_by_text("1 active correction ", exact=False)).to_be_visible(timeout=2_000)
        print(f"tab B showed tab A's correction {time.monotonic() - t0:.2f} s after tab A stored it")
        assert b.label is a.label and b.player.frame_pos == start - 1  # B kept its own scan
        # Tab A was opened for reviewer "ana": its panel says so, and the correction carries the name.
        expect(page_a.get_by_text("Reviewing as ana", exact=True)).to_be_visible(timeout=10_000)
        with open_db(street["live"].settings.database) as db:
            (correction,) = crud.list_corrections(db, street["pid"])
        assert correction.reviewer == "ana"
        _polls_rarely_when_idle(page_b)  # tab B, showing what A did, is left alone
    finally:
        page_a.close()
        page_b.close()


def test_a_run_started_on_the_project_page_reaches_an_open_viewer(street: dict[str, Any]) -> None:
    from playwright.sync_api import expect

    live, api, pid = street["live"], street["api"], street["pid"]
    page, session = _open_tab(street)
    project = street["browser"].new_page(viewport={"width": 1280, "height": 800})
    # What the tab's panel is told about runs (the real panel, watched): a run whose stages are mostly
    # reused can pass through "running" between two looks of the page.
    told: list[tuple[int, str]] = []
    panel_progress = session.panel.on_run_progress

    def on_run_progress(info: Any) -> None:
        told.append((info.run_id, info.status))
        panel_progress(info)

    session.panel.on_run_progress = on_run_progress
    try:
        shown = session.run
        assert shown is not None
        # New prompts for a class: the run relabels the images, so it is in progress for a while.
        edited = api.patch(f"/projects/{pid}/classes/car", json={"prompts": ["car", "automobile"]})
        assert edited.status_code == 200, edited.text
        project.goto(f"{live.base}/#/projects/{pid}")
        project.locator("#run-button").click()

        def started() -> dict[str, Any] | None:
            runs = api.get(f"/projects/{pid}/runs").json()["data"]
            return next((r for r in runs if r["id"] != shown.run_id and r["id"] > shown.run_id), None)

        run = wait_until(started, 30, "the run started on the project page")
        number, run_id = run["number"], run["id"]
        # The open viewer follows the run's progress, then loads it when it ends.
        wait_until(lambda: session.run is not None and session.run.run_id == run_id, 600, "the new run")
        assert any(r == run_id and status in ("queued", "running") for r, status in told), told
        expect(page.get_by_text(f"Run {number} (id {run_id})", exact=False)).to_be_visible(timeout=30_000)
        expect(page.get_by_text(f"Stay on run {number}", exact=True)).to_be_visible(timeout=10_000)
    finally:
        project.close()
        page.close()


def test_two_reviewers_claim_disjoint_batches(street: dict[str, Any]) -> None:
    from playwright.sync_api import expect

    from app import reviewers
    from app.core.db import open_db

    live, api, pid, browser = street["live"], street["api"], street["pid"], street["browser"]
    # A ranked queue to split: the least-confident queue of a viewer tab, saved to the project.
    page, session = _open_tab(street)
    tab = live.app.state.viewers.viewer(pid).tab_id(session)
    ranked = api.post(f"/projects/{pid}/viewer/review/queue?tab={tab}", json={"kind": "confidence"})
    assert ranked.status_code == 200, ranked.text
    total = ranked.json()["total"]
    assert total >= 2, "the street's queue must hold two batches"
    batch = total // 2
    page.close()

    held: dict[str, list[str]] = {}
    # Two browser profiles: each its own localStorage.
    contexts = [browser.new_context(viewport={"width": 1280, "height": 800}) for _ in range(2)]
    try:
        for context, name in zip(contexts, ("ana", "ben"), strict=True):
            p = context.new_page()
            browserfixtures.echo_console(p)
            p.goto(f"{live.base}/#/projects/{pid}")
            p.locator("#reviewer-name").fill(name)
            p.locator("#reviewer-name").press("Enter")
            p.locator("#reviewer-name").blur()
            p.locator("#claim-count").fill(str(batch))
            p.locator("#claim-button").click()
            expect(p.locator("#claim-message")).to_contain_text(f"You hold {batch} regions", timeout=20_000)
            row = p.locator(f'#reviewer-table tr[data-reviewer="{name}"] td.claimed')
            expect(row).to_have_text(str(batch), timeout=20_000)
            with open_db(live.settings.database) as db:
                claims = reviewers.active_claims(db, pid)
            held[name] = sorted(r for r, c in claims.items() if c.reviewer == name)
            # The name is kept in this browser: a reload fills it in again.
            p.reload()
            expect(p.locator("#reviewer-name")).to_have_value(name, timeout=20_000)
        assert len(held["ana"]) == len(held["ben"]) == batch and not set(held["ana"]) & set(held["ben"])
    finally:
        for context in contexts:
            context.close()
