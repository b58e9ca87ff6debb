"""Viewer tabs: the memory each open tab adds, and how fast a correction reaches the other tabs.

Opens ``--tabs`` real review sessions (each its own viser server, panel and renderer, as
:class:`app.viewer.manager.ProjectViewer` opens one per browser tab) on one synthetic map of ``--voxels``
voxels (:func:`bench_viewer.synthetic_grid`), in the same process, two ways:

- **shared** (what the app does): every tab shows the same ``ReviewGrid`` object and takes its corrected
  labels from one :class:`app.viewer.corrections.OverlayCache`;
- **copied** (baseline: a viewer per tab that loads its own copy of the run): every tab gets its own copy
  of the grid and its own overlay.

It reports the resident memory (VmRSS) each tab adds once drawn, and, with shared tabs, the time from a
correction stored in tab 1 until every other tab has relabelled and redrawn (what the push runs:
``Corrections.refresh`` on each, on threads) beside the time tab 1 takes for the same correction itself.

With ``--idle`` it measures instead what idle tabs cost the server: a real server (``python -m app.main``)
on 127.0.0.1 with a reduced demo street and ``--runs`` finished runs (the history the viewer follows), and
real Chromium pages (``/usr/bin/chromium`` through playwright) showing its viewer, nobody touching them. It
reports the server process's CPU seconds over ``--window`` seconds with 0 tabs open (the baseline), then 1,
then 3, and the share of a core each idle tab adds to the baseline.

Run: ``.venv/bin/python benchmarks/bench_viewer_tabs.py [--voxels 2000000] [--tabs 4] [--quick]``, or
``... --idle [--window 20] [--runs 10]``. Prints tables and writes
``benchmarks/results/bench_viewer_tabs.json`` (``bench_viewer_tabs_idle.json`` with ``--idle``).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_viewer import MemoryBackend, synthetic_grid
from common import _status_kb, machine_info, print_table

from app.viewer.corrections import OverlayCache
from app.viewer.lod import LodConfig
from app.viewer.panel import ReviewPanel
from app.viewer.records import RunInfo, Selection, SessionConfig
from app.viewer.session import ReviewSession
from leap_core.schema import builtin_schema

RESULTS = (
    Path(os.environ.get("LEAP_BENCH_RESULTS") or Path(__file__).resolve().parent / "results")
    / "bench_viewer_tabs.json"
)


def _rss_mb() -> float:
    gc.collect()
    return (_status_kb("VmRSS") or 0) / 1024


def open_tabs(
    grid: Any, backend: MemoryBackend, tabs: int, *, shared: bool, run_dir: Path, voxels: int
) -> dict[str, Any]:
    """``tabs`` sessions on ``grid`` (or, not ``shared``, each on its own identical grid, as a tab that reads
    the run itself would hold); the resident memory each one added once drawn, and the sessions."""
    overlays = OverlayCache() if shared else None
    cfg = SessionConfig(follow_ego=False, lod=LodConfig(budget=1 << 62))
    run = RunInfo(1, 1, "done", 100.0, None, None, run_dir, backend.schema)
    sessions: list[ReviewSession] = []
    added: list[float] = []
    for _ in range(tabs):
        before = _rss_mb()
        session = ReviewSession(backend, panel=ReviewPanel, config=cfg, overlays=overlays)
        own = grid if shared else synthetic_grid(voxels, len(backend.schema.classes))
        session.show_grid(run, own, None)
        assert session.renderer.wait_drawn(600)
        sessions.append(session)
        added.append(_rss_mb() - before)
    return {"sessions": sessions, "added_mb": added}


def push_times(sessions: list[ReviewSession], repeats: int) -> dict[str, list[float]]:
    """Per repeat: tab 1's own correction (store, relabel, redraw) and the others' refresh after it."""
    first, others = sessions[0], sessions[1:]
    names = first.class_names()
    rng = np.random.default_rng(1)
    own, pushed = [], []
    for r in range(repeats):
        rows = np.sort(rng.choice(first.grid.num_voxels, 10_000, replace=False)).astype(np.int64)  # type: ignore[union-attr]
        t0 = time.perf_counter()
        first.corrections.assign_selection(names[r % len(names)], selection=Selection(rows))
        assert first.renderer.wait_drawn(600)
        own.append(time.perf_counter() - t0)
        t1 = time.perf_counter()
        threads = [threading.Thread(target=s.corrections.refresh) for s in others]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for s in others:
            assert s.renderer.wait_drawn(600)
            assert s.label is first.label
        pushed.append(time.perf_counter() - t1)
    return {"own_s": own, "push_s": pushed}


IDLE_TABS = (0, 1, 3)
"""Open tabs measured by ``--idle``, in this order (each step opens the tabs it adds)."""
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--no-first-run",
]


def idle_tabs(window: float, frames: int, runs: int) -> dict[str, Any]:
    """Server CPU seconds over ``window`` s with each count of :data:`IDLE_TABS` idle viewer tabs."""
    import tempfile

    import httpx
    from bench_app_load import SMALL_STREET, TERMINAL, process_cpu, start_server
    from playwright.sync_api import sync_playwright

    from app.demo import synth_config
    from leap_core.synth import generate_sequence

    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="leap-idle-") as tmp:
        data_root = Path(tmp) / "data"
        street = synth_config({**SMALL_STREET, "frames": frames})
        dataset = generate_sequence(data_root / "street", street).path
        proc, base = start_server(data_root)
        try:
            with httpx.Client(base_url=f"{base}/api/v1", timeout=60) as api:
                dataset_spec = {"kind": "folder", "path": str(dataset)}
                made = api.post("/projects", json={"name": "idle", "dataset": dataset_spec})
                made.raise_for_status()
                project = made.json()["id"]
                for _ in range(runs):  # a project's history: the viewer's follower reads its runs
                    run = api.post(f"/projects/{project}/runs", json={}).json()
                    while (status := api.get(f"/runs/{run['id']}").json()["status"]) not in TERMINAL:
                        time.sleep(0.25)
                    if status != "done":
                        raise SystemExit(f"the street's run ended {status}")
                with sync_playwright() as p:
                    browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
                    pages = []
                    for tabs in IDLE_TABS:
                        while len(pages) < tabs:
                            opened = api.post(f"/projects/{project}/viewer", json={})
                            opened.raise_for_status()
                            page = browser.new_page(viewport={"width": 1280, "height": 800})
                            page.goto(base + opened.json()["url"])
                            page.get_by_text("Color by", exact=True).wait_for(timeout=120_000)
                            page.locator("#leap-review").wait_for(state="attached", timeout=60_000)
                            pages.append(page)
                        time.sleep(3.0)  # the scene has reached the page; what follows is idle
                        cpu0, t0 = process_cpu(proc.pid), time.perf_counter()
                        time.sleep(window)
                        cpu, wall = process_cpu(proc.pid) - cpu0, time.perf_counter() - t0
                        rows.append({"tabs": tabs, "server_cpu_s": cpu, "wall_s": wall})
                        print(f"{tabs} idle tab(s): server used {cpu:.2f} CPU s in {wall:.1f} s", flush=True)
                    browser.close()
        finally:
            proc.terminate()
            proc.wait(30)
    return {"window_s": window, "frames": frames, "runs": runs, "rows": rows}


def print_idle(out: dict[str, Any]) -> None:
    rows = out["rows"]
    base = rows[0]["server_cpu_s"] / rows[0]["wall_s"]
    table = []
    for r in rows:
        cores = r["server_cpu_s"] / r["wall_s"]
        per_tab = (cores - base) / r["tabs"] if r["tabs"] else float("nan")
        table.append([r["tabs"], round(r["server_cpu_s"], 2), round(100 * cores, 2), round(100 * per_tab, 2)])
    print_table(
        f"Server CPU with idle viewer tabs (real Chromium pages; {out['runs']} finished runs), "
        f"{out['window_s']:.0f} s each",
        ["idle tabs", "server CPU s", "% of a core", "% of a core per tab over 0 tabs (baseline)"],
        table,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--voxels", type=int, default=2_000_000)
    parser.add_argument("--tabs", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="20k voxels, 2 tabs, 1 repeat (the smoke test)")
    parser.add_argument(
        "--idle", action="store_true", help="server CPU with 0, 1 and 3 idle tabs in Chromium"
    )
    parser.add_argument("--window", type=float, default=20.0, help="--idle: seconds measured per tab count")
    parser.add_argument("--frames", type=int, default=4, help="--idle: frames of the street")
    parser.add_argument("--runs", type=int, default=10, help="--idle: finished runs of the project")
    args = parser.parse_args()
    if args.idle:
        idle = {"machine": machine_info(), **idle_tabs(args.window, args.frames, args.runs)}
        print_idle(idle)
        path = RESULTS.with_name("bench_viewer_tabs_idle.json")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(idle, indent=2, default=float))
        return
    if args.quick:
        args.voxels, args.tabs, args.repeats = 20_000, 2, 1
    schema = builtin_schema()
    grid = synthetic_grid(args.voxels, schema.num_classes)
    run_dir = Path(os.environ.get("TMPDIR", "/tmp"))
    out: dict[str, Any] = {"machine": machine_info(), "voxels": grid.num_voxels, "tabs": args.tabs}
    rows = []
    for shared in (True, False):
        backend = MemoryBackend(schema, run_dir)
        opened = open_tabs(grid, backend, args.tabs, shared=shared, run_dir=run_dir, voxels=args.voxels)
        sessions = opened["sessions"]
        try:
            extra = opened["added_mb"][1:]
            key = "shared" if shared else "copied (baseline)"
            out[key] = {"added_mb": opened["added_mb"]}
            rows.append([key, opened["added_mb"][0], statistics.median(extra) if extra else float("nan")])
            if shared and len(sessions) > 1:
                out["push"] = push_times(sessions, args.repeats)
        finally:
            for s in sessions:
                s.close()
            del sessions, opened
    print_table(
        f"Memory per viewer tab, {grid.num_voxels:,} voxels, {args.tabs} tabs (MB of VmRSS added once drawn)",
        ["tabs", "first tab", "each further tab (median)"],
        rows,
    )
    if "push" in out:
        p = out["push"]
        print_table(
            f"A 10k-voxel correction in tab 1 reaching the {args.tabs - 1} other tab(s), "
            f"{grid.num_voxels:,} voxels",
            ["what", "median s", "max s"],
            [
                [
                    "tab 1's own correction (store, relabel, redraw; baseline)",
                    statistics.median(p["own_s"]),
                    max(p["own_s"]),
                ],
                [
                    "the other tabs, pushed (relabel, redraw)",
                    statistics.median(p["push_s"]),
                    max(p["push_s"]),
                ],
            ],
        )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2, default=float))


if __name__ == "__main__":
    main()
