"""The LeAP Studio server: ``create_app(settings)`` builds the FastAPI app, ``serve()`` runs it.

One process serves the REST API under ``/api/v1``, the static web UI at ``/`` and owns the job manager
whose worker threads execute runs in child processes.
"""

from __future__ import annotations

import gc
import logging
import sqlite3
import time
from collections.abc import AsyncIterator, Awaitable, Callable, MutableMapping
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path, PurePosixPath
from typing import Any

import uvicorn
from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from starlette.responses import Response

from app.api.main import api_router
from app.core.body_limit import BodyLimit
from app.core.config import LOOPBACK_NAMES, Settings, get_settings
from app.core.db import ConnectionPool, init_db, set_size_cap
from app.core.errors import AppError, InvalidField, disk_full_message, printable, validation_errors
from app.core.instance import ServerLock, StartupRefused, bind_socket
from app.core.request_head import KEEP_ALIVE_S, head_limit_protocol
from app.core.security import UNSAFE_METHODS, cross_origin_reason
from app.demo import seed_agri_demo_project, seed_demo_project
from app.jobs.apply import applier
from app.jobs.manager import JobManager
from app.jobs.models import ModelJobs
from leap_core import __version__

API_PREFIX = "/api/v1"
WEB_DIR = Path(str(resources.files("app.web")))
"""The web UI: the repository's ``web/``, installed as the package ``app.web`` (pyproject.toml's
package-dir), so that an editable install serves the repository's folder and a regular install its copy."""

log = logging.getLogger("leap.app")

Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[MutableMapping[str, Any]]]
Send = Callable[[MutableMapping[str, Any]], Awaitable[None]]


WEB_SUFFIXES = frozenset({"", ".html", ".js", ".css"})
"""What the web UI's folder serves: its pages, modules and styles (a folder path serves its index page). The
folder is also the Python package ``app.web`` (its ``__init__.py`` is how it ships), which is not served."""


class WebFiles(StaticFiles):
    """:class:`StaticFiles` of the web UI that serves only :data:`WEB_SUFFIXES` (404 for anything else)."""

    async def get_response(self, path: str, scope: Scope) -> Response:
        if PurePosixPath(path).suffix not in WEB_SUFFIXES:
            raise HTTPException(status_code=404)
        return await super().get_response(path, scope)


class LoopbackHostGuard:
    """Without an access token the app trusts only requests addressed to a loopback name.

    A web page on another site cannot then reach the API through DNS rebinding (its requests carry
    that site's host name in the ``Host`` header).
    """

    def __init__(self, app: Callable[..., Awaitable[None]], allowed: set[str]) -> None:
        self.app = app
        self.allowed = allowed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] in ("http", "websocket"):
            host = ""
            for key, value in scope.get("headers", []):
                if key == b"host":
                    host = value.decode("latin-1")
                    break
            name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
            name = name.strip("[]").lower()
            if name not in self.allowed:
                if scope["type"] == "http":
                    response = JSONResponse({"detail": f"Host {host!r} is not allowed"}, status_code=403)
                    await response(scope, receive, send)
                else:
                    await send({"type": "websocket.close", "code": 1008})
                return
        await self.app(scope, receive, send)


class SameOriginGuard:
    """Refuses state-changing requests (POST, PUT, PATCH, DELETE) and websocket handshakes that a page of
    another origin sent, with or without an access token.

    A browser sends a ``no-cors`` POST from any page and attaches the user's cookies (the viewer's
    ``leap_token``): without this check a page on another port or loopback alias could start runs or open
    viewers. What counts as another origin is :func:`app.core.security.cross_origin_reason`; requests
    without ``Origin`` and ``Sec-Fetch-Site`` (curl, the CLI, scripts) are not from a page and pass.
    """

    def __init__(self, app: Callable[..., Awaitable[None]]) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind == "websocket" or (kind == "http" and scope["method"] in UNSAFE_METHODS):
            headers: dict[str, str] = {}
            for key, value in scope.get("headers", []):
                headers.setdefault(key.decode("latin-1").lower(), value.decode("latin-1"))
            reason = cross_origin_reason(headers)
            if reason is not None:
                log.warning(
                    "refused a cross-origin %s %s: %s",
                    scope.get("method", "websocket"),
                    scope.get("path", ""),
                    reason,
                )
                if kind == "http":
                    detail = f"Cross-origin request refused ({reason})"
                    await JSONResponse({"detail": detail}, status_code=403)(scope, receive, send)
                else:
                    await send({"type": "websocket.close", "code": 1008})
                return
        await self.app(scope, receive, send)


class ServerTiming:
    """Adds ``Server-Timing: app;dur=<ms>`` (time from the request's arrival to the response head) to every
    HTTP response, so clients can tell the app's own time from network and scheduling delays."""

    def __init__(self, app: Callable[..., Awaitable[None]]) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()

        async def timed_send(message: MutableMapping[str, Any]) -> None:
            if message["type"] == "http.response.start":
                ms = (time.perf_counter() - start) * 1000.0
                message["headers"] = [
                    *message.get("headers", []),
                    (b"server-timing", f"app;dur={ms:.2f}".encode()),
                ]
            await send(message)

        await self.app(scope, receive, timed_send)


def _operation_id(route: APIRoute) -> str:
    return f"{route.tags[0]}-{route.name}" if route.tags else route.name


def create_app(settings: Settings | None = None) -> FastAPI:  # noqa: PLR0915  the app assembled in one place
    """Build the app; the database is created or migrated now, the workers start with the server."""
    settings = settings or get_settings()
    settings.work_dir.mkdir(parents=True, exist_ok=True)
    set_size_cap(settings.database, None if settings.db_max_mb is None else int(settings.db_max_mb * 2**20))
    init_db(settings.database)
    jobs = JobManager(settings)
    model_jobs = ModelJobs(settings)
    # Corrections made while a run worked reach its export when it ends, not only at the next edit.
    jobs.on_run_done(applier(settings).request)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Import the pipeline (torch included) before accepting requests, so no request pays for it.
        import leap_core.pipeline  # noqa: F401, PLC0415  # warm-up when serving, not on import of app.main

        jobs.start()
        model_jobs.start()
        if settings.seed_demo:
            seed_demo_project(settings, jobs)
            if settings.seed_agri_demo:
                seed_agri_demo_project(settings, jobs)
        announce = getattr(app.state, "announce", None)
        if announce:
            # Its own line on stdout, apart from the log lines and any progress bar on stderr.
            print(f"\n{announce}\n", flush=True)
        try:
            yield
        finally:
            _close_viewers(app)
            model_jobs.stop()
            jobs.stop()
            app.state.db_pool.close()

    app = FastAPI(
        title="LeAP Studio",
        summary="Open-vocabulary 3D point labeling: projects, runs, progress, metrics and exports.",
        version=__version__,
        openapi_url=f"{API_PREFIX}/openapi.json",
        docs_url=None,  # FastAPI's page loads Swagger UI from a CDN; ours (below) works offline
        redoc_url=None,
        lifespan=lifespan,
        generate_unique_id_function=_operation_id,
    )
    app.state.settings = settings
    app.state.jobs = jobs
    app.state.model_jobs = model_jobs
    app.state.db_pool = ConnectionPool(settings.database)

    @app.exception_handler(AppError)
    async def _app_error(_request: Request, exc: AppError) -> JSONResponse:
        if isinstance(exc, InvalidField):
            return JSONResponse({"detail": exc.as_detail()}, status_code=exc.status_code)
        return JSONResponse({"detail": printable(exc.detail)}, status_code=exc.status_code)

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(_request: Request, exc: RequestValidationError) -> JSONResponse:
        # FastAPI's own handler repeats the whole input (and the whole body of a JSON syntax error) and
        # fails on a lone surrogate in it: answer with the errors only, each input cut short.
        return JSONResponse({"detail": validation_errors(exc.errors())}, status_code=422)

    @app.exception_handler(OSError)
    async def _file_error(_request: Request, exc: OSError) -> JSONResponse:
        # Reads write files too (an export's zip and counts, a run preview's scratch folder): a full disk
        # is the user's to fix wherever it is met; any other file error stays a 500.
        message = disk_full_message(exc)
        if message is None:
            log.error("file error", exc_info=exc)
            return JSONResponse({"detail": "Internal Server Error"}, status_code=500)
        return JSONResponse({"detail": printable(message)}, status_code=507)

    @app.exception_handler(sqlite3.OperationalError)
    async def _db_error(_request: Request, exc: sqlite3.OperationalError) -> JSONResponse:
        # A full disk is the user's to fix, so it gets a message; other database errors stay a 500.
        message = disk_full_message(exc)
        if message is None:
            log.error("database error", exc_info=exc)
            return JSONResponse({"detail": "Internal Server Error"}, status_code=500)
        return JSONResponse({"detail": message}, status_code=507)

    app.include_router(api_router, prefix=API_PREFIX)

    @app.get("/api/docs", include_in_schema=False)
    def _api_docs() -> FileResponse:
        """The REST reference: a self-contained page (web/api-docs.*) rendering the OpenAPI document."""
        return FileResponse(WEB_DIR / "api-docs.html")

    if WEB_DIR.is_dir():
        app.mount("/", WebFiles(directory=WEB_DIR, html=True), name="web")
    if settings.token is None:
        allowed = set(LOOPBACK_NAMES) | {settings.host.lower()}
        app.add_middleware(LoopbackHostGuard, allowed=allowed)
    app.add_middleware(SameOriginGuard)
    app.add_middleware(ServerTiming)
    # Outermost: an oversized body is refused before any other layer sees the request.
    app.add_middleware(BodyLimit, limit=settings.max_body_bytes)
    return app


def _close_viewers(app: FastAPI) -> None:
    """Stop the 3D viewers (an optional module) before the workers."""
    try:
        # Optional: the app runs without app/viewer (see app.api.main); imported by then if present.
        from app.api.routes.viewer import close_viewers  # noqa: PLC0415  # optional module, may be absent
    except ImportError:
        return
    close_viewers(app)


def serve(settings: Settings | None = None, lock: ServerLock | None = None) -> None:
    """Run the server in the foreground until interrupted.

    Refused with a one-line message (exit status 1) and without touching the database when another
    server owns the work folder or the database, or the port cannot be bound (see :mod:`app.core.instance`).

    Args:
        lock: the work folder's and database's lock when the caller already holds it (``leap demo``).
    """
    settings = settings or get_settings()
    logging.basicConfig(
        level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    scheme_host = f"[{settings.host}]" if ":" in settings.host else settings.host
    try:
        if lock is None:
            lock = ServerLock(settings.work_dir, settings.database)
            lock.acquire(f"{scheme_host}:{settings.port}")
        sock = bind_socket(settings.host, settings.port)
    except StartupRefused as exc:
        raise SystemExit(f"error: {exc}") from None
    try:
        app = create_app(settings)
        app.state.announce = f"LeAP Studio: http://{scheme_host}:{settings.port}/"
        # Importing the pipeline (torch included) leaves ~240k long-lived objects that every full garbage
        # collection would walk: one took 0.3 s under load with the GIL held, stalling every request and
        # stream at once. Moved to the permanent generation, they are never walked again (the lifespan's
        # own import of the pipeline is then free).
        import leap_core.pipeline  # noqa: F401, PLC0415  # warm-up before gc.freeze(), see the comment above

        gc.collect()
        gc.freeze()
        config = uvicorn.Config(
            app,
            host=settings.host,
            port=settings.port,
            log_level=settings.log_level,
            access_log=False,
            http=head_limit_protocol(settings.request_head_timeout_s),
            timeout_keep_alive=KEEP_ALIVE_S,
        )
        uvicorn.Server(config).run(sockets=[sock])
    finally:
        sock.close()
        lock.release()


if __name__ == "__main__":
    serve()
