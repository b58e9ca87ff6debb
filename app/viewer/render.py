"""Drawing the voxel map: coalesced redraws on a thread, exactly or with level of detail.

GUI callbacks only record the requested :class:`~app.viewer.view_logic.ViewState` (in the session's
:class:`~app.viewer.shared.SharedState`) and wake the drawing thread, which always draws the newest state; a
slider dragged across 50 values costs as many redraws as the thread has time for, not 50. A grid with more
voxels than ``LodConfig.budget`` is drawn within the budget (:mod:`app.viewer.lod`,
:mod:`app.viewer.lod_plan`): first as an evenly strided subset while its index is built on a thread, then
at full resolution near the focus and one point per block elsewhere.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time

import numpy as np
import numpy.typing as npt

from app.viewer import lod, lod_plan
from app.viewer import region_logic as rl
from app.viewer import view_logic as vl
from app.viewer.data import ReviewGrid
from app.viewer.lod import LodConfig
from app.viewer.lod_cache import LodCache
from app.viewer.lod_cull import thin_rows
from app.viewer.scene import FOCUS_SCALE, ReviewScene
from app.viewer.shared import Notifier, SharedState
from leap_core.fusion import key_coords

log = logging.getLogger(__name__)

SELECTION_RGB = (15, 15, 15)
"""Highlight of selected voxels: near-black, unlike every class colour and the light background."""


def view_score(
    grid: ReviewGrid,
    state: vl.ViewState,
    label: npt.NDArray[np.int16],
    conf: npt.NDArray[np.float32],
    corrected: npt.NDArray[np.bool_],
    shared: SharedState | None = None,
) -> tuple[npt.NDArray[np.floating], npt.NDArray[np.floating] | None]:
    """``(score, column)`` of the view: the value the threshold applies to, and the mode's column (the
    probability of ``state.class_index``, corrections applied, or the disagreement rate; None in the
    other modes)."""
    column = mode_column(grid, state, label, shared)
    column = vl.corrected_class_prob(state, label, column, corrected)
    return vl.view_score(state, conf, column), column


def mode_column(
    grid: ReviewGrid, state: vl.ViewState, label: npt.NDArray[np.int16], shared: SharedState | None
) -> npt.NDArray[np.floating] | None:
    """The per-voxel column a :data:`~app.viewer.view_logic.COLUMN_MODES` mode colours by: the class's
    posterior; the camera-vs-final disagreement rate (0 for voxels no camera-labelled point fell in;
    :meth:`RunOutputs.disagreement`, kept per grid); or whether the voxel's class (``label``) changed since
    the run before (:class:`app.viewer.run_delta.RunDelta`). None in the other modes."""
    if state.mode == "class_probability":
        return grid.class_prob(state.class_index)
    outputs = None if shared is None else shared.outputs
    if state.mode == "disagreement" and outputs is not None:
        return outputs.disagreement(grid)[0]
    delta, run = (None, None) if shared is None else (shared.delta, shared.run)
    if state.mode == "delta" and delta is not None and run is not None and shared is not None:
        return delta.column(run, grid, label, shared.class_names())
    if state.mode in vl.COLUMN_MODES:
        return np.zeros(grid.num_voxels, np.float32)
    return None


def blend_dim(colors: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """How voxels outside the focused region are drawn (:func:`app.viewer.view_logic.dim_outside`)."""
    return vl.dim_outside(colors, np.zeros(colors.shape[0], np.int64), np.zeros(0, np.int64))


class LodRenderer:
    """The voxel map's drawing: the view's rows and colours, the drawing thread, level of detail, the
    selection highlight and the map's display settings.

    Args:
        shared: the session's shared state (read; the class toggles are written here).
        scene: the viser facade drawn into.
        config: level of detail.
        notify: where draws are reported (panel ``on_drawn``, event ``drawn``).
        stop: set when the session closes (ends the drawing thread).
    """

    def __init__(
        self,
        shared: SharedState,
        scene: ReviewScene,
        config: LodConfig,
        notify: Notifier,
        stop: threading.Event,
    ) -> None:
        self.shared = shared
        self.scene = scene
        self.config = config
        self.notify = notify
        self._stop = stop
        self.lod_index: lod.LodIndex | None = None
        """Spatial index of the shown grid when it has more voxels than ``config.budget`` (else None: the
        map is drawn exactly)."""
        self.lod_focus: npt.NDArray[np.float64] | None = None
        """Point the full-resolution area is centred on (the scan, region or look-at point last focused)."""
        self.lod_plan: lod_plan.LodPlan | None = None
        """What the last level-of-detail draw sent (None after an exact draw)."""
        self.lod_seconds: dict[str, float] = {}
        """Server seconds of the last level-of-detail steps (``index`` at load, ``tables``, ``plan``)."""
        self.cache = LodCache(self.lod_seconds)
        """The level-of-detail view's per-block tables and overview colours."""
        self.map_visible = True
        """The panel's "Show voxel map": both map layers (voxels and overview) follow it."""
        self.last_draw_s = 0.0
        self.draw_count = 0
        self._lod_centre: npt.NDArray[np.float64] | None = None
        self._shown_blocks: tuple[lod.Blocks, npt.NDArray[np.int64]] | None = None
        self._shown: tuple[ReviewGrid, npt.NDArray[np.int64]] | None = None
        self._drawing = False
        self._indexing = False
        self._draw_wanted = threading.Event()
        self._drawn = threading.Condition()
        self._thread = threading.Thread(target=self._draw_loop, name="viewer-draw", daemon=True)

    def start(self) -> None:
        """Start the drawing thread (once the panel it reports to exists)."""
        self._thread.start()

    def close(self) -> None:
        """End the drawing thread (``stop`` is set by the session)."""
        self._draw_wanted.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def reset(self) -> None:
        """Forget the previous grid's index, caches and plan (a new grid is shown; caller holds the lock)."""
        self.lod_index = None
        self.lod_seconds = {}
        self.cache = LodCache(self.lod_seconds)
        self._shown_blocks, self.lod_plan = None, None
        self._lod_centre = None

    # ------------------------------------------------------------------------------------------ view
    def set_class_enabled(self, index: int, on: bool) -> None:
        """Show or hide the voxels of class ``index`` and schedule a redraw."""
        sh = self.shared
        with sh.lock:
            enabled = list(sh.view_state.enabled)
            if 0 <= index < len(enabled):
                enabled[index] = on
            sh.view_state = dataclasses.replace(sh.view_state, enabled=tuple(enabled))
        self._draw_wanted.set()

    def needs_lod(self, grid: ReviewGrid) -> bool:
        """Whether ``grid`` is drawn with level of detail (more voxels than the budget)."""
        return grid.num_voxels > self.config.budget

    def _budget(self, state: vl.ViewState) -> int:
        budget = self.config.budget
        return budget if state.max_points is None else max(2, min(budget, state.max_points))

    def compute_view(self, limit: int | None = None) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
        """Rows of the visible voxels and their colours for the current state (pure on the shared arrays);
        ``limit`` caps them like "Max points" (an even stride)."""
        sh = self.shared
        with sh.lock:
            grid, state = sh.grid, sh.view_state
            label, conf, corrected, palette = sh.label, sh.conf, sh.corrected, sh.palette
        if grid is None:
            return np.zeros(0, np.int64), np.zeros((0, 3), np.uint8)
        if limit is not None:
            state = dataclasses.replace(state, max_points=min(limit, state.max_points or limit))
        class_prob = mode_column(grid, state, label, sh)
        rows, colors = vl.render_view(state, label, conf, palette, class_prob, corrected)
        focus = sh.focus
        if focus is not None and focus.rows.size:
            colors = vl.dim_outside(colors, rows, focus.rows)
        return rows, colors

    def visible_mask(self, grid: ReviewGrid) -> npt.NDArray[np.bool_]:
        """(V,) the voxels the view shows (threshold and class toggles; every one, drawn or thinned)."""
        sh = self.shared
        with sh.lock:
            state, label, conf, corrected = sh.view_state, sh.label, sh.conf, sh.corrected
        score, _ = view_score(grid, state, label, conf, corrected, sh)
        return vl.visible_mask(label, score, state.threshold, state.enabled)

    # --------------------------------------------------------------------------------------- drawing
    def request_draw(self) -> None:
        """Schedule a redraw on the drawing thread."""
        self._draw_wanted.set()

    def wait_drawn(self, timeout: float = 10.0) -> bool:
        """Block until no redraw is pending (tests and the benchmark use this)."""
        deadline = time.monotonic() + timeout
        with self._drawn:
            while self._draw_wanted.is_set() or self._drawing or self._indexing:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._drawn.wait(min(left, 0.05))
        return True

    def draw_now(self) -> None:
        """Recompute and push the voxel layer (and selection highlight) synchronously."""
        t0 = time.perf_counter()
        with self.shared.lock:
            grid, index = self.shared.grid, self.lod_index
        if grid is None:
            return
        shown = self._draw_lod(grid, index) if index is not None else None
        if shown is None:
            shown = self._draw_exact()
        self.draw_selection()
        self.draw_focus()
        self.last_draw_s = time.perf_counter() - t0
        self.draw_count += 1
        self.notify.panel.on_drawn(shown=shown, total=grid.num_voxels, seconds=self.last_draw_s)
        with self._drawn:
            self._drawn.notify_all()
        self.notify.emit("drawn")

    def _draw_loop(self) -> None:
        while not self._stop.is_set():
            self._draw_wanted.wait()
            if self._stop.is_set():
                return
            self._drawing = True
            self._draw_wanted.clear()
            try:
                self.draw_now()
            except Exception:  # keep the viewer alive; the panel shows the error
                log.exception("viewer redraw failed")
                self.notify.panel.set_status("Redraw failed; see the server log.")
            finally:
                self._drawing = False
                with self._drawn:
                    self._drawn.notify_all()

    def _draw_exact(self) -> int:
        """Draw every visible voxel (a map within the budget; a bigger one evenly strided to the budget until
        its index is built); returns the points sent."""
        grid = self.shared.grid
        if grid is None:
            return 0
        # A big map: an even stride within the budget (colours computed for those voxels only).
        limit = self._budget(self.shared.view_state) if self.needs_lod(grid) else None
        rows, colors = self.compute_view(limit)
        self._put_voxels(grid, rows, colors)
        self.lod_plan = None
        if self.scene.overview.visible:
            self.scene.overview.visible = False
        return int(rows.shape[0])

    def _put_voxels(
        self, grid: ReviewGrid, rows: npt.NDArray[np.int64], colors: npt.NDArray[np.uint8]
    ) -> None:
        shown = self._shown
        if shown is not None and shown[0] is grid and np.array_equal(shown[1], rows):
            # Same voxels (a colouring change): only the colours go over the wire.
            self.scene.voxels.set_colors(colors)
        else:
            self.scene.voxels.set(grid.centres[rows], colors)
            self._shown = (grid, rows)

    def _draw_lod(self, grid: ReviewGrid, index: lod.LodIndex) -> int | None:
        """Draw a big map within the budget: the voxels near :attr:`lod_focus` in the voxel layer, one point
        per block elsewhere in the overview layer. Returns the points sent, or None when every visible voxel
        fits the budget (then the caller draws exactly)."""
        sh = self.shared
        with sh.lock:
            state, palette, region = sh.view_state, sh.palette, sh.focus
            label, conf, corrected = sh.label, sh.conf, sh.corrected
            focus = self.lod_focus
        cfg = self.config
        budget = self._budget(state)
        blocks = index.blocks(index.overview_level(budget, cfg.overview_share))
        score, class_prob = view_score(grid, state, label, conf, corrected, sh)
        hist, ssum = self.cache.block_tables(
            blocks,
            state=state,
            label=label,
            conf=conf,
            corrected=corrected,
            score=score,
            num_classes=grid.num_classes,
        )
        t0 = time.perf_counter()
        columns = lod_plan.enabled_columns(state.enabled, grid.num_classes)
        counts = lod_plan.visible_counts(hist, columns)
        if int(counts.sum()) <= budget:
            return None
        if focus is None:
            if self._lod_centre is None:  # until something is focused: the middle of the map's blocks
                lower = blocks.lower
                self._lod_centre = (lower.min(axis=0) + lower.max(axis=0) + blocks.edge) / 2.0
            focus = self._lod_centre
        plan = lod_plan.plan_view(blocks, index.order, counts, focus, cfg.radius, budget)
        rows = vl.visible_rows(state, label, score, plan.rows)
        colors = vl.view_colors(state, label, conf, class_prob, palette, rows)
        block_colors = self.cache.block_colors(hist, ssum, columns, state.mode, palette)[plan.blocks]
        if region is not None and region.rows.size:
            colors = vl.dim_outside(colors, rows, region.rows)
            block_colors = blend_dim(block_colors)
        self._put_voxels(grid, rows, colors)
        shown = self._shown_blocks
        if shown is not None and shown[0] is blocks and np.array_equal(shown[1], plan.blocks):
            self.scene.overview.set_colors(block_colors)
        else:
            self.scene.overview.set(blocks.mean[plan.blocks], block_colors)
            self._shown_blocks = (blocks, plan.blocks)
        size = blocks.edge * self.scene.voxels.point_size / grid.voxel_size
        if not np.isclose(self.scene.overview.point_size, size):
            self.scene.overview.point_size = size
        if self.scene.overview.visible != self.map_visible:
            self.scene.overview.visible = self.map_visible
        self.lod_plan = plan
        self.lod_seconds["plan"] = time.perf_counter() - t0
        return int(rows.shape[0] + plan.blocks.shape[0])

    def draw_selection(self) -> None:
        """Highlight the selection (voxels, their overview blocks, or the shown scan's points)."""
        sh = self.shared
        grid, selection = sh.grid, sh.selection
        rows = selection.rows
        if grid is None or rows.size == 0:
            self.scene.selection.visible = False
            return
        plan, index = self.lod_plan, self.lod_index
        if selection.target == "map" and plan is not None and index is not None:
            # Selected voxels of the overview are highlighted by their blocks: the budget holds.
            points = thin_rows(index.blocks(plan.level), plan.full, grid.centres, rows)
            cols = np.empty((points.shape[0], 3), np.uint8)
            cols[:] = SELECTION_RGB
            self.scene.selection.set(points, cols)
            self.scene.selection.visible = True
            return
        cols = np.empty((rows.shape[0], 3), np.uint8)
        cols[:] = SELECTION_RGB
        if selection.target == "scan":
            view = sh.scan_view
            if view is None or view.frame_id != selection.frame_id:
                self.scene.selection.visible = False
                return
            self.scene.selection.set(view.points[rows], cols)
        else:
            self.scene.selection.set(grid.centres[rows], cols)
        self.scene.selection.visible = True

    def draw_focus(self) -> None:
        """Draw the focused review region filled on top of the map (its voxels' current class colours
        pulled toward the review cyan, larger points), or hide it when nothing is focused."""
        sh = self.shared
        with sh.lock:
            grid, region, label, palette = sh.grid, sh.focus, sh.label, sh.palette
        if grid is None or region is None or region.rows.size == 0 or not self.map_visible:
            self.scene.focus.visible = False
            return
        colors = rl.highlight_colors(vl.class_colors(label[region.rows], palette))
        self.scene.focus.set(grid.centres[region.rows], colors)
        self.scene.focus.visible = True

    # ------------------------------------------------------------------------------- level of detail
    def build_index(self, grid: ReviewGrid) -> None:
        """Build ``grid``'s level-of-detail index on a thread, then redraw with it."""
        self._indexing = True

        def build() -> None:
            try:
                t0 = time.perf_counter()
                index = lod.build_index(grid.centres, grid.voxel_size, key_coords(grid.keys))
                cfg = self.config
                level = index.overview_level(self._budget(self.shared.view_state), cfg.overview_share)
                blocks = index.blocks(level)
                # Per-voxel block arrays now, not on the first draw or correction that needs them.
                _ = blocks.of_row, blocks.mean, index.blocks(index.query_level(cfg.query_edge))
                with self.shared.lock:
                    if self.shared.grid is grid:
                        self.lod_index = index
                        self.lod_seconds["index"] = time.perf_counter() - t0
                self.request_draw()
            except Exception:  # keep the strided view; the panel says why
                log.exception("building the viewer's level-of-detail index failed")
                self.notify.panel.set_status(
                    "The map's level of detail could not be built; see the server log."
                )
            finally:
                self._indexing = False
                with self._drawn:
                    self._drawn.notify_all()

        threading.Thread(target=build, name="viewer-lod-index", daemon=True).start()

    def focus_lod(self, point: npt.ArrayLike) -> None:
        """Centre the full-resolution area of a big map on ``point`` (3,) and redraw (no-op for a map drawn
        exactly; kept for the level-of-detail view while its index is built)."""
        grid = self.shared.grid
        if grid is None or not self.needs_lod(grid):
            return
        self.lod_focus = np.asarray(point, dtype=np.float64).reshape(3).copy()
        if self.lod_index is not None:
            self.request_draw()

    def camera_moved(self, look_at: npt.NDArray[np.float64]) -> None:
        """Follow a browser's look-at point once it left the full-resolution area's centre by
        ``refine_distance`` (horizontally); the scene calls this on every camera update."""
        if self.lod_index is None:
            return
        focus = self.lod_focus if self.lod_focus is not None else self._lod_centre
        if focus is None or float(np.hypot(*(look_at[:2] - focus[:2]))) > self.config.refine_distance:
            self.focus_lod(look_at)

    # ------------------------------------------------------------------------------- display settings
    def set_map_visible(self, on: bool) -> None:
        """Show or hide the voxel map (both its layers)."""
        self.map_visible = bool(on)
        self.scene.voxels.visible = self.map_visible
        self.draw_focus()
        if self.lod_plan is not None or not self.map_visible:
            self.scene.overview.visible = self.map_visible

    def set_point_size(self, size: float) -> None:
        """Voxel point size (m); overview blocks keep their size relative to it."""
        grid = self.shared.grid
        self.scene.voxels.point_size = float(size)
        self.scene.focus.point_size = float(size) * FOCUS_SCALE
        if grid is not None and self._shown_blocks is not None:
            self.scene.overview.point_size = self._shown_blocks[0].edge * float(size) / grid.voxel_size


__all__ = ["SELECTION_RGB", "LodRenderer", "blend_dim", "view_score"]
