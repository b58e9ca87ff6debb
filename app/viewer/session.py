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

import numpy as np
import numpy.typing as npt

from app.viewer import view_logic as vl
from app.viewer.data import ReviewGrid, RunOutputs, ScanView
from app.viewer.scene import ReviewScene
from leap_core import review
from leap_core.fusion import key_centres, voxel_keys
from leap_core.schema import ClassDef, Schema

if TYPE_CHECKING:
    from typing_extensions import Unpack  # typing.Unpack from Python 3.11

log = logging.getLogger(__name__)

QueueKind = Literal["confidence", "disagreement"]


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
    """Folder with the run's outputs."""
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
    """Assigned class."""
    voxel_size: float
    """Voxel edge of ``keys``."""
    keys: npt.NDArray[np.int64]
    """Packed voxel keys."""
    active: bool
    """False once undone."""


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

    def add_correction(self, class_name: str, voxel_size: float, keys: npt.NDArray[np.int64]) -> int: ...

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


@dataclass
class _Selection:
    rows: npt.NDArray[np.int64]


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
        self.label = np.zeros(0, np.int16)
        self.conf = np.zeros(0, np.float32)
        self.corrected = np.zeros(0, bool)
        self.selection = _Selection(np.zeros(0, np.int64))
        self.regions: list[vl.Region] = []
        self.region_pos = -1
        self.queue_kind: QueueKind = "confidence"
        self._init_review_state()
        self.frame_pos = 0
        self.last_draw_s = 0.0
        self.draw_count = 0
        self.scene_version = 0
        """Bumped every time a run's data is (re)loaded into the scene."""
        self.watched_run: int | None = None
        self._lock = threading.RLock()
        self._draw_wanted = threading.Event()
        self._drawn = threading.Condition()
        self._stop = threading.Event()
        self._listeners: list[Callable[[str], None]] = []
        self.panel = panel(self)
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
        """Stop the drawing and watching threads and the viser server."""
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
        with self._lock:
            self.run = run
            self.grid = grid
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
        if self.scene_version == 1:
            # Frame the map once; a reload after a re-run keeps the camera where the user left it.
            self._frame_whole_map()
        self.scene.set_review_box(None)
        if outputs.frame_indices:
            self.show_scan(len(outputs.frame_indices) // 2)
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

    def _apply_corrections_locked(self) -> None:
        assert self.grid is not None
        names = {n: i for i, n in enumerate(self.class_names())}
        keys_all, labels_all = [], []
        for rec in self.backend.corrections():
            if not rec.active or rec.class_name not in names or rec.keys.size == 0:
                continue
            keys = rec.keys
            if not np.isclose(rec.voxel_size, self.grid.voxel_size):
                keys = voxel_keys(key_centres(keys, rec.voxel_size), self.grid.voxel_size)
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
            self.state = dataclasses.replace(self.state, **changes)
        self._draw_wanted.set()

    def set_class_enabled(self, index: int, on: bool) -> None:
        with self._lock:
            enabled = list(self.state.enabled)
            if 0 <= index < len(enabled):
                enabled[index] = on
            self.state = dataclasses.replace(self.state, enabled=tuple(enabled))
        self._draw_wanted.set()

    def compute_view(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
        """Rows of the visible voxels and their colours for the current state (pure on the session's
        arrays)."""
        with self._lock:
            grid, state = self.grid, self.state
            label, conf, corrected, palette = self.label, self.conf, self.corrected, self.palette
        if grid is None:
            return np.zeros(0, np.int64), np.zeros((0, 3), np.uint8)
        class_prob = grid.class_prob(state.class_index) if state.mode == "class_probability" else None
        rows, colors = vl.render_view(state, label, conf, palette, class_prob, corrected)
        focus = self.focus
        if focus is not None and focus.rows.size:
            colors = vl.dim_outside(colors, rows, focus.rows)
        return rows, colors

    def draw_now(self) -> None:
        """Recompute and push the voxel layer (and selection highlight) synchronously."""
        t0 = time.perf_counter()
        rows, colors = self.compute_view()
        grid = self.grid
        if grid is None:
            return
        shown = self._shown
        if shown is not None and shown[0] is grid and np.array_equal(shown[1], rows):
            # Same voxels (a colouring change): only the colours go over the wire.
            self.scene.voxels.set_colors(colors)
        else:
            self.scene.voxels.set(grid.centres[rows], colors)
            self._shown = (grid, rows)
        self._draw_selection()
        self.last_draw_s = time.perf_counter() - t0
        self.draw_count += 1
        self.panel.on_drawn(shown=rows.shape[0], total=grid.num_voxels, seconds=self.last_draw_s)
        with self._drawn:
            self._drawn.notify_all()
        self._emit("drawn")

    def request_draw(self) -> None:
        self._draw_wanted.set()

    def wait_drawn(self, timeout: float = 10.0) -> bool:
        """Block until no redraw is pending (tests and the benchmark use this)."""
        deadline = time.monotonic() + timeout
        with self._drawn:
            while self._draw_wanted.is_set() or self._drawing:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._drawn.wait(min(left, 0.05))
        return True

    _drawing = False
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
        cols = np.empty((rows.shape[0], 3), np.uint8)
        cols[:] = SELECTION_RGB
        self.scene.selection.set(grid.centres[rows], cols)
        self.scene.selection.visible = True

    def _frame_whole_map(self) -> None:
        grid = self.grid
        if grid is None or grid.num_voxels == 0:
            return
        lo = np.percentile(grid.centres, 2, axis=0)
        hi = np.percentile(grid.centres, 98, axis=0)
        centre = (lo + hi) / 2.0
        centre[2] = float(np.percentile(grid.centres[:, 2], 20))
        extent = float(np.linalg.norm(hi[:2] - lo[:2]))
        pos, tgt = vl.orbit_view(centre, max(10.0, 0.85 * extent), elevation_deg=50.0, azimuth_deg=200.0)
        self.scene.look_at(pos, tgt)

    # ------------------------------------------------------------------------------------ scan browser
    def show_scan(self, pos: int) -> ScanView | None:
        """Show the ``pos``-th labelled scan: its points, camera frustum and labelled image."""
        outputs = self.outputs
        if outputs is None or not outputs.frame_indices:
            return None
        pos = int(np.clip(pos, 0, len(outputs.frame_indices) - 1))
        view = outputs.scan_view(outputs.frame_indices[pos], self.palette)
        view = self._mark_region_in_image(view, pos)
        self.frame_pos = pos
        self.scene.scan.set(view.points, vl.class_colors(view.label, self.palette))
        self.scene.camera.set(
            position=view.cam_position,
            wxyz=view.cam_wxyz,
            fov_y=view.fov_y,
            aspect=view.aspect,
            image=view.overlay,
        )
        self.panel.on_scan(view, pos, len(outputs.frame_indices))
        return view

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
                    grid.centres, conf, candidates, cfg.queue_cell, min_count=cfg.queue_min_count,
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
                    grid.centres, rate, candidates, cfg.queue_cell, min_count=cfg.queue_min_count,
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
        self.request_draw()
        best = self._best_scan(region)
        if best is not None:
            with self._lock:
                self.focus_frame = best
            self.show_scan(best)
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
    def select_rect(
        self,
        position: npt.ArrayLike,
        wxyz: npt.ArrayLike,
        fov_y: float,
        aspect: float,
        rect_min: tuple[float, float],
        rect_max: tuple[float, float],
    ) -> int:
        """Select the visible voxels inside a screen rectangle seen from a camera; returns the count."""
        grid = self.grid
        if grid is None:
            return 0
        rows, _ = self.compute_view()
        inside = vl.select_in_rect(
            grid.centres[rows],
            list(np.asarray(position)),
            list(np.asarray(wxyz)),
            fov_y,
            aspect,
            rect_min=rect_min,
            rect_max=rect_max,
        )
        with self._lock:
            self.selection = _Selection(rows[inside])
        self._draw_selection()
        self.panel.on_selection(int(inside.sum()))
        return int(inside.sum())

    def clear_selection(self) -> None:
        with self._lock:
            self.selection = _Selection(np.zeros(0, np.int64))
        self._draw_selection()
        self.panel.on_selection(0)

    def assign_selection(self, class_name: str) -> int | None:
        """Store a correction assigning ``class_name`` to the selected voxels; returns its id."""
        grid = self.grid
        rows = self.selection.rows
        if grid is None or rows.size == 0:
            return None
        if class_name not in self.class_names():
            raise ValueError(f"unknown class {class_name!r}")
        cid = self.backend.add_correction(class_name, grid.voxel_size, grid.keys[rows])
        self.history.push(cid)
        with self._lock:
            self.selection = _Selection(np.zeros(0, np.int64))
            self._apply_corrections_locked()
        self.panel.on_selection(0)
        self.panel.on_history()
        self.request_draw()
        return cid

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
        self.panel.on_history()
        self.request_draw()

    def correction_count(self) -> int:
        return sum(1 for c in self.backend.corrections() if c.active)

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
    "ProjectBackend",
    "QueueKind",
    "ReviewMarkRecord",
    "ReviewSession",
    "RunInfo",
    "SessionConfig",
    "ViewChanges",
]
