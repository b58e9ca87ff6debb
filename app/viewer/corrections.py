"""Corrections in the viewer: a selection + class becomes a stored correction, undo / redo toggle it, and the
project's active corrections are overlaid on the shown grid and scan.

A correction's scope is the map (voxel keys: every point in those voxels in every scan) or the shown scan
only (its point indices). Each one is a row of the project's store
(:class:`~app.viewer.records.ProjectBackend`), so the web UI and every later run see it.
"""

from __future__ import annotations

import threading
from collections.abc import Hashable

import numpy as np
import numpy.typing as npt

from app.viewer import view_logic as vl
from app.viewer.data import ReviewGrid
from app.viewer.player import ScanPlayer
from app.viewer.records import ObjectAction, ProjectBackend, Scope, Selection
from app.viewer.render import LodRenderer
from app.viewer.selection_tool import SelectionTool, object_info
from app.viewer.shared import Notifier, SharedState
from leap_core.fusion import voxel_keys
from leap_core.pipeline.object_corrections import CorrectedTracks
from leap_core.pipeline.tracks_file import SequenceTracks

Overlay = tuple[npt.NDArray[np.int16], npt.NDArray[np.float32], npt.NDArray[np.bool_]]
"""(label, conf, corrected) of a grid with the corrections applied
(:func:`app.viewer.view_logic.apply_corrections`)."""


class OverlayCache:
    """The corrected labels of each shown grid, computed once for every viewer tab that shows it.

    Tabs of one project show the same grid object; each (V,) array set is kept for the grid and the
    corrections it was computed from, so a second tab (or a tab told of another's correction) takes the
    same arrays instead of a copy. Arrays are never changed in place (see :class:`SharedState`).
    """

    def __init__(self, keep: int = 4) -> None:
        self._lock = threading.Lock()
        self._keep = keep
        self._entries: list[tuple[ReviewGrid, Hashable, Overlay]] = []

    def overlay(
        self, grid: ReviewGrid, key: Hashable, keys: npt.NDArray[np.int64], labels: npt.NDArray[np.int16]
    ) -> Overlay:
        """``grid`` with ``labels`` imposed on the voxels ``keys``; ``key`` identifies those corrections."""
        # Computed under the lock: tabs told of a correction at once wait for the first and share its arrays.
        with self._lock:
            for g, k, arrays in self._entries:
                if g is grid and k == key:
                    return arrays
            arrays = vl.apply_corrections(grid.keys, grid.label, grid.conf, keys, labels)
            # One entry per grid (its latest corrections), for the last ``keep`` grids shown.
            others = [e for e in self._entries if e[0] is not grid]
            self._entries = [*others[max(0, len(others) - self._keep + 1) :], (grid, key, arrays)]
        return arrays


class Corrections:
    """Assigning classes to selections, undo / redo, and the corrections overlaid on the grid.

    Args:
        shared: the session's shared state (writes ``label`` / ``conf`` / ``corrected`` / ``corrections``;
            clears ``selection`` after a correction).
        backend: the project store the corrections are kept in.
        renderer: redraws after a change.
        player: relabels the shown scan after a change.
        tools: the selection tools (their default scope).
        notify: where changes are reported (panel ``on_selection`` / ``on_history``, event ``corrected``).
    """

    def __init__(
        self,
        shared: SharedState,
        backend: ProjectBackend,
        renderer: LodRenderer,
        player: ScanPlayer,
        tools: SelectionTool,
        notify: Notifier,
        *,
        overlays: OverlayCache | None = None,
    ) -> None:
        self.overlays = overlays or OverlayCache(keep=1)
        """Where the corrected labels come from (shared by the tabs of one project in the app)."""
        self.shared = shared
        self.backend = backend
        self.renderer = renderer
        self.player = player
        self.tools = tools
        self.notify = notify
        self.history: vl.EditHistory[int] = vl.EditHistory()
        """Ids of the corrections this viewer made, for undo / redo."""
        self._objects: tuple[Hashable, SequenceTracks, CorrectedTracks] | None = None
        """The last :meth:`_objects_locked` result with what it was computed from."""

    def apply_locked(self) -> None:
        """Read the project's corrections and overlay the active map-scope ones on the shown grid (caller
        holds the shared lock; a grid is shown)."""
        sh = self.shared
        grid = sh.grid
        assert grid is not None
        names = sh.class_ids()
        keys_all, labels_all, used = [], [], []
        sh.corrections = self.backend.corrections()
        for rec in sh.corrections:
            if rec.scope != "map" or not rec.active or rec.class_name not in names or rec.keys.size == 0:
                continue
            keys = sh.grid_keys(rec)
            keys_all.append(keys)
            labels_all.append(np.full(keys.shape[0], names[rec.class_name], np.int16))
            used.append((rec.id, names[rec.class_name]))
        ck = np.concatenate(keys_all) if keys_all else np.zeros(0, np.int64)
        cl = np.concatenate(labels_all) if labels_all else np.zeros(0, np.int16)
        # Correction rows never change but for ``active``: the ids and classes applied identify the result.
        sh.label, sh.conf, sh.corrected = self.overlays.overlay(grid, tuple(used), ck, cl)
        sh.objects = self._objects_locked()

    def _objects_locked(self) -> CorrectedTracks | None:
        """The shown run's tracks with the project's active object corrections on top, computed again only
        when the run or those corrections changed (caller holds the shared lock)."""
        sh = self.shared
        run, outputs, schema = sh.run, sh.outputs, sh.run_schema
        tracks = None if outputs is None else outputs.tracks()
        if run is None or tracks is None or schema is None:
            return None
        key = (run.run_id, tuple(r.id for r in sh.corrections if r.scope == "object" and r.active))
        if self._objects is None or self._objects[0] != key or self._objects[1] is not tracks:
            edits = self.backend.object_corrections(schema.names)
            self._objects = (key, tracks, CorrectedTracks.of(tracks, edits, schema.things()))
        return self._objects[2]

    def assign_selection(
        self, class_name: str, *, scope: Scope | None = None, selection: Selection | None = None
    ) -> int | None:
        """Store a correction assigning ``class_name`` (``""``: erase to unlabeled) to the selection;
        returns its id (None when nothing is selected).

        ``scope`` (default :attr:`ToolSettings.scope <app.viewer.records.ToolSettings.scope>`): ``map``
        stores the voxels (of the selected voxels, or of the voxels holding the selected scan points);
        ``scan`` stores the shown scan's points (the selected points, or the scan's points inside the
        selected voxels). ``selection`` defaults to the current one; either way the current selection is
        cleared once the correction is stored.
        """
        scope = self.tools.settings.scope if scope is None else scope
        if scope not in ("map", "scan"):
            raise ValueError(f"scope must be 'map' or 'scan', got {scope!r}")
        sh = self.shared
        with sh.lock:
            grid, view = sh.grid, sh.scan_view
            selection = sh.selection if selection is None else selection
        rows = selection.rows
        if grid is None or rows.size == 0:
            return None
        if class_name != "" and class_name not in sh.class_names():
            raise ValueError(f"unknown class {class_name!r}")
        if selection.target == "map":
            keys = grid.keys[rows]
        else:
            if view is None or view.frame_id != selection.frame_id:
                raise ValueError("the selected scan is no longer shown; select again")
            keys = np.unique(voxel_keys(view.points[rows].astype(np.float64), grid.voxel_size))
        if scope == "map":
            cid = self.backend.add_correction(class_name, grid.voxel_size, keys)
        else:
            if view is None:
                raise ValueError("no scan is shown: a scan-scope correction needs one")
            if selection.target == "scan":
                points = rows
            else:
                scan_keys = voxel_keys(view.points.astype(np.float64), grid.voxel_size)
                points = np.flatnonzero(np.isin(scan_keys, keys))
            cid = self.backend.add_correction(
                class_name,
                grid.voxel_size,
                keys,
                scope="scan",
                frame_id=view.frame_id,
                points=points.astype(np.int64),
            )
        self.history.push(cid)
        with sh.lock:
            sh.selection = Selection.empty()
            self.apply_locked()
        self.player.recolour_scan()
        self.notify.panel.on_selection(0)
        self.notify.panel.on_history()
        self.renderer.request_draw()
        self.notify.emit("corrected")
        return cid

    def relabel_object(self, class_name: str) -> int | None:
        """Store an object-scope correction giving ``class_name`` (``""``: erase) to the inspected object
        (the last clicked point's object, :meth:`SelectionTool.pick_object`): every point of it in every
        scan, with one action. Returns its id (None when no object is inspected)."""
        if class_name != "" and class_name not in self.shared.class_names():
            raise ValueError(f"unknown class {class_name!r}")
        return self._edit_object(class_name, "relabel")

    def split_object(self) -> int | None:
        """Split the inspected object at the scan shown: its points from that scan on become a new object
        (a ``split`` object correction). Returns its id (None when no object is inspected).

        Raises:
            InvalidField: the object has no point before the shown scan (nothing to split off).
        """
        found = self.tools.inspected_object
        if found is None:
            return None
        return self._edit_object("", "split", frame=found.frame_id)

    def merge_object(self, other: int) -> int | None:
        """Merge object ``other`` of the shown run into the inspected one (a ``merge`` object correction:
        one id, the inspected object's class). Returns its id (None when no object is inspected).

        Raises:
            InvalidField: ``other`` is the inspected object or no object with points.
        """
        return self._edit_object("", "merge", other=other)

    def _edit_object(
        self, class_name: str, action: ObjectAction, *, other: int | None = None, frame: str | None = None
    ) -> int | None:
        found = self.tools.inspected_object
        if found is None:
            return None
        cid = self.backend.add_object_correction(
            class_name, found.run_id, found.track, action=action, other_track_id=other, frame=frame
        )
        self.history.push(cid)
        self.refresh()
        with self.shared.lock:
            objects = self.shared.objects
        track = found.track
        if objects is not None and action == "split":
            track = next((r.new_track for c, r in objects.results if c == cid and r.applied), track)
        self.tools.inspected_object = None if objects is None else object_info(objects, found, track)
        self.notify.panel.on_object(self.tools.inspected_object)
        self.notify.emit("corrected")
        return cid

    def assign_slot(self, slot: int) -> int | None:
        """Assign the ``slot``-th class (1-based, the order of the class picker) to the selection."""
        names = self.shared.class_names()
        if not 1 <= slot <= len(names):
            raise ValueError(f"slot must lie in [1, {len(names)}], got {slot}")
        return self.assign_selection(names[slot - 1])

    def show_correction(self, correction_id: int) -> int:
        """Jump to a stored correction: select what it covers and frame the camera on it. A map-scope
        correction selects its voxels present in the shown map; a scan-scope one shows its scan and selects
        its points there. Returns how many voxels or points are selected.

        Raises:
            LookupError: no correction ``correction_id`` in this project's sequence.
            ValueError: nothing of it lies in the shown run (its voxels or its scan are not in it).
        """
        sh = self.shared
        with sh.lock:
            rec = next((c for c in sh.corrections if c.id == correction_id), None)
            grid, outputs = sh.grid, sh.outputs
        if rec is None:
            raise LookupError(f"correction {correction_id} is not one of this sequence's corrections")
        if grid is None:
            raise ValueError("no run is shown")
        rows = grid.rows_of(rec.keys)
        rows = rows[rows >= 0]
        if rows.size == 0:
            raise ValueError(f"correction {correction_id}: none of its voxels is in the shown run's map")
        centres = grid.centres[rows]
        lo, hi = centres.min(axis=0), centres.max(axis=0)
        extent = float(np.linalg.norm(hi - lo)) / 2
        if rec.scope == "scan" and rec.points is not None and outputs is not None:
            ids = [outputs.seq.frame_ids[i] for i in outputs.frame_indices]
            if rec.frame_id not in ids:
                raise ValueError(f"correction {correction_id}: scan {rec.frame_id} is not in the shown run")
            self.player.show_scan(ids.index(rec.frame_id), move_camera=False)
            count = self.tools.select_rows(rec.points, "scan", rec.frame_id)
        else:
            count = self.tools.select_rows(rows)
        pos, target = vl.orbit_view((lo + hi) / 2, max(12.0, 3.0 * extent), elevation_deg=45.0)
        self.renderer.focus_lod((lo + hi) / 2)
        self.renderer.scene.look_at(pos, target)
        return count

    def undo(self) -> int | None:
        """Deactivate the last correction made here; returns its id (None: nothing to undo)."""
        cid = self.history.undo()
        if cid is not None:
            self.backend.set_correction_active(cid, False)
            self._after_history()
        return cid

    def redo(self) -> int | None:
        """Reactivate the last undone correction; returns its id (None: nothing to redo)."""
        cid = self.history.redo()
        if cid is not None:
            self.backend.set_correction_active(cid, True)
            self._after_history()
        return cid

    def _after_history(self) -> None:
        self.refresh()
        self.notify.emit("corrected")

    def refresh(self) -> None:
        """Read the project's corrections again and show them (after an undo / redo here, or a correction
        made elsewhere: another tab, the web UI)."""
        with self.shared.lock:
            if self.shared.grid is not None:
                self.apply_locked()
        self.player.recolour_scan()
        self.notify.panel.on_history()
        self.renderer.request_draw()

    def correction_count(self) -> int:
        """Number of the project's active corrections."""
        return sum(1 for c in self.shared.corrections if c.active)


__all__ = ["Corrections", "Overlay", "OverlayCache"]
