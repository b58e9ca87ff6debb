"""The review queue in a real browser: keys highlight a region, jump to the scan that saw it most, and
accept / skip marks survive a restart of the app on the same work folder.

The app runs in this process (uvicorn on a real port, like tests/browser/test_viewer.py) so the test can
check the scene the server sends: the focused region's voxels at full colour and every other voxel dimmed,
the scan slider on the best observing scan. It is then shut down (its viewers and job manager with it) and
a new app is started on the same work folder: only SQLite carries the marks across.
"""

from __future__ import annotations

import re
import sys
import threading
from pathlib import Path
from typing import Any

import browserfixtures
import numpy as np
import pytest

from app.viewer.render import blend_dim

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

artifacts = browserfixtures.artifacts
wait_until = browserfixtures.wait_until
FRAMES = 6

pytestmark = [pytest.mark.browser, pytest.mark.slow]


class LiveApp:
    """``create_app`` served by uvicorn in a thread; :meth:`stop` runs the app's shutdown. Unlike
    ``browserfixtures.running_app`` it seeds no demo and can be stopped and started again on one work dir."""

    def __init__(self, settings: Any) -> None:
        import uvicorn

        from app.main import create_app

        self.settings = settings
        self.app = create_app(settings)
        self.base = f"http://127.0.0.1:{settings.port}"
        self.server = uvicorn.Server(
            uvicorn.Config(self.app, host="127.0.0.1", port=settings.port, log_level="warning")
        )
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        wait_until(lambda: self.server.started, 30, "the app to start")

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(30)
        assert not self.thread.is_alive(), "the app did not shut down"


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from serverproc import make_small_street

    root = tmp_path_factory.mktemp("review-e2e")
    dataset = make_small_street(root / "data" / "street", FRAMES)
    return root, dataset


def _street_project(api: Any, dataset: Path) -> int:
    """A project on the street folder with its first run finished; its id."""
    r = api.post("/projects", json={"name": "Street", "dataset": {"kind": "folder", "path": str(dataset)}})
    assert r.status_code == 201, r.text
    pid = int(r.json()["id"])
    run = api.post(f"/projects/{pid}/runs", json={})
    assert run.status_code == 202, run.text
    done = wait_until(
        lambda: (x := api.get(f"/runs/{run.json()['id']}").json())["status"] in ("done", "failed") and x,
        300,
        "the first run",
    )
    assert done["status"] == "done", done.get("error")
    return pid


def _settings(root: Path) -> Any:
    from app.core.config import Settings

    return Settings(
        port=browserfixtures.free_port(), work_dir=root / "work", data_roots=[root / "data"], seed_demo=False
    )


def _open_viewer(page: Any, live: LiveApp, pid: int, api: Any) -> Any:
    opened = api.post(f"/projects/{pid}/viewer")
    assert opened.status_code == 200, opened.text
    page.goto(live.base + opened.json()["url"])
    page.get_by_text("Color by", exact=True).wait_for(timeout=60_000)
    session = live.app.state.viewers.get(pid)
    assert session is not None and session.renderer.wait_drawn(30)
    page.locator("#leap-review").wait_for(state="attached", timeout=30_000)  # review.js bound its keys
    return session


def test_review_queue_highlights_jumps_and_marks_survive_a_restart(
    workdir: tuple[Path, Path], artifacts: Path
) -> None:
    import httpx
    from playwright.sync_api import expect

    from app import crud
    from app.core.db import open_db
    from leap_core import review

    root, dataset = workdir
    live = LiveApp(_settings(root))
    try:
        api = httpx.Client(base_url=f"{live.base}/api/v1", timeout=30)
        pid = _street_project(api, dataset)

        with browserfixtures.launch_chromium() as browser:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            browserfixtures.echo_console(page)
            page.on("pageerror", lambda exc: print(f"[page error] {exc}"))
            session = _open_viewer(page, live, pid, api)
            grid = session.grid
            full = session.scene.voxels.handle.colors.copy()

            # n: rank the least-confident queue and focus its first region.
            page.get_by_text("Review queue", exact=True).click()
            page.evaluate("document.activeElement && document.activeElement.blur()")  # keys go to the page
            page.keyboard.press("n")
            badge = page.locator("#leap-review")
            expect(badge).to_contain_text(re.compile(r"0 / \d+ reviewed"), timeout=60_000)
            expect(badge).to_contain_text("region 1/")
            region = session.queue.focus
            assert region is not None and region is session.queue.regions[0] and region.rows.size > 0
            total = len(session.queue.regions)

            # Highlighted: the region's voxels keep their colours, every other voxel is dimmed.
            assert session.renderer.wait_drawn(30)
            colors = session.scene.voxels.handle.colors
            inside = np.isin(np.arange(grid.num_voxels), region.rows)
            np.testing.assert_array_equal(colors[inside], full[inside])
            np.testing.assert_array_equal(colors[~inside], blend_dim(full[~inside]))
            box = session.scene.review_box
            assert box is not None and box.visible

            # The scan slider jumped to the scan that observed the region most: every scan counted here,
            # nearest the region first (equal counts go to the nearer scan).
            out = session.outputs
            keys = grid.keys[region.rows]
            frames = np.asarray(out.frame_indices)
            near = review.nearest_scans(out.seq.poses[frames, :3, 3], region.centre, len(frames))
            counts = [out.region_observers(int(frames[i]), keys, grid.voxel_size) for i in near]
            found = review.best_observer([c[1] for c in counts], [c[0] for c in counts])
            assert found is not None and counts[found][1] > 0, "the region should be in some camera image"
            best = int(near[found])
            assert session.player.frame_pos == best
            fid = out.seq.frame_ids[out.frame_indices[best]]
            expect(page.get_by_text(f"Seen best in scan {fid}", exact=False)).to_be_visible(timeout=20_000)
            scan_info = page.get_by_text(re.compile(rf"Scan {fid} \({best + 1}/{FRAMES}\)"))
            expect(scan_info).to_be_visible(timeout=20_000)
            expect(badge).to_contain_text(f"scan {fid}")
            page.wait_for_timeout(2500)  # software WebGL draws the dimmed map
            page.screenshot(path=str(artifacts / "viewer-review-1-region.png"))

            # a accepts (and moves on), s skips; both land in SQLite.
            page.keyboard.press("a")
            expect(badge).to_contain_text(f"1 / {total} reviewed", timeout=30_000)
            expect(badge).to_contain_text("region 2/", timeout=30_000)
            page.keyboard.press("s")
            expect(badge).to_contain_text(f"1 / {total} reviewed, 1 skipped", timeout=30_000)
            accepted_id, skipped_id = session.queue.regions[0].id, session.queue.regions[1].id
            with open_db(live.settings.database) as db:
                marks = crud.list_review_marks(db, pid)
            assert marks[accepted_id].state == "accepted" and marks[skipped_id].state == "skipped"
            page.close()
    finally:
        live.stop()

    # A new app on the same work folder: the marks and the progress come back from SQLite.
    live = LiveApp(_settings(root))
    try:
        api = httpx.Client(base_url=f"{live.base}/api/v1", timeout=30)
        with browserfixtures.launch_chromium() as browser:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            browserfixtures.echo_console(page)
            page.goto(f"{live.base}/#/projects/{pid}")
            expect(page.locator("#review-progress")).to_contain_text(
                f"1 / {total} reviewed, 1 skipped", timeout=30_000
            )
            session = _open_viewer(page, live, pid, api)
            assert session.queue.regions == []  # nothing in memory: a fresh viewer
            page.keyboard.press("n")
            badge = page.locator("#leap-review")
            expect(badge).to_contain_text(f"1 / {total} reviewed, 1 skipped", timeout=60_000)
            expect(badge).to_contain_text(f"region 1/{total} (accepted")
            assert [session.queue.region_state(i) for i in (0, 1)] == ["accepted", "skipped"]
            assert (session.queue.regions[0].id, session.queue.regions[1].id) == (accepted_id, skipped_id)
            page.keyboard.press("n")
            expect(badge).to_contain_text(f"region 2/{total} (skipped", timeout=30_000)

            # r opens the class picker on the region; a class relabels it (a correction) and accepts it.
            page.keyboard.press("r")
            picker = page.locator("#leap-review-picker")
            expect(picker).to_contain_text(f"Relabel region 2 ({session.queue.regions[1].count} voxels) as")
            picker.get_by_role("button", name="building", exact=True).click()
            expect(badge).to_contain_text(f"2 / {total} reviewed", timeout=30_000)
            with open_db(live.settings.database) as db:
                (correction,) = crud.list_corrections(db, pid)
                assert crud.list_review_marks(db, pid)[skipped_id].state == "accepted"
            assert correction.class_name == "building"
            np.testing.assert_array_equal(correction.keys, session.grid.keys[session.queue.regions[1].rows])
            page.wait_for_timeout(1500)
            page.screenshot(path=str(artifacts / "viewer-review-2-after-restart.png"))
    finally:
        live.stop()


@pytest.fixture(scope="module")
def labelled_app(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """An app (in this process) with one labelled street project: ``(live, project id, api client, colours)``,
    colours holding the map's unfocused colours once a test has seen them."""
    import httpx
    from serverproc import make_small_street

    root = tmp_path_factory.mktemp("review-leave")
    dataset = make_small_street(root / "data" / "street", FRAMES)
    live = LiveApp(_settings(root))
    try:
        api = httpx.Client(base_url=f"{live.base}/api/v1", timeout=30)
        pid = _street_project(api, dataset)
        yield live, pid, api, {}
    finally:
        live.stop()


def _focus_a_region(page: Any, session: Any, full: np.ndarray) -> Any:
    """Press N and wait until the map is dimmed around the next region, its box shown."""
    from playwright.sync_api import expect

    page.evaluate("document.activeElement && document.activeElement.blur()")  # keys go to the page
    page.keyboard.press("n")
    badge = page.locator("#leap-review")
    expect(badge).to_contain_text(re.compile(r"region \d+/\d+"), timeout=60_000)
    expect(badge.get_by_role("button", name="Leave review (Esc)")).to_be_visible()
    region = session.queue.focus
    assert region is not None
    inside = np.isin(np.arange(session.grid.num_voxels), region.rows)
    wait_until(
        lambda: np.array_equal(session.scene.voxels.handle.colors[~inside], blend_dim(full[~inside])),
        30,
        "the map dimmed around the region",
    )
    assert session.scene.review_box is not None and session.scene.review_box.visible
    return region


def _wait_unfocused(page: Any, session: Any, full: np.ndarray, *, badge: bool = True) -> None:
    """The review is left: no focus, the whole map at full colour, no box (and no region in the badge,
    which follows the page's keys and buttons, not the panel's)."""
    from playwright.sync_api import expect

    wait_until(lambda: session.queue.focus is None, 30, "the focus to be cleared")
    wait_until(
        lambda: np.array_equal(session.scene.voxels.handle.colors, full), 30, "the map at full colour again"
    )
    box = session.scene.review_box
    assert box is None or not box.visible
    if badge:
        badge = page.locator("#leap-review")
        expect(badge).not_to_contain_text(re.compile(r"region \d+/\d+"), timeout=30_000)
        expect(badge.get_by_role("button", name="Leave review (Esc)")).to_have_count(0)


def _viewer_page(browser: Any, labelled: Any) -> tuple[Any, Any, np.ndarray]:
    """A viewer page on the labelled project, its session and the map's unfocused colours."""
    live, pid, api, colours = labelled
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    browserfixtures.echo_console(page)
    page.on("pageerror", lambda exc: print(f"[page error] {exc}"))
    session = _open_viewer(page, live, pid, api)
    if "full" not in colours:
        # Read before anything was focused (a previous test's focus would be dimming the map).
        assert session.queue.focus is None and not session.queue.queue_built
        colours["full"] = session.scene.voxels.handle.colors.copy()
    return page, session, colours["full"]


def test_esc_leaves_the_review(labelled_app: Any, artifacts: Path) -> None:
    from playwright.sync_api import expect

    _, pid, api, _ = labelled_app
    with browserfixtures.launch_chromium() as browser:
        page, session, full = _viewer_page(browser, labelled_app)
        first = _focus_a_region(page, session, full)
        page.keyboard.press("Escape")
        _wait_unfocused(page, session, full)
        page.screenshot(path=str(artifacts / "viewer-review-3-left.png"))

        # Leaving keeps the queue: N goes on with the next region, and a verdict needs a shown region.
        assert session.queue.regions and session.queue.regions[0] is first
        page.keyboard.press("Escape")
        gone = api.post(f"/projects/{pid}/viewer/review/mark", json={"state": "accepted"})
        assert gone.status_code == 409 and "press Next region" in gone.json()["detail"], gone.text
        page.keyboard.press("n")
        expect(page.locator("#leap-review")).to_contain_text("region 2/", timeout=60_000)
        page.close()


def test_leave_review_buttons_leave_the_review(labelled_app: Any) -> None:
    with browserfixtures.launch_chromium() as browser:
        page, session, full = _viewer_page(browser, labelled_app)
        # The badge's button on the page.
        _focus_a_region(page, session, full)
        page.get_by_role("button", name="Leave review (Esc)", exact=True).click()
        _wait_unfocused(page, session, full)

        # The panel's button in the "Review queue" folder.
        page.get_by_text("Review queue", exact=True).click()
        _focus_a_region(page, session, full)
        page.get_by_role("button", name="Leave review", exact=True).click()
        _wait_unfocused(page, session, full, badge=False)
        page.close()


def test_a_reloaded_viewer_page_is_out_of_the_review(labelled_app: Any) -> None:
    with browserfixtures.launch_chromium() as browser:
        page, session, full = _viewer_page(browser, labelled_app)
        _focus_a_region(page, session, full)
        page.reload()
        page.get_by_text("Color by", exact=True).wait_for(timeout=60_000)
        _wait_unfocused(page, session, full)
        page.close()
