"""Scan navigation, voxel inspection, the shortcut overlay and readable scalar views, in a real browser.

Debian's Chromium (software WebGL) at 1280×720 drives the viser client the app relays, on the seeded demo
project's first run (a short generated sequence). Keys go through web/viewer/nav.js to
app/api/routes/viewer_nav.py; the checks read the server-side session and the browser's camera as viser's
server sees it (``client.camera``, which the browser reports back). The inspect and shortcut screenshots are
the README's (``scripts/screenshots.py`` copies them to docs/images).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import browserfixtures
import numpy as np
import pytest

from app.viewer import nav_logic as nl
from app.viewer import view_logic as vl

artifacts = browserfixtures.artifacts
live_app = browserfixtures.live_app
wait_until = browserfixtures.wait_until

pytestmark = [pytest.mark.browser, pytest.mark.slow]

VIEWPORT = {"width": 1280, "height": 720}
INSPECT_SHOT = "review-inspect.png"
SHORTCUTS_SHOT = "review-shortcuts.png"


@pytest.fixture(scope="module")
def viewer(live_app: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """The demo project's viewer open in a 1280×720 Chromium page, its first run loaded."""
    import httpx

    base, app = live_app["base"], live_app["app"]
    api = httpx.Client(base_url=f"{base}/api/v1", timeout=30)
    project = wait_until(
        lambda: next((p for p in api.get("/projects").json()["data"] if p["is_demo"]), None), 30, "the demo"
    )
    pid = project["id"]

    def first_run() -> dict[str, Any] | None:
        runs = api.get(f"/projects/{pid}/runs").json()["data"]
        return runs[-1] if runs and runs[-1]["status"] in ("done", "failed") else None

    run = wait_until(first_run, 600, "the demo's first run")
    assert run["status"] == "done", run.get("error")
    opened = api.post(f"/projects/{pid}/viewer")
    assert opened.status_code == 200, opened.text
    session = app.state.viewers.get(pid)
    assert session is not None and session.grid is not None
    with browserfixtures.launch_chromium() as browser:
        page = browser.new_page(viewport=VIEWPORT)
        browserfixtures.echo_console(page)
        page.goto(base + opened.json()["url"])
        page.get_by_text(f"LeAP review: {project['name']}", exact=True).wait_for(timeout=60_000)
        page.get_by_text("Color by", exact=True).wait_for(timeout=30_000)
        alert = page.get_by_role("alert")
        if alert.count():
            alert.get_by_role("button").first.click()
        wait_until(session.scene.clients, 30, "the browser's viser client")
        assert session.renderer.wait_drawn(30)
        page.wait_for_timeout(3000)  # software WebGL draws the map
        yield {"page": page, "session": session, "api": api, "pid": pid}


def _client_camera(session: Any) -> Any:
    (client,) = session.scene.clients().values()
    return client.camera


def _screen_of(session: Any, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cam = _client_camera(session)
    return vl.project_to_screen(points, list(cam.position), list(cam.wxyz), float(cam.fov), float(cam.aspect))


def test_arrow_keys_change_the_scan_and_the_camera_follows_the_ego_pose(viewer: dict[str, Any]) -> None:
    page, session = viewer["page"], viewer["session"]
    assert session.player.follow_ego
    start = session.player.frame_pos
    assert 0 < start < session.player.scan_count - 1
    before = np.array(_client_camera(session).position)

    page.keyboard.press("ArrowRight")
    wait_until(lambda: session.player.frame_pos == start + 1, 20, "the next scan")
    ego = session.player.scan_view.ego_pose[:3, 3]
    expected, _ = nl.follow_view(session.player.scan_view.ego_pose)

    def camera_follows() -> bool:
        cam = _client_camera(session)
        return bool(np.linalg.norm(np.array(cam.position) - expected) < 1.0)

    wait_until(camera_follows, 20, "the browser camera behind the ego pose")
    assert np.linalg.norm(np.array(_client_camera(session).position) - before) > 5.0
    # The browser's own orientation (it reports wxyz back) puts the ego vehicle in view, near the middle.
    uv, in_front = _screen_of(session, ego[None, :])
    assert in_front[0] and 0.2 < uv[0, 0] < 0.8 and 0.2 < uv[0, 1] < 0.9, uv

    page.keyboard.press(",")
    wait_until(lambda: session.player.frame_pos == start, 20, "the previous scan again")
    back, _ = nl.follow_view(session.player.scan_view.ego_pose)
    wait_until(
        lambda: np.linalg.norm(np.array(_client_camera(session).position) - back) < 1.0, 20, "the camera back"
    )
    page.keyboard.press(".")
    wait_until(lambda: session.player.frame_pos == start + 1, 20, "'.' to step forward")


def test_enlarged_image_stays_open_while_navigating(viewer: dict[str, Any]) -> None:
    page, session = viewer["page"], viewer["session"]
    page.keyboard.press("i")
    box = page.locator("#leap-image")
    box.wait_for(state="visible", timeout=10_000)
    img = box.locator("img")
    wait_until(lambda: img.evaluate("i => i.complete && i.naturalWidth") > 0, 20, "the image to load")
    width = box.bounding_box()["width"]
    canvas = page.locator("canvas").first.bounding_box()
    assert width >= 0.95 * canvas["width"] > 600
    src = img.get_attribute("src")
    pos = session.player.frame_pos
    page.keyboard.press("ArrowLeft")
    wait_until(lambda: session.player.frame_pos == pos - 1, 20, "the previous scan")
    wait_until(lambda: img.get_attribute("src") != src, 10, "the image of the new scan")
    assert box.is_visible()
    page.keyboard.press("i")
    box.wait_for(state="hidden", timeout=10_000)


def test_clicking_a_voxel_shows_its_distribution(viewer: dict[str, Any], artifacts: Path) -> None:
    page, session = viewer["page"], viewer["session"]
    page.keyboard.press("g")  # stop following so the map view below stays put
    wait_until(lambda: not session.player.follow_ego, 10, "following off")
    page.keyboard.press("Shift+F")
    grid = session.grid
    rows, _ = session.renderer.compute_view()
    centres = grid.centres[rows]

    def settled() -> bool:
        uv, front = _screen_of(session, centres)
        return bool((front & (uv[:, 0] > 0) & (uv[:, 0] < 1)).sum() > 0.5 * len(rows))

    wait_until(settled, 20, "the whole map in view")
    page.wait_for_timeout(2500)
    # The voxel nearest the camera among those well inside the view: nothing can stand in front of it.
    cam = _client_camera(session)
    uv, front = _screen_of(session, centres)
    inside = front & (uv[:, 0] > 0.3) & (uv[:, 0] < 0.7) & (uv[:, 1] > 0.3) & (uv[:, 1] < 0.8)
    depth = np.linalg.norm(centres - np.array(cam.position), axis=1)
    target = int(np.flatnonzero(inside)[np.argmin(depth[inside])])
    box = page.locator("canvas").first.bounding_box()
    x = box["x"] + uv[target, 0] * box["width"]
    y = box["y"] + uv[target, 1] * box["height"]
    page.mouse.click(x, y)

    found = wait_until(lambda: session.tools.inspected, 20, "the clicked voxel to be inspected")
    # The picked voxel is the one under the cursor (within a voxel's size on screen).
    got_uv, _ = _screen_of(session, grid.centres[found.row][None, :])
    assert abs((got_uv[0, 0] - uv[target, 0]) * box["width"]) < 12
    assert abs((got_uv[0, 1] - uv[target, 1]) * box["height"]) < 12
    # ... and the first one along the ray: no farther than the nearest voxel under the cursor.
    assert found.distance <= depth[target] + grid.voxel_size
    names = session.class_names()
    top = names[int(np.argmax(found.probs))]
    panel = page.get_by_text(f"observed by {found.views} scan", exact=False)
    panel.wait_for(timeout=10_000)
    rows_shown = page.locator(".leap-dist-row")
    wait_until(lambda: rows_shown.count() >= 1, 10, "the distribution bars")
    first = rows_shown.first.inner_text()
    assert top in first and f"{float(found.probs.max()):.2f}" in first
    assert found.views >= 1
    page.wait_for_timeout(1500)
    page.screenshot(path=str(artifacts / INSPECT_SHOT))


def test_shortcut_overlay_lists_every_key(viewer: dict[str, Any], artifacts: Path) -> None:
    page = viewer["page"]
    page.keyboard.press("?")
    help_box = page.locator("#leap-shortcuts")
    help_box.wait_for(state="visible", timeout=10_000)
    text = help_box.inner_text()
    for what, keys in [
        ("Next scan", ["→", "."]),
        ("Previous scan", ["←", ","]),
        ("Play / pause through the scans", ["Space"]),
        ("Fit the view to the shown scan", ["F"]),
        ("Fit the view to the whole map", ["Shift+F"]),
        ("Camera follows the ego vehicle on scan changes (on/off)", ["G"]),
        ("Enlarge / shrink the scan's camera image", ["I"]),
        ("Show or hide this list", ["?"]),
    ]:
        row = help_box.locator("tr", has_text=what)
        assert row.count() == 1, f"{what!r} missing from the overlay:\n{text}"
        assert [k.strip() for k in row.locator("kbd").all_inner_texts()] == keys
    page.screenshot(path=str(artifacts / SHORTCUTS_SHOT))
    page.keyboard.press("?")
    help_box.wait_for(state="detached", timeout=10_000)


def test_probability_view_draws_the_scan_grey(viewer: dict[str, Any]) -> None:
    page, session = viewer["page"], viewer["session"]
    scan = session.scene.scan.handle
    assert scan is not None
    assert len({tuple(c) for c in np.asarray(scan.colors)}) > 1  # class colours in the class view
    browserfixtures.pick(page, "Color by", "class probability")
    wait_until(lambda: session.state.mode == "class_probability", 20, "the probability view")
    wait_until(
        lambda: bool((np.asarray(scan.colors) == nl.SCAN_GREY_RGB).all()), 20, "the scan points drawn grey"
    )
    # A newly shown scan is grey too. The dropdown keeps the focus, and keys typed into an input are not
    # shortcuts: leave it first, as a user clicking back into the view would.
    page.evaluate("document.activeElement && document.activeElement.blur()")
    pos = session.player.frame_pos
    page.keyboard.press("ArrowLeft" if pos == session.player.scan_count - 1 else "ArrowRight")
    wait_until(lambda: session.player.frame_pos != pos, 20, "a scan change")
    wait_until(
        lambda: session.scene.scan.count == session.player.scan_view.points.shape[0], 20, "the new scan"
    )
    assert (np.asarray(scan.colors) == nl.SCAN_GREY_RGB).all()
    browserfixtures.pick(page, "Color by", "class")
    wait_until(lambda: len({tuple(c) for c in np.asarray(scan.colors)}) > 1, 20, "class colours again")
