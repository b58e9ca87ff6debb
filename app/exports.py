"""Exports of a finished run: where they may be written (the app's policy), the stand-alone zip, and the
point counts the export dialog shows.

Where an export may go (README, "Security"): a dataset's ``predictions/`` folder (a ``predictions``
folder beside a sequence's ``velodyne/``), or a folder inside the app's own export folder
(``<work_dir>/exports``). Never a sequence's input folders (``labels/``, ``velodyne/``, ``image_2/``, ...),
a run folder, or anything else in the work folder; :func:`leap_core.export.export_target_problem` holds the
dataset / run-folder rules, this module the app's part. Existing files are replaced only on request.
"""

from __future__ import annotations

import datetime
import threading
import zipfile
from pathlib import Path
from typing import Any

from app import models
from app.core.config import Settings
from app.core.errors import Conflict, Forbidden, NotFound
from app.core.security import resolve_in_roots
from app.jobs.multi import run_sequences_of, sequence_layouts
from app.services import pipeline_config
from leap_core import __version__
from leap_core.config import config_to_dict
from leap_core.errors import LeapError
from leap_core.export import (
    LABEL_MAP_FILE,
    PREDICTIONS,
    SUMMARY_FILE,
    ExportConflict,
    existing_export_files,
    export_target_problem,
    label_map,
    label_map_yaml,
    summary_yaml,
    write_export_folder,
    write_export_zip,
)
from leap_core.pipeline.coverage import (
    ExportCoverage,
    coverage_counts,
    export_coverage,
    read_coverage_file,
    write_coverage_file,
)
from leap_core.pipeline.multi import export_sequences, export_targets, export_zip
from leap_core.run_layout import RunLayout
from leap_core.schema import Schema

EXPORTS_FOLDER = "exports"
"""The app's own export folder inside the work folder."""

_lock = threading.Lock()
"""Serialises building the cached files (zip, counts) of runs, so two requests never build one twice."""

REASONS: tuple[tuple[str, str, str], ...] = (
    (
        "outside_view",
        "outside every camera view",
        "No point of its voxel was inside the camera image in any frame of the run, "
        "so no 2D label reached it.",
    ),
    (
        "no_mask",
        "in view, no mask",
        "Its voxel was inside the camera image, but no 2D mask covered it there (the labeler found nothing, "
        "e.g. a detector box below the box threshold was dropped) or depth clustering removed it "
        "from the mask.",
    ),
)
"""(key, label, explanation) of each reason a point stays unlabeled (leap_core.pipeline.coverage)."""

THRESHOLD_NOTE = (
    "No confidence threshold is applied in 3D: every point of a labeled voxel keeps the voxel's most likely "
    "class, so no point is unlabeled for being below a threshold (thresholds act in 2D and count as "
    "'no mask')."
)


def exports_dir(settings: Settings) -> Path:
    """The app-owned folder exports may be written into (besides datasets' ``predictions/``)."""
    return settings.work_dir / EXPORTS_FOLDER


# ------------------------------------------------------------------------------------ target policy
def _inside(path: Path, folder: Path) -> bool:
    return path == folder or path.is_relative_to(folder)


def export_target(settings: Settings, project: dict[str, Any], raw: str | None) -> Path:
    """The resolved folder an export of ``project``'s run may be written into.

    ``raw`` None means the project dataset's ``predictions/``; a relative ``raw`` is taken inside the first
    data root.

    Raises:
        Forbidden: outside the data roots and the app's export folder; a dataset input folder, a run
            folder, the work folder; or neither a dataset's ``predictions/`` nor inside the app's exports.
    """
    own = exports_dir(settings).resolve()
    work = settings.work_dir.resolve()
    shown = raw if raw else str(Path(project["dataset_path"]) / PREDICTIONS)
    roots = [*settings.data_roots, own]
    if project["dataset_kind"] == "demo":
        # The built-in demo lives in the work folder; its predictions/ folder is allowed too.
        roots.append(Path(project["dataset_path"]).resolve() / PREDICTIONS)
    target = resolve_in_roots(shown, roots, what="export path")
    problem = export_target_problem(target)
    if problem is not None:
        raise Forbidden(f"export path {shown!r}: {problem}")
    if _inside(target, own):
        if target == own:
            raise Forbidden(f"export path {shown!r}: name a folder inside the app's export folder {own}")
        return target
    is_predictions = target.name == PREDICTIONS and (target.parent / "velodyne").is_dir()
    if not is_predictions:
        raise Forbidden(
            f"export path {shown!r}: exports go into a dataset's {PREDICTIONS}/ folder "
            "(beside its velodyne/) "
            f"or into a folder inside the app's export folder {own}"
        )
    demo_predictions = (
        project["dataset_kind"] == "demo" and target == Path(project["dataset_path"]).resolve() / PREDICTIONS
    )
    if _inside(target, work) and not demo_predictions:
        raise Forbidden(f"export path {shown!r} is inside the app's work folder {work}")
    return target


# ------------------------------------------------------------------------------------------- the run
def _finished_export(run: dict[str, Any]) -> RunLayout:
    lay = RunLayout(Path(run["run_dir"]))
    if run["status"] != "done":
        raise Conflict(f"Run {run['id']} is {run['status']}; only finished runs have exports")
    if not lay.export_dir.is_dir():
        raise NotFound(f"Run {run['id']} has no export folder")
    return lay


def _frames(run: dict[str, Any]) -> range | None:
    frames = run["params"].get("frames")
    return None if frames is None else range(int(frames[0]), int(frames[1]))


def _schema(run: dict[str, Any]) -> Schema:
    return Schema.from_dict(run["params"]["schema"], source=f"run {run['id']} schema")


def coverage(run: dict[str, Any]) -> ExportCoverage:
    """The run's export counts (:func:`~leap_core.pipeline.coverage.export_coverage`), computed once and
    cached in the run folder (until the "apply corrections" job changes the export: :func:`invalidate`);
    a run of several sequences sums its sequences' counts (each cached in its own folder)."""
    if run_sequences_of(run["params"]) is None:
        return _coverage(run, _finished_export(run), Path(run["params"]["dataset"]))
    parts = [_coverage(run, lay, dataset) for lay, dataset in _sequence_exports(run)]
    raw: dict[int, int] = {}
    for c in parts:
        for k, v in c.raw_counts.items():
            raw[k] = raw.get(k, 0) + v
    return ExportCoverage(
        frames=sum(c.frames for c in parts),
        points=sum(c.points for c in parts),
        labeled=sum(c.labeled for c in parts),
        outside_view=sum(c.outside_view for c in parts),
        no_mask=sum(c.no_mask for c in parts),
        raw_counts=dict(sorted(raw.items())),
    )


def _sequence_exports(run: dict[str, Any]) -> list[tuple[RunLayout, Path]]:
    """(run layout, dataset) per sequence of a finished multi-sequence run, each with its export folder."""
    if run["status"] != "done":
        raise Conflict(f"Run {run['id']} is {run['status']}; only finished runs have exports")
    out = []
    for name, dataset, lay in sequence_layouts(Path(run["run_dir"]), run["params"]):
        if not lay.export_dir.is_dir():
            raise NotFound(f"Run {run['id']} has no export folder for sequence {name!r}")
        out.append((lay, dataset))
    return out


def _coverage(run: dict[str, Any], lay: RunLayout, dataset: Path) -> ExportCoverage:
    with _lock:
        # Written without a stage key: the app invalidates the file itself (the "apply corrections" job
        # rewrites the export without a stage record and deletes it, ``invalidate``), so any file present
        # is current; a `leap run` never trusts a keyless file (coverage.cached_export_coverage).
        cached = read_coverage_file(lay.export_coverage)
        if cached is not None:
            return cached
        cfg = pipeline_config(run["params"]["pipeline"], loc=("run", "params", "pipeline"))
        try:
            cov = export_coverage(lay.run_dir, dataset, _frames(run), cfg.fusion.voxel_size)
        except LeapError as exc:
            raise Conflict(f"Run {run['id']}: cannot count its export ({exc})") from None
        write_coverage_file(lay.export_coverage, cov, None)
        return cov


def export_info(settings: Settings, run: dict[str, Any], project: dict[str, Any]) -> models.ExportInfo:
    """What the export dialog shows: the counts, the reasons for unlabeled points, and the default target."""
    cov = coverage(run)
    schema = _schema(run)
    by_reason = {"outside_view": cov.outside_view, "no_mask": cov.no_mask}
    names = [n for n, _ in run_sequences_of(run["params"]) or []]
    predictions = (
        Path(project["dataset_path"]) / PREDICTIONS
        if not names
        else default_multi_target(settings, project, run)
    )
    target: Path | None
    try:
        target = (
            export_target(settings, project, None)
            if not names
            else multi_target(settings, project, run, None)
        )
    except Forbidden:
        target = None
    if target is None:
        existing = []
    elif names:
        existing = [f for n in names for f in existing_export_files(target / SEQUENCES / n / PREDICTIONS)]
    else:
        existing = existing_export_files(target)
    return models.ExportInfo(
        run_id=run["id"],
        frames=cov.frames,
        points=cov.points,
        labeled=cov.labeled,
        unlabeled=cov.unlabeled,
        reasons=[
            models.UnlabeledReason(key=key, label=label, points=by_reason[key], explanation=why)
            for key, label, why in REASONS
        ],
        threshold_note=THRESHOLD_NOTE,
        classes=[
            models.ExportClassCount(
                name=c.name,
                export_id=c.export_id,
                color="#{:02x}{:02x}{:02x}".format(*c.color),
                points=cov.raw_counts.get(c.export_id, 0),
            )
            for c in schema.classes
        ],
        predictions_path=str(target if target is not None else predictions),
        predictions_allowed=target is not None,
        predictions_existing=len(existing),
        sequences=names,
    )


# ------------------------------------------------------------------------------------------- zip
def build_zip(run: dict[str, Any], project: dict[str, Any], include_confidence: bool) -> Path:
    """The run's stand-alone export zip (:meth:`RunLayout.export_zip`), built once and cached beside it:
    ``sequences/<seq>/predictions/<frame>.label`` (+ ``confidences/<frame>.conf``), ``label-map.yaml``
    and ``summary.yaml`` (:func:`leap_core.export.write_export_zip`)."""
    if run_sequences_of(run["params"]) is not None:
        return _build_multi_zip(run, include_confidence)
    lay = _finished_export(run)
    target = lay.export_zip(include_confidence)
    cov = coverage(run)
    with _lock:
        if target.is_file() and _current_zip(target):
            return target
        schema = _schema(run)
        dataset = Path(run["params"]["dataset"])
        cfg = pipeline_config(run["params"]["pipeline"], loc=("run", "params", "pipeline"))
        name = f"{project['name']} run {run['number']}"
        summary = summary_yaml(
            project={"id": project["id"], "name": project["name"]},
            run={"id": run["id"], "number": run["number"], "finished_at": run.get("finished_at")},
            dataset=dataset,
            frames=_frames(run),
            schema=schema,
            pipeline=config_to_dict(cfg),
            counts=coverage_counts(cov),
            with_confidence=include_confidence,
            version=__version__,
            written_at=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        )
        lmap = label_map(schema, cov.raw_counts, name=name, sequence=dataset.name)
        extra = {LABEL_MAP_FILE: label_map_yaml(lmap), SUMMARY_FILE: summary}
        # The cached zip is the app's own file: rebuilding it (older layout) replaces it.
        write_export_zip(
            target, lay.export_dir, dataset.name, extra, include_confidence=include_confidence, overwrite=True
        )
    return target


def _build_multi_zip(run: dict[str, Any], include_confidence: bool) -> Path:
    """A multi-sequence run's zip (:func:`leap_core.pipeline.multi.export_zip`: ``sequences/<name>/
    predictions/<frame>.label`` per sequence, one label map and summary), cached in the run folder."""
    _sequence_exports(run)
    target = RunLayout(Path(run["run_dir"])).export_zip(include_confidence)
    cov = coverage(run)
    with _lock:
        if target.is_file() and _current_zip(target):
            return target
        cfg = pipeline_config(run["params"]["pipeline"], loc=("run", "params", "pipeline"))
        try:
            export_zip(
                Path(run["run_dir"]),
                target,
                _schema(run),
                config=cfg,
                with_conf=include_confidence,
                overwrite=True,
                raw_counts=cov.raw_counts,
                version=__version__,
            )
        except LeapError as exc:
            raise Conflict(f"Run {run['id']}: cannot build its zip ({exc})") from None
    return target


def invalidate(run_dir: Path) -> None:
    """Forget a run's cached zips and counts after its export files changed (the "apply corrections" job):
    under the lock, so a zip being built from the old files is removed once it is written."""
    lay = RunLayout(run_dir)
    with _lock:
        for path in (lay.export_zip(False), lay.export_zip(True), lay.export_coverage):
            path.unlink(missing_ok=True)


def _current_zip(path: Path) -> bool:
    """A cached zip in today's layout (zips cached by older versions lack the label map: rebuilt)."""
    try:
        with zipfile.ZipFile(path) as zf:
            return LABEL_MAP_FILE in zf.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


# ------------------------------------------------------------------------------------- folder export
def write_export(
    settings: Settings, run: dict[str, Any], project: dict[str, Any], payload: models.ExportWrite
) -> models.ExportWritten:
    """Copy the run's ``.label`` (and ``.conf``) files into the allowed target folder (a fresh folder renamed
    into place); existing files only with ``payload.overwrite``.

    Raises:
        Forbidden: a target the policy refuses (:func:`export_target`).
        Conflict: the target holds files and ``overwrite`` is off, or holds files an export does not write.
    """
    if run_sequences_of(run["params"]) is not None:
        return _write_multi_export(settings, run, project, payload)
    lay = _finished_export(run)
    target = export_target(settings, project, payload.path)
    suffixes = (".label", ".conf") if payload.include_confidence else (".label",)
    files = sorted(p for p in lay.export_dir.iterdir() if p.suffix in suffixes and p.is_file())
    try:
        replaced = write_export_folder(target, files, overwrite=payload.overwrite)
    except ExportConflict as exc:
        raise Conflict(str(exc)) from None
    return models.ExportWritten(run_id=run["id"], path=str(target), files=len(files), replaced=replaced)


# ------------------------------------------------------------------------- runs of several sequences
SEQUENCES = "sequences"
"""An export of several sequences writes ``<folder>/sequences/<name>/predictions/`` (SemanticKITTI's
layout)."""


def default_multi_target(settings: Settings, project: dict[str, Any], run: dict[str, Any]) -> Path:
    """Where a multi-sequence run's export goes by default: the datasets' common root when every sequence
    is ``<root>/sequences/<name>`` (each sequence's own ``predictions/``), else
    ``<work_dir>/exports/<project>-run<N>``."""
    listed = run_sequences_of(run["params"]) or []
    roots = {dataset.parent.parent for _, dataset in listed}
    if len(roots) == 1 and all(d.parent.name == SEQUENCES and d.name == n for n, d in listed):
        return roots.pop()
    stem = "".join(ch if ch.isalnum() or ch in "-_" else "-" for ch in project["name"])[:40] or "project"
    return exports_dir(settings) / f"{stem}-run{run['number']}"


def multi_target(settings: Settings, project: dict[str, Any], run: dict[str, Any], raw: str | None) -> Path:
    """The folder a multi-sequence run's export may go into: each ``<folder>/sequences/<name>/predictions``
    must be allowed by :func:`export_target` (a dataset's ``predictions/`` beside its ``velodyne/``, or a
    folder inside the app's export folder).

    Raises:
        Forbidden: naming the first sequence folder the policy refuses.
    """
    shown = raw if raw else str(default_multi_target(settings, project, run))
    roots = [*settings.data_roots, exports_dir(settings).resolve()]
    base = resolve_in_roots(shown, roots, what="export path")
    for name, _ in run_sequences_of(run["params"]) or []:
        folder = base / SEQUENCES / name / PREDICTIONS
        try:
            export_target(settings, project, str(folder))
        except Forbidden as exc:
            raise Forbidden(f"export path {shown!r}, sequence {name!r}: {exc.detail}") from None
    return base


def _write_multi_export(
    settings: Settings, run: dict[str, Any], project: dict[str, Any], payload: models.ExportWrite
) -> models.ExportWritten:
    _sequence_exports(run)
    target = multi_target(settings, project, run, payload.path)
    names = [n for n, _ in run_sequences_of(run["params"]) or []]
    replaced = sum(
        len(existing_export_files(folder))
        for folders in export_targets(target, names, with_conf=payload.include_confidence).values()
        for folder in folders
    )
    try:
        written = export_sequences(
            Path(run["run_dir"]), target, with_conf=payload.include_confidence, overwrite=payload.overwrite
        )
    except ExportConflict as exc:
        raise Conflict(str(exc)) from None
    except LeapError as exc:
        raise Forbidden(f"export path {str(target)!r}: {exc}") from None
    return models.ExportWritten(
        run_id=run["id"],
        path=str(target),
        files=sum(written.values()),
        replaced=replaced if payload.overwrite else 0,
    )


__all__ = [
    "REASONS",
    "build_zip",
    "coverage",
    "export_info",
    "export_target",
    "exports_dir",
    "invalidate",
    "write_export",
]
