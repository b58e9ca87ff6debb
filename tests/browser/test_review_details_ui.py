"""Details of reviewing in a real browser, on the demo street (19 classes) through the real app: number keys
reach classes past the ninth, the panel's box button arms the one box tool (the Tool dropdown shows it), a
shortcut works after a pick from a panel dropdown, the corrections list jumps to a correction in the viewer,
an apply that changed no scan says so, a long project name stays inside the page, a 422 reads as a
field-named sentence, and a conflict names the run by its number."""

from __future__ import annotations

from typing import Any

import browserfixtures
import numpy as np
import pytest

wait_until = browserfixtures.wait_until

pytestmark = [pytest.mark.browser, pytest.mark.slow]

FRAMES = 6


@pytest.fixture(scope="module")
def demo_app(tmp_path_factory: pytest.TempPathFactory) -> Any:
    with browserfixtures.running_app(tmp_path_factory.mktemp("review-details"), FRAMES) as app:
        yield app


def _corrections(api: Any, pid: int) -> list[dict[str, Any]]:
    return list(api.get(f"/projects/{pid}/corrections").json()["corrections"])


def test_review_details(demo_app: dict[str, Any]) -> None:
    import httpx

    from app import crud
    from app.core.db import open_db
    from leap_core.fusion import voxel_keys

    base, app = demo_app["base"], demo_app["app"]
    api = httpx.Client(base_url=f"{base}/api/v1", timeout=30)
    project = wait_until(
        lambda: next((p for p in api.get("/projects").json()["data"] if p["is_demo"]), None), 30, "the demo"
    )
    pid = project["id"]
    run = wait_until(
        lambda: (
            (r := api.get(f"/projects/{pid}/runs").json()["data"])
            and r[0]["status"] in ("done", "failed")
            and r[0]
        ),
        600,
        "the first run",
    )
    assert run["status"] == "done", run.get("error")
    opened = api.post(f"/projects/{pid}/viewer")
    assert opened.status_code == 200, opened.text
    session = app.state.viewers.get(pid)
    with browserfixtures.launch_chromium() as browser:
        page = browserfixtures.open_viewer(browser, base + opened.json()["url"], project["name"], session)
        page.locator("#leap-review").wait_for(state="attached", timeout=30_000)  # the page's keys are bound
        names = session.class_names()
        assert len(names) >= 12

        # The Corrections folder's box button arms the Selection tools' box: the Tool dropdown shows it.
        page.get_by_text("Corrections", exact=True).click()
        page.get_by_role("button", name="Select box").click()
        # The button's callback sets the tool, the dropdown and the scene one after the other: wait for all.
        wait_until(
            lambda: (
                session.tools.settings.tool == "box"
                and session.panel.tools.tool.value == "box"
                and session.scene.rect_select_armed
            ),
            10,
            "the box tool armed and shown in the Tool dropdown",
        )

        # "1" then "2": the twelfth class; "0": the tenth.
        assert browserfixtures.box_select_centre(page, session) > 0
        page.keyboard.press("1")
        page.keyboard.press("2")
        wait_until(lambda: len(_corrections(api, pid)) == 1, 20, "the first correction")
        assert _corrections(api, pid)[0]["class_name"] == names[11]
        assert browserfixtures.box_select_centre(page, session) > 0
        page.keyboard.press("0")
        wait_until(lambda: len(_corrections(api, pid)) == 2, 20, "the second correction")
        assert max(_corrections(api, pid), key=lambda c: c["id"])["class_name"] == names[9]

        # A pick from a panel dropdown leaves the shortcuts working (and colours the map by disagreement).
        browserfixtures.pick(page, "Color by", "camera vs final disagreement")
        wait_until(lambda: session.state.mode == "disagreement", 10, "the disagreement view")
        page.keyboard.press("?")
        page.locator("#leap-shortcuts").wait_for(timeout=10_000)
        page.keyboard.press("?")

        # The project page: each correction has "Show in 3D", which opens the viewer with it selected.
        project_page = browser.new_page(viewport={"width": 1280, "height": 900})
        project_page.goto(f"{base}/#/projects/{pid}")
        first = _corrections(api, pid)[0]
        button = project_page.get_by_role("button", name=f"Show correction {first['id']} in 3D")
        with project_page.expect_popup() as popup:
            button.click()
        popup.value.wait_for_load_state()
        # The jump opens a viewer tab of its own, with its own selection: the tab opened last.
        shown = wait_until(
            lambda: (s := app.state.viewers.get(pid)) is not session and s.grid is not None and s,
            30,
            "the tab",
        )
        grid = shown.grid
        with open_db(demo_app["settings"].database) as db:
            stored = next(c for c in crud.list_corrections(db, pid) if c.id == first["id"])
        rows = np.unique(grid.rows_of(stored.keys))
        wait_until(lambda: shown.tools.selection.rows.size == rows[rows >= 0].size, 20, "the jump")
        np.testing.assert_array_equal(shown.tools.selection.rows, rows[rows >= 0])

        # A correction of a voxel no scan holds: the apply job changes no scan and says so.
        far = int(voxel_keys(np.array([[4000.0, 4000.0, 40.0]]), grid.voxel_size)[0])
        r = api.post(
            f"/projects/{pid}/corrections",
            json={"class_name": names[0], "voxel_size": grid.voxel_size, "keys": [far]},
        )
        assert r.status_code == 201, r.text
        applied = project_page.locator("#corrections-apply")
        wait_until(lambda: "up to date" in applied.inner_text(), 60, "the apply job's answer")
        assert "0 scans" not in applied.inner_text()

        # A long project name wraps in the head instead of widening the page.
        long_name = "WideName" * 15  # 120 characters and nowhere to break a line
        r = api.post(
            "/projects",
            json={"name": long_name, "dataset": {"kind": "folder", "path": project["dataset"]["path"]}},
        )
        assert r.status_code == 201, r.text
        other = r.json()["id"]
        project_page.goto(f"{base}/#/projects/{other}")
        project_page.locator("#project-name", has_text=long_name).wait_for(timeout=10_000)
        widths = project_page.evaluate(
            "() => [document.documentElement.scrollWidth, window.innerWidth,"
            " document.getElementById('project-name').getBoundingClientRect().right]"
        )
        assert widths[0] <= widths[1] and widths[2] <= widths[1], widths

        # A validation error reads as a sentence naming the field.
        message = project_page.evaluate(
            """async () => {
                const { post } = await import("/api.js");
                try { await post("/projects", { name: "", dataset: { kind: "demo" } }); return "accepted"; }
                catch (err) { return err.message; }
            }"""
        )
        assert message == "name: must not be empty"

        # A conflict names the run by its number (the project's first run has another database id).
        started = api.post(f"/projects/{other}/runs", json={})
        assert started.status_code == 202, started.text
        run_id = started.json()["id"]
        assert run_id != 1
        again = api.post(f"/projects/{other}/runs", json={})
        assert again.status_code == 409 and f"already has run 1 (id {run_id})" in again.json()["detail"]
        api.post(f"/runs/{run_id}/cancel")
