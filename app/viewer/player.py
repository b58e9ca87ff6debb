"""The scan browser of a review session: showing one scan, stepping and playing through them, the camera
that follows the ego pose or frames the scan / map, and the scan's labelled image.

The panel's Browse / Fit view / Follow ego / Enlarge image widgets and the page's keys
(:mod:`app.api.routes.viewer_nav`) call the same methods, so both act on one state.
"""

from __future__ import annotations

import dataclasses
import logging
import threading

import cv2
import numpy as np
import numpy.typing as npt

from app.viewer import nav_logic as nl
from app.viewer.data import ScanView
from app.viewer.records import Selection, SessionConfig
from app.viewer.region_logic import REVIEW_BOX_RGB
from app.viewer.render import LodRenderer
from app.viewer.scene import ReviewScene
from app.viewer.shared import Notifier, SharedState
from leap_core import review

log = logging.getLogger(__name__)


class ScanPlayer:
    """Scan playback and the camera that goes with it.

    Scan changes are serialised by the player's own lock (a step reads the position and shows the next scan
    as one move); it is taken before the shared lock, never inside it.

    Args:
        shared: the session's shared state (writes ``scan_view`` / ``scan_label``; drops a scan selection).
        scene: the viser facade.
        renderer: moves the full-resolution area to the shown scan and redraws the selection.
        config: ``play_interval_s`` and the initial ``follow_ego``.
        notify: where scan changes are reported (panel ``on_scan``, ``on_nav``, ``on_selection``).
        stop: set when the session closes (ends playing).
    """

    def __init__(
        self,
        shared: SharedState,
        scene: ReviewScene,
        renderer: LodRenderer,
        config: SessionConfig,
        notify: Notifier,
        stop: threading.Event,
    ) -> None:
        self.shared = shared
        self.scene = scene
        self.renderer = renderer
        self.notify = notify
        self._interval = config.play_interval_s
        self._stop = stop
        self.frame_pos = 0
        """Position of the shown scan among the run's labelled scans."""
        self.follow_ego = config.follow_ego
        """Move the camera behind the ego vehicle on every scan change."""
        self.playing = False
        self.image_open = False
        """The page shows the scan's image enlarged (web/viewer/nav.js reads it, so it stays open while
        navigating and the panel's button and the ``i`` key act on the same state)."""
        self._image_jpeg: tuple[ScanView, bytes] | None = None
        self.camera = 0
        """The rig camera whose image (and pose) the shown scan comes with (0: the primary one)."""
        self.zoomed: tuple[ScanView, tuple[int, int, int, int]] | None = None
        """The scan view whose image boxes the focused region, and the crop around the region
        (:func:`leap_core.review.zoom_box`) that the enlarged image shows zoomed."""
        self._scan_lock = threading.RLock()
        self._player: threading.Thread | None = None

    @property
    def scan_view(self) -> ScanView | None:
        """The scan shown."""
        return self.shared.scan_view

    @property
    def scan_count(self) -> int:
        """Number of scans the run labelled (the positions :meth:`show_scan` takes)."""
        outputs = self.shared.outputs
        return 0 if outputs is None else len(outputs.frame_indices)

    def show_scan(self, pos: int, *, move_camera: bool | None = None) -> ScanView | None:
        """Show the ``pos``-th labelled scan (clipped to the run's scans): its points, camera frustum and
        labelled image. The camera follows the ego pose when ``move_camera`` is True, or when it is None and
        :attr:`follow_ego` is on."""
        sh = self.shared
        outputs = sh.outputs
        if outputs is None or not outputs.frame_indices:
            return None
        with self._scan_lock:
            pos = int(np.clip(pos, 0, len(outputs.frame_indices) - 1))
            view = outputs.scan_view(outputs.frame_indices[pos], sh.palette, camera=self.camera)
            box = self.region_box(view, pos)
            view = self.mark_region_in_image(view, pos, box)
            if box is not None and view.overlay is not None:
                h, w = view.overlay.shape[:2]
                self.zoomed = (view, review.zoom_box(box, w, h))
            self.frame_pos = pos
            with sh.lock:
                sh.scan_view = view
                dropped = sh.selection.target == "scan" and sh.selection.rows.size > 0
                if dropped:  # a scan selection belongs to the scan it was made on
                    sh.selection = Selection.empty()
                sh.scan_label = sh.scan_labels(view)
                colors = self._colors()
                self.scene.scan.set(view.points, colors)
            if dropped:
                self.renderer.draw_selection()
                self.notify.panel.on_selection(0)
            self.scene.camera.set(
                position=view.cam_position,
                wxyz=view.cam_wxyz,
                fov_y=view.fov_y,
                aspect=view.aspect,
                image=view.overlay,
            )
            if move_camera if move_camera is not None else self.follow_ego:
                self.follow_scan()
            if sh.focus is None or sh.focus_frame != pos:
                # A focused region keeps the full resolution on itself while its best scan is shown.
                ego = view.ego_pose[:3, 3] if view.ego_pose is not None else view.cam_position
                self.renderer.focus_lod(ego)
        self.notify.panel.on_scan(view, pos, len(outputs.frame_indices))
        return view

    def set_camera(self, camera: int) -> ScanView | None:
        """Show the shown scan through the rig's camera ``camera`` (its image, labels and frustum)."""
        with self._scan_lock:
            self.camera = camera
            return self.show_scan(self.frame_pos, move_camera=False)

    def step_scan(self, step: int) -> ScanView | None:
        """Show the scan ``step`` positions after (before, when negative) the shown one."""
        with self._scan_lock:
            return self.show_scan(self.frame_pos + step)

    def region_box(self, view: ScanView, pos: int) -> tuple[int, int, int, int] | None:
        """The focused region's pixel box in the image of the scan at slider position ``pos`` (None: no
        focus, no image, or its camera does not see the region)."""
        sh = self.shared
        region, outputs, grid = sh.focus, sh.outputs, sh.grid
        if region is None or outputs is None or grid is None or view.overlay is None:
            return None
        keys = grid.keys[region.rows]  # rows ascend, so the keys stay sorted
        _, _, uv = outputs.region_observers(outputs.frame_indices[pos], keys, grid.voxel_size, self.camera)
        h, w = view.overlay.shape[:2]
        return review.image_box(uv, w, h)

    def mark_region_in_image(
        self, view: ScanView, pos: int, box: tuple[int, int, int, int] | None = None
    ) -> ScanView:
        """The scan view with the focused region boxed in its image (when this scan's camera sees it;
        ``box``: :meth:`region_box`, when already known)."""
        box = box if box is not None else self.region_box(view, pos)
        if box is None or view.overlay is None:
            return view
        return dataclasses.replace(view, overlay=review.draw_box(view.overlay, box, REVIEW_BOX_RGB))

    def color_scan(self) -> None:
        """Recolour the shown scan for the current colour mode (its labels unchanged)."""
        sh = self.shared
        with self._scan_lock:
            view = sh.scan_view
            if view is not None and self.scene.scan.count == view.points.shape[0]:
                with sh.lock:
                    colors = self._colors()
                self.scene.scan.set_colors(colors)

    def recolour_scan(self) -> None:
        """Relabel and recolour the shown scan after the corrections changed."""
        sh = self.shared
        with sh.lock:
            view = sh.scan_view
            if view is None:
                return
            sh.scan_label = sh.scan_labels(view)
            colors = self._colors()
        self.scene.scan.set_colors(colors)

    def _colors(self) -> npt.NDArray[np.uint8]:
        """The shown scan's point colours for the colour mode, faded while a review region is focused
        (caller holds the shared lock)."""
        sh = self.shared
        view = sh.scan_view
        instance, moving = (None, None) if view is None else (sh.scan_instance, sh.scan_moving)
        colors = nl.scan_colors(sh.view_state.mode, sh.scan_label, sh.palette, instance, moving)
        return nl.focus_scan_colors(colors, sh.focus is not None)

    # ---------------------------------------------------------------------------------------- camera
    def fit_map(self) -> None:
        """Move the camera so that the whole voxel map is in view (key ``shift+f``)."""
        grid = self.shared.grid
        centres = None if grid is None else grid.centres
        if centres is not None and self.renderer.lod_index is not None:
            # Percentiles of a big map's evenly strided sample (keys sort by x): framing needs no more.
            centres = centres[:: max(1, centres.shape[0] // 1_000_000)]
        view = None if centres is None else nl.fit_view(centres)
        if view is not None:
            self.scene.look_at(*view)

    def fit_scan(self) -> None:
        """Move the camera so that the shown scan's points are in view (key ``f``)."""
        view = self.shared.scan_view
        framing = None if view is None else nl.fit_view(view.points)
        if framing is not None:
            self.scene.look_at(*framing)

    def follow_scan(self) -> None:
        """Move the camera behind and above the shown scan's ego pose (:func:`nav_logic.follow_view`)."""
        view = self.shared.scan_view
        if view is not None and view.ego_pose is not None:
            # The ground under a drone is far below it: follow_view then looks at the ground ahead.
            ground = float(np.percentile(view.points[:, 2], 20)) if len(view.points) else None
            self.scene.look_at(*nl.follow_view(view.ego_pose, ground_z=ground))

    def set_follow(self, on: bool | None = None) -> bool:
        """Turn camera following on or off (None toggles); turning it on moves the camera at once."""
        self.follow_ego = (not self.follow_ego) if on is None else bool(on)
        if self.follow_ego:
            self.follow_scan()
        self.notify.panel.on_nav()
        return self.follow_ego

    # ----------------------------------------------------------------------------------------- image
    def is_zoomed(self, view: ScanView | None = None) -> bool:
        """Whether the enlarged image of the shown scan (``view``: that scan) is a focused region's zoomed
        crop (what the page's polls ask; :meth:`zoomed_image` makes the crop)."""
        zoomed, view = self.zoomed, view or self.shared.scan_view
        return zoomed is not None and view is not None and zoomed[0] is view and self.shared.focus is not None

    def zoomed_image(self, view: ScanView | None = None) -> npt.NDArray[np.uint8] | None:
        """The focused region's zoomed crop of the shown scan's image (``view``: that scan), or None when
        no region is focused in it."""
        view = view or self.shared.scan_view
        if not self.is_zoomed(view) or view is None or self.zoomed is None:
            return None
        zoomed = self.zoomed
        assert view.overlay is not None  # a crop is only kept for a view with an image
        # A box of a few pixels is easy to miss: the enlarged image shows the crop around it, zoomed.
        return review.crop_zoom(view.overlay, zoomed[1])

    def set_image_open(self, on: bool | None = None) -> bool:
        """Show or hide the enlarged scan image in the page (None toggles)."""
        self.image_open = (not self.image_open) if on is None else bool(on)
        self.notify.panel.on_nav()
        return self.image_open

    def scan_image_jpeg(self, quality: int = 90) -> bytes | None:
        """The shown scan's labelled camera image as JPEG, or None when it has none (encoded once per
        scan)."""
        view = self.shared.scan_view
        if view is None or view.overlay is None:
            return None
        cached = self._image_jpeg
        if cached is not None and cached[0] is view:
            return cached[1]
        image = self.zoomed_image(view)
        image = view.overlay if image is None else image
        ok, buf = cv2.imencode(".jpg", image[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError(f"could not encode the image of scan {view.frame_id}")
        data = buf.tobytes()
        self._image_jpeg = (view, data)
        return data

    # -------------------------------------------------------------------------------------- playing
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
        self.notify.panel.on_nav()
        return self.playing

    def _play_loop(self) -> None:
        while self.playing and not self._stop.wait(self._interval):
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
                self.notify.panel.on_nav()
                return


__all__ = ["ScanPlayer"]
