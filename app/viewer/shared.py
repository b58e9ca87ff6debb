"""What the rooms of a review session share, and where they report to.

:class:`SharedState` holds the data every room reads: the shown run and grid, its labels with the project's
corrections overlaid, the view the user asked for, the selection, the focused review region and the shown
scan. Each field names the rooms that write it; the others only read it. :class:`Notifier` carries
what the rooms tell the GUI panel and the session's event listeners.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from app.viewer import nav_logic as nl
from app.viewer import view_logic as vl
from app.viewer.data import ReviewGrid, RunOutputs, ScanView
from app.viewer.records import CorrectionRecord, RunInfo, Selection, SessionView
from app.viewer.region_logic import Region
from app.viewer.run_delta import RunDelta
from leap_core.fusion import key_centres, voxel_keys
from leap_core.pipeline.object_corrections import NO_CLASS, CorrectedTracks
from leap_core.schema import Schema
from leap_core.types import UNLABELED

log = logging.getLogger(__name__)


class SharedState:
    """The shown run and how it is shown; every field is guarded by :attr:`lock`.

    Arrays are never changed in place: a writer replaces them under the lock, so a reader that took a
    reference under the lock keeps a consistent snapshot after releasing it.
    """

    def __init__(self, project_schema: Schema) -> None:
        self.lock = threading.RLock()
        """The session's one lock (see :class:`app.viewer.session.ReviewSession` for what it guards)."""
        self.run: RunInfo | None = None
        """The shown run (written by the session on load)."""
        self.grid: ReviewGrid | None = None
        """Its voxel map (written by the session on load)."""
        self.outputs: RunOutputs | None = None
        """Its scans (written by the session on load)."""
        self.run_schema: Schema | None = None
        """Schema the run was made with (None: it does not describe the grid; generic names are shown)."""
        self.project_schema = project_schema
        """The project's current schema (written on load and by :class:`app.viewer.steering.ClassEditor`)."""
        self.palette: npt.NDArray[np.uint8] = project_schema.colors()
        """(C, 3) class colours of the shown grid (:meth:`refresh_palette`)."""
        self.view_state = vl.ViewState()
        """What the user asked to see (written by the session and the renderer's class toggles)."""
        self.label = np.zeros(0, np.int16)
        """(V,) class per voxel with the corrections applied (written by
        :class:`app.viewer.corrections.Corrections`)."""
        self.conf = np.zeros(0, np.float32)
        """(V,) confidence per voxel, 1 where corrected."""
        self.corrected = np.zeros(0, bool)
        """(V,) voxels an active correction overrides."""
        self.corrections: list[CorrectionRecord] = []
        """The project's corrections as last read from the backend: re-read on every correction change (and
        run load), not on every scan change."""
        self.selection = Selection.empty()
        """The selection (written by :class:`app.viewer.selection_tool.SelectionTool`; cleared by a
        correction, a load, or a scan change for a scan selection)."""
        self.focus: Region | None = None
        """The review region shown highlighted (its voxels at full colour, the rest dimmed; written by
        :class:`app.viewer.review_queue.ReviewQueue`)."""
        self.focus_frame: int | None = None
        """Position (in the scan slider) of the scan the focused region was seen best in."""
        self.scan_view: ScanView | None = None
        """The scan shown (points, labels, ego pose, image; written by
        :class:`app.viewer.player.ScanPlayer`)."""
        self.scan_label = np.zeros(0, np.int16)
        """Labels of the shown scan's points with the corrections overlaid (what the scan layer shows)."""
        self.objects: CorrectedTracks | None = None
        """The shown run's objects with the active object corrections on top (merges, splits, relabels:
        what its export holds once the apply job has run); None without objects (written by
        :meth:`app.viewer.corrections.Corrections.apply_locked`)."""
        self.scan_instance: npt.NDArray[np.uint32] | None = None
        """(N,) object id of each point of the shown scan as the export writes it (0: none), or None."""
        self.scan_moving: npt.NDArray[np.bool_] | None = None
        """(N,) whether that object moves, or None."""
        self.delta: RunDelta | None = None
        """The ``delta`` colour mode's source (the run before the shown one; set by the session)."""

    def class_names(self) -> list[str]:
        """Names of the displayed grid's classes (index order)."""
        grid = self.grid
        if grid is None:
            return self.project_schema.names
        if self.run_schema is not None:
            return self.run_schema.names
        return [f"class {i}" for i in range(grid.num_classes)]

    def class_ids(self) -> dict[str, int]:
        """Class name → index of the displayed grid; ``""`` (erase) → unlabeled (-1)."""
        return {"": UNLABELED, **{n: i for i, n in enumerate(self.class_names())}}

    def refresh_palette(self) -> None:
        """Class colours of the displayed grid: the run's schema, recoloured by the project's current
        colours where the class names match (so a recolour in the panel shows at once). Caller holds
        :attr:`lock`."""
        if self.grid is None:
            return
        if self.run_schema is None:
            rng = np.random.default_rng(0)
            self.palette = rng.integers(40, 255, (self.grid.num_classes, 3)).astype(np.uint8)
            return
        current = {c.name: c.color for c in self.project_schema.classes}
        self.palette = np.array(
            [current.get(c.name, c.color) for c in self.run_schema.classes], dtype=np.uint8
        ).reshape(-1, 3)

    def grid_keys(self, rec: CorrectionRecord) -> npt.NDArray[np.int64]:
        """``rec``'s voxel keys at the displayed grid's voxel size (a correction made on another size)."""
        grid = self.grid
        assert grid is not None
        if np.isclose(rec.voxel_size, grid.voxel_size):
            return rec.keys
        return voxel_keys(key_centres(rec.keys, rec.voxel_size), grid.voxel_size)

    def scan_labels(self, view: ScanView) -> npt.NDArray[np.int16]:
        """The scan's run labels with the active corrections overlaid: map corrections through the voxel
        of each point, then this scan's own corrections in the order they were made. Caller holds
        :attr:`lock`."""
        label: npt.NDArray[np.int16] = view.label.copy()
        self.scan_instance, self.scan_moving = view.instance, view.moving
        grid = self.grid
        if grid is None or self.corrected.size != grid.num_voxels:
            return label
        objects = self.objects
        if objects is not None and view.instance is not None:
            # Object corrections first: map and scan corrections win on the points they label.
            _, _, self.scan_instance, self.scan_moving = objects.point_objects(view.frame_id, view.label)
            tracked, obj = objects.scan_rows(view.frame_id)
            cls = objects.track_class[obj]
            fixed = cls != NO_CLASS
            label[tracked[fixed]] = cls[fixed]
        if self.corrected.any():
            rows = grid.rows_of(voxel_keys(view.points.astype(np.float64), grid.voxel_size))
            hit = rows >= 0
            hit[hit] = self.corrected[rows[hit]]
            label[hit] = self.label[rows[hit]]
        names = self.class_ids()
        n = label.shape[0]
        for rec in self.corrections:
            if (
                rec.scope == "scan"
                and rec.active
                and rec.frame_id == view.frame_id
                and rec.points is not None
                and rec.class_name in names
            ):
                pts = rec.points[(rec.points >= 0) & (rec.points < n)]
                label[pts] = names[rec.class_name]
        return label

    def object_classes(self) -> list[tuple[int, int]]:
        """``(object id, class index)`` of the shown run's objects an active relabel reaches (after the
        merges and splits made before it: :attr:`objects`), by id. Caller holds :attr:`lock`."""
        objects = self.objects
        if objects is None:
            return []
        fixed = np.flatnonzero(objects.track_class != NO_CLASS)
        return [(int(t), int(objects.track_class[t])) for t in fixed]

    def confidence_histograms(self, bins: int = 10) -> npt.NDArray[np.int64]:
        """(C, bins) voxel counts per shown class and confidence bin (corrections applied; see
        :func:`app.viewer.nav_logic.confidence_histograms`)."""
        with self.lock:
            label, conf = self.label, self.conf
        return nl.confidence_histograms(label, conf, len(self.class_names()), bins)


class Notifier:
    """Where the rooms report: the GUI panel (bound once the session has built it) and the session's event
    listeners."""

    def __init__(self) -> None:
        self._panel: SessionView | None = None
        self._listeners: list[Callable[[str], None]] = []

    def bind(self, panel: SessionView) -> None:
        """Report to ``panel`` from now on."""
        self._panel = panel

    @property
    def panel(self) -> SessionView:
        """The GUI panel.

        Raises:
            RuntimeError: the panel is not built yet (nothing reports before the first run loads).
        """
        if self._panel is None:
            raise RuntimeError("the viewer's panel is not built yet")
        return self._panel

    def on_event(self, listener: Callable[[str], None]) -> None:
        """Call ``listener(name)`` on every :meth:`emit`."""
        self._listeners.append(listener)

    def emit(self, name: str) -> None:
        """Tell every listener that ``name`` happened (a failing listener is logged, not raised)."""
        for fn in list(self._listeners):
            try:
                fn(name)
            except Exception:  # a listener must not break the viewer
                log.exception("viewer listener failed")


__all__ = ["Notifier", "SharedState"]
