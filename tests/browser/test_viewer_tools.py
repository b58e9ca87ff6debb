"""Selection tools of the viewer page in a real browser: lasso with front-surface depth, brush with a class
filter, driven with the page's keys and mouse through the real app, job queue and pipeline.

The scene is the generated demo street with two flat walls of points added to every scan, one 3.5 m behind
the other on the line of sight of the test's camera: a lasso drawn inside the front wall's outline must
correct the front wall only (checked in the run's exported ``.label`` files, which the apply-corrections job
updates without a run), the back wall keeps its labels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import browserfixtures
import numpy as np
import pytest

wait_until = browserfixtures.wait_until

pytestmark = [pytest.mark.browser, pytest.mark.slow]

FRAMES = 6
WALLS = {
    # (centre in the first scan's LiDAR frame: x forward, z up; half extents), metres.
    "front": ((18.0, 0.0, -0.5), (0.1, 0.8, 0.8)),
    "back": ((21.5, 0.0, -0.3), (0.1, 2.0, 1.2)),
}
SPACING = 0.05


def _wall(centre: tuple[float, ...], half: tuple[float, ...]) -> np.ndarray:
    ys = np.arange(-half[1], half[1] + 1e-9, SPACING)
    zs = np.arange(-half[2], half[2] + 1e-9, SPACING)
    xs = np.array([-half[0] / 2, half[0] / 2])
    g = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
    return g + np.asarray(centre)


def _add_walls(seq_dir: Path) -> None:
    """Append both walls (world-fixed, placed from the first scan's pose) to every scan and its labels."""
    from leap_core.datasets.kitti import KittiSequence, read_label, read_scan, write_label, write_scan

    seq = KittiSequence(seq_dir)
    pose0 = seq.frame(0).pose
    local = np.concatenate([_wall(*WALLS["front"]), _wall(*WALLS["back"])])
    world = local @ pose0[:3, :3].T + pose0[:3, 3]
    for i, fid in enumerate(seq.frame_ids):
        pose = seq.frame(i).pose
        inv = np.linalg.inv(pose)
        pts = world @ inv[:3, :3].T + inv[:3, 3]
        scan_path = seq_dir / "velodyne" / f"{fid}.bin"
        scan = read_scan(scan_path)
        extra = np.concatenate([pts, np.full((pts.shape[0], 1), 0.5)], axis=1).astype(np.float32)
        write_scan(scan_path, np.concatenate([scan, extra]))
        label_path = seq_dir / "labels" / f"{fid}.label"
        if label_path.exists():
            raw = read_label(label_path, scan.shape[0])
            raw = np.concatenate([raw, np.zeros(pts.shape[0], np.uint32)])
            write_label(label_path, raw & 0xFFFF, raw >> 16)


@pytest.fixture(scope="module")
def tools_app(tmp_path_factory: pytest.TempPathFactory) -> Any:
    with browserfixtures.running_app(tmp_path_factory.mktemp("viewer-tools"), FRAMES, _add_walls) as app:
        yield app


def _wall_points(seq_dir: Path) -> tuple[list[np.ndarray], int, int]:
    """World points of every scan, and how many front / back wall points end each scan."""
    from leap_core.datasets.kitti import KittiSequence

    seq = KittiSequence(seq_dir)
    out = []
    for i in range(len(seq.frame_ids)):
        frame = seq.frame(i)
        out.append(frame.points[:, :3].astype(np.float64) @ frame.pose[:3, :3].T + frame.pose[:3, 3])
    return out, _wall(*WALLS["front"]).shape[0], _wall(*WALLS["back"]).shape[0]


def _open(api: Any, app: Any, base: str, browser: Any) -> tuple[Any, Any, dict[str, Any]]:
    project = wait_until(
        lambda: next((p for p in api.get("/projects").json()["data"] if p["is_demo"]), None),
        30,
        "the project",
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
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    browserfixtures.echo_console(page)
    page.goto(base + opened.json()["url"])
    page.get_by_text(f"LeAP review: {project['name']}", exact=True).wait_for(timeout=60_000)
    page.get_by_text("Color by", exact=True).wait_for(timeout=30_000)
    close = page.get_by_role("alert").get_by_role("button")
    if close.count() and close.first.is_visible():
        close.first.click(timeout=5000)
    assert session.renderer.wait_drawn(30)
    return page, session, {"project": project, "run": run}


def _look(session: Any, page: Any, position: np.ndarray, target: np.ndarray) -> Any:
    """Move the browser's camera and wait until the browser reports it back."""
    session.scene.look_at(position, target)

    def arrived() -> Any:
        try:
            cam = session.tools.latest_camera()
        except LookupError:
            return None
        return cam if np.allclose(cam.position, position, atol=0.05) else None

    wait_until(arrived, 20, "the browser's camera")
    page.wait_for_timeout(1500)
    return session.tools.latest_camera()


def _drag(page: Any, points_uv: list[tuple[float, float]]) -> None:
    box = page.locator("canvas").first.bounding_box()
    xy = [(box["x"] + u * box["width"], box["y"] + v * box["height"]) for u, v in points_uv]
    page.mouse.move(*xy[0])
    page.mouse.down()
    for p in xy[1:]:
        page.mouse.move(*p, steps=6)
    page.mouse.up()


def test_lasso_front_surface_corrects_only_the_front_wall(tools_app: dict[str, Any]) -> None:
    import httpx

    from app import crud
    from app.core.db import open_db
    from leap_core.datasets.kitti import KittiSequence, read_label
    from leap_core.fusion import voxel_keys
    from leap_core.selection import project_to_screen

    base, app, settings = tools_app["base"], tools_app["app"], tools_app["settings"]
    api = httpx.Client(base_url=f"{base}/api/v1", timeout=30)
    with browserfixtures.launch_chromium() as browser:
        page, session, info = _open(api, app, base, browser)
        pid, first = info["project"]["id"], info["run"]
        seq_dir = Path(info["project"]["dataset"]["path"])
        world, n_front, n_back = _wall_points(seq_dir)
        pose0 = KittiSequence(seq_dir).frame(0).pose
        to_world = lambda p: np.asarray(p) @ pose0[:3, :3].T + pose0[:3, 3]  # noqa: E731
        grid = session.grid
        front_keys = np.unique(voxel_keys(to_world(_wall(*WALLS["front"])), grid.voxel_size))
        back_keys = np.unique(voxel_keys(to_world(_wall(*WALLS["back"])), grid.voxel_size))
        # The map holds the walls (voxels the pipeline kept: those with labelled points).
        in_front, in_back = grid.rows_of(front_keys) >= 0, grid.rows_of(back_keys) >= 0
        print(f"wall voxels in the map: front {in_front.mean():.0%}, back {in_back.mean():.0%}")
        assert in_front.mean() > 0.5 and in_back.mean() > 0.5
        front_keys, back_keys = front_keys[in_front], back_keys[in_back]

        # Level with the walls, 3 m in front of the front one (nothing stands between), looking through both.
        cam = _look(session, page, to_world([15.0, 0.0, -0.5]), to_world([18.0, 0.0, -0.5]))
        (fc, fh) = WALLS["front"]
        corners = [
            (fc[0] - fh[0], fc[1] + sy * fh[1], fc[2] + sz * fh[2])
            for sy, sz in ((-1, -1), (1, -1), (1, 1), (-1, 1))
        ]
        uv, front = project_to_screen(to_world(corners), cam.position, cam.wxyz, cam.fov_y, cam.aspect)
        assert front.all()
        centre = uv.mean(axis=0)
        polygon = [tuple(centre + 0.75 * (p - centre)) for p in uv]
        # The lasso's outline covers part of the back wall too (it stands right behind).
        buv, bfront = project_to_screen(
            grid.centres[grid.rows_of(back_keys)], cam.position, cam.wxyz, cam.fov_y, cam.aspect
        )
        lo, hi = np.min(polygon, axis=0), np.max(polygon, axis=0)
        assert (bfront & (buv >= lo).all(axis=1) & (buv <= hi).all(axis=1)).sum() > 20

        names = session.class_names()
        before = set(session.label[grid.rows_of(np.concatenate([front_keys, back_keys]))].tolist())
        slot = next(i + 1 for i, n in enumerate(names[:9]) if i not in before)
        target = names[slot - 1]
        assert session.tools.settings.depth_mode == "front"  # the default: front surface only
        page.keyboard.press("l")
        wait_until(lambda: session.tools.settings.tool == "lasso", 10, "the lasso to be armed")
        page.locator("#leap-tool-canvas").wait_for(timeout=10_000)
        _drag(page, [*polygon, polygon[0]])
        selected = wait_until(lambda: session.tools.selection.rows.size, 20, "the lasso selection")
        page.wait_for_timeout(1000)
        page.screenshot(
            path=str(
                browserfixtures.Path(__file__).resolve().parents[2]
                / "test-artifacts"
                / "viewer-tools-lasso.png"
            )
        )
        keys = grid.keys[session.tools.selection.rows]
        other = keys[~np.isin(keys, front_keys)]
        where = (grid.centres[grid.rows_of(other)] - pose0[:3, 3]) @ pose0[:3, :3]
        assert other.size == 0, (
            f"off the front wall: {np.isin(other, back_keys).sum()} of the back wall, "
            f"{other.size} in all, at {where[:10].round(2).tolist()}"
        )
        assert selected >= 10
        export_id = next(
            c["export_id"] for c in api.get(f"/projects/{pid}/classes").json()["data"] if c["name"] == target
        )
        with open_db(settings.database) as db:
            export_dir = crud.require_run(db, first["id"]).sequence_layout("00").export_dir
        seq = KittiSequence(seq_dir)
        sizes = [w.shape[0] for w in world]
        pairs = zip(seq.frame_ids, sizes, strict=True)
        before = [read_label(export_dir / f"{fid}.label", n) & 0xFFFF for fid, n in pairs]
        page.keyboard.press(str(slot))
        with open_db(settings.database) as db:
            (corr,) = wait_until(lambda: crud.list_corrections(db, pid), 20, "the correction")
        assert corr.class_name == target
        np.testing.assert_array_equal(np.sort(corr.keys), np.sort(keys))

    # The correction reaches the run's export at once (the apply-corrections job), without a run.
    def front_changed() -> tuple[int, int] | None:
        changed = total = 0
        for i, fid in enumerate(seq.frame_ids):
            after = read_label(export_dir / f"{fid}.label", sizes[i]) & 0xFFFF
            f = slice(sizes[i] - n_front - n_back, sizes[i] - n_back)
            b = slice(sizes[i] - n_back, sizes[i])
            in_sel = np.isin(voxel_keys(world[i][f], grid.voxel_size), corr.keys)
            total += int(in_sel.sum())
            changed += int((after[f][in_sel] == export_id).sum())
            np.testing.assert_array_equal(after[b], before[i][b], err_msg=f"back wall changed in scan {fid}")
            assert not (before[i][f][in_sel] == export_id).any()
        return (changed, total) if total > 0 and changed == total else None

    wait_until(front_changed, 30, "the corrected front wall in the export")
    assert len(api.get(f"/projects/{pid}/runs").json()["data"]) == 1, "no run was started"


def test_brush_with_a_class_filter_changes_only_that_class(tools_app: dict[str, Any]) -> None:
    import httpx

    from leap_core.datasets.kitti import KittiSequence
    from leap_core.selection import select_points, stroke_mask

    base, app = tools_app["base"], tools_app["app"]
    api = httpx.Client(base_url=f"{base}/api/v1", timeout=30)
    with browserfixtures.launch_chromium() as browser:
        page, session, info = _open(api, app, base, browser)
        pose0 = KittiSequence(info["project"]["dataset"]["path"]).frame(0).pose
        to_world = lambda p: np.asarray(p) @ pose0[:3, :3].T + pose0[:3, 3]  # noqa: E731
        cam = _look(session, page, to_world([6.0, -12.0, 14.0]), to_world([12.0, 0.0, -1.7]))
        names = session.class_names()
        road = names.index("road")
        stroke = [(0.2, 0.6), (0.5, 0.55), (0.8, 0.6)]

        # Without a filter the same stroke would take voxels of other classes as well.
        rows, _ = session.renderer.compute_view()
        mask = stroke_mask(
            stroke, session.tools.settings.brush_radius * cam.height_px, cam.width_px, cam.height_px
        )
        under = rows[select_points(session.grid.centres[rows], cam, mask, depth_mode="through")]
        assert (session.label[under] == road).sum() > 0 and (session.label[under] != road).sum() > 0

        page.get_by_text("Selection tools", exact=True).click()
        browserfixtures.pick(page, "Depth", "through")
        browserfixtures.pick(page, "Only class", "road")
        wait_until(
            lambda: (
                session.tools.settings.class_filter == "road"
                and session.tools.settings.depth_mode == "through"
            ),
            20,
            "the class filter",
        )
        label_before = session.label.copy()
        page.mouse.move(5, 5)
        page.keyboard.press("b")
        page.locator("#leap-tool-canvas").wait_for(timeout=10_000)
        _drag(page, stroke)
        wait_until(lambda: session.tools.selection.rows.size, 20, "the brush selection")
        picked = session.tools.selection.rows.copy()
        assert (label_before[picked] == road).all()
        page.keyboard.press("e")  # erase to unlabeled
        wait_until(lambda: bool((session.label[picked] == -1).all()), 20, "the erased voxels")
        changed = np.flatnonzero(session.label != label_before)
        assert changed.size == picked.size and (label_before[changed] == road).all()
        page.keyboard.press("Control+z")
        wait_until(lambda: bool((session.label == label_before).all()), 20, "the undo")
