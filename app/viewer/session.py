"""One review session: a run's data, the scene, the GUI panel, and the project it steers.

In the app each browser tab has its own session, with its own viser server
(:class:`app.viewer.manager.ProjectViewer`); the tabs of a project share the loaded run (``data=``) and the
corrected labels (``overlays=``), and are told of each other's corrections, marks and runs.

:class:`ReviewSession` coordinates rooms, one object per concern, each a handle the panel and the API routes
call (as viser's ``server.scene`` / ``server.gui``):

- :attr:`~ReviewSession.renderer` (:class:`~app.viewer.render.LodRenderer`): the voxel map's drawing,
  coalesced on a thread, with level of detail above the point budget;
- :attr:`~ReviewSession.player` (:class:`~app.viewer.player.ScanPlayer`): the shown scan, stepping and
  playing, the camera that follows it, its image;
- :attr:`~ReviewSession.tools` (:class:`~app.viewer.selection_tool.SelectionTool`): lasso / brush / box
  selections, their settings, and the click inspector;
- :attr:`~ReviewSession.corrections` (:class:`~app.viewer.corrections.Corrections`): assigning classes,
  undo / redo, the corrections overlaid on the grid;
- :attr:`~ReviewSession.queue` (:class:`~app.viewer.review_queue.ReviewQueue`): ranked review regions, the
  focused one, accept / skip / relabel;
- :attr:`~ReviewSession.classes` and :attr:`~ReviewSession.runs` (:mod:`app.viewer.steering`): class edits,
  re-runs and the run watcher.

The rooms share one :class:`~app.viewer.shared.SharedState` (the shown run, its corrected labels, the view,
the selection, the focused region and the shown scan; each field names the rooms that write it) and report
through one :class:`~app.viewer.shared.Notifier` (the panel and the event listeners). Each is handed the
rooms it calls at construction, in dependency order (renderer ← player ← tools ← corrections ← queue),
never the session. The session loads runs, changes the view and wires the rooms to the scene and the
panel. The panel (:class:`app.viewer.panel.ReviewPanel`) is given as a constructor, so it imports the
session and not the reverse.

Locks (one discipline):

- ``shared.lock`` (:attr:`SharedState.lock <app.viewer.shared.SharedState.lock>`, re-entrant) is the
  session's one lock. It guards every field of the shared state, and the rooms' fields that other threads
  read together: the queue's regions, signatures, marks, position and building flag, the tool settings, and
  the renderer's level-of-detail index (set by the index thread). It is held to read or replace those
  references; a load, a correction and a scan change also do the store read or scene update that goes with
  the new state under it, as one step. No code holding it waits for another thread. Arrays are replaced,
  never changed in place, so references taken under the lock stay a consistent snapshot after it is
  released; single references are also read without it (an assignment is atomic).
- The player's scan lock (re-entrant) serialises scan changes (show, step, play) so that a step reads the
  position and shows the next scan as one move. It is taken before ``shared.lock``, never inside it.
- The renderer's draw request (an event) and ``drawn`` condition coalesce redraws and wake
  :meth:`~app.viewer.render.LodRenderer.wait_drawn`; its caches (block tables, shown layers) are used by the
  drawing thread, and by the synchronous first draw of a load.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from app.viewer import view_logic as vl
from app.viewer.corrections import Corrections, OverlayCache
from app.viewer.data import ReviewGrid, RunOutputs
from app.viewer.object_queue import ObjectQueue
from app.viewer.player import ScanPlayer
from app.viewer.records import (
    CorrectionRecord,
    Inspection,
    ProjectBackend,
    QueueKind,
    ReviewMarkRecord,
    RunInfo,
    Scope,
    Selection,
    SessionConfig,
    SessionView,
    Target,
    ToolKind,
    ToolSettings,
    ViewChanges,
)
from app.viewer.render import LodRenderer
from app.viewer.review_queue import ReviewQueue
from app.viewer.run_delta import RunDelta
from app.viewer.scene import ReviewScene
from app.viewer.selection_tool import SelectionTool
from app.viewer.shared import Notifier, SharedState
from app.viewer.steering import ClassEditor, RunWatcher

if TYPE_CHECKING:
    from typing_extensions import Unpack  # typing.Unpack from Python 3.11


RunData = Callable[[RunInfo], tuple[ReviewGrid, RunOutputs]]
"""Reads a finished run's grid and scans (the app's viewer shares one copy between its tabs)."""


def read_run(run: RunInfo, dataset: Path) -> tuple[ReviewGrid, RunOutputs]:
    """A finished run's grid and scans, read from its folder and its dataset."""
    return ReviewGrid.load(run.run_dir, run.pipeline), RunOutputs(run.run_dir, dataset)


class ReviewSession:
    """A viewer for one project: shows a run, edits the project, starts re-runs, records corrections.

    Args:
        backend: the project store.
        panel: builds the GUI panel on the new session's scene (:class:`app.viewer.panel.ReviewPanel`);
            called once the session's rooms exist, before the first run loads.
        run_id: run to show (default: the latest finished one).
        host, port: where viser binds (port 0 = any free port; read :attr:`port`).
        config: tunables.
        data: reads a run's grid and scans (default: from its folder, for this session alone).
        overlays: the corrected labels, shared with other sessions showing the same grids.
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
        data: RunData | None = None,
        overlays: OverlayCache | None = None,
    ) -> None:
        self.backend = backend
        self._data = data or (lambda run: read_run(run, backend.dataset_path()))
        self.stay_on_run = False
        """Keep showing the loaded run when a newer one finishes (the panel's "Stay on run N")."""
        self.newer_run: RunInfo | None = None
        """A run that finished while :attr:`stay_on_run` kept the shown one (loaded when it is unticked)."""
        self.config = cfg = config or SessionConfig()
        self.scene = ReviewScene(host=host, port=port, label=f"LeAP review: {backend.project_name()}")
        self.shared = sh = SharedState(backend.load_schema())
        sh.delta = RunDelta(backend)
        self.notify = notify = Notifier()
        self.scene_version = 0
        """Bumped every time a run's data is (re)loaded into the scene."""
        self._stop = threading.Event()
        self.renderer = LodRenderer(sh, self.scene, cfg.lod, notify, self._stop)
        self.player = ScanPlayer(sh, self.scene, self.renderer, cfg, notify, self._stop)
        self.tools = SelectionTool(sh, self.scene, self.renderer, cfg.lod.query_edge, notify)
        self.corrections = Corrections(
            sh, backend, self.renderer, self.player, self.tools, notify, overlays=overlays
        )
        self.queue = ReviewQueue(
            sh,
            backend,
            self.scene,
            cfg,
            renderer=self.renderer,
            player=self.player,
            corrections=self.corrections,
            notify=notify,
        )
        self.objects = ObjectQueue(sh, cfg.objects, player=self.player, tools=self.tools, scene=self.scene)
        self.classes = ClassEditor(sh, backend, self.renderer, notify)
        self.runs = RunWatcher(backend, self.follow_run, notify, cfg.poll_interval_s, self._stop)
        self.panel = panel(self)
        notify.bind(self.panel)
        self.scene.on_look_at(self.renderer.camera_moved)
        self.renderer.start()
        try:
            first = backend.run_info(run_id) if run_id is not None else backend.latest_finished_run()
            if first is not None and first.status == "done":
                self.load_run(first)
            else:
                self.panel.set_status("No finished run yet: press Re-run to label this project.")
            active = backend.active_run()
            if active is not None:
                self.runs.watch(active.run_id)
        except BaseException:
            self.close()  # free the port and threads of a viewer that could not start
            raise

    # ------------------------------------------------------------------------------------- plumbing
    @property
    def port(self) -> int:
        return self.scene.port

    def on_event(self, listener: Callable[[str], None]) -> None:
        """Call ``listener(name)`` on session events ("loaded", "drawn", "selection", "corrected", "marked",
        "tools", "run_started", "run_finished")."""
        self.notify.on_event(listener)

    def close(self) -> None:
        """Stop the drawing, playing and watching threads and the viser server."""
        self.player.playing = False
        self._stop.set()
        self.renderer.close()
        self.runs.close()
        self.scene.stop()

    # ------------------------------------------------------------------------------------ what is shown
    @property
    def run(self) -> RunInfo | None:
        """The shown run."""
        return self.shared.run

    @property
    def grid(self) -> ReviewGrid | None:
        """The shown run's voxel map."""
        return self.shared.grid

    @property
    def outputs(self) -> RunOutputs | None:
        """The shown run's scans."""
        return self.shared.outputs

    @property
    def state(self) -> vl.ViewState:
        """The view the user asked for (:meth:`set_state` changes it)."""
        return self.shared.view_state

    @property
    def palette(self) -> npt.NDArray[np.uint8]:
        """(C, 3) class colours of the shown grid."""
        return self.shared.palette

    @property
    def label(self) -> npt.NDArray[np.int16]:
        """(V,) class per voxel, corrections applied."""
        return self.shared.label

    @property
    def conf(self) -> npt.NDArray[np.float32]:
        """(V,) confidence per voxel (1 where corrected)."""
        return self.shared.conf

    @property
    def corrected(self) -> npt.NDArray[np.bool_]:
        """(V,) voxels an active correction overrides."""
        return self.shared.corrected

    def class_names(self) -> list[str]:
        """Names of the displayed grid's classes (index order)."""
        return self.shared.class_names()

    def set_state(self, **changes: Unpack[ViewChanges]) -> None:
        """Change the view (``mode``, ``class_index``, ``threshold``, ``enabled``, ``max_points``) and
        schedule a redraw (a new colour mode recolours the shown scan at once)."""
        sh = self.shared
        with sh.lock:
            old_mode = sh.view_state.mode
            sh.view_state = dataclasses.replace(sh.view_state, **changes)
            mode = sh.view_state.mode
        if mode != old_mode:
            self.player.color_scan()
        self.renderer.request_draw()

    # ------------------------------------------------------------------------------------- loading
    def load_run(self, run: RunInfo) -> None:
        """Load a finished run's grid (with the project's corrections overlaid) and draw it."""
        self.newer_run = None
        grid, outputs = self._data(run)
        self.show_grid(run, grid, outputs)

    def follow_run(self, run: RunInfo) -> None:
        """A run of the project finished: load it, unless :attr:`stay_on_run` keeps the shown one or it is
        the shown run already (the tab's watcher and the project's follower can both hand over a run that
        finished while the other was loading it)."""
        shown = self.run
        if shown is not None and shown.run_id == run.run_id:
            return
        if self.stay_on_run and shown is not None and shown.run_id != run.run_id:
            self.newer_run = run
            self.notify.panel.set_status(
                f"Run {run.number} finished; you stay on run {shown.number} (untick *Stay on run "
                f"{shown.number}* to load run {run.number})."
            )
            return
        self.load_run(run)

    def set_stay_on_run(self, on: bool) -> None:
        """Keep the shown run when newer ones finish, or (off) load the newest that finished meanwhile."""
        self.stay_on_run = on
        newer = self.newer_run
        if not on and newer is not None:
            self.load_run(newer)

    def show_grid(self, run: RunInfo, grid: ReviewGrid, outputs: RunOutputs | None) -> None:
        """Show a run's grid already in memory (:meth:`load_run` reads it from the run's folder), with its
        scans when ``outputs`` is given.

        A map above the level-of-detail budget is first drawn as an evenly strided subset within the budget;
        its spatial index is built on a thread meanwhile, and the level-of-detail view replaces it when ready.
        """
        sh = self.shared
        with sh.lock:
            sh.run = run
            sh.grid = grid
            self.renderer.reset()
            sh.outputs = outputs
            sh.run_schema = run.schema or sh.project_schema
            if sh.run_schema.num_classes != grid.num_classes:
                # The snapshot does not describe this grid; fall back to generic names rather than mislabel.
                sh.run_schema = None
            sh.project_schema = self.backend.load_schema()
            sh.refresh_palette()
            sh.selection = Selection.empty()
            rebuild = self.queue.reset()
            enabled = tuple(True for _ in range(grid.num_classes))
            cls = min(sh.view_state.class_index, grid.num_classes - 1)
            sh.view_state = dataclasses.replace(sh.view_state, enabled=enabled, class_index=cls)
            self.corrections.apply_locked()
            self.scene.voxels.point_size = grid.voxel_size
            self.player.frame_pos = 0
            self.scene_version += 1
        self.notify.panel.on_run_loaded()
        self.renderer.draw_now()
        if self.renderer.needs_lod(grid):
            self.renderer.build_index(grid)
        if self.scene_version == 1:
            # Frame the map once; a reload after a re-run keeps the camera where the user left it.
            self.player.fit_map()
        self.tools.clear_inspection()
        self.scene.set_review_box(None)
        if outputs is not None and outputs.frame_indices:
            # The map framing above is the first view; following starts with the user's first scan change.
            self.player.show_scan(len(outputs.frame_indices) // 2, move_camera=False)
        if rebuild:
            # After a re-run the queue is ranked again on the new grid, in the background.
            self.queue.rebuild_in_background()
        self.notify.emit("loaded")


__all__ = [
    "CorrectionRecord",
    "Inspection",
    "ProjectBackend",
    "QueueKind",
    "ReviewMarkRecord",
    "ReviewSession",
    "RunData",
    "RunInfo",
    "Scope",
    "SessionConfig",
    "Target",
    "ToolKind",
    "ToolSettings",
    "ViewChanges",
]
