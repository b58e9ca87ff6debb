"""Real-browser fixtures: Debian's chromium driven by Playwright (no bundled browser download).

Imported by name from the test modules (like tests/app/appfixtures.py): a second conftest.py would shadow
the top-level one for `from conftest import ...`.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",  # CI runs as root, where chromium refuses its sandbox
    "--disable-gpu",  # software WebGL; there is no GPU on the CI machine
    "--disable-background-networking",  # the machine has no internet: no update or sync traffic
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


@contextlib.contextmanager
def launch_chromium() -> Iterator[Any]:
    """A headless chromium for the duration of the ``with`` block.

    Start it only after any server the test runs in this thread: Playwright's sync API creates an asyncio
    loop in the calling thread, and a server set up afterwards in that thread can pick that loop up and then
    only progress while Playwright is pumping it.
    """
    if not CHROMIUM.exists():
        pytest.skip("Debian chromium is not installed at /usr/bin/chromium (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def echo_console(page: Any) -> None:
    """Print the page's console messages, websocket events and failed requests, with seconds since now.

    pytest shows a failed test's captured output, so a browser-side failure (a websocket that never
    connects, a script error) comes with its own timeline.
    """
    t0 = time.monotonic()

    def say(what: str) -> None:
        print(f"[browser {time.monotonic() - t0:7.2f}s] {what}")

    def on_websocket(ws: Any) -> None:
        say(f"websocket open {ws.url}")
        ws.on("close", lambda *_: say(f"websocket closed {ws.url}"))
        ws.on("socketerror", lambda err: say(f"websocket error {err}"))

    page.on("console", lambda msg: say(f"console {msg.type}: {msg.text}"))
    page.on("websocket", on_websocket)
    page.on("requestfailed", lambda req: say(f"request failed {req.url}: {req.failure}"))


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """One headless chromium per test module (for tests whose servers run in their own processes)."""
    with launch_chromium() as b:
        yield b


@pytest.fixture(scope="session")
def artifacts() -> Path:
    """``test-artifacts/`` at the repository root: screenshots worth keeping from a CI run."""
    path = Path(__file__).resolve().parents[2] / "test-artifacts"
    path.mkdir(parents=True, exist_ok=True)
    return path


# ------------------------------------------------------------------------- the live app (viewer tests)
DEMO_FRAMES = 14
"""Frames of the generated demo sequence (enough for a readable street, small enough for software WebGL)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(check: Callable[[], Any], timeout: float, what: str, interval: float = 0.2) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


@contextlib.contextmanager
def running_app(
    root: Path, frames: int = DEMO_FRAMES, prepare: Callable[[Path], None] | None = None
) -> Iterator[dict[str, Any]]:
    """The real app on a real HTTP port, with the demo project seeded on a short generated sequence.

    ``prepare(sequence_dir)`` may change the generated sequence before the app starts (and labels it).
    """
    import uvicorn

    from app.core.config import Settings
    from app.main import create_app

    port = free_port()
    settings = Settings(
        port=port,
        work_dir=root / "work",
        data_roots=[root],
        seed_demo=True,
        seed_agri_demo=False,  # the farm drone demo's run would queue behind the street's and slow these
        demo_synth={"frames": frames},
    )
    # Generate the demo sequence here, in one process: the app then finds it instead of generating it.
    from synthcache import synth_copy

    from leap_core.synth import SynthConfig

    synth_copy(settings.demo_dataset.parent.parent, SynthConfig(frames=frames))
    if prepare is not None:
        prepare(settings.demo_dataset)
    app = create_app(settings)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_until(lambda: server.started, 30, "the app to start")
    try:
        yield {"base": f"http://127.0.0.1:{port}", "app": app, "settings": settings}
    finally:
        server.should_exit = True
        thread.join(30)


@pytest.fixture(scope="module")
def live_app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """The real app on a real HTTP port, with the demo project seeded on a short generated sequence."""
    with running_app(tmp_path_factory.mktemp("viewer-e2e")) as app:
        yield app


def panel_input(page: Any, label: str) -> Any:
    """viser puts each widget's label in a paragraph before its input."""
    return page.get_by_text(label, exact=True).locator("xpath=following::input[not(@type='hidden')][1]")


def pick(page: Any, dropdown: str, option: str) -> None:
    page.get_by_role("combobox", name=dropdown).click()
    page.get_by_role("option", name=option, exact=True).click()


def box_select_centre(page: Any, session: Any) -> int:
    """Arm the panel's box selection, drag a 180 × 100 px box around the canvas centre (in two strokes,
    as a hand does), and return how many voxels the viewer selected."""
    page.get_by_role("button", name="Select box").click()
    wait_until(lambda: session.scene.rect_select_armed, 10, "box selection to be armed")
    page.wait_for_timeout(500)  # the server armed it; the browser hears of it over the websocket
    canvas = page.locator("canvas").first.bounding_box()
    cx, cy = canvas["x"] + canvas["width"] / 2, canvas["y"] + canvas["height"] / 2
    page.mouse.move(cx - 90, cy - 50)
    page.mouse.down()
    page.mouse.move(cx, cy, steps=8)
    page.mouse.move(cx + 90, cy + 50, steps=8)
    page.mouse.up()
    return int(wait_until(lambda: session.tools.selection.rows.size, 20, "voxels to be selected"))


def open_viewer(browser: Any, url: str, project_name: str, session: Any) -> Any:
    """A new page on the project's 3D viewer, connected, its dialog dismissed, the scene drawn."""
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    echo_console(page)
    page.goto(url)
    # The status badge reads "Connected" only until the server's panel label arrives (viser shows a
    # set label in its place): waiting for "Connected" raced with the scene replay and timed out under
    # load. The label comes only over an open websocket, so it proves the connection instead.
    page.get_by_text(f"LeAP review: {project_name}", exact=True).wait_for(timeout=60_000)
    page.get_by_text("Color by", exact=True).wait_for(timeout=30_000)
    alert = page.get_by_role("alert")
    if alert.count():
        alert.get_by_role("button").first.click()
    assert session.renderer.wait_drawn(30)
    return page
