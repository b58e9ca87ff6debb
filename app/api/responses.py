"""The error answers of the API, declared once for the OpenAPI schema (``responses=`` of the routers).

Every status a route can answer with is listed in its ``responses``, so clients (and schemathesis) can
rely on the schema: the ones any route can give are on the API router, the rest on each resource router.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field


class ErrorPublic(BaseModel):
    """Every error except 422: one line saying what is wrong."""

    detail: str


class ValidationErrorItem(BaseModel):
    loc: list[str | int] = Field(description="where: `body`, `path` or `query`, then the field's path")
    msg: str
    type: str
    input: Any = Field(default=None, description="the rejected value, at most its first 120 characters")
    ctx: dict[str, str] | None = None


class ValidationErrorPublic(BaseModel):
    """422: the fields that failed, each with its location and the problem."""

    detail: list[ValidationErrorItem]


Responses = dict[int | str, dict[str, Any]]
"""The type of FastAPI's ``responses=`` argument."""


def _error(status: int, description: str, model: type[BaseModel] = ErrorPublic) -> Responses:
    return {status: {"model": model, "description": description}}


BAD_REQUEST = _error(400, "The body could not be read (not JSON, or a number too long to parse)")
FORBIDDEN = _error(403, "Access token missing or wrong, or a path outside the data roots")
TOO_LARGE = _error(413, "The request body is larger than the server's limit (`LEAP_MAX_BODY_BYTES`)")
INVALID = _error(422, "A parameter or a body field is invalid", ValidationErrorPublic)
NOT_FOUND = _error(404, "No such project, run, class or prompt (or the resource has nothing to show)")
CONFLICT = _error(409, "The request conflicts with the resource's state (e.g. a run is active)")

FULL_DISK = _error(
    507,
    "The disk is full: the database's (or `LEAP_DB_MAX_MB` is reached), or the one a file the request "
    "writes goes to (an export folder, an export's zip or counts, a run preview's scratch files), or a "
    "run would start with less free space than `LEAP_MIN_FREE_DISK_MB`",
)

COMMON_RESPONSES: Responses = {**BAD_REQUEST, **FORBIDDEN, **TOO_LARGE, **INVALID, **FULL_DISK}
"""What any API route can answer besides its success: every route is behind the token check, the body
limit and request validation, and any database or file write (reads included: an export's zip is built
on its first download) can meet a full disk."""
