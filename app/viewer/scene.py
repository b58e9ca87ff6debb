"""A facade over one ``viser.ViserServer``: intention-level methods returning typed handles.

Scene nodes are created once and then updated in place through their handles (points, colours, images,
visibility), never removed and re-added: an update sends only the changed property. Positions go out as
float32 (float16, viser's default, loses centimetres a few hundred metres from the origin); colours as
uint8.

viser is not ASGI: it serves its own client and websocket on its own port. The server binds 127.0.0.1
only, and browsers reach it through the app's authenticated relay (:mod:`app.api.routes.viewer`). Anyone on
the machine can reach 127.0.0.1, so the port itself streams the scene only to the relay: a websocket must
carry the scene's per-session secret (:data:`SECRET_HEADER`) and no ``Origin`` (browsers always send one,
the relay never does); any other is closed with 1008 before a single message is sent
(:func:`guard_websocket`).
"""

from __future__ import annotations

import contextlib
import hmac
import secrets
import threading
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import numpy.typing as npt
import rich
import viser

from app.viewer import view_logic as vl
from app.viewer.region_logic import Region

RectSelectFn = Callable[[viser.SceneRectSelectEvent], None]
ClickFn = Callable[[viser.SceneClickEvent], None]

SECRET_HEADER = "X-Leap-Viewer-Secret"
"""Handshake header carrying :attr:`ReviewScene.secret` (set by the app's relay only)."""


def guard_websocket(server: viser.ViserServer, secret: str) -> None:
    """Close every websocket to ``server`` that lacks ``secret`` or comes from a browser page.

    viser offers no handshake hook, but it runs its connect callbacks after the handshake and before it
    starts sending (the scene backlog included), with the raw connection already registered: the check
    runs there. Clients connected before the guard (the server accepts from its construction on) are
    dropped so that they reconnect through it.

    Raises:
        RuntimeError: viser's internals changed so that the guard cannot be installed (the viewer then does
            not start, rather than start unguarded).
    """
    ws_server = getattr(server, "_websock_server", None)
    live = getattr(ws_server, "_live_connections", None)
    if ws_server is None or not isinstance(live, dict):
        raise RuntimeError(f"viser {viser.__version__}: cannot guard the viewer's websocket port")
    expected = secret.encode()

    async def check(client: Any) -> None:
        connection = live.get(client.client_id)
        request = getattr(connection, "request", None)
        if connection is None or request is None:
            return
        given = (request.headers.get(SECRET_HEADER) or "").encode()
        if "origin" in request.headers or not hmac.compare_digest(given, expected):
            await connection.close(1008, "only the LeAP Studio relay may connect")

    ws_server.on_client_connect(check)
    ws_server.disconnect_all_clients()


FOCUS_SCALE = 1.6
"""Point size of the focused region's highlight relative to the map's voxels."""


def _xyz(values: npt.ArrayLike) -> tuple[float, float, float]:
    """A 3-vector as the tuple of floats viser's positions take."""
    x, y, z = (float(v) for v in np.asarray(values).reshape(3))
    return x, y, z


def _wxyz(values: npt.ArrayLike) -> tuple[float, float, float, float]:
    """A quaternion as the tuple of floats viser's orientations take."""
    w, x, y, z = (float(v) for v in np.asarray(values).reshape(4))
    return w, x, y, z


class _Layer:
    """One scene node, created lazily by the subclass's ``set`` and kept (hidden, never removed) after."""

    _handle: viser.SceneNodeHandle | None = None

    @property
    def visible(self) -> bool:
        return self._handle is not None and bool(self._handle.visible)

    @visible.setter
    def visible(self, value: bool) -> None:
        if self._handle is not None:
            self._handle.visible = value


class PointLayer(_Layer):
    """One point cloud, created on first :meth:`set` and afterwards updated in place."""

    def __init__(self, server: viser.ViserServer, name: str, *, point_size: float) -> None:
        self._server = server
        self._name = name
        self._point_size = point_size
        self._handle: viser.PointCloudHandle | None = None
        self._count = 0
        self._lock = threading.Lock()

    @property
    def name(self) -> str:
        return self._name

    @property
    def count(self) -> int:
        """Number of points currently shown."""
        return self._count

    @property
    def handle(self) -> viser.PointCloudHandle | None:
        return self._handle

    def set(self, points: npt.NDArray[np.float32], colors: npt.NDArray[np.uint8]) -> None:
        """Show ``points`` (M, 3) with ``colors`` (M, 3) uint8 (M may differ from the previous call).

        Both properties change in one atomic message group, so a client never draws M points with
        another M's colours.
        """
        pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        cols = np.ascontiguousarray(colors, dtype=np.uint8).reshape(-1, 3)
        if pts.shape != cols.shape:
            raise ValueError(f"points {pts.shape} and colors {cols.shape} must both be (M, 3)")
        with self._lock:
            if self._handle is None:
                self._handle = self._server.scene.add_point_cloud(
                    self._name,
                    pts,
                    cols,
                    point_size=self._point_size,
                    precision="float32",
                    point_shape="square",
                    point_shading="flat",
                )
            else:
                with self._server.atomic():
                    self._handle.points = pts
                    self._handle.colors = cols
            self._count = pts.shape[0]

    def set_colors(self, colors: npt.NDArray[np.uint8]) -> None:
        """Recolour the current points (same count): only the colours go over the wire."""
        cols = np.ascontiguousarray(colors, dtype=np.uint8).reshape(-1, 3)
        with self._lock:
            if self._handle is None or cols.shape[0] != self._count:
                raise ValueError(f"set_colors needs {self._count} colours, got {cols.shape[0]}")
            self._handle.colors = cols

    @property
    def point_size(self) -> float:
        return self._point_size

    @point_size.setter
    def point_size(self, value: float) -> None:
        self._point_size = float(value)
        if self._handle is not None:
            self._handle.point_size = float(value)


class CameraLayer(_Layer):
    """The camera frustum of the scan being browsed, with its (label-overlaid) image."""

    def __init__(self, server: viser.ViserServer, name: str) -> None:
        self._server = server
        self._name = name
        self._handle: viser.CameraFrustumHandle | None = None

    @property
    def handle(self) -> viser.CameraFrustumHandle | None:
        return self._handle

    def set(
        self,
        *,
        position: npt.ArrayLike,
        wxyz: npt.ArrayLike,
        fov_y: float,
        aspect: float,
        image: npt.NDArray[np.uint8] | None,
        scale: float = 1.5,
    ) -> None:
        pos = _xyz(position)
        quat = _wxyz(wxyz)
        if self._handle is None:
            self._handle = self._server.scene.add_camera_frustum(
                self._name,
                fov=fov_y,
                aspect=aspect,
                scale=scale,
                color=(255, 255, 255),
                image=image,
                format="jpeg",
                wxyz=quat,
                position=pos,
                thickness=0.05,
            )
            return
        with self._server.atomic():
            self._handle.position = pos
            self._handle.wxyz = quat
            self._handle.fov = fov_y
            self._handle.aspect = aspect
            self._handle.image = image


_rich_quiet = threading.Lock()


@contextlib.contextmanager
def _quiet_viser() -> Iterator[None]:
    """Silence viser's start banner and stop line (printed through rich even with ``verbose=False``): they
    name its internal port, which users must not open (the app relays the viewer on its own port)."""
    console = rich.get_console()
    with _rich_quiet:
        before = console.quiet
        console.quiet = True
        try:
            yield
        finally:
            console.quiet = before


class ReviewScene:
    """The viewer's 3D scene: voxel map, selection highlight, one scan and its camera.

    Args:
        host: address viser binds (keep 127.0.0.1: remote access goes through the app's relay).
        port: 0 picks a free port; a busy port silently moves, so always read :attr:`port`.
        label: title shown in the viser panel.
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 0, label: str = "LeAP review") -> None:
        with _quiet_viser():
            self.server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
        self.secret = secrets.token_urlsafe(32)
        """Per-session secret a websocket must send in :data:`SECRET_HEADER` (the app's relay does)."""
        try:
            guard_websocket(self.server, self.secret)
        except RuntimeError:
            with _quiet_viser():
                self.server.stop()
            raise
        self.server.gui.configure_theme(control_width="large", dark_mode=False, show_share_button=False)
        # A docked panel never hides the map (a floating one covers part of the canvas).
        self.server.gui.main_panel.dock_right()
        self.voxels = PointLayer(self.server, "/map/voxels", point_size=0.2)
        """The voxel map (one point per voxel centre; on a big map, the voxels near the focus)."""
        self.overview = PointLayer(self.server, "/map/overview", point_size=0.4)
        """A big map's overview: one point per block away from the focus (:mod:`app.viewer.lod`)."""
        self.focus = PointLayer(self.server, "/map/focus", point_size=0.2 * FOCUS_SCALE)
        """The focused review region's voxels, filled and larger than the map's, so they cover the dimmed
        map and the scan's points around them (:mod:`app.viewer.review_queue`)."""
        self.selection = PointLayer(self.server, "/map/selection", point_size=0.26)
        """Highlight of the voxels selected for a correction."""
        self.scan = PointLayer(self.server, "/scan/points", point_size=0.08)
        """The browsed scan's points in their final label colours."""
        self.camera = CameraLayer(self.server, "/scan/camera")
        self.inspected = PointLayer(self.server, "/map/inspected", point_size=0.35)
        """Marker of the voxel shown in the panel's Inspect section."""
        self._rect_cb: RectSelectFn | None = None
        self._review_box: viser.BoxHandle | None = None
        self._closed = False

    @property
    def port(self) -> int:
        """The port viser actually bound."""
        return int(self.server.get_port())

    @property
    def host(self) -> str:
        return str(self.server.get_host())

    def look_at(self, position: npt.ArrayLike, target: npt.ArrayLike) -> None:
        """Move every connected client's camera (and new clients' initial camera) to look at ``target``."""
        pos = np.asarray(position, dtype=np.float64).reshape(3)
        tgt = np.asarray(target, dtype=np.float64).reshape(3)
        self.server.initial_camera.position = _xyz(pos)
        self.server.initial_camera.look_at = _xyz(tgt)
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.up_direction = (0.0, 0.0, 1.0)
                client.camera.position = pos
                client.camera.look_at = tgt

    def frame_region(self, region: Region, *, min_distance: float = 14.0) -> None:
        """Point the camera at a review region from above and to the side, with its surroundings in view."""
        distance = max(min_distance, 4.0 * region.extent)
        pos, tgt = vl.orbit_view(region.centre, distance, elevation_deg=40.0)
        self.look_at(pos, tgt)

    def set_review_box(
        self,
        centre: npt.ArrayLike | None,
        size: npt.ArrayLike | None = None,
        color: tuple[int, int, int] = (0, 255, 255),
    ) -> None:
        """Outline the focused review region with a wireframe box (``centre`` None hides it)."""
        if centre is None or size is None:
            if self._review_box is not None:
                self._review_box.visible = False
            return
        dims = _xyz(np.maximum(np.asarray(size, dtype=np.float64), 0.1))
        if self._review_box is None:
            self._review_box = self.server.scene.add_box(
                "/map/review_box", color=color, dimensions=dims, wireframe=True, position=_xyz(centre)
            )
            return
        with self.server.atomic():
            self._review_box.dimensions = dims
            self._review_box.position = _xyz(centre)
            self._review_box.visible = True

    @property
    def review_box(self) -> viser.BoxHandle | None:
        return self._review_box

    def arm_rect_select(self, callback: RectSelectFn) -> None:
        """Make the next box drag on the canvas a selection (camera orbit is suspended meanwhile)."""
        self.disarm_rect_select()
        self._rect_cb = callback
        self.server.scene.on_rect_select()(callback)

    def disarm_rect_select(self) -> None:
        if self._rect_cb is not None:
            self.server.scene.remove_rect_select_callback(self._rect_cb)
            self._rect_cb = None

    def on_look_at(self, callback: Callable[[npt.NDArray[np.float64]], None]) -> None:
        """Call ``callback(look_at)`` with the (3,) look-at point whenever a browser's camera moves (every
        connected browser and every later one)."""

        def attach(client: Any) -> None:
            client.camera.on_update(lambda camera: callback(np.asarray(camera.look_at, dtype=np.float64)))

        self.server.on_client_connect(attach)

    def on_click(self, callback: ClickFn) -> None:
        """Call ``callback`` for every plain click on the canvas (a drag still orbits the camera; clicks
        with a modifier held are left to other tools)."""
        self.server.scene.on_click()(callback)

    @property
    def rect_select_armed(self) -> bool:
        return self._rect_cb is not None

    def clients(self) -> dict[int, Any]:
        return dict(self.server.get_clients())

    def stop(self) -> None:
        """Close the server and free its port (idempotent)."""
        if not self._closed:
            self._closed = True
            with _quiet_viser():
                self.server.stop()


__all__ = ["SECRET_HEADER", "CameraLayer", "PointLayer", "ReviewScene", "guard_websocket"]
