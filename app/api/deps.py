"""Request dependencies, as ``Annotated`` aliases used in every route signature."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Iterator
from typing import Annotated

import sqlite_utils
from fastapi import Depends, HTTPException, Request, status
from fastapi.exceptions import RequestValidationError
from starlette.requests import HTTPConnection

from app.api.types import PlainJsonError, check_plain_json
from app.core.config import Settings
from app.core.db import ConnectionPool, open_db
from app.core.security import token_matches
from app.jobs.manager import JobManager

TOKEN_HEADER = "X-Leap-Token"
TOKEN_QUERY = "token"
TOKEN_COOKIE = "leap_token"


# The trivial dependencies are ``async def``: FastAPI runs a plain ``def`` dependency in the thread pool,
# which costs every request one thread hand-off each (three for a status poll) under load.
async def get_settings(connection: HTTPConnection) -> Settings:
    """The settings the app was created with (override in tests with ``app.dependency_overrides``)."""
    settings: Settings = connection.app.state.settings
    return settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


@contextlib.contextmanager
def _connection(connection: HTTPConnection, settings: Settings) -> Iterator[sqlite_utils.Database]:
    """A SQLite connection from the app's pool (a fresh one if the app has none, or another database)."""
    pool: ConnectionPool | None = getattr(connection.app.state, "db_pool", None)
    if pool is None or pool.path != settings.database:
        with open_db(settings.database) as db:
            yield db
        return
    with pool.connection() as db:
        yield db


def get_db(connection: HTTPConnection, settings: SettingsDep) -> Iterator[sqlite_utils.Database]:
    """A SQLite connection for this request; FastAPI runs this in its thread pool."""
    with _connection(connection, settings) as db:
        yield db


DbDep = Annotated[sqlite_utils.Database, Depends(get_db)]


async def get_read_db(
    connection: HTTPConnection, settings: SettingsDep
) -> AsyncIterator[sqlite_utils.Database]:
    """A pooled connection for ``async`` handlers that only READ a few rows.

    Such handlers run on the event loop without a thread hand-off: in WAL mode a read never waits for a
    writer, and a primary-key lookup takes well under a millisecond. Handlers that write use ``DbDep``.
    """
    with _connection(connection, settings) as db:
        yield db


ReadDbDep = Annotated[sqlite_utils.Database, Depends(get_read_db)]


async def get_jobs(request: Request) -> JobManager:
    jobs: JobManager = request.app.state.jobs
    return jobs


JobsDep = Annotated[JobManager, Depends(get_jobs)]


def request_token(request: HTTPConnection) -> str | None:
    """The token a request presents: ``Authorization: Bearer``, ``X-Leap-Token``, ``?token=`` or cookie.

    The query form exists for ``EventSource`` and download links, which cannot set headers.
    """
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return (
        request.headers.get(TOKEN_HEADER)
        or request.query_params.get(TOKEN_QUERY)
        or request.cookies.get(TOKEN_COOKIE)
    )


async def require_token(connection: HTTPConnection, settings: SettingsDep) -> None:
    """Every API call (and websocket) presents the configured access token, when one is configured."""
    if not token_matches(settings.token, request_token(connection)):
        raise HTTPException(status.HTTP_403_FORBIDDEN, detail="Access token missing or wrong")


AuthDep = Depends(require_token)


async def require_plain_body(request: HTTPConnection) -> None:
    """A JSON body holds only values the app can store and send back (:mod:`app.api.types`).

    Runs for every API route after the token check. FastAPI has already parsed the body by then and
    Starlette keeps the parsed value, so this costs a walk over a small document, nothing more.
    """
    if not isinstance(request, Request):  # a websocket has no body
        return
    content_type = request.headers.get("content-type", "")
    if request.method in ("GET", "HEAD", "OPTIONS") or "json" not in content_type.lower():
        return
    if not await request.body():
        return
    try:
        document = await request.json()
    except ValueError:
        return  # not JSON: FastAPI's own parsing reports it
    try:
        check_plain_json(document)
    except PlainJsonError as exc:
        raise RequestValidationError(
            [{"type": "value_error", "loc": ("body", *exc.loc), "msg": exc.problem, "input": exc.value}]
        ) from None


PlainBodyDep = Depends(require_plain_body)
