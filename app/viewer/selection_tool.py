"""Picking on screen: the selection tools (lasso, brush, box) with their settings, and the click inspector.

The page (web/viewer/tools.js through :mod:`app.api.routes.viewer_tools`) and the panel's "Selection tools"
folder share :attr:`SelectionTool.settings`. A selection is made with the camera of a browser, on every
visible voxel of the grid (a big map's coarse cubes are culled first, :mod:`app.viewer.lod_cull`) or on the
shown scan's points; it lands in the session's shared state, where the corrections read it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import numpy.typing as npt

from app.viewer import lod_cull
from app.viewer import nav_logic as nl
from app.viewer.records import Inspection, ObjectInfo, Selection, Target, ToolKind, ToolSettings
from app.viewer.render import LodRenderer
from app.viewer.scene import ReviewScene
from app.viewer.shared import Notifier, SharedState
from leap_core import selection as sel
from leap_core.picking import pick_voxel
from leap_core.pipeline.object_corrections import NO_CLASS, CorrectedTracks


def camera_of(camera: Any) -> sel.PinholeCamera:
    """The :class:`~leap_core.selection.PinholeCamera` of a viser client camera (its canvas size capped at
    :data:`~leap_core.selection.MAX_CANVAS_PX`, keeping the aspect)."""
    w, h = int(camera.image_width), int(camera.image_height)
    scale = min(1.0, sel.MAX_CANVAS_PX / max(w, h, 1))
    p = np.asarray(camera.position, dtype=np.float64).reshape(3)
    q = np.asarray(camera.wxyz, dtype=np.float64).reshape(4)
    return sel.PinholeCamera(
        (float(p[0]), float(p[1]), float(p[2])),
        (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
        float(camera.fov),
        max(1, int(w * scale)),
        max(1, int(h * scale)),
    )


class SelectionTool:
    """Selections and the click inspector.

    Args:
        shared: the session's shared state (writes ``selection``).
        scene: the viser facade (client cameras, the scan layer's point size, the inspected marker).
        renderer: what the view shows (rows, visible mask, level-of-detail index) and the highlight.
        query_edge: smallest edge (m) of the coarse cubes a big map's selections and clicks are culled with.
        notify: where changes are reported (panel ``on_selection`` / ``on_inspect``, events ``selection``
            and ``tools``).
    """

    def __init__(
        self,
        shared: SharedState,
        scene: ReviewScene,
        renderer: LodRenderer,
        query_edge: float,
        notify: Notifier,
    ) -> None:
        self.shared = shared
        self.scene = scene
        self.renderer = renderer
        self.notify = notify
        self._query_edge = query_edge
        self.settings = ToolSettings()
        """The tools' settings (:meth:`set_tools` changes them)."""
        self.inspected: Inspection | None = None
        """The voxel last clicked (None until a click hits one, and after a run loads)."""
        self.inspected_object: ObjectInfo | None = None
        """The object under the last click (:meth:`pick_object`; None when it hit none)."""

    @property
    def selection(self) -> Selection:
        """The current selection."""
        return self.shared.selection

    def set_tools(self, **changes: Any) -> ToolSettings:
        """Change the selection tools' settings (fields of :class:`ToolSettings`); validated here so the
        panel and the viewer page's routes share one rule."""
        tools = dataclasses.replace(self.settings, **changes)
        if tools.tool not in (None, "lasso", "brush", "box"):
            raise ValueError(f"tool must be lasso, brush, box or none, got {tools.tool!r}")
        if tools.depth_mode not in ("front", "through"):
            raise ValueError(f"depth_mode must be 'front' or 'through', got {tools.depth_mode!r}")
        if not 0.0 <= tools.distance <= 100.0:
            raise ValueError(f"distance must lie in [0, 100] m, got {tools.distance}")
        if tools.target not in ("map", "scan") or tools.scope not in ("map", "scan"):
            raise ValueError(
                f"target and scope must be 'map' or 'scan', got {tools.target!r}, {tools.scope!r}"
            )
        if not 0.001 <= tools.brush_radius <= 0.5:
            raise ValueError(
                f"brush_radius must lie in [0.001, 0.5] of the canvas height, got {tools.brush_radius}"
            )
        if tools.class_filter is not None and tools.class_filter not in self.shared.class_names():
            raise ValueError(f"class_filter: unknown class {tools.class_filter!r}")
        with self.shared.lock:
            self.settings = tools
        self.notify.emit("tools")
        return tools

    def latest_camera(self) -> sel.PinholeCamera:
        """The camera of the most recently updated browser (each moves its own camera; the one moved last
        is the one the user is drawing on).

        Raises:
            LookupError: no browser has reported its camera yet.
        """
        best = None
        for client in self.scene.clients().values():
            try:
                stamp = client.camera.update_timestamp
            except AssertionError:  # viser asserts until the client's first camera message
                continue
            if best is None or stamp > best[0]:
                best = (stamp, client.camera)
        if best is None:
            raise LookupError("no viewer page has reported its camera yet")
        return camera_of(best[1])

    # ------------------------------------------------------------------------------------ selecting
    def select_screen(
        self,
        tool: ToolKind,
        outline: npt.ArrayLike,
        camera: sel.PinholeCamera,
        *,
        add: bool = False,
    ) -> int:
        """Select with a tool's outline drawn on the canvas of ``camera``; returns the selection's size.

        ``outline``: (K, 2) normalised screen points: the lasso's polygon, the brush's stroke, or the box's
        two corners. The depth mode, distance, class filter and target come from :attr:`settings`; ``add``
        adds to the current selection (same target and scan) instead of replacing it.
        """
        tools = self.settings
        w, h = camera.width_px, camera.height_px
        if tool == "lasso":
            mask = sel.polygon_mask(outline, w, h)
        elif tool == "brush":
            mask = sel.stroke_mask(outline, tools.brush_radius * h, w, h)
        elif tool == "box":
            corners = np.asarray(outline, dtype=np.float64).reshape(-1, 2)
            if corners.shape[0] != 2:
                raise ValueError(f"a box needs 2 corners, got {corners.shape[0]}")
            mask = sel.rect_mask(corners[0], corners[1], w, h)
        else:
            raise ValueError(f"unknown tool {tool!r}")
        sh = self.shared
        with sh.lock:
            grid, view, label = sh.grid, sh.scan_view, sh.label
            scan_label = sh.scan_label
        if grid is None:
            return 0
        cls = None if tools.class_filter is None else sh.class_ids().get(tools.class_filter)
        frame_id = None
        index = self.renderer.lod_index
        if tools.target == "map" and index is not None:
            # A big map: the full grid's visible voxels, culled by coarse cubes first (same result).
            chosen = lod_cull.select_culled(
                index,
                index.blocks(index.query_level(self._query_edge)),
                camera,
                mask,
                visible=self.renderer.visible_mask(grid),
                eligible=None if cls is None else label == cls,
                depth_mode=tools.depth_mode,
                distance=tools.distance,
                splat_size=grid.voxel_size,
            )
            return self._set_selection(chosen, tools.target, None, add)
        if tools.target == "map":
            rows, _ = self.renderer.compute_view()
            points, splat = grid.centres[rows], grid.voxel_size
            eligible = None if cls is None else label[rows] == cls
        else:
            if view is None:
                raise ValueError("no scan is shown to select from")
            rows = np.arange(view.points.shape[0], dtype=np.int64)
            points, splat, frame_id = view.points, float(self.scene.scan.point_size), view.frame_id
            eligible = None if cls is None else scan_label == cls
        picked = sel.select_points(
            points,
            camera,
            mask,
            depth_mode=tools.depth_mode,
            distance=tools.distance,
            splat_size=splat,
            eligible=eligible,
        )
        return self._set_selection(rows[picked], tools.target, frame_id, add)

    def _set_selection(
        self, chosen: npt.NDArray[np.int64], target: Target, frame_id: str | None, add: bool
    ) -> int:
        sh = self.shared
        with sh.lock:
            old = sh.selection
            if add and old.target == target and old.frame_id == frame_id:
                chosen = np.union1d(old.rows, chosen)
            sh.selection = Selection(chosen, target, frame_id)
        self.renderer.draw_selection()
        self.notify.panel.on_selection(int(chosen.size))
        self.notify.emit("selection")
        return int(chosen.size)

    def select_rows(
        self, rows: npt.NDArray[np.int64], target: Target = "map", frame_id: str | None = None
    ) -> int:
        """Select exactly ``rows`` (grid rows, or the shown scan ``frame_id``'s point indices for target
        ``scan``); returns the count."""
        return self._set_selection(np.unique(np.asarray(rows, np.int64)), target, frame_id, False)

    def select_rect(
        self,
        position: npt.ArrayLike,
        wxyz: npt.ArrayLike,
        fov_y: float,
        aspect: float,
        rect_min: tuple[float, float],
        rect_max: tuple[float, float],
        *,
        height_px: int = 1080,
    ) -> int:
        """Select with a screen rectangle seen from a camera (the box tool); returns the count."""
        p = np.asarray(position, dtype=np.float64).reshape(3)
        q = np.asarray(wxyz, dtype=np.float64).reshape(4)
        camera = sel.PinholeCamera(
            (float(p[0]), float(p[1]), float(p[2])),
            (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
            float(fov_y),
            max(1, round(height_px * aspect)),
            height_px,
        )
        return self.select_screen("box", [rect_min, rect_max], camera)

    def clear_selection(self) -> None:
        """Select nothing."""
        with self.shared.lock:
            self.shared.selection = Selection.empty()
        self.renderer.draw_selection()
        self.notify.panel.on_selection(0)
        self.notify.emit("selection")

    # ------------------------------------------------------------------------------------ inspecting
    def inspect_ray(self, origin: npt.ArrayLike, direction: npt.ArrayLike) -> Inspection | None:
        """Inspect the first shown voxel a click ray enters (:func:`leap_core.picking.pick_voxel`): its
        class distribution, confidence, number of scans that observed it and its correction history.
        Returns None (and changes nothing) when the ray hits no shown voxel.

        The object under the click is found too (:meth:`pick_object`) and reported to the panel
        (``on_object``), the voxel or not."""
        sh = self.shared
        grid = sh.grid
        if grid is None:
            return None
        self.pick_object(origin, direction, grid.voxel_size)
        index = self.renderer.lod_index
        if index is not None:
            # Every visible voxel of a big map can be picked, overview or not; cubes off the ray are skipped.
            cubes = index.blocks(index.query_level(self._query_edge))
            rows = lod_cull.ray_rows(index, cubes, origin, direction)
            rows = rows[self.renderer.visible_mask(grid)[rows]]
        else:
            rows, _ = self.renderer.compute_view()
        pick = pick_voxel(origin, direction, grid.centres[rows], grid.voxel_size)
        if pick is None:
            return None
        row = int(rows[pick.index])
        key = int(grid.keys[row])
        history = [rec for rec in sh.corrections if np.any(sh.grid_keys(rec) == key)]
        views = sh.outputs.view_counts(grid) if sh.outputs is not None else None
        with sh.lock:
            label, conf, corrected = int(sh.label[row]), float(sh.conf[row]), bool(sh.corrected[row])
        cx, cy, cz = (float(v) for v in grid.centres[row])
        found = Inspection(
            row=row,
            key=key,
            centre=(cx, cy, cz),
            probs=np.asarray(grid.probs[row], dtype=np.float32),
            label=label,
            conf=conf,
            corrected=corrected,
            views=0 if views is None else int(views[row]),
            history=tuple(history),
            distance=pick.distance,
        )
        self.inspected = found
        # Larger than a voxel, so the marker shows around the voxel it covers.
        self.scene.inspected.point_size = 1.6 * grid.voxel_size
        self.scene.inspected.set(grid.centres[row : row + 1], np.array([nl.INSPECT_RGB], np.uint8))
        self.scene.inspected.visible = True
        self.notify.panel.on_inspect(found)
        return found

    def pick_object(
        self, origin: npt.ArrayLike, direction: npt.ArrayLike, voxel_size: float
    ) -> ObjectInfo | None:
        """The object of the shown scan's first point a click ray enters (each point a cube of the voxel
        size, :func:`leap_core.picking.pick_voxel`; only points of objects are candidates, so a mover kept
        out of the map is picked where its points are), as the corrections leave it (a merged object is
        both parts, a split-off part its own). Kept in :attr:`inspected_object` and told to the panel
        (None: the ray meets no object's point)."""
        sh = self.shared
        with sh.lock:
            view, run, objects, instance = sh.scan_view, sh.run, sh.objects, sh.scan_instance
        found = None
        if view is not None and instance is not None and run is not None and objects is not None:
            rows = np.flatnonzero(instance > 0)
            pick = pick_voxel(origin, direction, view.points[rows].astype(np.float64), voxel_size)
            if pick is not None:
                shown = ObjectInfo(run.run_id, 0, -1, 0, False, 0.0, 0, view.frame_id)
                found = object_info(objects, shown, int(instance[rows[pick.index]]))
        self.inspected_object = found
        self.notify.panel.on_object(found)
        return found

    def inspect_track(self, track: int) -> ObjectInfo | None:
        """Make object ``track`` of the shown run (its id as the export shows it, the corrections on top)
        the inspected object (as a click on one of its points in the shown scan would: *Relabel object*,
        *Split here* and *Merge with* then apply to it), and tell the panel. None (nothing changed) when the
        run has no such object."""
        sh = self.shared
        with sh.lock:
            view, run, objects = sh.scan_view, sh.run, sh.objects
        if view is None or run is None or objects is None or not 1 <= track <= objects.count:
            return None
        if not objects.object_scans(track):
            return None  # merged into another object: that one holds its points
        found = object_info(objects, ObjectInfo(run.run_id, 0, -1, 0, False, 0.0, 0, view.frame_id), track)
        self.inspected_object = found
        self.notify.panel.on_object(found)
        return found

    def clear_inspection(self) -> None:
        """Forget the inspected voxel and object and hide the voxel's marker (a run was loaded)."""
        self.inspected = None
        self.inspected_object = None
        self.scene.inspected.visible = False


def object_info(objects: CorrectedTracks, shown: ObjectInfo, track: int) -> ObjectInfo:
    """Object ``track`` of ``objects`` (the shown run's, corrections on top) as the panel shows it, in the
    scan ``shown`` is of."""
    scans = objects.object_scans(track)
    _, obj = objects.scan_rows(shown.frame_id)
    fixed = int(objects.track_class[track])
    return ObjectInfo(
        run_id=shown.run_id,
        track=track,
        class_index=int(objects.label[track]),
        scans=len(scans),
        moving=bool(objects.moving[track]),
        speed=float(np.linalg.norm(objects.velocity[track])),
        points=int(np.count_nonzero(obj == track)),
        frame_id=shown.frame_id,
        corrected_to=None if fixed == NO_CLASS else fixed,
    )


__all__ = ["SelectionTool", "camera_of", "object_info"]
