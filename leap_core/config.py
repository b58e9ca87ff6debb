"""The pipeline's configuration: one frozen tree of the per-module configs, and its dict form.

``PipelineConfig`` nests the config dataclass of every stage; each lives beside the code it configures.
Project files (``pipeline:`` section), the app's SQLite rows and the CLI all speak the plain-dict form
produced by :func:`config_to_dict` and read back by :func:`config_from_dict`, which applies nested
overrides onto a base config and rejects unknown keys, wrong types and out-of-range values with a
one-line :class:`~leap_core.errors.LeapError` naming the field path, e.g.
``pipeline.fusion.voxel_size: must be a positive number, got 0``.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from leap_core.consistency.config import ConsistencyConfig
from leap_core.errors import LeapError
from leap_core.fusion import FusionConfig
from leap_core.labelers.grounded_sam import GroundedSamConfig
from leap_core.labelers.simulated import SimulatedLabelerConfig
from leap_core.projection import ProjectionConfig
from leap_core.smoothing import SmoothingConfig

LabelerName = Literal["simulated", "grounded-sam"]


@dataclass(frozen=True)
class PipelineConfig:
    """Every parameter of a pipeline run (METHOD.md stages A-C), grouped by stage."""

    labeler: LabelerName = "simulated"
    """2D labeler: "simulated" (from a dataset's 2D ground truth, with a noise model) or "grounded-sam"."""
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
        if self.labeler not in ("simulated", "grounded-sam"):
            raise LeapError(f"labeler must be 'simulated' or 'grounded-sam', got {self.labeler!r}")
        if not self.correction_strength > 0:
            raise LeapError(f"correction_strength must be > 0, got {self.correction_strength}")

    def validate(self) -> None:
        """Run the nested configs' own ``validate()`` where they have one (``__post_init__`` covers the rest).

        Raises:
            LeapError: naming the field path.
        """
        _validate_tree(self, "pipeline")


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
    "labeler": FormField("labeler", "2D labeler", "select", "which model turns camera images into 2D labels",
                         choices=(("simulated", "simulated (from 2D ground truth)"),
                                  ("grounded-sam", "Grounding DINO + SAM"))),
    "threshold": FormField("grounded_sam.box_threshold", "Box threshold", "number",
                           "Grounding DINO boxes below this similarity are dropped", 0.0, 1.0, 0.01),
    "voxel_size": FormField("fusion.voxel_size", "Voxel size (m)", "number",
                            "edge of the fusion grid's voxels", 0.01, None, 0.05),
    "k": FormField("smoothing.k", "kNN smoothing k", "integer", "neighbours averaged per voxel", 1, None, 1),
    "cluster_gap": FormField("projection.cluster_gap", "Depth-cluster gap (m)", "number",
                             "depth gap that splits a mask's points into clusters", 0.0, None, 0.1),
    "consistency": FormField("consistency.enabled", "3D Consistency Network", "checkbox",
                             "train a 3D network on the most confident voxels and fuse it back"),
    "share": FormField("consistency.share", "3D-CN label share", "number",
                       "share of each class's most confident points used for training", 0.0, 1.0, 0.05),
    "temperature": FormField("consistency.temperature", "3D-CN temperature", "number",
                             "weight of the network's evidence when fused back (lower = stronger)", 0.0, None,
                             0.1),
    "iterations": FormField("consistency.iterations", "3D-CN iterations", "integer",
                            "self-training rounds", 1, None, 1),
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
    return _plain(cfg)


# ---------------------------------------------------------------------------------------- from dict
class _BadValue(Exception):
    """Internal: a value does not fit a field's type; the caller adds the field path."""


def _type_name(tp: Any) -> str:
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


def _coerce(value: Any, tp: Any) -> Any:
    """``value`` converted to type ``tp`` (strictly: no str→number, no bool→int); raises _BadValue."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin is Literal:
        if value in args and not isinstance(value, bool):
            return value
        raise _BadValue(f"must be {_type_name(tp)}, got {value!r}")
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
        raise _BadValue(f"must be {_type_name(tp)}, got {value!r}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise _BadValue(f"must be {_type_name(tp)}, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0]) for v in value)
        if len(value) != len(args):
            raise _BadValue(f"must be {_type_name(tp)}, got {len(value)} values")
        return tuple(_coerce(v, a) for v, a in zip(value, args))
    if origin is dict:
        if not isinstance(value, Mapping):
            raise _BadValue(f"must be {_type_name(tp)}, got {value!r}")
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
            return float(value)
    elif tp is str:
        if isinstance(value, str):
            return value
    else:
        raise _BadValue(f"has an unsupported type {tp!r}")
    raise _BadValue(f"must be {_type_name(tp)}, got {value!r}")


_FIELD_PROBLEM = re.compile(r"^(?P<path>[A-Za-z_][\w\-]*(?:\.[\w\-]+)*) (?P<problem>must\b.*)$", re.DOTALL)


def _rephrase(message: str, obj: Any, path: str) -> str:
    """Turn a config's own "<Class or section>.<field> must ..." message into "<path>.<field>: must ..."."""
    m = _FIELD_PROBLEM.match(message.strip())
    if not m:
        return f"{path}: {message}"
    parts = m.group("path").split(".")
    section = path.rsplit(".", 1)[-1]
    if parts[0] in (type(obj).__name__, section):
        parts = parts[1:]
    return ".".join([path, *parts]) + ": " + m.group("problem")


def _apply(obj: Any, overrides: Mapping[str, Any], path: str) -> Any:
    if not isinstance(overrides, Mapping):
        raise LeapError(f"{path}: must be a mapping of settings, got {overrides!r}")
    hints = typing.get_type_hints(type(obj))
    names = [f.name for f in dataclasses.fields(obj)]
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        where = f"{path}.{key}"
        if key not in names:
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"known: {', '.join(names)}"
            raise LeapError(f"{where}: unknown setting ({hint})")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            changes[key] = _apply(current, value, where)
            continue
        try:
            changes[key] = _coerce(value, hints[key])
        except _BadValue as exc:
            raise LeapError(f"{where}: {exc}") from None
    try:
        new = dataclasses.replace(obj, **changes) if changes else obj
    except (ValueError, TypeError) as exc:
        raise LeapError(_rephrase(str(exc), obj, path)) from None
    _validate_one(new, path)
    return new


def _validate_one(obj: Any, path: str) -> None:
    validate = getattr(obj, "validate", None)
    if callable(validate) and not isinstance(obj, PipelineConfig):
        try:
            validate()
        except (ValueError, TypeError) as exc:
            raise LeapError(_rephrase(str(exc), obj, path)) from None


def _validate_tree(obj: Any, path: str) -> None:
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            _validate_tree(value, f"{path}.{f.name}")
    _validate_one(obj, path)


def config_from_dict(d: Mapping[str, Any] | None, base: PipelineConfig | None = None) -> PipelineConfig:
    """``base`` with the nested overrides of ``d`` applied (missing keys keep ``base``'s values).

    Args:
        d: nested mapping as written by :func:`config_to_dict` (any subset of it); None = no overrides.
        base: the config to start from; default ``PipelineConfig()``.

    Raises:
        LeapError: ``"pipeline.<field path>: <problem>"`` for an unknown key, a wrong type or a value out of
            range.
    """
    return _apply(base if base is not None else PipelineConfig(), d or {}, "pipeline")


def overrides_from_form(form: Mapping[str, Any]) -> dict[str, Any]:
    """Nested overrides from the app form's flat names (:data:`FORM_FIELDS`).

    Raises:
        LeapError: for a name that is not a form field.
    """
    out: dict[str, Any] = {}
    for name, value in form.items():
        if name not in FORM_FIELDS:
            raise LeapError(f"pipeline form: unknown field {name!r} (known: {', '.join(FORM_FIELDS)})")
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
    "FormField",
    "LabelerName",
    "PipelineConfig",
    "config_from_dict",
    "config_to_dict",
    "form_values",
    "overrides_from_form",
]
