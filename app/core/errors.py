"""Domain errors raised by services and crud; :func:`app.main.create_app` maps them to HTTP responses."""

from __future__ import annotations

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
