"""The 3D review viewer in a real browser, through the real app, job queue and pipeline.

Debian's Chromium (software WebGL) drives the viser client the app relays under its own port. On the
seeded demo project's finished run it: shows the map in class colours, switches to one class's probability
view, moves the threshold, makes a manual correction (box select + assign), edits a class's prompts,
presses Re-run, watches the run finish and the scene reload, and finally checks that the correction is in
the new run's exported ``.label`` files. Screenshots go to ``test-artifacts/``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import browserfixtures
import numpy as np
import pytest

# The browser fixtures (this folder has no conftest.py; see browserfixtures), found by name here.
artifacts = browserfixtures.artifacts
live_app = browserfixtures.live_app
wait_until = browserfixtures.wait_until
_pick = browserfixtures.pick

MAX_BROWSER_POINTS = 200_000
"""Software WebGL stays responsive up to about this many points (docs/METHOD.md, Facts about the tools)."""
CORRECTED_CLASS = "traffic-sign"
CORRECTED_EXPORT_ID = 81

pytestmark = [
    pytest.mark.browser,
    pytest.mark.slow,
]


_panel_input = browserfixtures.panel_input


def _shot(page: Any, artifacts: Path, name: str) -> Path:
    path = artifacts / name
    page.screenshot(path=str(path))
    return path


def test_review_steer_rerun_and_correct_in_a_real_browser(live_app: dict[str, Any], artifacts: Path) -> None:
    import httpx

    from app import crud
    from app.core.db import open_db
    from leap_core.datasets.kitti import KittiSequence, read_label
    from leap_core.fusion import voxel_keys

    base, app, settings = live_app["base"], live_app["app"], live_app["settings"]
    api = httpx.Client(base_url=f"{base}/api/v1", timeout=30)

    # 1. The seeded demo project finishes its first run.
    project = wait_until(
        lambda: next((p for p in api.get("/projects").json()["data"] if p["is_demo"]), None),
        30,
        "the demo project",
    )
    pid = project["id"]

    def last_run() -> dict[str, Any] | None:
        runs = api.get(f"/projects/{pid}/runs").json()["data"]
        return runs[0] if runs else None

    first = wait_until(
        lambda: (r := last_run()) and r["status"] in ("done", "failed") and r, 600, "the first run"
    )
    assert first["status"] == "done", first.get("error")

    # 2. The app starts the viewer and relays it under its own port.
    opened = api.post(f"/projects/{pid}/viewer")
    assert opened.status_code == 200, opened.text
    viewer = opened.json()
    assert viewer["run_id"] == first["id"]
    session = app.state.viewers.get(pid)
    assert session is not None and session.grid is not None
    assert session.grid.num_voxels <= MAX_BROWSER_POINTS, "demo map too large for software WebGL"
    names = session.class_names()

    with browserfixtures.launch_chromium() as browser:
        page = browserfixtures.open_viewer(browser, base + viewer["url"], project["name"], session)
        page.wait_for_timeout(4000)  # software WebGL draws the map
        _shot(page, artifacts, "viewer-1-classes.png")
        page.get_by_text(f"{session.grid.num_voxels:,} voxels, {len(names)} classes", exact=False).wait_for(
            timeout=10_000
        )

        # 3. One class's probability view, with its colour-scale legend.
        _pick(page, "Color by", "class probability")
        _pick(page, "Class", "road")
        wait_until(
            lambda: (
                session.state.mode == "class_probability" and session.state.class_index == names.index("road")
            ),
            20,
            "the road probability view",
        )
        page.get_by_text("P(road)").wait_for(timeout=10_000)
        assert session.renderer.wait_drawn(30)
        page.wait_for_timeout(2500)
        _shot(page, artifacts, "viewer-2-road-probability.png")

        # 4. The threshold hides voxels below it.
        shown_before = session.scene.voxels.count
        threshold = _panel_input(page, "Min probability")
        threshold.fill("0.5")
        threshold.press("Enter")
        wait_until(lambda: abs(session.state.threshold - 0.5) < 1e-9, 20, "the threshold to reach the server")
        assert session.renderer.wait_drawn(30)
        road_prob = session.grid.class_prob(names.index("road"))
        assert session.scene.voxels.count == int((road_prob >= 0.5).sum()) < shown_before
        page.wait_for_timeout(2500)
        _shot(page, artifacts, "viewer-3-road-threshold.png")

        # 5. A manual correction: back to classes, box-select the middle of the view, assign a class.
        _pick(page, "Color by", "class")
        threshold = _panel_input(page, "Min confidence")
        threshold.fill("0")
        threshold.press("Enter")
        wait_until(
            lambda: session.state.mode == "class" and session.state.threshold == 0, 20, "the class view"
        )
        page.get_by_text("Corrections", exact=True).click()
        _pick(page, "Assign class", CORRECTED_CLASS)
        selected = browserfixtures.box_select_centre(page, session)
        page.get_by_text(f"{selected:,} voxels selected.").wait_for(timeout=10_000)
        page.wait_for_timeout(2000)
        _shot(page, artifacts, "viewer-4-selection.png")
        page.get_by_role("button", name="Apply to selection").click()
        with open_db(settings.database) as db:
            corrections = wait_until(
                lambda: crud.list_corrections(db, pid), 20, "the correction to be stored"
            )
        (correction,) = corrections
        assert correction.class_name == CORRECTED_CLASS and correction.keys.size == selected
        # The correction is stored before the session relabels its voxels: wait for the relabel, not
        # only for the row (under load the check could otherwise run in between).
        rows = session.grid.rows_of(correction.keys)

        def relabelled() -> bool:
            return bool((session.label[rows] == names.index(CORRECTED_CLASS)).all())

        wait_until(relabelled, 30, "the corrected labels")
        assert session.renderer.wait_drawn(30)

        # 6. Edit a class's prompts; it lands in the project (the same data the web UI edits).
        page.get_by_text("Classes and prompts", exact=True).click()
        _pick(page, "Edit class", "car")
        prompts = _panel_input(page, "Prompts")
        wait_until(lambda: "car" in prompts.input_value(), 10, "the class editor to fill in")
        prompts.fill("car, automobile, hatchback")
        prompts.press("Tab")
        page.get_by_role("button", name="Save class").click()
        car = wait_until(
            lambda: next(
                (
                    c
                    for c in api.get(f"/projects/{pid}/classes").json()["data"]
                    if c["name"] == "car" and "hatchback" in c["prompts"]
                ),
                None,
            ),
            20,
            "the edited prompts in the project",
        )
        assert car["prompts"] == ["car", "automobile", "hatchback"]

        # 7. Re-run from the panel: progress shows, the run finishes, the scene reloads.
        version = session.scene_version
        page.get_by_role("button", name="Re-run").click()
        second = wait_until(lambda: (r := last_run()) and r["id"] != first["id"] and r, 30, "the new run")
        page.get_by_text(re.compile(rf"Run {second['number']} (queued|running)")).wait_for(timeout=30_000)
        page.wait_for_timeout(500)
        _shot(page, artifacts, "viewer-5-rerun-progress.png")
        wait_until(lambda: session.scene_version > version, 600, "the new run's scene")
        assert session.scene_version == version + 1 and session.run is not None
        assert session.run.run_id == second["id"]
        page.get_by_text(f"Run {second['number']}", exact=False).first.wait_for(timeout=30_000)
        assert session.renderer.wait_drawn(30)
        page.wait_for_timeout(4000)
        _shot(page, artifacts, "viewer-6-after-rerun.png")

        # 8. The review queue moves the camera to the least confident region.
        page.get_by_text("Review queue", exact=True).click()
        page.get_by_role("button", name="Next region").click()
        page.get_by_text(re.compile(r"Region 1/\d+: about \d+ voxels expected wrong")).wait_for(
            timeout=30_000
        )
        region = session.queue.regions[0]
        assert region.expected_wrong == max(r.expected_wrong for r in session.queue.regions)
        page.wait_for_timeout(3000)
        _shot(page, artifacts, "viewer-7-review-queue.png")

    # 9. The correction is in the new run's exported .label files (and in the first run's).
    run = api.get(f"/runs/{second['id']}").json()
    assert run["status"] == "done"
    with open_db(settings.database) as db:
        run_dir = crud.require_run(db, second["id"]).sequence_layout("00").folder
        first_dir = crud.require_run(db, first["id"]).sequence_layout("00").folder
    seq = KittiSequence(project["dataset"]["path"])
    voxel_size = session.grid.voxel_size
    hit_new = hit_old = total = 0
    for i, fid in enumerate(seq.frame_ids):
        frame = seq.frame(i)
        xyz = frame.points[:, :3].astype(np.float64) @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        inside = np.isin(voxel_keys(xyz, voxel_size), correction.keys)
        total += int(inside.sum())
        new = read_label(run_dir / "export" / f"{fid}.label", frame.points.shape[0]) & 0xFFFF
        old = read_label(first_dir / "export" / f"{fid}.label", frame.points.shape[0]) & 0xFFFF
        hit_new += int((new[inside] == CORRECTED_EXPORT_ID).sum())
        hit_old += int((old[inside] == CORRECTED_EXPORT_ID).sum())
    assert total > 0
    print(
        f"corrected voxels hold {total} points: {hit_new} exported as {CORRECTED_CLASS} after the re-run "
        f"({hit_new / total:.1%}), {hit_old} before"
    )
    # The apply-corrections job already put it into the first run's export, without the re-run
    # (tests/browser/test_corrections_export.py checks that against the export before the correction).
    assert hit_old == total
    # Corrections are re-imposed after smoothing (and after each 3D-CN round): every point of a corrected
    # voxel is exported with the corrected class.
    assert hit_new == total
