"""The viewer's GUI panel: typed viser widgets wired to a :class:`~app.viewer.session.ReviewSession`.

Widgets only translate user actions into session calls and show what the session reports back
(``on_*`` methods, the session's :class:`~app.viewer.records.SessionView` protocol). Errors from an action
(an invalid class name, a failed save) are shown in the status line instead of breaking the viewer.
"""

from __future__ import annotations

import functools
import html
import logging
from collections.abc import Callable
from typing import Any

import numpy as np
import viser

from app.jobs.stages import stage_words
from app.viewer import view_logic as vl
from app.viewer.data import ScanView
from app.viewer.panel_nav import NavPanel
from app.viewer.panel_review import QUEUE_KINDS, ObjectQueuePanel, ReviewQueuePanel
from app.viewer.panel_tools import ToolsPanel
from app.viewer.records import Inspection, ObjectInfo, RunInfo
from app.viewer.region_logic import Region
from app.viewer.selection_tool import camera_of
from app.viewer.session import ReviewSession
from leap_core.labelers import LABELERS

log = logging.getLogger(__name__)

COLOR_BY = (
    "class",
    "confidence",
    "class probability",
    "camera vs final disagreement",
    "Δ since the run before",
    "objects",
)
"""Labels of the colouring modes, in :data:`app.viewer.view_logic.ColorMode` order."""
_MODE_OF: dict[str, vl.ColorMode] = {
    "class": "class",
    "confidence": "confidence",
    "class probability": "class_probability",
    "camera vs final disagreement": "disagreement",
    "Δ since the run before": "delta",
    "objects": "objects",
}


def _hex(rgb: Any) -> str:
    r, g, b = (int(v) for v in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"


def legend_html(
    mode: str, names: list[str], palette: np.ndarray, class_name: str | None = None, note: str | None = None
) -> str:
    """HTML legend: class swatches in the class and Δ modes (the Δ mode first says what it compares with,
    ``note``), a colour bar with ticks in the scalar modes."""
    if mode == "objects":
        return (
            '<div style="font-size:11px">The shown scan\'s points in the colour of their object (track id); '
            "<b>full colour: moving</b>, pale: static, grey: no object. The map is pale. Click a point to "
            "see its object.</div>"
        )
    if mode == "delta":
        grey = _hex(vl.UNCHANGED_RGB)
        head = (
            f'<div style="font-size:11px"><span style="display:inline-block;width:12px;height:12px;'
            f'border-radius:2px;background:{grey}"></span> {html.escape(note or "")}</div>'
        )
        return head + legend_html("class", names, palette)
    if mode == "class":
        items = "".join(
            f'<div style="display:flex;align-items:center;gap:4px;font-size:11px;white-space:nowrap">'
            f'<span style="display:inline-block;width:12px;height:12px;border-radius:2px;'
            f'background:{_hex(rgb)}"></span>{html.escape(n)}</div>'
            # Not strict: the palette is refreshed with the grid, so while none is loaded a class just added
            # to the schema has a name but no colour yet (and gets no swatch).
            for n, rgb in zip(names, palette, strict=False)
        )
        # Three columns: 19 classes in 7 rows, so the Scan section starts within a 720 px high window.
        return f'<div style="display:grid;grid-template-columns:1fr 1fr 1fr;gap:1px 6px">{items}</div>'
    stops = ", ".join(f"{_hex(vl.CONFIDENCE_LUT[int(i)])}" for i in np.linspace(0, 255, 9))
    title = {
        "confidence": "confidence (max posterior)",
        "disagreement": "share of camera-labelled points the final label disagrees with",
    }.get(mode, f"P({html.escape(class_name or '')})")
    return (
        f'<div style="font-size:12px">{title}'
        f'<div style="height:12px;border-radius:2px;background:linear-gradient(to right, {stops})"></div>'
        '<div style="display:flex;justify-content:space-between"><span>0</span><span>0.25</span>'
        "<span>0.5</span><span>0.75</span><span>1</span></div></div>"
    )


class ReviewPanel:
    """Builds the panel on the session's viser server and keeps it in sync with the session."""

    # Class note: viser defines each widget's ``value`` setter apart from its getter (a method sits between
    # them), which mypy reads as a read-only property, so the assignments to ``.value`` below carry
    # ``type: ignore[misc]``. Only that code is ignored: the assigned value is still checked against the
    # widget's type.

    def __init__(self, session: ReviewSession) -> None:
        self.s = session
        gui = session.scene.server.gui
        self.gui = gui
        self._class_boxes: list[viser.GuiCheckboxHandle] = []
        self._error: str | None = None
        """The error a failed action put in the status line (cleared by the next action that works)."""

        self._add_run_folder()

        with gui.add_folder("View", order=1):
            self.color_by = gui.add_dropdown("Color by", COLOR_BY, initial_value="class")
            self.prob_class = gui.add_dropdown("Class", ["-"], initial_value="-", visible=False)
            self.threshold = gui.add_slider("Min confidence", min=0.0, max=1.0, step=0.01, initial_value=0.0)
            self.legend = gui.add_html("")
            self._add_display_folder()

        self.classes_folder = gui.add_folder("Classes shown", order=2, expand_by_default=False)

        self.scan_folder = gui.add_folder("Scan", order=3, expand_by_default=True)
        with self.scan_folder:
            self.scan_slider = gui.add_slider("Scan", min=0, max=1, step=1, initial_value=0, disabled=True)
            self.scan_info = gui.add_markdown("")
            self.camera = gui.add_dropdown(
                "Camera",
                ["image_2"],
                initial_value="image_2",
                visible=False,
                hint="The rig camera whose image is shown",
            )
            self.scan_image = gui.add_image(
                np.zeros((8, 8, 3), np.uint8), label="camera + labels", format="jpeg", visible=False
            )

        with gui.add_folder("Review queue", order=4, expand_by_default=False):
            self.review = ReviewQueuePanel(self)
            with gui.add_folder("Objects to review", expand_by_default=False):
                self.objects = ObjectQueuePanel(self)

        with gui.add_folder("Corrections", order=5, expand_by_default=False):
            self.assign_class = gui.add_dropdown("Assign class", ["-"], initial_value="-")
            self.select_button = gui.add_button("Select box", hint="Then drag a box over the voxels")
            self.apply_button = gui.add_button("Apply to selection", disabled=True)
            self.clear_button = gui.add_button("Clear selection", disabled=True)
            self.undo_button = gui.add_button("Undo", disabled=True)
            self.redo_button = gui.add_button("Redo", disabled=True)
            self.corr_info = gui.add_markdown("")

        with gui.add_folder("Classes and prompts", order=6, expand_by_default=False):
            self.edit_class = gui.add_dropdown("Edit class", ["-"], initial_value="-")
            self.class_name = gui.add_text("Name", "")
            self.class_color = gui.add_rgb("Color", (200, 200, 200))
            self.class_prompts = gui.add_text("Prompts", "", hint="Comma-separated prompt list")
            self.save_class = gui.add_button("Save class")
            self.remove_class = gui.add_button("Remove class", color="red")
            self.new_class = gui.add_text("New class", "")
            self.add_class = gui.add_button("Add class")
            self.steer_info = gui.add_markdown("")

        self.nav = NavPanel(session, gui, self.scan_folder, self.guard)
        self._wire()
        self.on_schema()
        self.tools = ToolsPanel(self)

    def _add_run_folder(self) -> None:
        # The run shown, its progress and who reviews it: the first folder, above the view settings.
        gui, session = self.gui, self.s
        with gui.add_folder("Run", order=0):
            self.status = gui.add_markdown("Loading…")
            self.progress = gui.add_progress_bar(0.0, visible=False)
            self.labeler = gui.add_dropdown(
                "2D labeler",
                tuple(LABELERS),
                initial_value=session.backend.labeler(),
                hint="The project's 2D labeler: the next re-run uses it ("
                + ", ".join(spec.title for spec in LABELERS.values())
                + ")",
            )
            self.rerun_button = gui.add_button(
                "Re-run",
                hint="Start a new run with the current classes, prompts, 2D labeler and corrections",
                color="blue",
            )
            self.stay = gui.add_checkbox(
                "Stay on this run",
                False,
                hint="Keep this run shown when a newer run of the project finishes (else it loads)",
            )
            reviewer = getattr(session.backend, "reviewer", None)
            self.reviewer = gui.add_markdown(
                f"Reviewing as **{html.escape(reviewer)}**"
                if reviewer
                else "No reviewer name: give it in the project page's *Reviewers* card first."
            )

    def _add_display_folder(self) -> None:
        # Rarely changed settings stay folded so that Scan, Review and Corrections fit at 1280×720.
        gui = self.gui
        with gui.add_folder("Display", expand_by_default=False):
            self.point_size = gui.add_slider("Point size", min=0.02, max=1.0, step=0.01, initial_value=0.2)
            self.limit = gui.add_checkbox("Limit points", False, hint="Decimate the map for slow browsers")
            self.max_points = gui.add_number(
                "Max points", int(self.s.config.max_points), min=1_000, step=1_000, visible=False
            )
            self.show_scan = gui.add_checkbox("Show scan", True)
            self.show_map = gui.add_checkbox("Show voxel map", True)
            self.stats = gui.add_markdown("")

    # ------------------------------------------------------------------------------------ wiring
    def guard(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            try:
                out = fn(*args, **kwargs)
            except Exception as exc:
                log.warning("viewer action %s failed: %s", fn.__name__, exc)
                self._error = f"**Error:** {html.escape(str(exc))}"
                self.set_status(self._error)
                return None
            # An action that worked clears the error a failed one left (unless something said more since).
            if self._error is not None and self.status.content == self._error:
                self.set_status("")
            self._error = None
            return out

        return wrapper

    def _wire(self) -> None:
        s, g = self.s, self.guard
        self.color_by.on_update(g(lambda _: self._mode_changed()))
        self.prob_class.on_update(g(lambda _: self._mode_changed()))
        self.threshold.on_update(g(lambda _: s.set_state(threshold=float(self.threshold.value))))
        self.point_size.on_update(g(lambda _: s.renderer.set_point_size(self.point_size.value)))
        self.limit.on_update(g(lambda _: self._limit_changed()))
        self.max_points.on_update(g(lambda _: self._limit_changed()))
        self.scan_slider.on_update(g(lambda _: self._slider_moved()))
        self.camera.on_update(g(lambda _: self._camera_chosen()))
        self.show_scan.on_update(g(lambda _: self._scan_visibility()))
        self.show_map.on_update(g(lambda _: s.renderer.set_map_visible(self.show_map.value)))
        # The same box tool as the Selection tools' "box" (and key M), so the Tool dropdown shows it armed.
        self.select_button.on_click(g(lambda _: s.tools.set_tools(tool="box")))
        self.apply_button.on_click(g(lambda _: s.corrections.assign_selection(str(self.assign_class.value))))
        self.clear_button.on_click(g(lambda _: s.tools.clear_selection()))
        self.undo_button.on_click(g(lambda _: s.corrections.undo()))
        self.redo_button.on_click(g(lambda _: s.corrections.redo()))
        self.edit_class.on_update(g(lambda _: self._fill_class_editor()))
        self.save_class.on_click(g(lambda _: self._save_class()))
        self.remove_class.on_click(g(lambda _: self._remove_class()))
        self.add_class.on_click(g(lambda _: self._add_class()))
        self.rerun_button.on_click(g(lambda _: self._rerun()))
        self.labeler.on_update(g(lambda _: self._labeler_chosen()))
        self.stay.on_update(g(lambda _: s.set_stay_on_run(bool(self.stay.value))))

    def _mode_changed(self) -> None:
        mode = _MODE_OF[str(self.color_by.value)]
        self.prob_class.visible = mode == "class_probability"
        names = self.s.class_names()
        index = names.index(self.prob_class.value) if self.prob_class.value in names else 0
        self.threshold.label = {
            "class_probability": "Min probability",
            "disagreement": "Min disagreement",
        }.get(mode, "Min confidence")
        self.s.set_state(mode=mode, class_index=index)
        self._update_legend()

    def _limit_changed(self) -> None:
        self.max_points.visible = bool(self.limit.value)
        self.s.set_state(max_points=int(self.max_points.value) if self.limit.value else None)

    def _slider_moved(self) -> None:
        # The session moves the slider itself after a key or button step: that echo must not reload.
        if int(self.scan_slider.value) != self.s.player.frame_pos:
            self.s.player.show_scan(int(self.scan_slider.value))

    def _camera_chosen(self) -> None:
        outputs = self.s.outputs
        names = outputs.camera_names() if outputs is not None else []
        chosen = str(self.camera.value)
        if chosen in names and names.index(chosen) != self.s.player.camera:
            self.s.player.set_camera(names.index(chosen))

    def _scan_visibility(self) -> None:
        on = bool(self.show_scan.value)
        self.s.scene.scan.visible = on
        self.s.scene.camera.visible = on

    def arm_select(self) -> None:
        """Arm viser's rectangle selection: the next box dragged on the canvas selects (the box tool)."""
        s = self.s

        def on_rect(event: viser.SceneRectSelectEvent) -> None:
            s.scene.disarm_rect_select()
            s.tools.select_screen("box", [event.screen_min, event.screen_max], camera_of(event.client.camera))
            if s.tools.settings.tool == "box":
                s.tools.set_tools(tool=None)

        s.scene.arm_rect_select(self.guard(on_rect))
        self.corr_info.content = "Drag a box over the voxels to select them."

    def _fill_class_editor(self) -> None:
        schema = self.s.classes.schema
        if self.edit_class.value not in schema.names:
            return
        c = schema.classes[schema.index(str(self.edit_class.value))]
        self.class_name.value = c.name  # type: ignore[misc]  # viser: split setter, see class note
        r, g, b = (int(v) for v in c.color)
        self.class_color.value = (r, g, b)  # type: ignore[misc]  # viser: split setter, see class note
        prompts = ", ".join(c.prompts)
        self.class_prompts.value = prompts  # type: ignore[misc]  # viser: split setter, see class note

    def _save_class(self) -> None:
        schema = self.s.classes.schema
        index = schema.index(str(self.edit_class.value))
        prompts = [p.strip() for p in str(self.class_prompts.value).split(",") if p.strip()]
        name = str(self.class_name.value).strip()
        r, g, b = (int(v) for v in self.class_color.value)
        self.s.classes.update_class(index, name=name, color=(r, g, b), prompts=prompts)
        self.edit_class.value = name  # type: ignore[misc]  # viser: split setter, see class note
        self.steer_info.content = f"Saved class **{html.escape(name)}**; press *Re-run* to apply prompts."

    def _remove_class(self) -> None:
        schema = self.s.classes.schema
        name = str(self.edit_class.value)
        self.s.classes.remove_class(schema.index(name))
        self.steer_info.content = f"Removed class **{html.escape(name)}**."

    def _add_class(self) -> None:
        name = str(self.new_class.value).strip()
        if not name:
            raise ValueError("type a name for the new class first")
        self.s.classes.add_class(name)
        self.new_class.value = ""  # type: ignore[misc]  # viser: split setter, see class note
        self.edit_class.value = name  # type: ignore[misc]  # viser: split setter, see class note
        self.steer_info.content = f"Added class **{html.escape(name)}**."

    def _labeler_chosen(self) -> None:
        name = str(self.labeler.value)
        if name == self.s.backend.labeler():
            return
        try:
            self.s.backend.set_labeler(name)
        except Exception:
            self.labeler.value = self.s.backend.labeler()  # type: ignore[misc]  # viser: split setter, see class note
            raise
        self.set_status(f"2D labeler: **{html.escape(LABELERS[name].title)}** for the next re-run.")

    def _rerun(self) -> None:
        self.rerun_button.disabled = True
        try:
            run_id = self.s.runs.rerun()
        except Exception:
            self.rerun_button.disabled = False
            raise
        self.on_run_progress(self.s.backend.run_info(run_id))

    # ----------------------------------------------------------------------------- session → panel
    def set_status(self, text: str) -> None:
        self.status.content = text

    def _update_legend(self) -> None:
        mode = _MODE_OF[str(self.color_by.value)]
        names = self.s.class_names()
        cls = names[self.s.state.class_index] if names and self.s.state.class_index < len(names) else None
        self.legend.content = legend_html(mode, names, self.s.palette, cls, self._delta_note(mode))

    def _delta_note(self, mode: str) -> str | None:
        sh = self.s.shared
        if mode != "delta" or sh.delta is None or sh.run is None:
            return None
        base = sh.delta.base_run(sh.run)
        if base is None:
            return "no earlier finished run to compare with: nothing is marked as changed"
        return f"unchanged since run {base.number}; changed voxels in their class colour"

    def on_run_loaded(self) -> None:
        s = self.s
        names = s.class_names()
        run = s.run
        grid = s.grid
        assert run is not None and grid is not None
        self.prob_class.options = names
        if self.prob_class.value not in names:
            self.prob_class.value = names[0]  # type: ignore[misc]  # viser: split setter, see class note
        self.assign_class.options = names
        self.review.on_run_loaded(names)
        self.objects.on_run_loaded()
        if self.assign_class.value not in names:
            self.assign_class.value = names[0]  # type: ignore[misc]  # viser: split setter, see class note
        for box in self._class_boxes:
            box.remove()
        self._class_boxes = []
        with self.classes_folder:
            for i, n in enumerate(names):
                box = self.gui.add_checkbox(n, True)
                box.on_update(self.guard(functools.partial(self._toggle_class, i)))
                self._class_boxes.append(box)
        size = round(float(grid.voxel_size), 2)
        self.point_size.value = size  # type: ignore[misc]  # viser: split setter, see class note
        n_frames = len(s.outputs.frame_indices) if s.outputs is not None else 0
        cameras = s.outputs.camera_names() if s.outputs is not None else ["image_2"]
        self.camera.options = cameras
        self.camera.visible = len(cameras) > 1
        if self.camera.value not in cameras or s.player.camera >= len(cameras):
            s.player.camera = 0
            self.camera.value = cameras[0]  # type: ignore[misc]  # viser: split setter, see class note
        self.scan_slider.max = max(1, n_frames - 1)
        self.scan_slider.disabled = n_frames <= 1
        self.set_status(
            f"Run **{run.number}** (id {run.run_id}): {grid.num_voxels:,} voxels, "
            f"{len(names)} classes, voxel {grid.voxel_size:g} m."
        )
        self.rerun_button.disabled = s.runs.watched_run is not None
        self.stay.label = f"Stay on run {run.number}"
        self._update_legend()
        self.on_history()
        self.nav.inspect_folder.visible = False
        self.nav.on_run_loaded(names)
        self.nav.on_nav()

    def _toggle_class(self, index: int, event: Any) -> None:
        self.s.renderer.set_class_enabled(index, bool(event.target.value))

    def on_drawn(self, *, shown: int, total: int, seconds: float) -> None:
        self.stats.content = f"Showing {shown:,} of {total:,} voxels (drawn in {seconds * 1000:.0f} ms)."

    def on_scan(self, view: ScanView, pos: int, count: int) -> None:
        labelled = int((view.label >= 0).sum())
        self.scan_info.content = (
            f"Scan **{view.frame_id}** ({pos + 1}/{count}): {view.points.shape[0]:,} points, "
            f"{labelled:,} labelled."
        )
        if view.camera != self.camera.value and view.camera in self.camera.options:
            self.camera.value = view.camera  # type: ignore[misc]  # viser: split setter, see class note
        if view.overlay is not None:
            self.scan_image.image = view.overlay
            self.scan_image.visible = True
        else:
            self.scan_image.visible = False
        if int(self.scan_slider.value) != pos:
            self.scan_slider.value = pos  # type: ignore[misc]  # viser: split setter, see class note

    def on_region(self, region: Region, pos: int, count: int, kind: str) -> None:
        self.review.on_region(region, pos, count, kind)

    def on_focus_cleared(self) -> None:
        self.review.on_focus_cleared()

    def on_queue(self, building: bool) -> None:
        self.review.on_queue(building)

    def on_selection(self, count: int) -> None:
        self.apply_button.disabled = count == 0
        self.clear_button.disabled = count == 0
        self.corr_info.content = f"{count:,} voxels selected." if count else self._corr_summary()

    def _corr_summary(self) -> str:
        n = self.s.corrections.correction_count()
        return f"{n} active correction{'' if n == 1 else 's'} (applied in every later run)."

    def on_history(self) -> None:
        self.undo_button.disabled = not self.s.corrections.history.can_undo
        self.redo_button.disabled = not self.s.corrections.history.can_redo
        self.corr_info.content = self._corr_summary()
        if self.s.grid is not None:
            self.nav.update_histogram()

    def on_inspect(self, inspection: Inspection) -> None:
        self.nav.on_inspect(inspection)

    def on_object(self, found: ObjectInfo | None) -> None:
        self.nav.on_object(found)
        self.objects.on_object(found)

    def on_nav(self) -> None:
        self.nav.on_nav()

    def on_schema(self) -> None:
        names = self.s.classes.schema.names
        current = self.edit_class.value
        self.edit_class.options = names
        shown = current if current in names else names[0]
        self.edit_class.value = shown  # type: ignore[misc]  # viser: split setter, see class note
        self._fill_class_editor()
        self._update_legend()

    def on_run_progress(self, info: RunInfo) -> None:
        if info.status in ("queued", "running"):
            self.progress.visible = True
            percent = float(min(100.0, max(0.0, info.percent)))
            self.progress.value = percent  # type: ignore[misc]  # viser: split setter, see class note
            self.rerun_button.disabled = True
            stage = f", {stage_words(info.stage)}" if info.stage else ""
            self.set_status(f"Run {info.number} {info.status}{stage}: {info.percent:.0f}%")
            return
        self.progress.visible = False
        self.rerun_button.disabled = False
        if info.status == "done":
            self.set_status(f"Run {info.number} done; loading…")
        else:
            why = f": {html.escape(info.error)}" if info.error else ""
            self.set_status(f"Run {info.number} {info.status}{why}")


__all__ = ["COLOR_BY", "QUEUE_KINDS", "ReviewPanel", "legend_html"]
