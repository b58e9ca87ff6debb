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


class ConfigError(LeapError):
    """A configuration value is invalid: ``problem`` says what is wrong with the setting at ``field``.

    The message is ``"<field joined by dots>: <problem>"``. A config dataclass raises it with the field
    path relative to itself (``ConfigError("must be in [0.01, 10] m, got 0", field=("voxel_size",))``);
    :func:`leap_core.config.config_from_dict` re-raises it with the absolute path through :meth:`within`
    (``pipeline.fusion.voxel_size: must be in [0.01, 10] m, got 0``), so no caller parses messages.
    """

    def __init__(self, problem: str, *, field: tuple[str, ...]) -> None:
        self.problem = problem
        super().__init__(f"{'.'.join(field)}: {problem}", field=field)

    def within(self, *parents: str) -> ConfigError:
        """The same problem, with ``parents`` prepended to the field path."""
        return ConfigError(self.problem, field=(*parents, *self.field))

    def __reduce__(self) -> tuple[object, ...]:
        # Exceptions pickle as ``cls(*args)``; the keyword-only field would be lost.
        return (_config_error, (self.problem, self.field))


def _config_error(problem: str, field: tuple[str, ...]) -> ConfigError:
    return ConfigError(problem, field=field)


class DatasetError(LeapError):
    """A dataset file is missing, malformed or inconsistent with its neighbours."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class PosesMissingError(DatasetError):
    """A stage needs one pose per scan and the sequence has none (no ``poses.txt``).

    Callers add advice that fits where it is shown (the CLI names ``leap poses`` / ``--estimate-poses``,
    the app its "estimate poses" option); the message itself names only the file and what needs it.
    """


class SchemaError(LeapError):
    """A class schema is invalid; the message names the offending entry."""


class ModelLoadError(LeapError):
    """A model folder is missing or unreadable; the message says how to get the weights."""


class Cancelled(Exception):
    """Raised from a progress callback to stop long work cleanly."""
