"""Domain errors raised by services and crud; :func:`app.main.create_app` maps them to HTTP responses."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any


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
        loc = [part if isinstance(part, int) else printable(str(part), 80) for part in self.loc]
        return [{"loc": loc, "msg": printable(self.detail), "type": "value_error"}]


# ------------------------------------------------------------------------------------ response bodies
MAX_ECHO_CHARS = 120
"""Longest part of a rejected input a 422 answer repeats (a 50 MB body must not come back)."""
MAX_MESSAGE_CHARS = 1000
"""Longest error message an answer carries."""


def printable(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``text`` cut to ``limit`` characters (marked with ``…``), lone surrogates written as ``\\udXXX``.

    A lone surrogate cannot be encoded as UTF-8, so a response that repeats one would fail to render
    (the server would answer 500 instead of the intended error).
    """
    if len(text) > limit:
        text = text[:limit] + "…"
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def echo(value: object) -> object:
    """What a 422 answer may repeat of a rejected input: scalars as they are (strings shortened), and
    for lists or mappings only a shortened ``repr``."""
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, int):
        return value if abs(value) < 2**63 else printable(repr(value), MAX_ECHO_CHARS)
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)  # JSON has no NaN / Infinity
    if isinstance(value, str):
        return printable(value, MAX_ECHO_CHARS)
    return printable(repr(value), MAX_ECHO_CHARS)


def validation_errors(errors: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """FastAPI's request validation errors, safe to send: each ``loc``/``msg``/``type``, the offending
    ``input`` shortened (:func:`echo`), and ``ctx`` values as short text. At most 20 errors."""
    out: list[dict[str, Any]] = []
    for err in list(errors)[:20]:
        item: dict[str, Any] = {
            "type": str(err.get("type", "value_error")),
            "loc": [p if isinstance(p, int) else printable(str(p), 80) for p in err.get("loc", ())],
            "msg": printable(str(err.get("msg", ""))),
        }
        if "input" in err:
            item["input"] = echo(err["input"])
        ctx = err.get("ctx")
        if isinstance(ctx, Mapping):
            item["ctx"] = {str(k): printable(str(v), MAX_ECHO_CHARS) for k, v in ctx.items()}
        out.append(item)
    return out
