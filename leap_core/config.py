"""The pipeline's configuration: one frozen tree of the per-module configs, and its dict form.

``PipelineConfig`` nests the config dataclass of every stage; each lives beside the code it configures.
Project files (``pipeline:`` section), the app's SQLite rows and run specs all store the plain-dict form
produced by :func:`config_to_dict`; :func:`config_from_dict` reads it back, applying nested overrides onto
a base config. Programs parse that dict once, where they read it, and pass the typed config on.

Validation, one style for every config dataclass: the checks live in ``__post_init__``, so a config
object that exists is valid (``dataclasses.replace`` checks again). Every numeric setting declares its
allowed range beside its field, and ``__post_init__`` checks them all in one call
(:func:`~leap_core.bounds.check_bounds`; :func:`setting_bounds` lists them). A failed check raises
:class:`~leap_core.errors.ConfigError` with ``field`` = the field's path relative to the dataclass
(``("voxel_size",)``, ``("class_recall", "car")``). :func:`config_from_dict` descends the tree, checks
keys and types itself and re-raises every error with the absolute path
(``("pipeline", "consistency", "backbone", "channels")``), so the message reads
``pipeline.fusion.voxel_size: must be in [0.01, 10] m, got 0`` and callers such as the app map
``exc.field`` onto their own error locations without reading the message.

Labelers. Each 2D labeler registered in :data:`~leap_core.labelers.LABELERS` brings its own config section
(``LabelerSpec.section`` and ``config_type``): ``PipelineConfig.labelers`` holds one config per registered
section, and the dict form has each as a top-level key beside ``labeler``
(``{labeler: simulated, simulated: {...}, grounded_sam: {...}, projection: {...}, ...}``), as it had when
the sections were fields. A labeler registered from beside leap_core (the research lab's) adds its section.

Deployment values (models folder, 2D cache folder, device, model downloads) are not config fields; they
are the run's :class:`~leap_core.runtime.Runtime`. A dict that still sets one of the former
``grounded_sam`` fields is refused with a message that names its replacement (:data:`RETIRED_FIELDS`).
So is a dict whose ``simulated`` section sets a noise term that moved to the research lab's
``simulated-paper`` labeler to anything but the value that left it off; dicts stored before the move hold
every such term at that value, and are read as if it were absent.

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
from typing import Any, Literal, TypeVar

from leap_core.bounds import Bound, bounds_rows, check_bounds, field_bound, within
from leap_core.consistency.config import ConsistencyConfig
from leap_core.errors import ConfigError, LeapError
from leap_core.fusion import FusionConfig
from leap_core.labelers import LABELERS, labeler_by_section
from leap_core.labelers.simulated import MOVED_TERMS, MOVED_TERMS_FIX
from leap_core.projection import ProjectionConfig
from leap_core.smoothing import SmoothingConfig
from leap_core.tracking import TrackingConfig


def _default_sections() -> dict[str, object]:
    return {spec.section: spec.config_type() for spec in LABELERS.values()}


C = TypeVar("C")


@dataclass(frozen=True)
class PipelineConfig:
    """Every parameter of a pipeline run (docs/METHOD.md stages A-C), grouped by stage."""

    labeler: str = "simulated"
    """2D labeler, a name in :data:`leap_core.labelers.LABELERS`: "simulated" (from a dataset's 2D ground
    truth, with a noise model) or "grounded-sam" (or one registered beside leap_core)."""
    labelers: Mapping[str, object] = field(default_factory=_default_sections)
    """Every registered labeler's settings, by its config section (``LabelerSpec.section``: ``simulated``,
    ``grounded_sam``), each an instance of its ``LabelerSpec.config_type``; sections left out get their
    defaults. In the dict form each section is a top-level key (:func:`config_to_dict`). Read one with
    :meth:`labeler_config` (typed) or ``LabelerSpec.config_of``."""
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)
    """Point projection and per-mask depth clustering."""
    fusion: FusionConfig = field(default_factory=FusionConfig)
    """Voxel size and the Bayesian update's floor and clip."""
    smoothing: SmoothingConfig = field(default_factory=SmoothingConfig)
    """kNN smoothing of the fused grid."""
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)
    """3D Consistency Network (off unless ``consistency.enabled``)."""
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    """Objects: per-scan segments of thing points, tracks, class votes and motion (docs/METHOD.md B.6)."""
    correction_strength: float = field(default=50.0, metadata=within(0, 1000, low_open=True, unit="nats"))
    """Log-odds of one manual correction (``corrections.npz`` in the run folder) when it is fused in."""

    def __post_init__(self) -> None:
        if self.labeler not in LABELERS:
            names = ", ".join(repr(n) for n in LABELERS)
            raise ConfigError(f"must be one of {names}, got {_short(self.labeler)}", field=("labeler",))
        check_bounds(self)
        own = {f.name for f in dataclasses.fields(self)}
        for section, value in self.labelers.items():
            spec = labeler_by_section(section)
            if spec is None:
                known = ", ".join(s.section for s in LABELERS.values())
                raise ConfigError(
                    f"no registered labeler has this config section (known: {known})", field=(section,)
                )
            if section in own:
                raise LeapError(f"labeler {spec.name!r}: its config section {section!r} is a pipeline field")
            if type(value) is not spec.config_type:
                raise ConfigError(
                    f"must be a {spec.config_type.__name__}, got a {type(value).__name__}", field=(section,)
                )
        # Every registered section, in the registry's order (the dict form's order): defaults where absent.
        full: dict[str, object] = {}
        for spec in LABELERS.values():
            value = self.labelers.get(spec.section)
            full[spec.section] = spec.config_type() if value is None else value
        object.__setattr__(self, "labelers", full)

    def labeler_section(self, section: str, config_type: type[C]) -> C:
        """The settings of config section ``section``, which hold a ``config_type`` (its defaults when this
        config was made before that section's labeler was registered).

        Raises:
            LeapError: no registered labeler has that section, or its config is of another type.
        """
        spec = labeler_by_section(section)
        if spec is None or spec.config_type is not config_type:
            raise LeapError(
                f"no registered labeler has a config section {section!r} of {config_type.__name__}"
            )
        value = self.labelers.get(section)
        if value is None:
            return config_type()
        assert isinstance(value, config_type)  # __post_init__ checked every section's type
        return value

    def labeler_config(self, config_type: type[C]) -> C:
        """The settings of the registered labeler whose config is a ``config_type``
        (``cfg.labeler_config(SimulatedLabelerConfig)``).

        Raises:
            LeapError: no registered labeler, or several, have that config type.
        """
        specs = [s for s in LABELERS.values() if s.config_type is config_type]
        if len(specs) != 1:
            raise LeapError(f"{len(specs)} registered labelers have a {config_type.__name__} config")
        return self.labeler_section(specs[0].section, config_type)

    def with_labeler_config(self, config: object, section: str | None = None) -> PipelineConfig:
        """This config with one labeler's settings replaced by ``config``, in ``section`` (default: the
        section of the one registered labeler whose config type is ``type(config)``)."""
        if section is None:
            specs = [s for s in LABELERS.values() if s.config_type is type(config)]
            if len(specs) != 1:
                raise LeapError(f"{len(specs)} registered labelers have a {type(config).__name__} config")
            section = specs[0].section
        return dataclasses.replace(self, labelers={**self.labelers, section: config})


def setting_bounds(sections: Mapping[str, type] | None = None) -> list[tuple[str, Bound]]:
    """``(dotted setting path, allowed range)`` of every bounded setting of :class:`PipelineConfig`, in the
    dict form's order (``correction_strength``, ``simulated.recall``, ..., ``consistency.backbone.knn``).

    Args:
        sections: labeler config section → its config type; default every registered labeler's.
    """
    chosen = sections if sections is not None else {s.section: s.config_type for s in LABELERS.values()}
    default = PipelineConfig()
    rows: list[tuple[str, Bound]] = []
    for f in dataclasses.fields(PipelineConfig):
        value = getattr(default, f.name)
        if f.name == "labelers":
            for section, config_type in chosen.items():
                rows += bounds_rows(config_type, f"{section}.")
        elif (bound := field_bound(PipelineConfig, f.name)) is not None:
            rows.append((f.name, bound))
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            rows += bounds_rows(type(value), f"{f.name}.")
    return rows


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
    """JSON/YAML-ready nested dict of every field (tuples become lists), each labeler's section a top-level
    key after ``labeler`` (``{labeler, simulated, grounded_sam, projection, ...}``); see
    :func:`config_from_dict`."""
    return {key: _plain(value) for key, value in _settings(cfg).items()}


def _settings(cfg: PipelineConfig) -> dict[str, Any]:
    """The top-level settings of ``cfg`` by their dict-form key: its fields, with the labeler sections in
    place of ``labelers``."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        if f.name == "labelers":
            out.update(cfg.labelers)
        else:
            out[f.name] = getattr(cfg, f.name)
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
    """Where the value is given now, completing "<problem>; ..."."""
    problem: str = "no longer a pipeline setting"
    """What the message says first."""


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
    **{
        ("simulated", name): RetiredField(
            off, MOVED_TERMS_FIX, "no longer a setting of the simulated labeler"
        )
        for name, off in MOVED_TERMS.items()
    },
}
"""Former config fields (path below ``pipeline``): deployment values now
(:class:`~leap_core.runtime.Runtime`), and the simulated labeler's noise terms that moved to the research
lab's labeler (:data:`~leap_core.labelers.simulated.MOVED_TERMS`)."""


def _is_former_default(value: Any, default: Any) -> bool:
    """Whether a stored ``value`` is a retired field's former ``default``: the same truth value for a
    switch, the same number for a number (``0`` for ``0.0``), an equal mapping for a table, else an equal
    value of the same type."""
    if isinstance(default, bool):
        return isinstance(value, bool) and value == default
    if isinstance(default, (int, float)):
        return isinstance(value, (int, float)) and not isinstance(value, bool) and value == default
    if isinstance(default, Mapping):
        return isinstance(value, Mapping) and dict(value) == dict(default)
    return type(value) is type(default) and bool(value == default)


def without_retired(d: Mapping[str, Any]) -> dict[str, Any]:
    """A config dict (any subset of :func:`config_to_dict`'s form) without the retired fields that hold
    their former defaults (:data:`RETIRED_FIELDS`): the settings :func:`config_from_dict` reads from it,
    so that a dict stored by an older version compares equal to today's form of the same config."""
    out = dict(d)
    for (section, name), retired in RETIRED_FIELDS.items():
        value = out.get(section)
        if isinstance(value, Mapping) and name in value and _is_former_default(value[name], retired.default):
            out[section] = {k: v for k, v in value.items() if k != name}
    return out


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


def _current(obj: Any) -> dict[str, Any]:
    """The settings of a config object by key: its fields; for :class:`PipelineConfig`, its dict form's
    top-level keys (each labeler's section in place of ``labelers``)."""
    if isinstance(obj, PipelineConfig):
        return _settings(obj)
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}


def _replace(obj: Any, changes: dict[str, Any]) -> Any:
    """``dataclasses.replace`` by the keys of :func:`_current`."""
    if isinstance(obj, PipelineConfig):
        sections = {k: v for k, v in changes.items() if labeler_by_section(k) is not None}
        rest = {k: v for k, v in changes.items() if k not in sections}
        if sections:
            rest["labelers"] = {**obj.labelers, **sections}
        return dataclasses.replace(obj, **rest)
    return dataclasses.replace(obj, **changes)


def _apply(obj: Any, overrides: Mapping[str, Any], path: tuple[str, ...]) -> Any:
    """``obj`` with ``overrides`` applied; every error carries the absolute field path."""
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"must be a mapping of settings, got {_short(overrides)}", field=path)
    obj, overrides = _preset_section(obj, overrides, path)
    hints = typing.get_type_hints(type(obj))
    current = _current(obj)
    names = list(current)
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        where = (*path, str(key))
        if key not in current:
            retired = RETIRED_FIELDS.get(where[1:])
            if retired is not None:
                if _is_former_default(value, retired.default):
                    continue
                raise ConfigError(f"{retired.problem}; {retired.replacement}", field=where)
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"known: {', '.join(names)}"
            raise ConfigError(f"unknown setting ({hint})", field=where)
        if dataclasses.is_dataclass(current[key]):
            changes[key] = _apply(current[key], value, where)
            continue
        try:
            changes[key] = _coerce(value, hints[key])
        except _BadValue as exc:
            raise ConfigError(str(exc), field=where) from None
    if not changes:
        return obj
    try:
        return _replace(obj, changes)
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


__all__ = [
    "RETIRED_FIELDS",
    "PipelineConfig",
    "RetiredField",
    "config_from_dict",
    "config_to_dict",
    "setting_bounds",
    "without_retired",
]
