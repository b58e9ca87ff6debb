"""The panel's "Selection tools" folder: tool, depth mode, distance, class filter, target, scope, brush size.

The widgets write :class:`~app.viewer.records.ToolSettings` through
:meth:`~app.viewer.selection_tool.SelectionTool.set_tools`, and follow the session's ``"tools"`` events, so
the viewer page's keys (web/viewer/tools.js, through app/api/routes/viewer_tools.py) and the panel always
show the same settings. Arming "box" arms viser's own rectangle selection; lasso and brush are drawn by the
page.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from app.viewer.selection_tool import SelectionTool
from app.viewer.session import ReviewSession

if TYPE_CHECKING:
    from app.viewer.panel import ReviewPanel

TOOLS = ("none (orbit)", "lasso", "brush", "box")
DEPTHS = ("front surface only", "through")
TARGETS = ("voxel map", "scan points")
SCOPES = ("voxel map", "this scan only")
ANY_CLASS = "any class"
_DEPTH_OF = {"front surface only": "front", "through": "through"}
_PLACE_OF = {"voxel map": "map", "scan points": "scan", "this scan only": "scan"}


class ToolsPanel:
    """Builds the folder on ``panel``'s GUI (one line in ``ReviewPanel.__init__``)."""

    def __init__(self, panel: ReviewPanel) -> None:
        self.panel = panel
        self.s: ReviewSession = panel.s
        self.tools: SelectionTool = panel.s.tools
        gui = panel.gui
        self._syncing = False
        with gui.add_folder("Selection tools", order=5.5, expand_by_default=False):
            self.tool = gui.add_dropdown(
                "Tool",
                TOOLS,
                initial_value=TOOLS[0],
                hint="Lasso (L), brush (B) or box (M); then drag on the view",
            )
            self.depth = gui.add_dropdown(
                "Depth",
                DEPTHS,
                initial_value=DEPTHS[0],
                hint="Front surface only: what is hidden behind is not selected",
            )
            self.distance = gui.add_number("Front distance (m)", 0.5, min=0.0, max=100.0, step=0.1)
            self.class_filter = gui.add_dropdown("Only class", [ANY_CLASS], initial_value=ANY_CLASS)
            self.target = gui.add_dropdown("Select from", TARGETS, initial_value=TARGETS[0])
            self.scope = gui.add_dropdown(
                "Correction scope",
                SCOPES,
                initial_value=SCOPES[0],
                hint="This scan only: for moving objects the voxel map smears",
            )
            self.brush = gui.add_slider("Brush radius", min=0.005, max=0.2, step=0.005, initial_value=0.03)
            self.erase_button = gui.add_button("Erase to unlabeled", disabled=True)
            self.info = gui.add_markdown(
                "Keys: L lasso, B brush, M box, 1-9 assign (1 2: the 12th class, 0: the 10th), E erase, "
                "Esc clear."
            )
        g = panel.guard
        widgets = (
            self.tool,
            self.depth,
            self.distance,
            self.class_filter,
            self.target,
            self.scope,
            self.brush,
        )
        for widget in widgets:
            widget.on_update(g(lambda _: self._changed()))
        self.erase_button.on_click(g(lambda _: self.s.corrections.assign_selection("")))
        self.s.on_event(self._on_event)

    def _changed(self) -> None:
        if self._syncing:
            return
        tool = str(self.tool.value)
        cls = str(self.class_filter.value)
        self.tools.set_tools(
            tool=None if tool == TOOLS[0] else tool,
            depth_mode=_DEPTH_OF[str(self.depth.value)],
            distance=float(self.distance.value),
            class_filter=None if cls == ANY_CLASS else cls,
            target=_PLACE_OF[str(self.target.value)],
            scope=_PLACE_OF[str(self.scope.value)],
            brush_radius=float(self.brush.value),
        )

    def _on_event(self, name: str) -> None:
        if name == "loaded":
            self._fill_classes()
        elif name == "tools":
            self._show()
        elif name in ("selection", "corrected"):
            self.erase_button.disabled = self.tools.selection.rows.size == 0

    def _fill_classes(self) -> None:
        names = [ANY_CLASS, *self.s.class_names()]
        self.class_filter.options = names
        if self.class_filter.value not in names:
            self._set(self.class_filter, ANY_CLASS)

    def _set(self, widget: Any, value: Any) -> None:
        if widget.value != value:
            widget.value = value

    def _show(self) -> None:
        """Reflect the session's settings (changed by a key on the page, or by these widgets)."""
        t = self.tools.settings
        self._syncing = True
        try:
            self._set(self.tool, t.tool or TOOLS[0])
            self._set(self.depth, DEPTHS[0] if t.depth_mode == "front" else DEPTHS[1])
            self._set(self.distance, t.distance)
            self._set(self.class_filter, t.class_filter or ANY_CLASS)
            self._set(self.target, TARGETS[0] if t.target == "map" else TARGETS[1])
            self._set(self.scope, SCOPES[0] if t.scope == "map" else SCOPES[1])
            self._set(self.brush, t.brush_radius)
            self.distance.disabled = t.depth_mode != "front"
        finally:
            self._syncing = False
        if t.tool == "box":
            if not self.s.scene.rect_select_armed:
                self.panel.arm_select()
        elif self.s.scene.rect_select_armed:
            self.s.scene.disarm_rect_select()


__all__ = ["ToolsPanel"]
