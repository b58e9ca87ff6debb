"""The app's pipeline form: its flat parameter names, their widgets and the dotted config paths they set.

The form shows a few settings of :class:`~leap_core.config.PipelineConfig` under flat names
(``voxel_size`` → ``fusion.voxel_size``). The web UI builds its parameter form from :data:`FORM_FIELDS`
(``GET /pipeline``); the API turns a form's values into config overrides (:func:`overrides_from_form`) and
a config into form values (:func:`form_values`). Which settings a config ignores is leap_core's rule
(:mod:`leap_core.pipeline.steering`, by dotted path); :func:`ignored_settings` and :func:`stage_switches`
put it in the form's names.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from leap_core.bounds import Bound
from leap_core.config import PipelineConfig, setting_bounds
from leap_core.errors import LeapError
from leap_core.labelers import LABELERS
from leap_core.pipeline.context import config_value
from leap_core.pipeline.stages import STAGE_TABLE
from leap_core.pipeline.steering import ignored_reason


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
    """Smallest value the input offers (the setting's bound, :func:`bounded`)."""
    maximum: float | None = None
    """Largest value the input offers."""
    step: float | None = None
    choices: tuple[tuple[str, str], ...] = ()
    """``select`` only: (value, label) pairs."""


BOUNDS: dict[str, Bound] = dict(setting_bounds())
"""Dotted config path → its allowed range (leap_core's, :func:`~leap_core.config.setting_bounds`)."""


def bounded(
    path: str, label: str, kind: Literal["number", "integer"], help_text: str, step: float
) -> FormField:
    """A number input for the setting at ``path`` offering the ends of its bound (the config refuses an
    open end itself, naming the field)."""
    bound = BOUNDS[path]
    return FormField(path, label, kind, help_text, bound.low, bound.high, step)


FORM_FIELDS: dict[str, FormField] = {
    "labeler": FormField(
        "labeler",
        "2D labeler",
        "select",
        "which model turns camera images into 2D labels",
        choices=tuple((name, spec.label) for name, spec in LABELERS.items()),
    ),
    "threshold": bounded(
        "grounded_sam.box_threshold",
        "Box threshold",
        "number",
        "Grounding DINO boxes below this similarity are dropped",
        0.01,
    ),
    "sam3_threshold": bounded(
        "sam3.score_threshold",
        "Instance score threshold",
        "number",
        "SAM 3 instances scoring below this are dropped",
        0.01,
    ),
    "voxel_size": bounded(
        "fusion.voxel_size", "Voxel size (m)", "number", "edge of the fusion grid's voxels", 0.05
    ),
    "k": bounded("smoothing.k", "kNN smoothing k", "integer", "neighbours averaged per voxel", 1),
    "cluster_gap": bounded(
        "projection.cluster_gap",
        "Depth-cluster gap (m)",
        "number",
        "depth gap that splits a mask's points into clusters",
        0.1,
    ),
    "consistency": FormField(
        "consistency.enabled",
        "3D Consistency Network",
        "checkbox",
        "train a 3D network on the most confident voxels and fuse it back",
    ),
    "share": bounded(
        "consistency.share",
        "3D-CN label share",
        "number",
        "share of each class's most confident points used for training",
        0.05,
    ),
    "temperature": bounded(
        "consistency.temperature",
        "3D-CN temperature",
        "number",
        "weight of the network's evidence when fused back (lower = stronger)",
        0.1,
    ),
    "iterations": bounded("consistency.iterations", "3D-CN iterations", "integer", "self-training rounds", 1),
}
"""The app form's flat parameter names → their :class:`FormField` (dotted path, label, widget)."""


PATH_LABELS: dict[str, str] = {f.path: f.label for f in FORM_FIELDS.values()}
"""Dotted config path → the form's label of it: the human names steering's reasons and run changes use."""


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
    return {name: config_value(cfg, f.path) for name, f in FORM_FIELDS.items()}


def stage_switches() -> dict[str, str]:
    """Stage name → flat name of the form field that switches it (stages whose switch is a form field)."""
    by_path = {f.path: name for name, f in FORM_FIELDS.items()}
    return {s.name: by_path[s.switch] for s in STAGE_TABLE if s.switch is not None and s.switch in by_path}


def ignored_settings(cfg: PipelineConfig) -> dict[str, str]:
    """Flat form name → why ``cfg`` ignores it, for every form field it ignores."""
    out: dict[str, str] = {}
    for name, f in FORM_FIELDS.items():
        reason = ignored_reason(cfg, f.path, PATH_LABELS)
        if reason is not None:
            out[name] = reason
    return out


__all__ = [
    "BOUNDS",
    "FORM_FIELDS",
    "PATH_LABELS",
    "FormField",
    "bounded",
    "form_values",
    "ignored_settings",
    "overrides_from_form",
    "stage_switches",
]
