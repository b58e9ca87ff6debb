"""The pipeline's configuration: one frozen tree of the per-module configs, and its dict form.

``PipelineConfig`` nests the config dataclass of every stage; each lives beside the code it configures.
Project files (``pipeline:`` section), the app's SQLite rows and run specs all store the plain-dict form
produced by :func:`config_to_dict`; :func:`config_from_dict` reads it back, applying nested overrides onto
a base config. Programs parse that dict once, where they read it, and pass the typed config on.

Validation, one style for every config dataclass: the checks live in ``__post_init__``, so a config
object that exists is valid (``dataclasses.replace`` checks again). A failed check raises
:class:`~leap_core.errors.ConfigError` with ``field`` = the field's path relative to the dataclass
(``("voxel_size",)``, ``("class_recall", "car")``). :func:`config_from_dict` descends the tree, checks
keys and types itself and re-raises every error with the absolute path
(``("pipeline", "consistency", "backbone", "channels")``), so the message reads
``pipeline.fusion.voxel_size: must be a positive number, got 0`` and callers such as the app map
``exc.field`` onto their own error locations without reading the message.

Deployment values (models folder, 2D cache folder, device, model downloads) are not config fields; they
are the run's :class:`~leap_core.runtime.Runtime`. A dict that still sets one of the former
``grounded_sam`` fields is refused with a message that names its replacement (:data:`RETIRED_FIELDS`).

Reading a config imports no torch: the nested configs' modules import it only where tensors are made.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from leap_core.consistency.config import ConsistencyConfig
from leap_core.errors import ConfigError, LeapError
from leap_core.fusion import FusionConfig
from leap_core.labelers import LABELERS
from leap_core.labelers.grounded_sam import GroundedSamConfig
from leap_core.labelers.simulated import SimulatedLabelerConfig
from leap_core.projection import ProjectionConfig
from leap_core.smoothing import SmoothingConfig


@dataclass(frozen=True)
class PipelineConfig:
    """Every parameter of a pipeline run (docs/METHOD.md stages A-C), grouped by stage."""

    labeler: str = "simulated"
    """2D labeler, a name in :data:`leap_core.labelers.LABELERS`: "simulated" (from a dataset's 2D ground
    truth, with a noise model) or "grounded-sam"."""
    simulated: SimulatedLabelerConfig = field(default_factory=SimulatedLabelerConfig)
    """Noise model of the simulated labeler."""
    grounded_sam: GroundedSamConfig = field(default_factory=GroundedSamConfig)
    """Grounding DINO + SAM models and thresholds."""
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)
    """Point projection and per-mask depth clustering."""
    fusion: FusionConfig = field(default_factory=FusionConfig)
    """Voxel size and the Bayesian update's floor and clip."""
    smoothing: SmoothingConfig = field(default_factory=SmoothingConfig)
    """kNN smoothing of the fused grid."""
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)
    """3D Consistency Network (off unless ``consistency.enabled``)."""
    correction_strength: float = 50.0
    """Log-odds of one manual correction (``corrections.npz`` in the run folder) when it is fused in."""

    def __post_init__(self) -> None:
        if self.labeler not in LABELERS:
            names = ", ".join(repr(n) for n in LABELERS)
            raise ConfigError(f"must be one of {names}, got {_short(self.labeler)}", field=("labeler",))
        if not self.correction_strength > 0:
            raise ConfigError(f"must be > 0, got {self.correction_strength}", field=("correction_strength",))


@dataclass(frozen=True)
class FormField:
    """One parameter of the app's pipeline form: a flat name for a dotted :class:`PipelineConfig` path."""

    path: str
    """Dotted path in :class:`PipelineConfig` (``"fusion.voxel_size"``)."""
    label: str
    """Short human label."""
    kind: Literal["select", "number", "integer", "checkbox"]
    """Input widget."""
    help: str = ""
    """One line on what the setting changes."""
    minimum: float | None = None
    maximum: float | None = None
    step: float | None = None
    choices: tuple[tuple[str, str], ...] = ()
    """``select`` only: (value, label) pairs."""


FORM_FIELDS: dict[str, FormField] = {
    "labeler": FormField(
        "labeler",
        "2D labeler",
        "select",
        "which model turns camera images into 2D labels",
        choices=tuple((name, spec.label) for name, spec in LABELERS.items()),
    ),
    "threshold": FormField(
        "grounded_sam.box_threshold",
        "Box threshold",
        "number",
        "Grounding DINO boxes below this similarity are dropped",
        0.0,
        1.0,
        0.01,
    ),
    "voxel_size": FormField(
        "fusion.voxel_size", "Voxel size (m)", "number", "edge of the fusion grid's voxels", 0.01, None, 0.05
    ),
    "k": FormField("smoothing.k", "kNN smoothing k", "integer", "neighbours averaged per voxel", 1, None, 1),
    "cluster_gap": FormField(
        "projection.cluster_gap",
        "Depth-cluster gap (m)",
        "number",
        "depth gap that splits a mask's points into clusters",
        0.0,
        None,
        0.1,
    ),
    "consistency": FormField(
        "consistency.enabled",
        "3D Consistency Network",
        "checkbox",
        "train a 3D network on the most confident voxels and fuse it back",
    ),
    "share": FormField(
        "consistency.share",
        "3D-CN label share",
        "number",
        "share of each class's most confident points used for training",
        0.0,
        1.0,
        0.05,
    ),
    "temperature": FormField(
        "consistency.temperature",
        "3D-CN temperature",
        "number",
        "weight of the network's evidence when fused back (lower = stronger)",
        0.0,
        None,
        0.1,
    ),
    "iterations": FormField(
        "consistency.iterations", "3D-CN iterations", "integer", "self-training rounds", 1, None, 1
    ),
}
"""The app form's flat parameter names → their :class:`FormField` (dotted path, label, widget)."""


# ------------------------------------------------------------------------------------------ to dict
def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def config_to_dict(cfg: PipelineConfig) -> dict[str, Any]:
    """JSON/YAML-ready nested dict of every field (tuples become lists); see :func:`config_from_dict`."""
    out: dict[str, Any] = _plain(cfg)
    return out


# ---------------------------------------------------------------------------------------- from dict
class _BadValue(Exception):
    """Internal: a value does not fit a field's type; the caller adds the field path."""


def _type_name(tp: Any) -> str:  # noqa: PLR0911  one return per kind of annotation, read as a table
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if tp is type(None):
        return "null"
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_type_name(args[0])}"
        return f"a list of {len(args)} values ({', '.join(_type_name(a) for a in args)})"
    if origin is dict:
        return f"a mapping of {_type_name(typing.get_args(tp)[1])}"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp))
    )


def _short(value: Any, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters: error messages quote what was given, never all of it."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def _coerce(value: Any, tp: Any) -> Any:  # noqa: PLR0911, PLR0912  one case per kind of annotation (a table)
    """``value`` converted to type ``tp`` (strictly: no str→number, no bool→int); raises _BadValue."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin is Literal:
        if value in args and not isinstance(value, bool):
            return value
        raise _BadValue(f"must be {_type_name(tp)}, got {_short(value)}")
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a)
            except _BadValue:
                pass
        raise _BadValue(f"must be {_type_name(tp)}, got {_short(value)}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise _BadValue(f"must be {_type_name(tp)}, got {_short(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0]) for v in value)
        if len(value) != len(args):
            raise _BadValue(f"must be {_type_name(tp)}, got {len(value)} values")
        return tuple(_coerce(v, a) for v, a in zip(value, args, strict=True))
    if origin is dict:
        if not isinstance(value, Mapping):
            raise _BadValue(f"must be {_type_name(tp)}, got {_short(value)}")
        kt, vt = args
        return {_coerce(k, kt): _coerce(v, vt) for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                number = float(value)
            except OverflowError:  # an integer beyond float range (1e308)
                bits = int(value).bit_length()
                raise _BadValue(f"must be a finite number, got an integer of {bits} bits") from None
            if not math.isfinite(number):
                # YAML's .inf / .nan and JSON's 1e400 parse as non-finite floats; no setting means them.
                raise _BadValue(f"must be a finite number, got {number}")
            return number
    elif tp is str:
        if isinstance(value, str):
            return value
    else:
        raise _BadValue(f"has an unsupported type {tp!r}")
    raise _BadValue(f"must be {_type_name(tp)}, got {_short(value)}")


@dataclass(frozen=True)
class RetiredField:
    """A setting that left the pipeline config: what it used to default to and what replaces it."""

    default: Any
    """Its former default; dicts stored by older versions carry it and are read as if it were absent."""
    replacement: str
    """Where the value is given now, completing "no longer a pipeline setting; ..."."""


RETIRED_FIELDS: dict[tuple[str, ...], RetiredField] = {
    ("grounded_sam", "models_dir"): RetiredField(
        None,
        "the models folder is given per run: `--models DIR` (leap run, leap labels2d), "
        "LEAP_MODELS_DIR or `leap serve --models DIR` (the app)",
    ),
    ("grounded_sam", "cache_dir"): RetiredField(
        None,
        "the 2D cache folder is given per run: `--cache DIR` (leap run, leap labels2d); the app keeps "
        "one per project",
    ),
    ("grounded_sam", "device"): RetiredField(
        "auto", "the device is given per run: `--device auto|cpu|cuda` (leap run, leap labels2d)"
    ),
    ("grounded_sam", "allow_download"): RetiredField(
        False, "model downloads are allowed per run: `--allow-download` (leap run, leap labels2d)"
    ),
}
"""Former config fields (path below ``pipeline``) that are deployment values now
(:class:`~leap_core.runtime.Runtime`)."""


def _preset_section(
    obj: Any, overrides: Mapping[str, Any], path: tuple[str, ...]
) -> tuple[Any, Mapping[str, Any]]:
    """A section whose dataclass has ``from_preset`` (the simulated labeler's) and whose overrides name a
    ``preset``: that preset replaces ``obj`` and the section's other keys are left to apply on top."""
    from_preset = getattr(type(obj), "from_preset", None)
    if from_preset is None or "preset" not in overrides:
        return obj, overrides
    name = overrides["preset"]
    if not isinstance(name, str):
        raise ConfigError(f"must be a preset name, got {_short(name)}", field=(*path, "preset"))
    try:
        preset = from_preset(name)
    except ConfigError as exc:
        raise exc.within(*path) from None
    return preset, {k: v for k, v in overrides.items() if k != "preset"}


def _apply(obj: Any, overrides: Mapping[str, Any], path: tuple[str, ...]) -> Any:
    """``obj`` with ``overrides`` applied; every error carries the absolute field path."""
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"must be a mapping of settings, got {_short(overrides)}", field=path)
    hints = typing.get_type_hints(type(obj))
    names = [f.name for f in dataclasses.fields(obj)]
    obj, overrides = _preset_section(obj, overrides, path)
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        where = (*path, str(key))
        if key not in names:
            retired = RETIRED_FIELDS.get(where[1:])
            if retired is not None:
                if value == retired.default and type(value) is type(retired.default):
                    continue
                raise ConfigError(f"no longer a pipeline setting; {retired.replacement}", field=where)
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"known: {', '.join(names)}"
            raise ConfigError(f"unknown setting ({hint})", field=where)
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            changes[key] = _apply(current, value, where)
            continue
        try:
            changes[key] = _coerce(value, hints[key])
        except _BadValue as exc:
            raise ConfigError(str(exc), field=where) from None
    if not changes:
        return obj
    try:
        return dataclasses.replace(obj, **changes)
    except ConfigError as exc:
        raise exc.within(*path) from None


def config_from_dict(d: Mapping[str, Any] | None, base: PipelineConfig | None = None) -> PipelineConfig:
    """``base`` with the nested overrides of ``d`` applied (missing keys keep ``base``'s values).

    Args:
        d: nested mapping as written by :func:`config_to_dict` (any subset of it); None = no overrides.
        base: the config to start from; default ``PipelineConfig()``.

    Raises:
        ConfigError: ``field`` = ``("pipeline", <field path>...)``, message
            ``"pipeline.<field path>: <problem>"``, for an unknown key, a wrong type, a value out of range
            or a retired field (:data:`RETIRED_FIELDS`) set to anything but its former default.
    """
    cfg = _apply(base if base is not None else PipelineConfig(), d or {}, ("pipeline",))
    assert isinstance(cfg, PipelineConfig)
    return cfg


def overrides_from_form(form: Mapping[str, Any]) -> dict[str, Any]:
    """Nested overrides from the app form's flat names (:data:`FORM_FIELDS`).

    Raises:
        LeapError: ``field = ("form", name)`` for a name that is not a form field.
    """
    out: dict[str, Any] = {}
    for name, value in form.items():
        if name not in FORM_FIELDS:
            raise LeapError(
                f"pipeline form: unknown field {name!r} (known: {', '.join(FORM_FIELDS)})",
                field=("form", str(name)),
            )
        *parents, leaf = FORM_FIELDS[name].path.split(".")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def form_values(cfg: PipelineConfig) -> dict[str, Any]:
    """The app form's flat values read from ``cfg``."""
    out: dict[str, Any] = {}
    for name, form_field in FORM_FIELDS.items():
        node: Any = cfg
        for part in form_field.path.split("."):
            node = getattr(node, part)
        out[name] = node
    return out


__all__ = [
    "FORM_FIELDS",
    "RETIRED_FIELDS",
    "FormField",
    "PipelineConfig",
    "RetiredField",
    "config_from_dict",
    "config_to_dict",
    "form_values",
    "overrides_from_form",
]
