"""Bounded request types: the one place that says which ids, strings and numbers the API accepts.

Every path parameter is declared through these aliases, and every JSON request body goes through
:func:`check_plain_json` (:func:`app.api.deps.require_plain_body`, a dependency of the API router, so
dict-typed fields such as ``pipeline`` are covered too). No value reaches SQLite, the file system or the
pipeline that they cannot hold:

- integers fit in SQLite's signed 64-bit INTEGER (larger ids would raise ``OverflowError`` in the driver);
- strings carry no NUL or other control characters (a NUL byte breaks every path operation) and no lone
  UTF-16 surrogates (they cannot be encoded as UTF-8, neither in the database nor in a response);
- numbers are finite (``1e400`` parses as ``inf``; JSON cannot carry it back out).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Annotated, Any

from fastapi import Path, Query
from pydantic import AfterValidator

from leap_core.schema import class_name_problem

MAX_INT = 2**63 - 1
"""Largest integer SQLite stores (signed 64-bit)."""

_BAD_CHARS = re.compile(r"[\x00-\x1f\x7f\ud800-\udfff]")
"""C0 control characters, DEL, and UTF-16 surrogates (which in a Python ``str`` are always lone)."""


def string_problem(value: str) -> str | None:
    """Why ``value`` is not an acceptable string, or None."""
    m = _BAD_CHARS.search(value)
    if m is None:
        return None
    ch = m.group()
    if "\ud800" <= ch <= "\udfff":
        return f"contains a lone UTF-16 surrogate (U+{ord(ch):04X}) at position {m.start()}"
    return f"contains the control character U+{ord(ch):04X} at position {m.start()}"


class PlainJsonError(ValueError):
    """A value in a request body no part of the app can hold; ``loc`` is its path inside the body."""

    def __init__(self, loc: tuple[str | int, ...], problem: str, value: object) -> None:
        super().__init__(problem)
        self.loc = loc
        self.problem = problem
        self.value = value


def check_plain_json(document: Any) -> None:
    """Walk a parsed JSON document (dicts, lists, scalars) and refuse what this module forbids.

    Iterative, so a deeply nested document cannot exhaust the interpreter's stack.

    Raises:
        PlainJsonError: the first offending value's path (``("pipeline", "fusion", "voxel_size")``) and
            the problem (dict keys are checked like string values).
    """
    stack: list[tuple[Any, tuple[str | int, ...]]] = [(document, ())]
    while stack:
        value, loc = stack.pop()
        if isinstance(value, str):
            problem = string_problem(value)
            if problem is not None:
                raise PlainJsonError(loc, f"text {problem}", value)
        elif isinstance(value, bool) or value is None:
            continue
        elif isinstance(value, int):
            if not -MAX_INT - 1 <= value <= MAX_INT:
                raise PlainJsonError(loc, "integer out of range (must fit in 64 bits)", value)
        elif isinstance(value, float):
            if not math.isfinite(value):
                raise PlainJsonError(loc, f"number must be finite, got {value}", value)
        elif isinstance(value, Mapping):
            for key, item in reversed(list(value.items())):
                key_text = str(key)
                problem = string_problem(key_text)
                if problem is not None:
                    raise PlainJsonError((*loc, _short_key(key_text)), f"key {problem}", key_text)
                stack.append((item, (*loc, key_text)))
        elif isinstance(value, (list, tuple)):
            stack.extend((item, (*loc, i)) for i, item in reversed(list(enumerate(value))))


def _short_key(key: str) -> str:
    return key.encode("utf-8", "backslashreplace").decode("ascii", "backslashreplace")[:40]


# ------------------------------------------------------------------------------------------ path params
ProjectId = Annotated[int, Path(ge=1, le=MAX_INT, description="project id")]
RunId = Annotated[int, Path(ge=1, le=MAX_INT, description="run id")]
CorrectionId = Annotated[int, Path(ge=1, le=MAX_INT, description="correction id")]
PromptIndex = Annotated[int, Path(ge=0, le=MAX_INT, description="index of the prompt in the class's list")]
SequenceQuery = Annotated[
    str | None,
    Query(
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$",
        description="one of the project's sequences (default: the run's own figures / the first sequence)",
    ),
]
"""``?sequence=`` of a project with several sequences (its names: ``app.models.SEQUENCE_NAME_PATTERN``)."""
SequenceName = Annotated[
    str, Path(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$", description="one of the project's sequences")
]
"""A sequence's name in a route's path (``app.models.SEQUENCE_NAME_PATTERN``)."""


def _class_name(value: str) -> str:
    problem = string_problem(value)
    if problem is not None:
        raise ValueError(f"text {problem}")
    problem = class_name_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return value


ClassName = Annotated[
    str, Path(min_length=1, max_length=64, description="class name"), AfterValidator(_class_name)
]
