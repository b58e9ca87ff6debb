"""The viewer's image panel on a rig of cameras, in a real browser: the demo street with a rear camera
(``leap synth --cameras 2``), labeled by the app; the panel's Camera dropdown switches the shown image (and
the enlarged one) to the rear camera's, with its projected labels."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import browserfixtures
import numpy as np
import pytest

artifacts = browserfixtures.artifacts
wait_until = browserfixtures.wait_until
pick = browserfixtures.pick

pytestmark = [pytest.mark.browser, pytest.mark.slow]

FRAMES = 4
"""Frames of the demo: enough for a run, few enough to render twice."""


def add_rear_camera(seq_dir: Path) -> None:
    """Give the generated demo sequence the rear camera of the same street (its front files are the
    same bytes in the two-camera sequence)."""
    from leap_core.synth import SynthConfig, generate_sequence

    with tempfile.TemporaryDirectory() as tmp:
        rig = generate_sequence(tmp, SynthConfig(frames=FRAMES, cameras=2), workers=1).path
        shutil.copytree(rig / "image_rear", seq_dir / "image_rear")
        shutil.copytree(rig / "gt2d" / "image_rear", seq_dir / "gt2d" / "image_rear")
        shutil.copy(rig / "cameras.yaml", seq_dir / "cameras.yaml")


@pytest.fixture(scope="module")
def rig_app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    root = tmp_path_factory.mktemp("viewer-rig")
    with browserfixtures.running_app(root, frames=FRAMES, prepare=add_rear_camera) as app:
        yield app


def test_camera_dropdown_switches_the_image_panel(rig_app: dict[str, Any], artifacts: Path) -> None:
    import httpx

    base, app = rig_app["base"], rig_app["app"]
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
    with browserfixtures.launch_chromium() as browser:
        page = browserfixtures.open_viewer(browser, base + opened.json()["url"], project["name"], session)
        wait_until(lambda: session.player.scan_view is not None, 30, "a scan to be shown")
        front = session.player.scan_view
        assert front.camera == "image_2" and front.overlay is not None
        page.keyboard.press("i")
        img = page.locator("#leap-image img")
        wait_until(lambda: img.evaluate("i => i.complete && i.naturalWidth") > 0, 20, "the enlarged image")
        src = img.get_attribute("src")
        pick(page, "Camera", "image_rear")
        wait_until(lambda: session.player.scan_view.camera == "image_rear", 20, "the rear camera's image")
        rear = session.player.scan_view
        assert rear.frame_id == front.frame_id and rear.overlay is not None
        assert not np.array_equal(rear.overlay, front.overlay)
        # The rear camera looks backwards: its frustum faces the other way.
        assert np.dot(_forward(rear.cam_wxyz), _forward(front.cam_wxyz)) < -0.9
        wait_until(lambda: img.get_attribute("src") != src, 10, "the enlarged image of the rear camera")
        assert "camera image_rear" in page.locator(".leap-image-caption").inner_text()
        page.screenshot(path=str(artifacts / "viewer-rear-camera.png"))
        # A scan change keeps the chosen camera (keys reach the page once the dropdown lets go of them).
        page.evaluate("document.activeElement && document.activeElement.blur()")
        page.keyboard.press("ArrowRight")
        wait_until(lambda: session.player.scan_view.frame_id != front.frame_id, 20, "the next scan")
        assert session.player.scan_view.camera == "image_rear"


def _forward(wxyz: np.ndarray) -> np.ndarray:
    """The optical axis (+z) of a camera of orientation ``wxyz``."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = wxyz
    return np.asarray(Rotation.from_quat([x, y, z, w]).apply([0.0, 0.0, 1.0]))
