"""Every message between the job manager (server) and a worker process, one JSON line each.

Server → worker, on the worker's stdin: one :class:`RunSpec` (what to run), then any number of
:class:`CancelRun` commands. Worker → server, on the message pipe: :class:`StageProgress` reports and
:class:`LogLine` warnings while the run works, and one :class:`RunOutcome` last.

A message is a frozen dataclass; its line is a JSON object ``{"type": <tag>, <field>: <value>, ...}``
(:meth:`Message.to_line`). :func:`decode` turns a line back into its message and checks it against the
class's annotations, so a malformed line raises :class:`MessageError` naming what is wrong instead of
surfacing later as a ``KeyError`` in whichever thread reads the field. The two processes always run the
same code, so the format carries no version.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

RunStatus = Literal["done", "failed", "cancelled"]
"""How a run ended, as the worker reports it (the manager may turn a failure into ``interrupted``)."""


class MessageError(ValueError):
    """A line that is not a well-formed message (bad JSON, unknown type, missing or mistyped field)."""


_REGISTRY: dict[str, type[Message]] = {}


@dataclass(frozen=True)
class Message:
    """Base of every message; a subclass names its wire tag in ``type``."""

    type: ClassVar[str]
    """Wire tag of the message class (the ``"type"`` key of its JSON line)."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        tag = cls.__dict__.get("type")
        if not isinstance(tag, str):
            raise TypeError(f"{cls.__name__} must set a 'type' tag")
        if tag in _REGISTRY:
            raise TypeError(f"message tag {tag!r} is used by {_REGISTRY[tag].__name__} and {cls.__name__}")
        _REGISTRY[tag] = cls

    def to_line(self) -> bytes:
        """The message as one JSON line (UTF-8, newline-terminated)."""
        body = {f.name: _encode(getattr(self, f.name)) for f in dataclasses.fields(self)}
        return (json.dumps({"type": self.type, **body}, separators=(",", ":")) + "\n").encode()


# ---------------------------------------------------------------------------------- server → worker
@dataclass(frozen=True)
class RunSpec(Message):
    """One run for a worker: the project snapshot taken when the run was queued, plus where it works."""

    type: ClassVar[str] = "run"
    run_id: int
    """Row id of the run (for log lines)."""
    run_dir: Path
    """The run's folder: outputs, ``run.log``, the folder lock."""
    sequences: list[tuple[str, Path, tuple[int, int] | None]]
    """(name, sequence folder, frame numbers ``start <= n < stop`` or None = all) per sequence, in run
    order."""
    demo: bool
    """The dataset is the built-in demo sequence: generate it first if it is missing."""
    demo_synth: dict[str, Any]
    """``SynthConfig`` overrides for generating the demo sequence (the server's ``demo_synth``)."""
    schema: dict[str, Any]
    """The class schema (``Schema.to_dict`` form)."""
    pipeline: dict[str, Any]
    """Pipeline parameter overrides (``config_to_dict`` form, possibly partial)."""
    models_dir: Path | None
    """The server's models folder (a deployment value: projects cannot name one); None = none configured."""
    cache_dir: Path | None
    """Per-project 2D cache shared across the project's runs."""
    progress_interval_s: float
    """Minimum seconds between two progress messages of one stage."""
    allow_download: bool = False
    """The server allows a model missing from the Hugging Face cache to be downloaded (its
    ``allow_download`` setting; a project cannot ask for it)."""
    estimate_poses: bool = False
    """The project estimates poses with KISS-ICP when its dataset has none (``app.jobs.poses``)."""
    poses_cache: Path | None = None
    """Where estimated poses are cached across runs (the server's cache folder)."""
    ray_address: str | None = None
    """The server's Ray cluster (its ``ray_address`` setting, ``Runtime.ray_address``); None = the
    worker computes the run itself."""


@dataclass(frozen=True)
class CancelRun(Message):
    """Stop the run at its next progress report (it ends ``cancelled``)."""

    type: ClassVar[str] = "cancel"


# ---------------------------------------------------------------------------------- worker → server
@dataclass(frozen=True)
class StageProgress(Message):
    """``done`` of ``total`` units of a stage are finished (throttled; a stage's first and last reports
    are always sent)."""

    type: ClassVar[str] = "stage"
    stage: str
    """Stage name (``leap_core.pipeline.STAGES`` or the demo generation pseudo-stage)."""
    done: int
    """Units finished."""
    total: int
    """Units in the stage."""
    skipped: str | None = None
    """Set on a stage's completion report when it computed nothing: why ("no ground truth", "unchanged
    since the last run"; :func:`leap_core.pipeline.skip_reason`)."""


@dataclass(frozen=True)
class LogLine(Message):
    """A warning or error the pipeline logged in the worker (e.g. random-weight test models in use), for
    the server's log."""

    type: ClassVar[str] = "log"
    level: int
    """``logging`` level number (30 = WARNING)."""
    logger: str
    """Name of the logger that emitted it."""
    message: str
    """The formatted message."""


@dataclass(frozen=True)
class RunOutcome(Message):
    """How the run ended; the last message of a worker."""

    type: ClassVar[str] = "result"
    status: RunStatus
    """done / failed / cancelled."""
    error: str | None = None
    """One-line reason of a failure."""


ToWorker = RunSpec | CancelRun
"""What the server sends to a worker."""
FromWorker = StageProgress | LogLine | RunOutcome
"""What a worker sends to the server."""


# ------------------------------------------------------------------------------------------ decoding
def decode(line: bytes | str) -> Message:
    """The message on one JSON line.

    Raises:
        MessageError: the line is not JSON, not an object, has an unknown ``type``, or a field is
            missing, unknown or of the wrong type. The message names the type and field.
    """
    try:
        doc = json.loads(line)
    except ValueError as exc:
        raise MessageError(f"not a JSON line ({exc}): {_excerpt(line)}") from None
    if not isinstance(doc, dict):
        raise MessageError(f"expected a JSON object with a 'type', got {_excerpt(line)}")
    tag = doc.pop("type", None)
    cls = _REGISTRY.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise MessageError(f"unknown message type {tag!r} (known: {', '.join(sorted(_REGISTRY))})")
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name in doc:
            values[f.name] = _decode(doc.pop(f.name), hints[f.name], f"{tag}.{f.name}")
        elif f.default is dataclasses.MISSING:
            raise MessageError(f"{tag}: missing field {f.name!r}")
    if doc:
        raise MessageError(f"{tag}: unknown field(s) {', '.join(sorted(map(repr, doc)))}")
    return cls(**values)


def decode_from_worker(line: bytes | str) -> FromWorker:
    """:func:`decode` for the server's side of the message pipe.

    Raises:
        MessageError: also for a well-formed message that a worker never sends.
    """
    message = decode(line)
    if not isinstance(message, (StageProgress, LogLine, RunOutcome)):
        raise MessageError(f"a worker does not send {message.type!r} messages")
    return message


def decode_to_worker(line: bytes | str) -> ToWorker:
    """:func:`decode` for the worker's stdin.

    Raises:
        MessageError: also for a well-formed message that the server never sends.
    """
    message = decode(line)
    if not isinstance(message, (RunSpec, CancelRun)):
        raise MessageError(f"the server does not send {message.type!r} messages")
    return message


def message_types() -> dict[str, type[Message]]:
    """Every message class by its wire tag."""
    return dict(_REGISTRY)


def _excerpt(line: bytes | str) -> str:
    text = line.decode("utf-8", "replace") if isinstance(line, bytes) else line
    return repr(text[:200])


def _encode(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (tuple, list)):
        return [_encode(v) for v in value]
    if isinstance(value, dict):
        return {k: _encode(v) for k, v in value.items()}
    return value


_SCALARS: dict[Any, tuple[Callable[[Any], bool], str]] = {
    type(None): (lambda v: v is None, "null"),
    bool: (lambda v: isinstance(v, bool), "true or false"),
    int: (lambda v: isinstance(v, int) and not isinstance(v, bool), "an integer"),
    float: (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool), "a number"),
    str: (lambda v: isinstance(v, str), "a string"),
    Path: (lambda v: isinstance(v, str), "a string"),
}
"""Annotation → (accepts the JSON value, what it expects in words)."""


def _decode(value: Any, tp: Any, where: str) -> Any:  # noqa: PLR0911  one return per kind of annotation
    """``value`` from JSON checked against (and converted to) the annotation ``tp``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        return _decode_union(value, args, where)
    if origin is Literal:
        if value not in args:
            raise MessageError(f"{where}: expected one of {', '.join(map(repr, args))}, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, list) or len(value) != len(args):
            raise MessageError(f"{where}: expected a list of {len(args)} values, got {value!r}")
        return tuple(_decode(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True)))
    if origin is dict:
        if not isinstance(value, dict):
            raise MessageError(f"{where}: expected an object, got {value!r}")
        return {k: _decode(v, args[1], f"{where}.{k}") for k, v in value.items()}
    if origin is list:
        if not isinstance(value, list):
            raise MessageError(f"{where}: expected a list, got {value!r}")
        return [_decode(v, args[0], f"{where}[{i}]") for i, v in enumerate(value)]
    if tp not in _SCALARS:
        raise TypeError(f"{where}: no JSON decoding for annotation {tp!r}")  # a message class's own bug
    accepts, expected = _SCALARS[tp]
    if not accepts(value):
        raise MessageError(f"{where}: expected {expected}, got {value!r}")
    return Path(value) if tp is Path else float(value) if tp is float else value


def _decode_union(value: Any, options: tuple[Any, ...], where: str) -> Any:
    """The first option of ``X | Y | None`` that accepts ``value`` (None first, so it stays None)."""
    if value is None and type(None) in options:
        return None
    problems = []
    for option in options:
        if option is type(None):
            continue
        try:
            return _decode(value, option, where)
        except MessageError as exc:
            problems.append(str(exc))
    raise MessageError(problems[0] if len(problems) == 1 else f"{where}: {value!r} fits none of {options}")


__all__ = [
    "CancelRun",
    "FromWorker",
    "LogLine",
    "Message",
    "MessageError",
    "RunOutcome",
    "RunSpec",
    "RunStatus",
    "StageProgress",
    "ToWorker",
    "decode",
    "decode_from_worker",
    "decode_to_worker",
    "message_types",
]
