"""Error types. Messages are one line and name the offending file or field."""

from __future__ import annotations

from pathlib import Path


class LeapError(ValueError):
    """Base class for every user-facing error raised by leap_core.

    ``field`` is the dotted path of the setting at fault, as a tuple (``("pipeline", "fusion",
    "voxel_size")``), when the error is about a configuration field; callers such as the app's API map
    it onto their own error locations without parsing the message.
    """

    def __init__(self, message: str, *, field: tuple[str, ...] = ()) -> None:
        self.field = tuple(field)
        super().__init__(message)


class DatasetError(LeapError):
    """A dataset file is missing, malformed or inconsistent with its neighbours."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class SchemaError(LeapError):
    """A class schema is invalid; the message names the offending entry."""


class ModelLoadError(LeapError):
    """A model folder is missing or unreadable; the message says how to get the weights."""


class Cancelled(Exception):
    """Raised from a progress callback to stop long work cleanly."""
