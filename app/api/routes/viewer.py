"""The 3D review viewer: open a tab of it on a project's run, and relay it under the app's own port.

Each browser tab has its own viewer session (:class:`app.viewer.manager.ProjectViewer`), with its own
viser server on its own port, bound to 127.0.0.1 only. The app relays its page and websocket under
``/api/v1/projects/{id}/viewer/tabs/{tab}/client/`` so that a browser reaches the viewer wherever it
reaches the app, and so the access token is checked for the viewer exactly as for the API (header,
``?token=`` or the ``leap_token`` cookie, which the page response sets so the websocket handshake
carries it). The relay's handshake must come from the app's own origin
(:func:`~app.core.security.cross_origin_reason`, also checked by the app's middleware); viser's port
streams only to the relay, which presents the tab's per-session secret
(:data:`app.viewer.scene.SECRET_HEADER`). The viewer routes act on the tab
their ``?tab=`` names (:data:`TAB_QUERY`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, ParamSpec, TypeVar

import viser
from fastapi import APIRouter, Body, Depends, HTTPException, Request, WebSocket, status
from fastapi import Path as PathParam
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.websockets import WebSocketDisconnect
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed
from websockets.typing import Subprotocol

from app.api.deps import TOKEN_COOKIE, TOKEN_HEADER, TOKEN_QUERY, AuthDep, SettingsDep, request_token
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import MAX_INT, ProjectId
from app.core.config import Settings
from app.core.errors import AppError, InvalidField
from app.core.security import cross_origin_reason, token_matches
from app.models import SEQUENCE_NAME_PATTERN
from app.reviewers import REVIEWER_MAX
from app.viewer.manager import TAB_PATTERN, ViewerManager
from app.viewer.scene import SECRET_HEADER
from app.viewer.session import ReviewSession
from leap_core.errors import LeapError

log = logging.getLogger("leap.viewer")

_P = ParamSpec("_P")
_T = TypeVar("_T")

router = APIRouter(
    prefix="/projects/{project_id}/viewer", tags=["viewer"], responses={**NOT_FOUND, **CONFLICT}
)

_CLIENT_HTML = Path(viser.__file__).resolve().parent / "client" / "build" / "index.html"
_OVERLAY_TAG = b'<script type="module" src="/viewer/overlay.js"></script>'
"""Our additions to viser's client page (web/viewer/overlay.js: shortcuts, free-hand tools), same origin."""


def client_page() -> bytes:
    """viser's client page with :data:`_OVERLAY_TAG` loaded after viser's own scripts."""
    html = _CLIENT_HTML.read_bytes()
    if b"</body>" not in html:  # a viser build we do not know: serve it as is rather than break the viewer
        log.warning("viser's client page has no </body>; viewer shortcuts and tools are not loaded")
        return html
    return html.replace(b"</body>", _OVERLAY_TAG + b"</body>", 1)


class ViewerOpen(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    run_id: int | None = Field(
        default=None, ge=1, le=MAX_INT, description="finished run to review (default: the latest)"
    )
    sequence: str | None = Field(
        default=None,
        pattern=SEQUENCE_NAME_PATTERN,
        description="the project sequence to review (default: the one shown, else the first); another "
        "sequence than the running viewer's replaces it",
    )
    reviewer: str | None = Field(
        default=None,
        min_length=1,
        max_length=REVIEWER_MAX,
        description="the reviewer's name, stored with the tab's corrections and review marks",
    )


TAB_QUERY = "tab"
"""Query parameter naming the viewer tab a viewer route acts on (web/viewer/viewer-api.js adds it to every
call; a request from a tab's page without it, such as the scan image, is that page's tab by its Referer;
else the tab opened last)."""

_TAB_PAGE = re.compile(r"/viewer/tabs/([^/?#]+)/client/")
"""A viewer tab's page in a Referer."""

TabId = Annotated[str, PathParam(pattern=TAB_PATTERN, description="the viewer tab")]


class ViewerPublic(BaseModel):
    project_id: int
    run_id: int | None = Field(description="run shown; None until the project has a finished run")
    port: int = Field(description="viser's own port on 127.0.0.1 (it streams only to the app's relay)")
    url: str = Field(description="viewer page relayed under the app's port (works wherever the app does)")
    sequence: str | None = Field(default=None, description="the project sequence shown")
    tab: str = Field(description="the tab's id; the viewer routes act on it given ?tab=<id>")


def get_viewers(request: Request) -> ViewerManager:
    """The app's :class:`ViewerManager` (created on first use, stopped by :func:`close_viewers`), bound to
    the tab the request's ``?tab=`` names, so that the viewer routes act on that tab's session."""
    state = request.app.state
    manager: ViewerManager | None = getattr(state, "viewers", None)
    if manager is None:
        manager = ViewerManager(state.settings, getattr(state, "jobs", None))
        state.viewers = manager
    tab = request.query_params.get(TAB_QUERY)
    if tab is None:
        # A link on a tab's page (the scan image) cannot add the query: its Referer names the tab.
        page = _TAB_PAGE.search(request.headers.get("referer", ""))
        tab = None if page is None else page.group(1)
    if tab is None:
        return manager
    if re.fullmatch(TAB_PATTERN, tab) is None:
        raise HTTPException(
            422,
            detail=f"?{TAB_QUERY}=: not a viewer tab id (open the 3D viewer again from the project page)",
        )
    return manager.for_tab(tab)


def close_viewers(app: object) -> None:
    """Stop every viewer of ``app`` (call from the app's shutdown)."""
    manager = getattr(getattr(app, "state", None), "viewers", None)
    if manager is not None:
        manager.close_all()


ViewersDep = Annotated[ViewerManager, Depends(get_viewers)]


def running_session(viewers: ViewerManager, project_id: int) -> ReviewSession:
    """The session of the viewer tab the request names (else the tab opened last), for the routes that act
    on it (404 when that tab is not open)."""
    session = viewers.get(project_id)
    if session is None:
        detail = "No viewer is running for this project"
        if viewers.tab is not None:
            detail = "This viewer tab was closed: open the 3D viewer again from the project page"
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=detail)
    return session


def _public(
    request: Request,
    project_id: int,
    run_id: int | None,
    port: int,
    sequence: str | None,
    tab: str,
) -> ViewerPublic:
    path = request.url_for("viewer_client", project_id=project_id, tab=tab).path
    return ViewerPublic(project_id=project_id, run_id=run_id, port=port, url=path, sequence=sequence, tab=tab)


async def run_blocking(fn: Callable[_P, _T], *args: _P.args, **kwargs: _P.kwargs) -> _T:
    # Starting a viewer loads a grid (hundreds of ms for millions of voxels): keep it off the event loop.
    return await asyncio.to_thread(fn, *args, **kwargs)


@router.post("", response_model=ViewerPublic, dependencies=[AuthDep])
async def open_viewer(
    project_id: ProjectId,
    request: Request,
    viewers: ViewersDep,
    settings: SettingsDep,
    payload: Annotated[ViewerOpen | None, Body()] = None,
) -> ViewerPublic:
    """Open a new tab of the project's viewer (starting the viewer if needed) on the given run, or the latest
    finished run; ``url`` is the tab's page."""
    if not settings.viewer_enabled:
        raise HTTPException(status.HTTP_409_CONFLICT, detail="The viewer is disabled in the settings")
    run_id = None if payload is None else payload.run_id
    sequence = None if payload is None else payload.sequence
    reviewer = None if payload is None else payload.reviewer
    try:
        info = await run_blocking(viewers.open, project_id, run_id, sequence, reviewer)
    except InvalidField as exc:
        raise HTTPException(exc.status_code, detail=exc.as_detail()) from None
    except AppError as exc:
        raise HTTPException(exc.status_code, detail=exc.detail) from None
    except LeapError as exc:  # the run's outputs are missing or malformed: say which file
        raise HTTPException(status.HTTP_409_CONFLICT, detail=str(exc)) from None
    return _public(request, project_id, info.run_id, info.port, info.sequence, info.tab)


@router.get("", response_model=ViewerPublic, dependencies=[AuthDep])
async def get_viewer(project_id: ProjectId, request: Request, viewers: ViewersDep) -> ViewerPublic:
    """The viewer tab ``?tab=`` names, else the tab opened last (404 when none is open)."""
    session = running_session(viewers, project_id)
    viewer = viewers.viewer(project_id)
    assert viewer is not None
    run_id = None if session.run is None else session.run.run_id
    tab = viewer.tab_id(session)
    return _public(request, project_id, run_id, session.port, viewer.sequence, tab)


@router.delete("", status_code=status.HTTP_204_NO_CONTENT, dependencies=[AuthDep])
async def close_viewer(project_id: ProjectId, viewers: ViewersDep) -> None:
    """Stop the project's viewer, every tab of it (404 when none is running)."""
    if not await run_blocking(viewers.close, project_id):
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail="No viewer is running for this project")


@router.get("/tabs/{tab}/client", include_in_schema=False)
async def viewer_client_noslash(project_id: ProjectId, tab: TabId, request: Request) -> RedirectResponse:
    target = request.url_for("viewer_client", project_id=project_id, tab=tab)
    return RedirectResponse(str(target.include_query_params(**request.query_params)))


@router.get("/tabs/{tab}/client/", name="viewer_client", include_in_schema=False, dependencies=[AuthDep])
async def viewer_client(
    project_id: ProjectId, tab: TabId, request: Request, viewers: ViewersDep, settings: SettingsDep
) -> HTMLResponse:
    """viser's client page of one tab. It opens its websocket on this path without the trailing slash."""
    if viewers.get(project_id, tab) is None:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND,
            detail="This viewer tab is closed (or the app restarted): open the 3D viewer from the project "
            "page",
        )
    response = HTMLResponse(client_page(), headers={"Cache-Control": "no-store"})
    token = request_token(request)
    if settings.token is not None and token is not None:
        # The websocket handshake cannot carry a header from the viser client: hand it a cookie.
        response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="strict", path="/")
    return response


def _ws_token(ws: WebSocket) -> str | None:
    auth = ws.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return ws.headers.get(TOKEN_HEADER) or ws.query_params.get(TOKEN_QUERY) or ws.cookies.get(TOKEN_COOKIE)


def _same_origin(ws: WebSocket) -> bool:
    """Browsers send cookies with cross-site websocket handshakes: accept only our own pages' origin (the
    app's middleware checks this too; the relay does not rely on being mounted behind it)."""
    return cross_origin_reason({k.lower(): v for k, v in ws.headers.items()}) is None


@router.websocket("/tabs/{tab}/client")
async def viewer_relay(ws: WebSocket, project_id: int, tab: str) -> None:
    """Relay the viser websocket between the browser and the tab's 127.0.0.1 port, message by message."""
    settings: Settings = ws.app.state.settings
    if not token_matches(settings.token, _ws_token(ws)) or not _same_origin(ws):
        await ws.close(code=status.WS_1008_POLICY_VIOLATION)
        return
    manager: ViewerManager | None = getattr(ws.app.state, "viewers", None)
    endpoint = None if manager is None else manager.endpoint(project_id, tab)
    if endpoint is None:
        await ws.close(code=status.WS_1011_INTERNAL_ERROR, reason="this viewer tab is not open")
        return
    port, secret = endpoint
    offered = [Subprotocol(p) for p in ws.scope.get("subprotocols", [])]
    try:
        # max_queue=None: with a bounded queue, a browser that is slow to take a large scene makes the relay
        # stop reading viser's socket, viser's keepalive pings then go unanswered and viser drops the
        # connection after 40 s. Reading eagerly keeps this local hop alive (the scene is bounded by
        # viewer_max_points); liveness of the browser is checked on the browser's own socket.
        upstream_cm = connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=offered or None,
            max_size=None,
            compression=None,
            open_timeout=10,
            max_queue=None,
            ping_interval=None,
            additional_headers={SECRET_HEADER: secret},
        )
        upstream = await upstream_cm.__aenter__()
    except (OSError, asyncio.TimeoutError) as exc:
        log.warning("viewer relay for project %d cannot reach port %d: %s", project_id, port, exc)
        await ws.close(code=status.WS_1011_INTERNAL_ERROR)
        return
    try:
        await ws.accept(subprotocol=upstream.subprotocol)

        async def browser_to_viewer() -> None:
            while True:
                message = await ws.receive()
                if message["type"] == "websocket.disconnect":
                    return
                data = message.get("bytes")
                await upstream.send(data if data is not None else message.get("text", ""))

        async def viewer_to_browser() -> None:
            async for data in upstream:
                if isinstance(data, bytes):
                    await ws.send_bytes(data)
                else:
                    await ws.send_text(data)

        tasks = [asyncio.create_task(browser_to_viewer()), asyncio.create_task(viewer_to_browser())]
        _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(
                asyncio.CancelledError, ConnectionClosed, WebSocketDisconnect, RuntimeError
            ):
                await task
        code = upstream.close_code
        if code is not None and code not in (1000, 1001):
            # The browser reconnects on its own; the reason is the only trace of why it had to.
            log.warning(
                "viewer relay for project %d: viser closed the connection (%s %s)",
                project_id,
                code,
                upstream.close_reason or "",
            )
    finally:
        await upstream_cm.__aexit__(None, None, None)
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await ws.close()
