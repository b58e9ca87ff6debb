"""One review session: a run's data, the scene, the GUI panel, and the project it steers.

The session is the controller between the pure view maths (:mod:`app.viewer.view_logic`), the scene facade
(:mod:`app.viewer.scene`), the panel and the project store (a :class:`ProjectBackend`, implemented over the
app's SQLite and job manager in :mod:`app.viewer.manager`). It reports to the panel through the
:class:`SessionView` protocol and is handed the panel's constructor, so the panel
(:class:`app.viewer.panel.ReviewPanel`) depends on the session and not the other way round.

Redraws are coalesced: GUI callbacks only record the requested :class:`~app.viewer.view_logic.ViewState`
and wake a drawing thread, which always draws the newest state; a slider dragged across 50 values costs
as many redraws as the drawing thread has time for, not 50.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypedDict

import cv2
import numpy as np
import numpy.typing as npt

from app.viewer import lod
from app.viewer import nav_logic as nl
from app.viewer import view_logic as vl
from app.viewer.data import ReviewGrid, RunOutputs, ScanView
from app.viewer.lod import LodConfig
from app.viewer.scene import ReviewScene
from leap_core import review
from leap_core import selection as sel
from leap_core.fusion import key_centres, key_coords, voxel_keys
from leap_core.picking import pick_voxel
from leap_core.schema import ClassDef, Schema
from leap_core.types import UNLABELED

if TYPE_CHECKING:
    from typing_extensions import Unpack  # typing.Unpack from Python 3.11

log = logging.getLogger(__name__)

QueueKind = Literal["confidence", "disagreement"]
ToolKind = Literal["lasso", "brush", "box"]
Target = Literal["map", "scan"]
"""What a selection tool picks from: voxels of the map, or points of the scan shown."""
Scope = Literal["map", "scan"]
"""What a correction changes: all points in its voxels in every scan (``map``), or listed points of one
scan (``scan``)."""


class ViewChanges(TypedDict, total=False):
    """Fields of :class:`~app.viewer.view_logic.ViewState` to change (:meth:`ReviewSession.set_state`)."""

    mode: vl.ColorMode
    class_index: int
    threshold: float
    enabled: tuple[bool, ...]
    max_points: int | None


REVIEW_BOX_RGB = (0, 255, 255)
"""Outline of the focused review region (3D box and image box): cyan, which no SemanticKITTI class uses
(magenta would vanish on the road)."""

SELECTION_RGB = (15, 15, 15)
"""Highlight of selected voxels: near-black, unlike every class colour and the light background."""


@dataclass(frozen=True)
class RunInfo:
    """What the viewer needs to know about a run."""

    run_id: int
    """Run id."""
    number: int
    """Run number within its project (shown to the user)."""
    status: str
    """queued / running / done / failed / cancelled / interrupted."""
    percent: float
    """Overall progress 0..100."""
    stage: str | None
    """Stage in progress."""
    error: str | None
    """Failure message."""
    run_dir: Path
    """The run's folder of the sequence shown (its outputs)."""
    schema: Schema | None
    """Class schema the run was made with (its class indices index the run's grid)."""
    pipeline: dict[str, Any] | None = None
    """Pipeline parameters the run was made with (which grid is final)."""


@dataclass(frozen=True)
class CorrectionRecord:
    """A stored manual correction (see :class:`app.crud.Correction`)."""

    id: int
    """Row id."""
    class_name: str
    """Assigned class (``""`` = erase to unlabeled)."""
    voxel_size: float
    """Voxel edge of ``keys``."""
    keys: npt.NDArray[np.int64]
    """Packed voxel keys."""
    active: bool
    """False once undone."""
    created_at: str = ""
    """ISO UTC time it was made ("" when the store does not say)."""

    scope: Scope = "map"
    """``map``: every point in ``keys``' voxels; ``scan``: only ``points`` of scan ``frame_id``."""
    frame_id: str | None = None
    """Scan of a scan-scope correction."""
    points: npt.NDArray[np.int64] | None = None
    """Scan scope: indices into that scan's points."""


@dataclass(frozen=True)
class Inspection:
    """What the panel shows of one clicked voxel (:meth:`ReviewSession.inspect_ray`)."""

    row: int
    """Row of the voxel in the displayed grid."""
    key: int
    """Its packed voxel key."""
    centre: tuple[float, float, float]
    """Voxel centre (metres)."""
    probs: npt.NDArray[np.float32]
    """(C,) the grid's class distribution of the voxel (before corrections)."""
    label: int
    """Shown class index (after corrections), -1 unlabeled."""
    conf: float
    """Shown confidence (1 for a corrected voxel)."""
    corrected: bool
    """An active correction overrides the voxel."""
    views: int
    """Number of the run's scans that observed the voxel (:meth:`RunOutputs.view_counts`)."""
    history: tuple[CorrectionRecord, ...]
    """Every correction (active or undone) whose voxels include this one, oldest first."""
    distance: float
    """Distance from the click ray's origin (metres)."""


@dataclass(frozen=True)
class ToolSettings:
    """The selection tools' settings (panel widgets and the viewer page's keys change them)."""

    tool: ToolKind | None = None
    """Armed tool: the next drag on the canvas draws its outline (None: the camera orbits)."""
    depth_mode: sel.DepthMode = "front"
    """``front``: only the first surface along each view ray (within ``distance``); ``through``: all."""
    distance: float = 0.5
    """Front-surface tolerance (m) behind the first hit."""
    class_filter: str | None = None
    """Select only what is currently labelled this class (None: any class)."""
    target: Target = "map"
    """Select voxels of the map or points of the scan shown."""
    scope: Scope = "map"
    """Scope of the corrections made from the selection."""
    brush_radius: float = 0.03
    """Brush radius as a share of the canvas height."""


@dataclass(frozen=True)
class ReviewMarkRecord:
    """A stored verdict on a review region (see :class:`app.crud.ReviewMark`)."""

    signature: str
    """Content signature the verdict was made on (:func:`leap_core.review.region_signatures`)."""
    state: str
    """``accepted`` or ``skipped``."""


class ProjectBackend(Protocol):
    """The project store the viewer reads and steers (the same data the web UI edits)."""

    project_id: int

    def project_name(self) -> str: ...

    def dataset_path(self) -> Path: ...

    def load_schema(self) -> Schema: ...

    def save_schema(self, schema: Schema) -> None: ...

    def latest_finished_run(self) -> RunInfo | None: ...

    def run_info(self, run_id: int) -> RunInfo: ...

    def active_run(self) -> RunInfo | None: ...

    def start_run(self) -> int: ...

    def corrections(self) -> list[CorrectionRecord]: ...

    def add_correction(
        self,
        class_name: str,
        voxel_size: float,
        keys: npt.NDArray[np.int64],
        *,
        scope: Scope = "map",
        frame_id: str | None = None,
        points: npt.NDArray[np.int64] | None = None,
    ) -> int: ...

    def set_correction_active(self, correction_id: int, active: bool) -> None: ...

    def review_marks(self) -> dict[str, ReviewMarkRecord]: ...

    def set_review_mark(self, region: str, signature: str, state: str, run_id: int | None) -> None: ...

    def save_review_queue(self, kind: str, run_id: int | None, regions: list[tuple[str, str]]) -> None: ...


class SessionView(Protocol):
    """What the session tells its GUI panel (implemented by :class:`app.viewer.panel.ReviewPanel`)."""

    def set_status(self, text: str) -> None: ...

    def on_run_loaded(self) -> None: ...

    def on_drawn(self, *, shown: int, total: int, seconds: float) -> None: ...

    def on_scan(self, view: ScanView, pos: int, count: int) -> None: ...

    def on_region(self, region: vl.Region, pos: int, count: int, kind: str) -> None: ...

    def on_queue(self, building: bool) -> None: ...

    def on_selection(self, count: int) -> None: ...

    def on_history(self) -> None: ...

    def on_schema(self) -> None: ...

    def on_run_progress(self, info: RunInfo) -> None: ...

    def on_inspect(self, inspection: Inspection) -> None: ...

    def on_nav(self) -> None: ...


@dataclass(frozen=True)
class SessionConfig:
    """Tunables of a review session."""

    queue_share: float = 0.05
    """Share of voxels (lowest confidence / highest disagreement) clustered into review regions."""
    queue_cell: float = 4.0
    """Edge (m) of the cells review regions are clustered into."""
    queue_min_count: int = 5
    """Cells with fewer candidate voxels are not regions."""
    poll_interval_s: float = 0.5
    """How often a started run's progress is polled."""
    max_points: int = 200_000
    """Default of the panel's "Max points" (decimation applies only once the user ticks "Limit points")."""
    queue_scans: int = 12
    """A focused region's scan is the best observer (:func:`leap_core.review.best_observer`) among this many
    scans whose sensor positions lie nearest the region: counting every scan's points would cost a pass over
    the whole sequence per region."""
    play_interval_s: float = 1.0
    """Seconds between scans while playing through them."""
    follow_ego: bool = True
    """Whether the camera follows the ego pose on a scan change when the viewer starts (key ``g``)."""
    lod: LodConfig = dataclasses.field(default_factory=LodConfig)
    """Level of detail of maps with more voxels than its budget (:mod:`app.viewer.lod`)."""


_Tables = tuple[tuple[Any, ...], npt.NDArray[np.float32], npt.NDArray[np.float32]]
"""Cached per-block tables: (what they were made from, counts, score sums)."""


@dataclass
class _Selection:
    rows: npt.NDArray[np.int64]
    """Rows of the grid (target ``map``) or indices of the shown scan's points (target ``scan``)."""
    target: Target = "map"
    frame_id: str | None = None


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


class ReviewSession:
    """A viewer for one project: shows a run, edits the project, starts re-runs, records corrections.

    Args:
        backend: the project store.
        panel: builds the GUI panel on the new session's scene (:class:`app.viewer.panel.ReviewPanel`);
            called once the session's state exists, before the first run loads.
        run_id: run to show (default: the latest finished one).
        host, port: where viser binds (port 0 = any free port; read :attr:`port`).
        config: tunables.
    """

    def __init__(
        self,
        backend: ProjectBackend,
        *,
        panel: Callable[[ReviewSession], SessionView],
        run_id: int | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
        config: SessionConfig | None = None,
    ) -> None:
        self.backend = backend
        self.config = config or SessionConfig()
        self.scene = ReviewScene(host=host, port=port, label=f"LeAP review: {backend.project_name()}")
        self.state = vl.ViewState()
        self.history: vl.EditHistory[int] = vl.EditHistory()
        self.grid: ReviewGrid | None = None
        self.outputs: RunOutputs | None = None
        self.run: RunInfo | None = None
        self.run_schema: Schema | None = None
        self.project_schema: Schema = backend.load_schema()
        self.palette = self.project_schema.colors()
        self._init_labels()
        self.selection = _Selection(np.zeros(0, np.int64))
        self.tools = ToolSettings()
        self.scan_label = np.zeros(0, np.int16)
        """Labels of the shown scan's points with the corrections overlaid (what the scan layer shows)."""
        self.regions: list[vl.Region] = []
        self.region_pos = -1
        self.queue_kind: QueueKind = "confidence"
        self._init_review_state()
        self.frame_pos = 0
        self._init_navigation()
        self.last_draw_s = 0.0
        self.draw_count = 0
        self._init_lod()
        self.scene_version = 0
        """Bumped every time a run's data is (re)loaded into the scene."""
        self.watched_run: int | None = None
        self._lock = threading.RLock()
        self._draw_wanted = threading.Event()
        self._drawn = threading.Condition()
        self._stop = threading.Event()
        self._listeners: list[Callable[[str], None]] = []
        self.panel = panel(self)
        self.scene.on_look_at(self._camera_moved)
        self._drawer = threading.Thread(target=self._draw_loop, name="viewer-draw", daemon=True)
        self._drawer.start()
        self._watcher: threading.Thread | None = None
        try:
            first = backend.run_info(run_id) if run_id is not None else backend.latest_finished_run()
            if first is not None and first.status == "done":
                self.load_run(first)
            else:
                self.panel.set_status("No finished run yet: press Re-run to label this project.")
            active = backend.active_run()
            if active is not None:
                self._watch(active.run_id)
        except BaseException:
            self.close()  # free the port and threads of a viewer that could not start
            raise

    def _init_review_state(self) -> None:
        self.queue_built = False
        """True once a queue was built for the loaded run (a re-run rebuilds it)."""
        self.queue_building = False
        self.signatures: list[str] = []
        """Content signature of each region of :attr:`regions` (same order)."""
        self.marks: dict[str, ReviewMarkRecord] = {}
        self.focus: vl.Region | None = None
        """The review region shown highlighted (its voxels at full colour, the rest dimmed)."""
        self.focus_frame: int | None = None
        """Position (in the scan slider) of the scan the focused region was seen best in."""

    def _init_lod(self) -> None:
        self.lod_index: lod.LodIndex | None = None
        """Spatial index of the shown grid when it has more voxels than ``config.lod.budget`` (else None:
        the map is drawn exactly)."""
        self.lod_focus: npt.NDArray[np.float64] | None = None
        """Point the full-resolution area is centred on (the scan, region or look-at point last focused)."""
        self.lod_plan: lod.LodPlan | None = None
        """What the last level-of-detail draw sent (None after an exact draw)."""
        self.lod_seconds: dict[str, float] = {}
        """Server seconds of the last level-of-detail steps (``index`` at load, ``tables``, ``plan``)."""
        self._lod_tables: _Tables | None = None
        self._lod_table_inputs: tuple[npt.NDArray[np.int16], npt.NDArray[np.floating]] | None = None
        self._lod_colors: tuple[tuple[Any, ...], npt.NDArray[np.uint8]] | None = None
        self._lod_centre: npt.NDArray[np.float64] | None = None
        self._shown_blocks: tuple[lod.Blocks, npt.NDArray[np.int64]] | None = None
        self.map_visible = True
        """The panel's "Show voxel map": both map layers (voxels and overview) follow it."""

    def _init_labels(self) -> None:
        self.label = np.zeros(0, np.int16)
        self.conf = np.zeros(0, np.float32)
        self.corrected = np.zeros(0, bool)
        self.corrections: list[CorrectionRecord] = []
        """The project's corrections as last read from the backend: re-read on every correction change (and
        run load), not on every scan change."""

    def _init_navigation(self) -> None:
        self.scan_view: ScanView | None = None
        """The scan shown (points, labels, ego pose, image)."""
        self.follow_ego = self.config.follow_ego
        """Move the camera behind the ego vehicle on every scan change."""
        self.playing = False
        self.image_open = False
        """The page shows the scan's image enlarged (web/viewer/nav.js reads it, so it stays open while
        navigating and the panel's button and the ``i`` key act on the same state)."""
        self.inspected: Inspection | None = None
        self._image_jpeg: tuple[ScanView, bytes] | None = None
        self._scan_lock = threading.RLock()
        self._player: threading.Thread | None = None

    # ------------------------------------------------------------------------------------- plumbing
    @property
    def port(self) -> int:
        return self.scene.port

    def on_event(self, listener: Callable[[str], None]) -> None:
        """Call ``listener(name)`` on session events ("loaded", "drawn", "run_started", "run_finished")."""
        self._listeners.append(listener)

    def _emit(self, name: str) -> None:
        for fn in list(self._listeners):
            try:
                fn(name)
            except Exception:  # a listener must not break the viewer
                log.exception("viewer listener failed")

    def close(self) -> None:
        """Stop the drawing, playing and watching threads and the viser server."""
        self.playing = False
        self._stop.set()
        self._draw_wanted.set()
        self._drawer.join(timeout=5)
        if self._watcher is not None:
            self._watcher.join(timeout=5)
        self.scene.stop()

    # ------------------------------------------------------------------------------------- loading
    def load_run(self, run: RunInfo) -> None:
        """Load a finished run's grid (with the project's corrections overlaid) and draw it."""
        grid = ReviewGrid.load(run.run_dir, run.pipeline)
        outputs = RunOutputs(run.run_dir, self.backend.dataset_path())
        self.show_grid(run, grid, outputs)

    def show_grid(self, run: RunInfo, grid: ReviewGrid, outputs: RunOutputs | None) -> None:
        """Show a run's grid already in memory (:meth:`load_run` reads it from the run's folder), with its
        scans when ``outputs`` is given.

        A map above the level-of-detail budget is first drawn as an evenly strided subset within the budget;
        its spatial index is built on a thread meanwhile, and the level-of-detail view replaces it when ready.
        """
        with self._lock:
            self.run = run
            self.grid = grid
            self.lod_index = None
            self.lod_seconds = {}
            self._lod_tables, self._lod_colors, self._shown_blocks, self.lod_plan = None, None, None, None
            self._lod_table_inputs = None
            self._lod_centre = None
            self.outputs = outputs
            self.run_schema = run.schema or self.project_schema
            if self.run_schema.num_classes != grid.num_classes:
                # The snapshot does not describe this grid; fall back to generic names rather than mislabel.
                self.run_schema = None
            self.project_schema = self.backend.load_schema()
            self._refresh_palette()
            self.selection = _Selection(np.zeros(0, np.int64))
            self.regions, self.region_pos, self.signatures = [], -1, []
            self.focus, self.focus_frame = None, None
            rebuild = self.queue_built
            self.queue_built = False
            enabled = tuple(True for _ in range(grid.num_classes))
            cls = min(self.state.class_index, grid.num_classes - 1)
            self.state = dataclasses.replace(self.state, enabled=enabled, class_index=cls)
            self._apply_corrections_locked()
            self.scene.voxels.point_size = grid.voxel_size
            self.frame_pos = 0
            self.scene_version += 1
        self.panel.on_run_loaded()
        self.draw_now()
        if self._needs_lod(grid):
            self._build_index(grid)
        if self.scene_version == 1:
            # Frame the map once; a reload after a re-run keeps the camera where the user left it.
            self._frame_whole_map()
        self.inspected = None
        self.scene.inspected.visible = False
        self.scene.set_review_box(None)
        if outputs is not None and outputs.frame_indices:
            # The map framing above is the first view; following starts with the user's first scan change.
            self.show_scan(len(outputs.frame_indices) // 2, move_camera=False)
        if rebuild:
            # After a re-run the queue is ranked again on the new grid (in the background: the disagreement
            # queue reads every scan); marks of regions whose signature did not change still count.
            threading.Thread(
                target=self._rebuild_queue, args=(self.queue_kind,), name="viewer-queue", daemon=True
            ).start()
        self._emit("loaded")

    def class_names(self) -> list[str]:
        """Names of the displayed grid's classes (index order)."""
        if self.grid is None:
            return self.project_schema.names
        if self.run_schema is not None:
            return self.run_schema.names
        return [f"class {i}" for i in range(self.grid.num_classes)]

    def _refresh_palette(self) -> None:
        """Class colours of the displayed grid: the run's schema, recoloured by the project's current
        colours where the class names match (so a recolour in the panel shows at once)."""
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

    def _class_ids(self) -> dict[str, int]:
        """Class name → index of the displayed grid; ``""`` (erase) → unlabeled (-1)."""
        return {"": UNLABELED, **{n: i for i, n in enumerate(self.class_names())}}

    def _grid_keys(self, rec: CorrectionRecord) -> npt.NDArray[np.int64]:
        """``rec``'s voxel keys at the displayed grid's voxel size (a correction made on another size)."""
        assert self.grid is not None
        if np.isclose(rec.voxel_size, self.grid.voxel_size):
            return rec.keys
        return voxel_keys(key_centres(rec.keys, rec.voxel_size), self.grid.voxel_size)

    def _apply_corrections_locked(self) -> None:
        assert self.grid is not None
        names = self._class_ids()
        keys_all, labels_all = [], []
        self.corrections = self.backend.corrections()
        for rec in self.corrections:
            if rec.scope != "map" or not rec.active or rec.class_name not in names or rec.keys.size == 0:
                continue
            keys = self._grid_keys(rec)
            keys_all.append(keys)
            labels_all.append(np.full(keys.shape[0], names[rec.class_name], np.int16))
        ck = np.concatenate(keys_all) if keys_all else np.zeros(0, np.int64)
        cl = np.concatenate(labels_all) if labels_all else np.zeros(0, np.int16)
        self.label, self.conf, self.corrected = vl.apply_corrections(
            self.grid.keys, self.grid.label, self.grid.conf, ck, cl
        )

    # ---------------------------------------------------------------------------------------- drawing
    def set_state(self, **changes: Unpack[ViewChanges]) -> None:
        """Change the view (``mode``, ``class_index``, ``threshold``, ``enabled``, ``max_points``) and
        schedule a redraw."""
        with self._lock:
            old_mode = self.state.mode
            self.state = dataclasses.replace(self.state, **changes)
            mode = self.state.mode
        if mode != old_mode:
            self._color_scan()
        self._draw_wanted.set()

    def set_class_enabled(self, index: int, on: bool) -> None:
        with self._lock:
            enabled = list(self.state.enabled)
            if 0 <= index < len(enabled):
                enabled[index] = on
            self.state = dataclasses.replace(self.state, enabled=tuple(enabled))
        self._draw_wanted.set()

    def compute_view(self, limit: int | None = None) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
        """Rows of the visible voxels and their colours for the current state (pure on the session's
        arrays); ``limit`` caps them like "Max points" (an even stride)."""
        with self._lock:
            grid, state = self.grid, self.state
            label, conf, corrected, palette = self.label, self.conf, self.corrected, self.palette
        if grid is None:
            return np.zeros(0, np.int64), np.zeros((0, 3), np.uint8)
        if limit is not None:
            state = dataclasses.replace(state, max_points=min(limit, state.max_points or limit))
        class_prob = grid.class_prob(state.class_index) if state.mode == "class_probability" else None
        rows, colors = vl.render_view(state, label, conf, palette, class_prob, corrected)
        focus = self.focus
        if focus is not None and focus.rows.size:
            colors = vl.dim_outside(colors, rows, focus.rows)
        return rows, colors

    def draw_now(self) -> None:
        """Recompute and push the voxel layer (and selection highlight) synchronously."""
        t0 = time.perf_counter()
        with self._lock:
            grid, index = self.grid, self.lod_index
        if grid is None:
            return
        shown = self._draw_lod(grid, index) if index is not None else None
        if shown is None:
            shown = self._draw_exact()
        self._draw_selection()
        self.last_draw_s = time.perf_counter() - t0
        self.draw_count += 1
        self.panel.on_drawn(shown=shown, total=grid.num_voxels, seconds=self.last_draw_s)
        with self._drawn:
            self._drawn.notify_all()
        self._emit("drawn")

    def _draw_exact(self) -> int:
        """Draw every visible voxel (a map within the budget; a bigger one evenly strided to the budget until
        its index is built); returns the points sent."""
        grid = self.grid
        if grid is None:
            return 0
        # A big map: an even stride within the budget (colours computed for those voxels only).
        rows, colors = self.compute_view(self._lod_budget(self.state) if self._needs_lod(grid) else None)
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

    def _lod_budget(self, state: vl.ViewState) -> int:
        budget = self.config.lod.budget
        return budget if state.max_points is None else max(2, min(budget, state.max_points))

    def _view_score(
        self,
        grid: ReviewGrid,
        state: vl.ViewState,
        label: npt.NDArray[np.int16],
        conf: npt.NDArray[np.float32],
        corrected: npt.NDArray[np.bool_],
    ) -> tuple[npt.NDArray[np.floating], npt.NDArray[np.floating] | None]:
        """``(score, class_prob)`` of the view: the value the threshold applies to, and the probability of
        ``state.class_index`` (corrections applied; None outside ``class_probability`` mode)."""
        class_prob = grid.class_prob(state.class_index) if state.mode == "class_probability" else None
        class_prob = vl.corrected_class_prob(state, label, class_prob, corrected)
        return vl.view_score(state, conf, class_prob), class_prob

    def _block_tables(
        self,
        blocks: lod.Blocks,
        *,
        state: vl.ViewState,
        label: npt.NDArray[np.int16],
        conf: npt.NDArray[np.float32],
        corrected: npt.NDArray[np.bool_],
        score: npt.NDArray[np.floating],
        num_classes: int,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """Per block and class counts and score sums of the voxels passing the threshold, kept until the
        labels, the scored quantity or the threshold change (a class toggle or a new focus reuses them; the
        class and confidence views share one table: both threshold and sum the confidence)."""
        prob = state.mode == "class_probability"
        key = (
            blocks,
            label,
            conf,
            corrected if prob else None,
            state.class_index if prob else -1,
            state.threshold,
        )
        cached = self._lod_tables
        if (
            cached is not None
            and len(cached[0]) == len(key)
            and all(
                a is b if isinstance(a, (np.ndarray, lod.Blocks)) else a == b
                for a, b in zip(cached[0], key, strict=True)
            )
        ):
            return cached[1], cached[2]
        t0 = time.perf_counter()
        thr = np.float32(state.threshold)
        hist_ssum = self._tables_after_edit(blocks, key, label, score, thr, num_classes)
        if hist_ssum is None:
            hist, ssum = blocks.index.sorted_tables(
                blocks, label, num_classes, threshold=float(thr), score=score
            )
            assert ssum is not None
        else:
            hist, ssum = hist_ssum
        self._lod_tables = (key, hist, ssum)
        self._lod_table_inputs = (label, score)
        self.lod_seconds["tables"] = time.perf_counter() - t0
        return hist, ssum

    def _tables_after_edit(
        self,
        blocks: lod.Blocks,
        key: tuple[Any, ...],
        label: npt.NDArray[np.int16],
        score: npt.NDArray[np.floating],
        thr: np.float32,
        num_classes: int,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None:
        """The cached tables moved to new labels / scores when only those changed, and in few voxels (a
        correction, an undo); None when they must be counted afresh."""
        cached, inputs = self._lod_tables, self._lod_table_inputs
        if cached is None or inputs is None or cached[0][0] is not blocks or cached[0][4:] != key[4:]:
            return None
        old_label, old_score = inputs
        if old_label.shape != label.shape or old_score.shape != score.shape:
            return None
        rows = np.flatnonzero((old_label != label) | (old_score != score))
        if rows.size > label.shape[0] // 20:
            return None
        hist, ssum = cached[1], cached[2]  # updated in place, and the colours made from them
        counted_old = old_score[rows] >= thr if thr > 0 else np.ones(rows.size, bool)
        counted_new = score[rows] >= thr if thr > 0 else np.ones(rows.size, bool)
        changed = blocks.of_row[rows]
        lod.update_tables(
            hist,
            ssum,
            changed,
            num_classes,
            (old_label[rows], old_score[rows], counted_old),
            (label[rows], score[rows], counted_new),
        )
        self._recolor_blocks(hist, ssum, np.unique(changed))
        return hist, ssum

    def _recolor_blocks(
        self, hist: npt.NDArray[np.float32], ssum: npt.NDArray[np.float32], changed: npt.NDArray[Any]
    ) -> None:
        """After an in-place table update, the cached overview colours of the ``changed`` blocks only (the
        other blocks' tables did not move): recolouring every block after a correction took 60-400 ms at
        10 M voxels, most of a correction's or an undo's time."""
        cached = self._lod_colors
        if cached is None or cached[0][0] is not hist:
            return
        (_, columns_bytes, mode, palette), colors = cached
        columns = np.frombuffer(columns_bytes, np.float32)
        if mode == "class":
            colors[changed] = vl.class_colors(lod.majority_class(hist, columns, changed), palette)
        else:
            colors[changed] = vl.scalar_colors(lod.mean_score(hist, ssum, columns, changed))

    def _all_block_colors(
        self,
        hist: npt.NDArray[np.float32],
        ssum: npt.NDArray[np.float32],
        columns: npt.NDArray[np.float32],
        mode: vl.ColorMode,
        palette: npt.NDArray[np.uint8],
    ) -> npt.NDArray[np.uint8]:
        """(B, 3) overview colour of every block (majority class or mean score of its visible voxels), kept
        until the tables, the class toggles, the mode or the palette change (a new focus reuses it)."""
        key = (hist, columns.tobytes(), mode, palette)
        cached = self._lod_colors
        same = cached is not None and cached[0][0] is hist and cached[0][3] is palette
        if cached is not None and same and cached[0][1:3] == key[1:3]:
            return cached[1]
        if mode == "class":
            colors = vl.class_colors(lod.majority_class(hist, columns), palette)
        else:
            colors = vl.scalar_colors(lod.mean_score(hist, ssum, columns))
        self._lod_colors = (key, colors)
        return colors

    def _draw_lod(self, grid: ReviewGrid, index: lod.LodIndex) -> int | None:
        """Draw a big map within the budget (:mod:`app.viewer.lod`): the voxels near :attr:`lod_focus` in the
        voxel layer, one point per block elsewhere in the overview layer. Returns the points sent, or None
        when every visible voxel fits the budget (then the caller draws exactly)."""
        with self._lock:
            state, palette, region = self.state, self.palette, self.focus
            label, conf, corrected = self.label, self.conf, self.corrected
            focus = self.lod_focus
        cfg = self.config.lod
        budget = self._lod_budget(state)
        blocks = index.blocks(index.overview_level(budget, cfg.overview_share))
        score, class_prob = self._view_score(grid, state, label, conf, corrected)
        hist, ssum = self._block_tables(
            blocks,
            state=state,
            label=label,
            conf=conf,
            corrected=corrected,
            score=score,
            num_classes=grid.num_classes,
        )
        t0 = time.perf_counter()
        columns = lod.enabled_columns(state.enabled, grid.num_classes)
        counts = lod.visible_counts(hist, columns)
        if int(counts.sum()) <= budget:
            return None
        if focus is None:
            if self._lod_centre is None:  # until something is focused: the middle of the map's blocks
                lower = blocks.lower
                self._lod_centre = (lower.min(axis=0) + lower.max(axis=0) + blocks.edge) / 2.0
            focus = self._lod_centre
        plan = lod.plan_view(blocks, index.order, counts, focus, cfg.radius, budget)
        rows = vl.visible_rows(state, label, score, plan.rows)
        colors = vl.view_colors(state, label, conf, class_prob, palette, rows)
        block_colors = self._all_block_colors(hist, ssum, columns, state.mode, palette)[plan.blocks]
        if region is not None and region.rows.size:
            colors = vl.dim_outside(colors, rows, region.rows)
            block_colors = self.blend_dim(block_colors)
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

    def set_map_visible(self, on: bool) -> None:
        """Show or hide the voxel map (both its layers)."""
        self.map_visible = bool(on)
        self.scene.voxels.visible = self.map_visible
        if self.lod_plan is not None or not self.map_visible:
            self.scene.overview.visible = self.map_visible

    def set_point_size(self, size: float) -> None:
        """Voxel point size (m); overview blocks keep their size relative to it."""
        grid = self.grid
        self.scene.voxels.point_size = float(size)
        if grid is not None and self._shown_blocks is not None:
            self.scene.overview.point_size = self._shown_blocks[0].edge * float(size) / grid.voxel_size

    def focus_lod(self, point: npt.ArrayLike) -> None:
        """Centre the full-resolution area of a big map on ``point`` (3,) and redraw (no-op for a map drawn
        exactly; kept for the level-of-detail view while its index is built)."""
        grid = self.grid
        if grid is None or not self._needs_lod(grid):
            return
        self.lod_focus = np.asarray(point, dtype=np.float64).reshape(3).copy()
        if self.lod_index is not None:
            self.request_draw()

    def _camera_moved(self, look_at: npt.NDArray[np.float64]) -> None:
        """Follow a browser's look-at point once it left the full-resolution area's centre by
        ``refine_distance`` (horizontally)."""
        if self.lod_index is None:
            return
        focus = self.lod_focus if self.lod_focus is not None else self._lod_centre
        if focus is None or float(np.hypot(*(look_at[:2] - focus[:2]))) > self.config.lod.refine_distance:
            self.focus_lod(look_at)

    def request_draw(self) -> None:
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

    _drawing = False
    _indexing = False
    _shown: tuple[ReviewGrid, npt.NDArray[np.int64]] | None = None

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
                self.panel.set_status("Redraw failed; see the server log.")
            finally:
                self._drawing = False
                with self._drawn:
                    self._drawn.notify_all()

    def _draw_selection(self) -> None:
        grid = self.grid
        rows = self.selection.rows
        if grid is None or rows.size == 0:
            self.scene.selection.visible = False
            return
        if self.selection.target == "map" and self.lod_plan is not None and self.lod_index is not None:
            # Selected voxels of the overview are highlighted by their blocks: the budget holds.
            blocks = self.lod_index.blocks(self.lod_plan.level)
            points = lod.thin_rows(blocks, self.lod_plan.full, grid.centres, rows)
            cols = np.empty((points.shape[0], 3), np.uint8)
            cols[:] = SELECTION_RGB
            self.scene.selection.set(points, cols)
            self.scene.selection.visible = True
            return
        cols = np.empty((rows.shape[0], 3), np.uint8)
        cols[:] = SELECTION_RGB
        if self.selection.target == "scan":
            view = self.scan_view
            if view is None or view.frame_id != self.selection.frame_id:
                self.scene.selection.visible = False
                return
            self.scene.selection.set(view.points[rows], cols)
        else:
            self.scene.selection.set(grid.centres[rows], cols)
        self.scene.selection.visible = True

    def _needs_lod(self, grid: ReviewGrid) -> bool:
        return grid.num_voxels > self.config.lod.budget

    def _build_index(self, grid: ReviewGrid) -> None:
        """Build ``grid``'s level-of-detail index on a thread, then redraw with it."""
        self._indexing = True

        def build() -> None:
            try:
                t0 = time.perf_counter()
                index = lod.build_index(grid.centres, grid.voxel_size, key_coords(grid.keys))
                cfg = self.config.lod
                blocks = index.blocks(index.overview_level(self._lod_budget(self.state), cfg.overview_share))
                # Per-voxel block arrays now, not on the first draw or correction that needs them.
                _ = blocks.of_row, blocks.mean, index.blocks(index.query_level(cfg.query_edge))
                with self._lock:
                    if self.grid is grid:
                        self.lod_index = index
                        self.lod_seconds["index"] = time.perf_counter() - t0
                self.request_draw()
            except Exception:  # keep the strided view; the panel says why
                log.exception("building the viewer's level-of-detail index failed")
                self.panel.set_status("The map's level of detail could not be built; see the server log.")
            finally:
                self._indexing = False
                with self._drawn:
                    self._drawn.notify_all()

        threading.Thread(target=build, name="viewer-lod-index", daemon=True).start()

    def _frame_whole_map(self) -> None:
        grid = self.grid
        centres = None if grid is None else grid.centres
        if centres is not None and self.lod_index is not None:
            # Percentiles of a big map's evenly strided sample (keys sort by x): framing needs no more.
            centres = centres[:: max(1, centres.shape[0] // 1_000_000)]
        view = None if centres is None else nl.fit_view(centres)
        if view is not None:
            self.scene.look_at(*view)

    def fit_map(self) -> None:
        """Move the camera so that the whole voxel map is in view (key ``shift+f``)."""
        self._frame_whole_map()

    def fit_scan(self) -> None:
        """Move the camera so that the shown scan's points are in view (key ``f``)."""
        view = self.scan_view
        framing = None if view is None else nl.fit_view(view.points)
        if framing is not None:
            self.scene.look_at(*framing)

    def follow_scan(self) -> None:
        """Move the camera behind and above the shown scan's ego pose (:func:`nav_logic.follow_view`)."""
        view = self.scan_view
        if view is not None and view.ego_pose is not None:
            # The ground under a drone is far below it: follow_view then looks at the ground ahead.
            ground = float(np.percentile(view.points[:, 2], 20)) if len(view.points) else None
            self.scene.look_at(*nl.follow_view(view.ego_pose, ground_z=ground))

    # ------------------------------------------------------------------------------------ scan browser
    @property
    def scan_count(self) -> int:
        """Number of scans the run labelled (the positions :meth:`show_scan` takes)."""
        outputs = self.outputs
        return 0 if outputs is None else len(outputs.frame_indices)

    def show_scan(self, pos: int, *, move_camera: bool | None = None) -> ScanView | None:
        """Show the ``pos``-th labelled scan (clipped to the run's scans): its points, camera frustum and
        labelled image. The camera follows the ego pose when ``move_camera`` is True, or when it is None and
        :attr:`follow_ego` is on."""
        outputs = self.outputs
        if outputs is None or not outputs.frame_indices:
            return None
        with self._scan_lock:
            pos = int(np.clip(pos, 0, len(outputs.frame_indices) - 1))
            view = outputs.scan_view(outputs.frame_indices[pos], self.palette)
            view = self._mark_region_in_image(view, pos)
            self.frame_pos = pos
            with self._lock:
                self.scan_view = view
                dropped = self.selection.target == "scan" and self.selection.rows.size > 0
                if dropped:  # a scan selection belongs to the scan it was made on
                    self.selection = _Selection(np.zeros(0, np.int64))
                self.scan_label = self._scan_labels_locked(view)
                colors = nl.scan_colors(self.state.mode, self.scan_label, self.palette)
                self.scene.scan.set(view.points, colors)
            if dropped:
                self._draw_selection()
                self.panel.on_selection(0)
            self.scene.camera.set(
                position=view.cam_position,
                wxyz=view.cam_wxyz,
                fov_y=view.fov_y,
                aspect=view.aspect,
                image=view.overlay,
            )
            if move_camera if move_camera is not None else self.follow_ego:
                self.follow_scan()
            if self.focus is None or self.focus_frame != pos:
                # A focused region keeps the full resolution on itself while its best scan is shown.
                ego = view.ego_pose[:3, 3] if view.ego_pose is not None else view.cam_position
                self.focus_lod(ego)
        self.panel.on_scan(view, pos, len(outputs.frame_indices))
        return view

    def step_scan(self, step: int) -> ScanView | None:
        """Show the scan ``step`` positions after (before, when negative) the shown one."""
        with self._scan_lock:
            return self.show_scan(self.frame_pos + step)

    def _color_scan(self) -> None:
        with self._scan_lock:
            view = self.scan_view
            if view is not None and self.scene.scan.count == view.points.shape[0]:
                self.scene.scan.set_colors(nl.scan_colors(self.state.mode, self.scan_label, self.palette))

    def set_follow(self, on: bool | None = None) -> bool:
        """Turn camera following on or off (None toggles); turning it on moves the camera at once."""
        self.follow_ego = (not self.follow_ego) if on is None else bool(on)
        if self.follow_ego:
            self.follow_scan()
        self.panel.on_nav()
        return self.follow_ego

    def set_image_open(self, on: bool | None = None) -> bool:
        """Show or hide the enlarged scan image in the page (None toggles)."""
        self.image_open = (not self.image_open) if on is None else bool(on)
        self.panel.on_nav()
        return self.image_open

    def scan_image_jpeg(self, quality: int = 90) -> bytes | None:
        """The shown scan's labelled camera image as JPEG, or None when it has none (encoded once per
        scan)."""
        view = self.scan_view
        if view is None or view.overlay is None:
            return None
        cached = self._image_jpeg
        if cached is not None and cached[0] is view:
            return cached[1]
        ok, buf = cv2.imencode(".jpg", view.overlay[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError(f"could not encode the image of scan {view.frame_id}")
        data = buf.tobytes()
        self._image_jpeg = (view, data)
        return data

    def set_playing(self, on: bool | None = None) -> bool:
        """Play through the scans, one every ``config.play_interval_s``, or pause (None toggles).

        Playing from the last scan starts again at the first; playing stops at the last scan.
        """
        with self._scan_lock:
            want = (not self.playing) if on is None else bool(on)
            if want and self.scan_count <= 1:
                want = False
            self.playing = want
            if want and self.frame_pos >= self.scan_count - 1:
                self.show_scan(0)
            if want and (self._player is None or not self._player.is_alive()):
                self._player = threading.Thread(target=self._play_loop, name="viewer-play", daemon=True)
                self._player.start()
        self.panel.on_nav()
        return self.playing

    def _play_loop(self) -> None:
        while self.playing and not self._stop.wait(self.config.play_interval_s):
            if not self.playing:
                return
            try:
                with self._scan_lock:
                    at_end = self.frame_pos + 1 >= self.scan_count - 1
                    self.step_scan(1)
                    if at_end:
                        self.playing = False
            except Exception:  # stop playing, keep the viewer
                log.exception("viewer could not show the next scan")
                self.playing = False
            if not self.playing:
                self.panel.on_nav()
                return

    # ------------------------------------------------------------------------------------- inspection
    def confidence_histograms(self, bins: int = 10) -> npt.NDArray[np.int64]:
        """(C, bins) voxel counts per shown class and confidence bin (corrections applied; see
        :func:`app.viewer.nav_logic.confidence_histograms`)."""
        with self._lock:
            label, conf = self.label, self.conf
        return nl.confidence_histograms(label, conf, len(self.class_names()), bins)

    def inspect_ray(self, origin: npt.ArrayLike, direction: npt.ArrayLike) -> Inspection | None:
        """Inspect the first shown voxel a click ray enters (:func:`leap_core.picking.pick_voxel`): its
        class distribution, confidence, number of scans that observed it and its correction history.
        Returns None (and changes nothing) when the ray hits no shown voxel."""
        grid = self.grid
        if grid is None:
            return None
        index = self.lod_index
        if index is not None:
            # Every visible voxel of a big map can be picked, overview or not; cubes off the ray are skipped.
            cubes = index.blocks(index.query_level(self.config.lod.query_edge))
            rows = lod.ray_rows(index, cubes, origin, direction)
            rows = rows[self._visible_mask(grid)[rows]]
        else:
            rows, _ = self.compute_view()
        pick = pick_voxel(origin, direction, grid.centres[rows], grid.voxel_size)
        if pick is None:
            return None
        row = int(rows[pick.index])
        key = int(grid.keys[row])
        history = [rec for rec in self.corrections if np.any(self._grid_keys(rec) == key)]
        views = self.outputs.view_counts(grid) if self.outputs is not None else None
        with self._lock:
            label, conf, corrected = int(self.label[row]), float(self.conf[row]), bool(self.corrected[row])
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
        self.panel.on_inspect(found)
        return found

    # ------------------------------------------------------------------------------------ review queue
    def build_queue(self, kind: QueueKind) -> list[vl.Region]:
        """Regions to review, worst first: lowest confidence, or most camera-vs-final disagreement.

        Each region gets its content signature; the queue (identities and signatures) is saved to the
        project so the web UI can count review progress, and the project's marks are read back.
        """
        cfg = self.config
        with self._lock:
            grid, conf, label, run = self.grid, self.conf, self.label, self.run
            self.queue_building = True
        self.panel.on_queue(True)
        try:
            if grid is None:
                return []
            if kind == "confidence":
                candidates = vl.lowest_share(conf, cfg.queue_share)
                regions = vl.rank_regions(
                    grid.centres,
                    conf,
                    candidates,
                    cfg.queue_cell,
                    min_count=cfg.queue_min_count,
                    ascending=True,
                )
            else:
                assert self.outputs is not None
                rate, observed = self.outputs.disagreement(grid)
                seen = observed > 0
                # lowest_share of -rate (unseen voxels last) is the highest-disagreement share.
                top = vl.lowest_share(np.where(seen, -rate, np.inf), cfg.queue_share)
                candidates = seen & (rate > 0) & top
                regions = vl.rank_regions(
                    grid.centres,
                    rate,
                    candidates,
                    cfg.queue_cell,
                    min_count=cfg.queue_min_count,
                    ascending=False,
                )
            signatures = review.region_signatures(
                grid.centres, grid.keys, label, [r.cell for r in regions], cfg.queue_cell
            )
            run_id = None if run is None else run.run_id
            pairs = [(r.id, g) for r, g in zip(regions, signatures, strict=True)]
            self.backend.save_review_queue(kind, run_id, pairs)
            marks = self.backend.review_marks()
            with self._lock:
                self.queue_kind = kind
                self.regions = regions
                self.signatures = signatures
                self.marks = marks
                self.region_pos = -1
                self.queue_built = True
            return regions
        finally:
            with self._lock:
                self.queue_building = False
            self.panel.on_queue(False)

    def _rebuild_queue(self, kind: QueueKind) -> None:
        try:
            self.build_queue(kind)
        except Exception:  # keep the viewer alive; the panel shows the error
            log.exception("rebuilding the review queue failed")
            self.panel.set_status("Ranking the review queue failed; see the server log.")

    def region_state(self, pos: int) -> str | None:
        """``accepted`` / ``skipped`` when region ``pos`` has a mark made on its current content, else
        None."""
        mark = self.marks.get(self.regions[pos].id)
        return mark.state if mark is not None and mark.signature == self.signatures[pos] else None

    def review_progress(self) -> dict[str, int]:
        """``{"total", "reviewed", "skipped"}`` over the current queue (marks on unchanged content only)."""
        with self._lock:
            states = [self.region_state(i) for i in range(len(self.regions))]
        return {
            "total": len(states),
            "reviewed": states.count("accepted"),
            "skipped": states.count("skipped"),
        }

    def next_region(self, step: int = 1) -> vl.Region | None:
        """Show the next (or previous, ``step=-1``) region of the queue (see :meth:`show_region`)."""
        with self._lock:
            if not self.regions:
                return None
            pos = (self.region_pos + step) % len(self.regions)
        return self.show_region(pos)

    def show_region(self, pos: int) -> vl.Region | None:
        """Focus region ``pos``: highlight its voxels and dim the rest, outline it, frame the camera on it,
        and show the scan that observed it best with the region boxed in its image."""
        with self._lock:
            if not 0 <= pos < len(self.regions):
                return None
            self.region_pos = pos
            region = self.regions[pos]
            self.focus = region
            self.focus_frame = None
            grid = self.grid
        assert grid is not None
        lo = grid.centres[region.rows].min(axis=0) - grid.voxel_size / 2
        hi = grid.centres[region.rows].max(axis=0) + grid.voxel_size / 2
        self.scene.set_review_box((lo + hi) / 2, hi - lo, REVIEW_BOX_RGB)
        self.scene.frame_region(region)
        self.focus_lod(region.centre)
        self.request_draw()
        best = self._best_scan(region)
        if best is not None:
            with self._lock:
                self.focus_frame = best
            self.show_scan(best, move_camera=False)  # keep the framing of the region
        self.panel.on_region(region, pos, len(self.regions), self.queue_kind)
        return region

    @staticmethod
    def blend_dim(colors: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """How voxels outside the focused region are drawn (:func:`app.viewer.view_logic.dim_outside`)."""
        return vl.dim_outside(colors, np.zeros(colors.shape[0], np.int64), np.zeros(0, np.int64))

    def clear_focus(self) -> None:
        with self._lock:
            self.focus, self.focus_frame = None, None
        self.scene.set_review_box(None)
        self.request_draw()

    def _region_keys(self, region: vl.Region) -> npt.NDArray[np.int64]:
        assert self.grid is not None
        return self.grid.keys[region.rows]  # rows ascend, so the keys stay sorted

    def _best_scan(self, region: vl.Region) -> int | None:
        """Slider position of the scan that observed ``region`` most, among the ``queue_scans`` scans
        nearest it (:func:`leap_core.review.best_observer`)."""
        outputs, grid = self.outputs, self.grid
        if outputs is None or grid is None or not outputs.frame_indices:
            return None
        frames = np.asarray(outputs.frame_indices)
        positions = outputs.seq.poses[frames, :3, 3]
        near = review.nearest_scans(positions, region.centre, self.config.queue_scans)
        keys = self._region_keys(region)
        counts = [outputs.region_observers(int(frames[i]), keys, grid.voxel_size)[:2] for i in near]
        best = review.best_observer([c[1] for c in counts], [c[0] for c in counts])
        return None if best is None else int(near[best])

    def _mark_region_in_image(self, view: ScanView, pos: int) -> ScanView:
        """The scan view with the focused region boxed in its image (when this scan's camera sees it)."""
        region, outputs, grid = self.focus, self.outputs, self.grid
        if region is None or outputs is None or grid is None or view.overlay is None:
            return view
        keys = self._region_keys(region)
        _, _, uv = outputs.region_observers(outputs.frame_indices[pos], keys, grid.voxel_size)
        h, w = view.overlay.shape[:2]
        box = review.image_box(uv, w, h)
        if box is None:
            return view
        return dataclasses.replace(view, overlay=review.draw_box(view.overlay, box, REVIEW_BOX_RGB))

    def mark_region(self, state: str) -> vl.Region | None:
        """Record ``accepted`` or ``skipped`` for the focused region (in the project's database) and show
        the next region without a mark; returns that region (None when every region has one)."""
        with self._lock:
            pos = self.region_pos
            if not 0 <= pos < len(self.regions):
                raise ValueError("no review region is shown; press Next region first")
            region, signature = self.regions[pos], self.signatures[pos]
        run_id = None if self.run is None else self.run.run_id
        self.backend.set_review_mark(region.id, signature, state, run_id)
        with self._lock:
            self.marks[region.id] = ReviewMarkRecord(signature, state)
            n = len(self.regions)
            following = [(pos + k) % n for k in range(1, n + 1)]
            nxt = next((i for i in following if self.region_state(i) is None), None)
        if nxt is None:
            self.panel.on_region(region, pos, n, self.queue_kind)
            return None
        return self.show_region(nxt)

    def relabel_region(self, class_name: str) -> int | None:
        """Assign ``class_name`` to the focused region's voxels (a correction, as a box selection would)
        and accept the region on its new content; returns the correction id."""
        with self._lock:
            pos = self.region_pos
            if not 0 <= pos < len(self.regions) or self.grid is None:
                raise ValueError("no review region is shown; press Next region first")
            region = self.regions[pos]
            self.selection = _Selection(region.rows)
        cid = self.assign_selection(class_name)
        assert self.grid is not None
        signature = review.region_signatures(
            self.grid.centres, self.grid.keys, self.label, [region.cell], self.config.queue_cell
        )[0]
        with self._lock:
            self.signatures[pos] = signature
        self.mark_region("accepted")
        return cid

    # ------------------------------------------------------------------------------------- corrections
    def set_tools(self, **changes: Any) -> ToolSettings:
        """Change the selection tools' settings (fields of :class:`ToolSettings`); validated here so the
        panel and the viewer page's routes share one rule."""
        tools = dataclasses.replace(self.tools, **changes)
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
        if tools.class_filter is not None and tools.class_filter not in self.class_names():
            raise ValueError(f"class_filter: unknown class {tools.class_filter!r}")
        with self._lock:
            self.tools = tools
        self._emit("tools")
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
        two corners. The depth mode, distance, class filter and target come from :attr:`tools`; ``add``
        adds to the current selection (same target and scan) instead of replacing it.
        """
        tools = self.tools
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
        with self._lock:
            grid, view, label = self.grid, self.scan_view, self.label
            scan_label = self.scan_label
        if grid is None:
            return 0
        cls = None if tools.class_filter is None else self._class_ids().get(tools.class_filter)
        frame_id = None
        index = self.lod_index
        if tools.target == "map" and index is not None:
            # A big map: the full grid's visible voxels, culled by coarse cubes first (same result).
            chosen = lod.select_culled(
                index,
                index.blocks(index.query_level(self.config.lod.query_edge)),
                camera,
                mask,
                visible=self._visible_mask(grid),
                eligible=None if cls is None else label == cls,
                depth_mode=tools.depth_mode,
                distance=tools.distance,
                splat_size=grid.voxel_size,
            )
            return self._set_selection(chosen, tools.target, None, add)
        if tools.target == "map":
            rows, _ = self.compute_view()
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
        with self._lock:
            old = self.selection
            if add and old.target == target and old.frame_id == frame_id:
                chosen = np.union1d(old.rows, chosen)
            self.selection = _Selection(chosen, target, frame_id)
        self._draw_selection()
        self.panel.on_selection(int(chosen.size))
        self._emit("selection")
        return int(chosen.size)

    def _visible_mask(self, grid: ReviewGrid) -> npt.NDArray[np.bool_]:
        """(V,) the voxels the view shows (threshold and class toggles; every one, drawn or thinned)."""
        with self._lock:
            state, label, conf, corrected = self.state, self.label, self.conf, self.corrected
        score, _ = self._view_score(grid, state, label, conf, corrected)
        return vl.visible_mask(label, score, state.threshold, state.enabled)

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
        with self._lock:
            self.selection = _Selection(np.zeros(0, np.int64))
        self._draw_selection()
        self.panel.on_selection(0)
        self._emit("selection")

    def assign_selection(self, class_name: str, *, scope: Scope | None = None) -> int | None:
        """Store a correction assigning ``class_name`` (``""``: erase to unlabeled) to the selection;
        returns its id (None when nothing is selected).

        ``scope`` (default :attr:`ToolSettings.scope`): ``map`` stores the voxels (of the selected voxels,
        or of the voxels holding the selected scan points); ``scan`` stores the shown scan's points (the
        selected points, or the scan's points inside the selected voxels).
        """
        scope = self.tools.scope if scope is None else scope
        if scope not in ("map", "scan"):
            raise ValueError(f"scope must be 'map' or 'scan', got {scope!r}")
        with self._lock:
            grid, selection, view = self.grid, self.selection, self.scan_view
        rows = selection.rows
        if grid is None or rows.size == 0:
            return None
        if class_name != "" and class_name not in self.class_names():
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
        with self._lock:
            self.selection = _Selection(np.zeros(0, np.int64))
            self._apply_corrections_locked()
        self._recolour_scan()
        self.panel.on_selection(0)
        self.panel.on_history()
        self.request_draw()
        self._emit("corrected")
        return cid

    def assign_slot(self, slot: int) -> int | None:
        """Assign the ``slot``-th class (1-based, the order of the class picker) to the selection."""
        names = self.class_names()
        if not 1 <= slot <= len(names):
            raise ValueError(f"slot must lie in [1, {len(names)}], got {slot}")
        return self.assign_selection(names[slot - 1])

    def _scan_labels_locked(self, view: ScanView) -> npt.NDArray[np.int16]:
        """The scan's run labels with the active corrections overlaid: map corrections through the voxel
        of each point, then this scan's own corrections in the order they were made."""
        label = view.label.copy()
        grid = self.grid
        if grid is None or self.corrected.size != grid.num_voxels:
            return label
        if self.corrected.any():
            rows = grid.rows_of(voxel_keys(view.points.astype(np.float64), grid.voxel_size))
            hit = rows >= 0
            hit[hit] = self.corrected[rows[hit]]
            label[hit] = self.label[rows[hit]]
        names = self._class_ids()
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

    def _recolour_scan(self) -> None:
        with self._lock:
            view = self.scan_view
            if view is None:
                return
            self.scan_label = self._scan_labels_locked(view)
            colors = nl.scan_colors(self.state.mode, self.scan_label, self.palette)
        self.scene.scan.set_colors(colors)

    def undo(self) -> int | None:
        cid = self.history.undo()
        if cid is not None:
            self.backend.set_correction_active(cid, False)
            self._after_history()
        return cid

    def redo(self) -> int | None:
        cid = self.history.redo()
        if cid is not None:
            self.backend.set_correction_active(cid, True)
            self._after_history()
        return cid

    def _after_history(self) -> None:
        with self._lock:
            if self.grid is not None:
                self._apply_corrections_locked()
        self._recolour_scan()
        self.panel.on_history()
        self.request_draw()

    def correction_count(self) -> int:
        return sum(1 for c in self.corrections if c.active)

    # -------------------------------------------------------------------------------------- steering
    def update_class(
        self,
        index: int,
        *,
        name: str | None = None,
        color: tuple[int, int, int] | None = None,
        prompts: list[str] | None = None,
    ) -> Schema:
        """Rename / recolour / re-prompt class ``index`` of the project schema and save it."""
        schema = self.backend.load_schema()
        classes = list(schema.classes)
        old = classes[index]
        classes[index] = dataclasses.replace(
            old,
            name=old.name if name is None else name,
            color=old.color if color is None else color,
            prompts=old.prompts if prompts is None else tuple(prompts),
        )
        return self._save_schema(schema.with_classes(classes))

    def add_class(self, name: str, *, color: tuple[int, int, int] = (200, 200, 200)) -> Schema:
        """Append a class (prompt = its name, next free export id) to the project schema and save it."""
        schema = self.backend.load_schema()
        used = {c.export_id for c in schema.classes}
        export_id = next(i for i in range(max(used, default=0) + 1, 1 << 16) if i not in used)
        new = ClassDef(name=name, color=color, prompts=(name,), export_id=export_id)
        return self._save_schema(schema.with_classes([*schema.classes, new]))

    def remove_class(self, index: int) -> Schema:
        schema = self.backend.load_schema()
        classes = [c for i, c in enumerate(schema.classes) if i != index]
        return self._save_schema(schema.with_classes(classes))

    def _save_schema(self, schema: Schema) -> Schema:
        self.backend.save_schema(schema)
        with self._lock:
            self.project_schema = self.backend.load_schema()
            self._refresh_palette()
        self.panel.on_schema()
        self.request_draw()
        return self.project_schema

    # -------------------------------------------------------------------------------------- re-runs
    def rerun(self) -> int:
        """Start a background run of the project (with its current schema and corrections)."""
        run_id = self.backend.start_run()
        self._emit("run_started")
        self._watch(run_id)
        return run_id

    def _watch(self, run_id: int) -> None:
        self.watched_run = run_id
        if self._watcher is not None and self._watcher.is_alive():
            return  # the running watcher follows ``watched_run``
        self._watcher = threading.Thread(target=self._watch_loop, name="viewer-run-watch", daemon=True)
        self._watcher.start()

    def _watch_loop(self) -> None:
        while not self._stop.is_set():
            run_id = self.watched_run
            if run_id is None:
                return
            try:
                info = self.backend.run_info(run_id)
            except Exception:  # a transient DB error must not kill the watcher
                log.exception("viewer could not read run %s", run_id)
                self._stop.wait(self.config.poll_interval_s)
                continue
            self.panel.on_run_progress(info)
            if info.status in ("done", "failed", "cancelled", "interrupted"):
                if self.watched_run == run_id:
                    self.watched_run = None
                if info.status == "done":
                    try:
                        self.load_run(info)
                    except Exception as exc:  # report, keep the old scene
                        log.exception("viewer could not load run %s", run_id)
                        self.panel.set_status(f"Run {info.number} finished but could not be loaded: {exc}")
                self._emit("run_finished")
                if self.watched_run is None:
                    return
                continue
            self._stop.wait(self.config.poll_interval_s)


__all__ = [
    "CorrectionRecord",
    "Inspection",
    "ProjectBackend",
    "QueueKind",
    "ReviewMarkRecord",
    "ReviewSession",
    "RunInfo",
    "Scope",
    "SessionConfig",
    "Target",
    "ToolKind",
    "ToolSettings",
    "ViewChanges",
    "camera_of",
]
