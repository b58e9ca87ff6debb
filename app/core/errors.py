"""Domain errors raised by services and crud; :func:`app.main.create_app` maps them to HTTP responses."""

from __future__ import annotations

import errno
import sqlite3
from collections.abc import Sequence


class AppError(Exception):
    """Base class; ``status_code`` is the HTTP status the API answers with."""

    status_code = 400

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class NotFound(AppError):
    status_code = 404


class Forbidden(AppError):
    status_code = 403


class Conflict(AppError):
    status_code = 409


class InvalidField(AppError):
    """A value failed a check beyond its type (schema rules, pipeline config); names the field."""

    status_code = 422

    def __init__(self, loc: Sequence[str | int], detail: str) -> None:
        super().__init__(detail)
        self.loc = list(loc)

    def as_detail(self) -> list[dict[str, object]]:
        """The same shape FastAPI uses for request validation errors."""
        return [{"loc": self.loc, "msg": self.detail, "type": "value_error"}]


class InsufficientStorage(AppError):
    """The disk (or the database's size cap) has no room for what was asked."""

    status_code = 507


def disk_full_message(exc: BaseException) -> str | None:
    """A one-line explanation when ``exc`` is a full disk, quota or size cap; None for any other error.

    SQLite reports it as ``database or disk is full`` (SQLITE_FULL, also raised at ``db_max_mb``);
    file writes fail with ENOSPC, EDQUOT or EFBIG.
    """
    if isinstance(exc, sqlite3.OperationalError) and "full" in str(exc).lower():
        return f"the disk holding the database is full ({exc}); free some space, then try again"
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        where = f" writing {exc.filename}" if exc.filename else ""
        return f"the disk is full ({exc.strerror}{where}); free some space, then try again"
    return None
