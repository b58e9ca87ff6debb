"""Exports of a finished run: where they may be written (the app's policy), the stand-alone zip, and the
point counts the export dialog shows.

Where an export may go (docs/SECURITY.md): each sequence's own ``predictions/`` folder (a ``predictions``
folder beside its ``velodyne/``; the default), or ``<folder>/sequences/<name>/predictions/`` for a folder
inside a data root whose sequences are datasets' (``<folder>`` = the datasets' common root) or inside the
app's own export folder (``<work_dir>/exports``). Never a sequence's input folders (``labels/``,
``velodyne/``, ``image_2/``, ...), a run folder, or anything else in the work folder;
:func:`leap_core.export.export_target_problem` holds the dataset / run-folder rules, this module the app's
part. Existing files are replaced only on request.
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
from app.rows import ProjectRow, RunRow
from app.services import pipeline_config
from leap_core import __version__
from leap_core.config import config_to_dict
from leap_core.errors import LeapError
from leap_core.export import (
    CONFIDENCES,
    LABEL_MAP_FILE,
    PREDICTIONS,
    SUMMARY_FILE,
    ExportConflict,
    ExportedSequence,
    existing_export_files,
    export_target_problem,
    export_targets,
    label_map,
    label_map_yaml,
    summary_yaml,
    write_export_zip,
    write_run_export,
)
from leap_core.paths import UnusablePath, real_path, real_path_or_none
from leap_core.pipeline.coverage import (
    ExportCoverage,
    coverage_counts,
    export_coverage,
    read_coverage_file,
    summed_coverage,
    write_coverage_file,
)
from leap_core.pipeline.provenance import provenance_lines, run_provenance
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


def _server_folder(path: Path, what: str) -> Path:
    """:func:`~app.core.security.real_path` of one of the server's own folders.

    Raises:
        Conflict: the folder cannot be looked up (it was made a symlink loop); nothing is written.
    """
    try:
        return real_path(path)
    except UnusablePath as exc:
        raise Conflict(f"{what} {path} {exc}; whoever runs the server must fix it") from None


def _own_exports(settings: Settings) -> Path:
    return _server_folder(exports_dir(settings), "the app's export folder")


def export_target(settings: Settings, project: ProjectRow, raw: str) -> Path:
    """The resolved folder ``raw`` names, when one sequence's export may be written into it: a dataset's
    ``predictions/`` folder (beside its ``velodyne/``) inside a data root (or the demo's), or a folder
    inside the app's export folder; a relative ``raw`` is taken inside the first data root.

    Raises:
        Forbidden: outside the data roots and the app's export folder; a dataset input folder, a run
            folder, the work folder; or neither a dataset's ``predictions/`` nor inside the app's exports.
    """
    own = _own_exports(settings)
    work = _server_folder(settings.work_dir, "the work folder")
    roots = [*settings.data_roots, own]
    folders = [real_path_or_none(s.dataset_path) for s in project.sequences]
    demo = [folder / PREDICTIONS for folder in folders if folder is not None]
    if project.dataset_kind == "demo":
        # The built-in demo lives in the work folder; its predictions/ folder is allowed too.
        roots += demo
    target = resolve_in_roots(raw, roots, what="export path")
    problem = export_target_problem(target)
    if problem is not None:
        raise Forbidden(f"export path {raw!r}: {problem}")
    if _inside(target, own):
        if target == own:
            raise Forbidden(f"export path {raw!r}: name a folder inside the app's export folder {own}")
        return target
    is_predictions = target.name == PREDICTIONS and (target.parent / "velodyne").is_dir()
    if not is_predictions:
        raise Forbidden(
            f"export path {raw!r}: exports go into a dataset's {PREDICTIONS}/ folder "
            "(beside its velodyne/) "
            f"or into a folder inside the app's export folder {own}"
        )
    if _inside(target, work) and not (project.dataset_kind == "demo" and target in demo):
        raise Forbidden(f"export path {raw!r} is inside the app's work folder {work}")
    return target


# ------------------------------------------------------------------------------------------- the run
def _exported(run: RunRow) -> list[ExportedSequence]:
    """Each sequence of a finished run with its export folder, in run order."""
    if run.status != "done":
        raise Conflict(f"Run {run.number} (id {run.id}) is {run.status}; only finished runs have exports")
    out = []
    for seq in run.params.sequences:
        export = run.sequence_layout(seq.name).export_dir
        if not export.is_dir():
            raise NotFound(f"Run {run.id} has no export folder for sequence {seq.name!r}")
        out.append(ExportedSequence(seq.name, export, seq.dataset, seq.frame_range))
    return out


def _schema(run: RunRow) -> Schema:
    return Schema.from_dict(run.params.schema, source=f"run {run.id} schema")


def coverage(run: RunRow) -> ExportCoverage:
    """The run's export counts, its sequences' summed (:func:`~leap_core.pipeline.coverage.export_coverage`
    of each, computed once and cached in the sequence's folder until the "apply corrections" job changes
    the export: :func:`invalidate`)."""
    return summed_coverage(_coverage(run, seq) for seq in _exported(run))


def _coverage(run: RunRow, seq: ExportedSequence) -> ExportCoverage:
    lay = run.sequence_layout(seq.name)
    with _lock:
        # Written without a stage key: the app invalidates the file itself (the "apply corrections" job
        # rewrites the export without a stage record and deletes it, ``invalidate``), so any file present
        # is current; a `leap run` never trusts a keyless file (coverage.cached_export_coverage).
        cached = read_coverage_file(lay.export_coverage)
        if cached is not None:
            return cached
        cfg = pipeline_config(run.params.pipeline, loc=("run", "params", "pipeline"))
        assert seq.dataset is not None
        try:
            cov = export_coverage(lay.folder, seq.dataset, seq.frames, cfg.fusion.voxel_size)
        except LeapError as exc:
            raise Conflict(f"Run {run.id}: cannot count its export ({exc})") from None
        write_coverage_file(lay.export_coverage, cov, None)
        return cov


def targets(
    settings: Settings, project: ProjectRow, run: RunRow, raw: str | None, *, with_conf: bool = False
) -> dict[str, list[Path]]:
    """Per sequence of the run, the folders an export writes (its ``.label`` files' folder, then its
    ``.conf`` files' with ``with_conf``): with ``raw`` None each sequence's own ``predictions/`` (and
    ``confidences/`` beside it), else ``<raw>/sequences/<name>/predictions`` (SemanticKITTI's layout),
    each allowed by :func:`export_target`.

    Raises:
        Forbidden: naming the first folder the policy refuses.
    """
    if raw is None:
        out = {}
        for seq in run.params.sequences:
            base = seq.dataset / PREDICTIONS
            out[seq.name] = [base, *([base.parent / CONFIDENCES] if with_conf else [])]
        shown: dict[str, str] = {name: str(folders[0]) for name, folders in out.items()}
    else:
        roots = [*settings.data_roots, _own_exports(settings)]
        base = resolve_in_roots(raw, roots, what="export path")
        out = export_targets(base, run.params.names, with_conf=with_conf)
        shown = {name: raw for name in out}
    for name, folders in out.items():
        try:
            export_target(settings, project, str(folders[0]))
        except Forbidden as exc:
            where = f"export path {shown[name]!r}" + (f", sequence {name!r}" if len(out) > 1 else "")
            raise Forbidden(f"{where}: {exc.detail}") from None
    return out


def provenance(run: RunRow) -> dict[str, Any]:
    """Where the run's labels came from (:func:`leap_core.pipeline.provenance.run_provenance`)."""
    cfg = pipeline_config(run.params.pipeline, loc=("run", "params", "pipeline"))
    return run_provenance(run.run_dir, _schema(run), cfg, [(s.name, s.dataset) for s in run.params.sequences])


def export_info(settings: Settings, run: RunRow, project: ProjectRow) -> models.ExportInfo:
    """What the export dialog shows: the counts, the reasons for unlabeled points, where "write into
    the dataset" puts each sequence's files (its own ``predictions/``), and where the labels came from."""
    cov = coverage(run)
    prov = provenance(run)
    schema = _schema(run)
    by_reason = {"outside_view": cov.outside_view, "no_mask": cov.no_mask}
    try:
        folders = targets(settings, project, run, None)
        allowed = True
    except Forbidden:
        folders = {s.name: [s.dataset / PREDICTIONS] for s in run.params.sequences}
        allowed = False
    return models.ExportInfo(
        run_id=run.id,
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
                # A thing's moving points carry its moving id: they are the class's points too.
                points=cov.raw_counts.get(c.export_id, 0)
                + (0 if c.moving_id is None else cov.raw_counts.get(c.moving_id, 0)),
            )
            for c in schema.classes
        ],
        targets=[
            models.ExportTargetPublic(
                sequence=name,
                path=str(paths[0]),
                existing=len(existing_export_files(paths[0])) if allowed else 0,
            )
            for name, paths in folders.items()
        ],
        predictions_allowed=allowed,
        provenance=prov,
        provenance_lines=provenance_lines(prov),
    )


# ------------------------------------------------------------------------------------------- zip
def build_zip(run: RunRow, project: ProjectRow, include_confidence: bool) -> Path:
    """The run's stand-alone export zip (:meth:`RunLayout.export_zip`), built once and cached beside it:
    ``sequences/<name>/predictions/<frame>.label`` (+ ``confidences/<frame>.conf``) per sequence,
    ``label-map.yaml`` and ``summary.yaml`` (:func:`leap_core.export.write_export_zip`)."""
    exported = _exported(run)
    target = run.layout.export_zip(include_confidence)
    cov = coverage(run)
    with _lock:
        if target.is_file() and _current_zip(target):
            return target
        schema = _schema(run)
        cfg = pipeline_config(run.params.pipeline, loc=("run", "params", "pipeline"))
        summary = summary_yaml(
            project={"id": project.id, "name": project.name},
            run={"id": run.id, "number": run.number, "finished_at": run.finished_at},
            sequences=exported,
            schema=schema,
            pipeline=config_to_dict(cfg),
            counts=coverage_counts(cov),
            with_confidence=include_confidence,
            version=__version__,
            written_at=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            provenance=provenance(run),
        )
        lmap = label_map(
            schema, cov.raw_counts, name=f"{project.name} run {run.number}", sequences=run.params.names
        )
        extra = {LABEL_MAP_FILE: label_map_yaml(lmap), SUMMARY_FILE: summary}
        # The cached zip is the app's own file: rebuilding it (older layout) replaces it.
        write_export_zip(target, exported, extra, include_confidence=include_confidence, overwrite=True)
    return target


def invalidate(run_dir: Path) -> None:
    """Forget a run's cached zips and counts after its export files changed (the "apply corrections" job):
    under the lock, so a zip being built from the old files is removed once it is written."""
    layout = RunLayout(run_dir)
    with _lock:
        for path in (layout.export_zip(False), layout.export_zip(True)):
            path.unlink(missing_ok=True)
        for name in layout.names():
            layout.sequence(name).export_coverage.unlink(missing_ok=True)


def _current_zip(path: Path) -> bool:
    """A cached zip in today's layout (zips cached by older versions lack the label map: rebuilt)."""
    try:
        with zipfile.ZipFile(path) as zf:
            return LABEL_MAP_FILE in zf.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


# ------------------------------------------------------------------------------------- folder export
def write_export(
    settings: Settings, run: RunRow, project: ProjectRow, payload: models.ExportWrite
) -> models.ExportWritten:
    """Copy each sequence's ``.label`` (and ``.conf``) files into its target folder (:func:`targets`;
    each a fresh folder renamed into place); existing files only with ``payload.overwrite``.

    Raises:
        Forbidden: a target the policy refuses (:func:`export_target`).
        Conflict: a target holds files and ``overwrite`` is off, or holds files an export does not write
            (nothing is written).
    """
    exported = _exported(run)
    folders = targets(settings, project, run, payload.path, with_conf=payload.include_confidence)
    try:
        written = write_run_export(
            folders, exported, with_conf=payload.include_confidence, overwrite=payload.overwrite
        )
    except ExportConflict as exc:
        raise Conflict(str(exc)) from None
    except LeapError as exc:
        raise Forbidden(f"export: {exc}") from None
    shown = payload.path if payload.path is not None else str(folders[run.params.names[0]][0])
    return models.ExportWritten(
        run_id=run.id,
        path=shown,
        files=sum(written.files.values()),
        replaced=written.replaced,
    )


__all__ = [
    "REASONS",
    "build_zip",
    "coverage",
    "export_info",
    "export_target",
    "exports_dir",
    "invalidate",
    "provenance",
    "targets",
    "write_export",
]
