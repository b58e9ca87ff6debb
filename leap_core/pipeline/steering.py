"""Steering a project between runs: which settings a configuration ignores, which stages a new run will
recompute, and what changed between two runs.

Everything here is derived from the registries, so no rule is written twice:

- A setting belongs to a **labeler** when its top-level config section is that labeler's
  ``LabelerSpec.section`` (``grounded_sam.box_threshold`` → ``grounded-sam``), and to a **switchable
  stage** when the stage's ``StageInfo.reads`` holds its section and the stage has a ``switch``
  (``consistency.share`` → ``3dcn``, whose switch is ``consistency.enabled``). It is ignored when another
  labeler is chosen or that stage is switched off.
- A stage is **recomputed** when the fingerprint a new run would give it differs from the one recorded in the
  latest run's ``stages.json`` (the rule :func:`~leap_core.pipeline.run_pipeline` applies when it reuses a
  seeded run folder), or when that run did not finish it.

Settings are named by their dotted config paths. A caller that shows them under human names (the app's
form) passes those names as data, ``labels``: dotted path → label.
"""

from __future__ import annotations

import json
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from leap_core.config import PipelineConfig, config_from_dict, config_to_dict, without_retired
from leap_core.errors import LeapError
from leap_core.labelers import LABELERS, labeler_by_section
from leap_core.pipeline.stages import STAGE_TABLE
from leap_core.schema import object_fields


# ------------------------------------------------------------------------------------ setting scopes
@dataclass(frozen=True)
class SettingScope:
    """What a setting (a dotted config path) depends on to have any effect."""

    labeler: str | None = None
    """Only this labeler (a :data:`LABELERS` name) reads it."""
    stage: str | None = None
    """Only this switchable stage reads it (ignored while the stage's switch is off)."""


def setting_scope(path: str) -> SettingScope:
    """The scope of the dotted config path ``path`` (``"grounded_sam.box_threshold"``)."""
    section = path.split(".", maxsplit=1)[0]
    spec = labeler_by_section(section)
    labeler = None if spec is None else spec.name
    stage = next(
        (s.name for s in STAGE_TABLE if s.switch is not None and section in s.reads and path != s.switch),
        None,
    )
    return SettingScope(labeler=labeler, stage=stage)


def ignored_reason(cfg: PipelineConfig, path: str, labels: Mapping[str, str] | None = None) -> str | None:
    """Why ``cfg`` ignores the setting at ``path``, or None when the setting has an effect.

    Args:
        labels: dotted path → human name of the settings the caller shows; a switched-off stage's reason
            names its switch by this name (``"(3D Consistency Network is unticked)"``) when given.
    """
    scope = setting_scope(path)
    if scope.labeler is not None and scope.labeler != cfg.labeler:
        return (
            f"only the {LABELERS[scope.labeler].label} labeler uses it; "
            f"the {LABELERS[cfg.labeler].label} labeler ignores it"
        )
    if scope.stage is not None:
        stage = next(s for s in STAGE_TABLE if s.name == scope.stage)
        if not stage.is_enabled(cfg):
            switch = (labels or {}).get(stage.switch or "")
            how = f" ({switch} is unticked)" if switch is not None else ""
            return f"the {stage.label} stage is off{how}"
    return None


# ----------------------------------------------------------------------------------- recompute plan
StageAction = Literal["recompute", "reuse", "off"]


@dataclass(frozen=True)
class StagePlan:
    """What a new run will do with one stage."""

    name: str
    label: str
    action: StageAction
    """``recompute``; ``reuse`` (the latest run's outputs are current); ``off`` (switched off: skipped)."""
    reason: str
    """One line: why (``"settings changed: smoothing"``, ``"after Voxel fusion"``, ...)."""


def recompute_plan(
    cfg: PipelineConfig,
    fingerprints: Mapping[str, str],
    previous: Mapping[str, Mapping[str, Any]] | None,
    changed_sections: Collection[str] = (),
    input_hint: str = "its inputs changed (classes, prompts, corrections or data)",
) -> list[StagePlan]:
    """Per stage (table order): will a run with ``fingerprints`` (:func:`~leap_core.pipeline.runner.
    stage_fingerprints`) recompute it, given the ``stages.json`` records ``previous`` of the run whose
    folder it starts from (None: no such run)?

    Args:
        cfg: the new run's config (which stages are switched on).
        fingerprints: stage name → the new run's fingerprint.
        previous: stage name → record with ``fingerprint`` and ``status``; None or {} = nothing to reuse.
        changed_sections: config sections (top-level keys) that differ from the previous run's, to name
            in the reasons.
        input_hint: the reason of a stage whose own settings and upstream stages are unchanged but whose
            other inputs (:attr:`StageInfo.inputs`, the class count) are not.
    """
    plans: list[StagePlan] = []
    changed: dict[str, bool] = {}
    label = {s.name: s.label for s in STAGE_TABLE}
    by_name = {s.name: s for s in STAGE_TABLE}
    for stage in STAGE_TABLE:
        rec = (previous or {}).get(stage.name)
        same = rec is not None and rec.get("fingerprint") == fingerprints[stage.name]
        finished = rec is not None and rec.get("status") in ("done", "skipped")
        changed[stage.name] = not (same and finished)
        if not stage.is_enabled(cfg):
            # Off, it writes nothing: it changes what follows only when it was on in the latest run.
            changed[stage.name] = bool(previous) and (rec or {}).get("status") != "skipped"
            plans.append(StagePlan(stage.name, stage.label, "off", "switched off"))
            continue
        if not changed[stage.name]:
            plans.append(StagePlan(stage.name, stage.label, "reuse", "unchanged since the latest run"))
            continue
        if not previous:
            reason = "no earlier run to reuse"
        elif rec is None:
            reason = "not run before"
        elif same:
            reason = f"unfinished in the latest run ({rec.get('status')})"
        else:
            parts = []
            own = [s for s in stage.reads if s in changed_sections]
            if own:
                parts.append(f"settings changed: {', '.join(own)}")
            ups = [
                label[u] + (" (switched off)" if not by_name[u].is_enabled(cfg) else "")
                for u in stage.upstream
                if changed[u]
            ]
            if ups:
                parts.append(f"after {', '.join(ups)}")
            reason = "; ".join(parts) or input_hint
        plans.append(StagePlan(stage.name, stage.label, "recompute", reason))
    return plans


def comparable(d: Mapping[str, Any]) -> dict[str, Any]:
    """A stored ``config_to_dict`` form as today's code reads it, for comparing two runs' settings: fields
    an older version stored at the value that meant "off" leave (:func:`~leap_core.config.
    without_retired`), and sections and fields added since (a new labeler's, a new option) come in at
    their defaults, which is what that older run did without them."""
    return _fill_missing(without_retired(d), config_to_dict(PipelineConfig()))


def _fill_missing(d: Mapping[str, Any], defaults: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(d)
    for k, v in defaults.items():
        if k not in out:
            out[k] = v
        elif isinstance(v, Mapping) and isinstance(out[k], Mapping):
            out[k] = _fill_missing(out[k], v)
    return out


def changed_sections(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """Top-level keys whose values differ between two ``config_to_dict`` forms (in ``new``'s order),
    compared as today's code reads them (:func:`comparable`)."""
    old, new = comparable(old), comparable(new)
    keys = list(new) + [k for k in old if k not in new]
    return [k for k in keys if _canon(old.get(k)) != _canon(new.get(k))]


def _canon(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=str)


# ------------------------------------------------------------------------------------ run changes
ChangeKind = Literal["dataset", "frames", "class", "parameter", "correction", "poses"]


@dataclass(frozen=True)
class Change:
    """One difference between two runs' inputs."""

    kind: ChangeKind
    subject: str
    """Class name, dotted parameter path, the sequence's name (a ``dataset`` or ``frames`` change), the
    correction's id (a ``correction`` change) or ``estimate_poses``."""
    text: str
    """One line for people (``prompts of car: + "sedan", − "jeep"``)."""
    ignored: str | None = None
    """For a parameter the newer run's config ignores: why (it then changed nothing)."""
    field: str | None = None
    """A ``class`` change of one class's field: which (``prompts``, ``thing``, ``moving_id``, ...); None
    for a class added, removed or reordered and for the other kinds."""


def _fmt(value: Any) -> str:
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list) and not value:
        return "none"
    return json.dumps(value, default=str)


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        path = f"{prefix}{k}"
        if isinstance(v, Mapping) and v:
            out.update(_flatten(v, path + "."))
        else:
            out[path] = v
    return out


def _class_changes(old: Sequence[Mapping[str, Any]], new: Sequence[Mapping[str, Any]]) -> list[Change]:
    out: list[Change] = []
    before = {c["name"]: c for c in old}
    after = {c["name"]: c for c in new}
    for c in new:
        if c["name"] not in before:
            ids = ", ".join(str(i) for i in c.get("gt_ids", [])) or "none"
            prompts = ", ".join(_fmt(p) for p in c.get("prompts", []))
            out.append(
                Change(
                    "class", c["name"], f"class {c['name']} added (prompts {prompts}; ground-truth ids {ids})"
                )
            )
    for c in old:
        if c["name"] not in after:
            out.append(Change("class", c["name"], f"class {c['name']} removed"))
    common_old = [c["name"] for c in old if c["name"] in after]
    common_new = [c["name"] for c in new if c["name"] in before]
    if common_old != common_new:
        out.append(Change("class", "order", "class order changed"))
    for name in common_new:
        a, b = before[name], after[name]
        for key, what in (("prompts", "prompts"), ("negative_prompts", "negative prompts")):
            pa, pb = list(a.get(key, [])), list(b.get(key, []))
            if pa != pb:
                plus = [f"+ {_fmt(p)}" for p in pb if p not in pa]
                minus = [f"− {_fmt(p)}" for p in pa if p not in pb]
                listed = ", ".join(plus + minus) or "reordered"
                out.append(Change("class", name, f"{what} of {name}: {listed}", field=key))
        ga, gb = sorted(a.get("gt_ids", [])), sorted(b.get("gt_ids", []))
        if ga != gb:
            out.append(
                Change("class", name, f"ground-truth ids of {name}: {_fmt(ga)} → {_fmt(gb)}", field="gt_ids")
            )
        for key, what in (("export_id", "export id"), ("category", "category"), ("color", "colour")):
            if a.get(key) != b.get(key):
                text = f"{what} of {name}: {_fmt(a.get(key))} → {_fmt(b.get(key))}"
                out.append(Change("class", name, text, field=key))
        out += _object_changes(name, a, b)
    return out


OBJECT_FIELDS = ("thing", "moving_id")
"""A class's fields that only the object stages read: the tracks stage its ``thing`` flag, the export its
``moving_id`` (and the evaluation what both change)."""


def _object_changes(name: str, old: Mapping[str, Any], new: Mapping[str, Any]) -> list[Change]:
    """A class's ``thing`` flag and moving id, compared as a schema reads them (an entry stored before
    classes had them at its defaults, :func:`~leap_core.schema.object_fields`)."""
    (ta, ma), (tb, mb) = object_fields(old), object_fields(new)
    out = []
    if ta != tb:
        text = f"{name} is {'a thing' if tb else 'stuff'} (was {'a thing' if ta else 'stuff'})"
        out.append(Change("class", name, text, field="thing"))
    if ma != mb:
        text = f"moving id of {name}: {'none' if ma is None else ma} → {'none' if mb is None else mb}"
        out.append(Change("class", name, text, field="moving_id"))
    return out


def _sequence_changes(old: list[Mapping[str, Any]], new: list[Mapping[str, Any]]) -> list[Change]:
    def frames(v: Any) -> str:
        return "all" if v is None else f"{v[0]}..{v[1] - 1}"

    before = {str(s["name"]): s for s in old}
    after = {str(s["name"]): s for s in new}
    out: list[Change] = []
    for name in list(after) + [n for n in before if n not in after]:
        a, b = before.get(name), after.get(name)
        if a is None:
            out.append(Change("dataset", name, f"sequence {name} added ({b['dataset'] if b else ''})"))
        elif b is None:
            out.append(Change("dataset", name, f"sequence {name} removed ({a['dataset']})"))
        else:
            if a.get("dataset") != b.get("dataset"):
                text = f"sequence {name}: dataset {a.get('dataset')} → {b.get('dataset')}"
                out.append(Change("dataset", name, text))
            if a.get("frames") != b.get("frames"):
                text = f"sequence {name}: frames {frames(a.get('frames'))} → {frames(b.get('frames'))}"
                out.append(Change("frames", name, text))
    return out


@dataclass(frozen=True)
class CorrectionNote:
    """What a change list says of one correction (the caller reads it from its store)."""

    text: str
    """``car, map, 340 voxels``."""
    made_after: bool
    """Made after the older run was queued (so "added", not "switched on")."""
    exists: bool = True
    """Still stored (switched off rather than deleted, when the newer run lacks it)."""


def correction_changes(
    old: Mapping[str, Sequence[int]],
    new: Mapping[str, Sequence[int]],
    notes: Mapping[int, CorrectionNote],
) -> list[Change]:
    """The corrections one run got and the other did not, per sequence (``{name: [correction ids]}``, older
    run first): in ``new`` only, *added* (made after the older run) or *switched on*; in ``old`` only,
    *switched off* or *removed*. A correction switched off and on again in between is no change (the runs
    got the same input). Sequences are named only when the runs have several."""
    out: list[Change] = []
    names = list(new) + [n for n in old if n not in new]
    for name in names:
        a, b = list(old.get(name, ())), list(new.get(name, ()))
        where = f" in sequence {name}" if len(names) > 1 else ""
        for cid in b:
            if cid not in a:
                note = notes.get(cid)
                verb = "added" if note is None or note.made_after else "switched on"
                what = f" ({note.text})" if note is not None else ""
                out.append(Change("correction", str(cid), f"correction {cid}{what}{where} {verb}"))
        for cid in a:
            if cid not in b:
                note = notes.get(cid)
                verb = "switched off" if note is not None and note.exists else "removed"
                what = f" ({note.text})" if note is not None else ""
                out.append(Change("correction", str(cid), f"correction {cid}{what}{where} {verb}"))
    return out


def run_changes(
    old: Mapping[str, Any], new: Mapping[str, Any], labels: Mapping[str, str] | None = None
) -> list[Change]:
    """What differs between two runs' input snapshots (``{"sequences": [{"name", "dataset", "frames"}],
    "schema": {"classes"}, "pipeline"}``, as the app stores them), older run first: sequences (added,
    removed, another folder, other frames), classes and prompts, then parameters (dotted paths, each
    marked when ``new``'s config ignores it; ``labels``: dotted path → human name, shown before the path
    of the settings it names). Pose estimation switched on or off is a ``poses`` change; the corrections
    each run got are compared by :func:`correction_changes`, which needs the caller's store."""
    out = _sequence_changes(old.get("sequences") or [], new.get("sequences") or [])
    if bool(old.get("estimate_poses")) != bool(new.get("estimate_poses")):
        turned = "off → on" if new.get("estimate_poses") else "on → off"
        out.append(Change("poses", "estimate_poses", f"Estimate poses (KISS-ICP): {turned}"))
    classes_old = (old.get("schema") or {}).get("classes", [])
    out += _class_changes(classes_old, (new.get("schema") or {}).get("classes", []))
    # A snapshot stored by an older version may hold fields that left the config at their former defaults,
    # or lack settings added since: neither changed anything, so neither is a parameter change.
    fa = _flatten(comparable(old.get("pipeline") or {}))
    fb = _flatten(comparable(new.get("pipeline") or {}))
    try:
        cfg: PipelineConfig | None = config_from_dict(new.get("pipeline") or {})
    except LeapError:
        cfg = None  # a snapshot from an older version: list its changes without the "ignored" notes
    labels = labels or {}
    for path in list(fb) + [p for p in fa if p not in fb]:
        if _canon(fa.get(path)) == _canon(fb.get(path)):
            continue
        name = f"{labels[path]} ({path})" if path in labels else path
        ignored = None if cfg is None else ignored_reason(cfg, path, labels)
        out.append(Change("parameter", path, f"{name}: {_fmt(fa.get(path))} → {_fmt(fb.get(path))}", ignored))
    return out


__all__ = [
    "OBJECT_FIELDS",
    "Change",
    "CorrectionNote",
    "SettingScope",
    "StagePlan",
    "changed_sections",
    "comparable",
    "correction_changes",
    "ignored_reason",
    "recompute_plan",
    "run_changes",
    "setting_scope",
]
