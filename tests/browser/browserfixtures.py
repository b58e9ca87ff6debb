"""Real-browser fixtures: Debian's chromium driven by Playwright (no bundled browser download).

Imported by name from the test modules (like tests/app/appfixtures.py): a second conftest.py would shadow
the top-level one for `from conftest import ...`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
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
