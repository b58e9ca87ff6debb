"""Project, class and run operations behind the API routes (and the viewer): validation, confinement
to the data roots, schema edits, and the conversion of rows into public schemas.

Routes stay thin: they parse the request, call one function here or in :mod:`app.jobs`, and return.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import re
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import sqlite_utils

from app import crud, models
from app.advice import report_dict, setting_fix
from app.core.config import Settings
from app.core.db import default_sequence_name, transaction
from app.core.errors import Conflict, Forbidden, InvalidField, NotFound
from app.core.security import outside_roots, resolve_in_roots
from app.forms import FORM_FIELDS, form_values, overrides_from_form
from app.jobs.progress import ProgressTracker
from app.rows import DatasetKind, ProjectRow, RunRow, labeled_sequences
from leap_core.colors import distinct_color
from leap_core.config import PipelineConfig, config_from_dict, config_to_dict
from leap_core.datasets.raw_ids import raw_id_names, scan_raw_ids
from leap_core.datasets.rig import rig_entries
from leap_core.errors import LeapError, SchemaError
from leap_core.io_utils import remove_tree
from leap_core.labelers import LABELERS
from leap_core.paths import UnusablePath, real_path, real_path_or_none
from leap_core.pipeline import PAPER, SequenceMetrics
from leap_core.pipeline.object_corrections import (
    CorrectedTracks,
    ObjectCorrections,
    ObjectEdit,
    ObjectIdentity,
)
from leap_core.pipeline.preflight import check_dataset, dataset_stamp
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.presets import builtin_preset
from leap_core.runtime import Runtime
from leap_core.schema import MAX_CLASS_LIST_BYTES, ClassListError, Schema, class_list_yaml, read_class_list
from leap_core.synth.names import DEMO_EXTRA_RAW_IDS
from leap_core.types import UNLABELED


# -------------------------------------------------------------------------------------- pipeline config
def pipeline_config(
    overrides: Mapping[str, Any] | None,
    base: PipelineConfig | None = None,
    *,
    loc: tuple[str, ...] = ("body", "pipeline"),
) -> PipelineConfig:
    """The app's one way in for a pipeline config: a dict (API payload, a project row's stored form)
    parsed onto ``base`` (default ``PipelineConfig()``). Everything past this point passes the typed
    config; SQLite and run specs store :func:`~leap_core.config.config_to_dict` of it.

    Raises:
        InvalidField: ``loc`` + the field's path below ``pipeline``, e.g.
            ``[body, pipeline, fusion, voxel_size]``.
    """
    try:
        return config_from_dict(overrides, base)
    except LeapError as exc:
        raise InvalidField([*loc, *_below_pipeline(exc.field)], str(exc)) from None


def _below_pipeline(path: tuple[str, ...]) -> tuple[str, ...]:
    return path[1:] if path[:1] == ("pipeline",) else path


def project_config(project: ProjectRow) -> PipelineConfig:
    """A project row's pipeline config (stored as a dict)."""
    return pipeline_config(project.pipeline, loc=("project", "pipeline"))


# --------------------------------------------------------------------------------------------- datasets
SEQUENCE_ENTRIES = ("velodyne", "image_2", "labels", "calib.txt", "poses.txt", "times.txt", "gt2d")
"""What the pipeline reads inside a sequence folder; each must resolve inside a data root (and so must what
a camera rig adds: ``leap_core.datasets.rig.rig_entries``)."""


def _inside(path: Path, roots: list[Path]) -> bool:
    return any(path == root or path.is_relative_to(root) for root in roots)


def escaping_entry(folder: Path, roots: list[Path]) -> tuple[str, Path] | None:
    """(name, real target) of the first entry of the sequence ``folder`` (itself resolved inside a root)
    that is a symbolic link leading outside every data root, or None.

    Raises:
        UnusablePath: an entry is a link that cannot be followed (a loop); the message starts with its name.
    """
    for name in (*SEQUENCE_ENTRIES, *rig_entries(folder)):
        entry = folder / name
        if entry.is_symlink():
            try:
                target = real_path(entry)
            except UnusablePath as exc:
                raise UnusablePath(f"{name} {exc}") from None
            if not _inside(target, roots):
                return name, target
    return None


def resolve_dataset(
    settings: Settings, ref: models.DatasetRef, loc: tuple[str | int, ...] = ("body", "dataset", "path")
) -> tuple[DatasetKind, Path]:
    """(kind, absolute sequence folder) of a dataset reference (``loc``: the payload field naming it).

    Raises:
        Forbidden: a folder outside the data roots, or one whose ``velodyne/`` (or another entry the
            pipeline reads) is a link to a place outside them.
        InvalidField: a folder that is not a KITTI-layout sequence.
    """
    if ref.kind == "demo":
        return "demo", settings.demo_dataset
    assert ref.path is not None
    path = resolve_in_roots(ref.path, settings.data_roots, what="dataset path", loc=loc)
    if not path.is_dir():
        raise InvalidField(loc, f"dataset path {ref.path!r}: no such folder")
    if not (path / "velodyne").is_dir():
        raise InvalidField(
            loc,
            f"dataset path {ref.path!r}: not a KITTI sequence folder (it has no velodyne/ folder; "
            "pick a folder like .../sequences/00)",
        )
    refuse_escaping_entries(path, settings.data_roots, shown=ref.path, loc=loc)
    return "folder", path


def refuse_escaping_entries(
    folder: Path, roots: list[Path], *, shown: str, loc: tuple[str | int, ...] = ("body", "dataset", "path")
) -> None:
    """Refuse the sequence ``folder`` (resolved inside a root; ``shown``: the path as the user gave it) when
    an entry the pipeline reads is a link out of the data roots, or a link that cannot be followed.

    Raises:
        Forbidden: naming the entry and its target.
        InvalidField: at ``loc``, an entry that is a symlink loop.
    """
    try:
        escape = escaping_entry(folder, roots)
    except UnusablePath as exc:
        raise InvalidField(loc, f"dataset path {shown!r}: {exc}") from None
    if escape is not None:
        name, target = escape
        raise Forbidden(
            f"dataset path {shown!r}: {name} is a symlink to {str(target)!r}, which is outside "
            + outside_roots(roots)
        )


def dataset_public(
    kind: DatasetKind, path: str, check: models.DatasetCheck | None = None
) -> models.DatasetPublic:
    folder = Path(path)
    velodyne = folder / "velodyne"
    frames = sum(1 for p in velodyne.glob("*.bin")) if velodyne.is_dir() else None
    return models.DatasetPublic(
        kind=kind,
        path=str(folder),
        exists=velodyne.is_dir(),
        frames=frames,
        has_ground_truth=(folder / "labels").is_dir(),
        check=check,
    )


# ------------------------------------------------------------------------------------------ dataset check
_CHECK_CACHE_SIZE = 256
_check_cache: dict[tuple[Any, ...], models.DatasetCheck] = {}
_check_lock = threading.Lock()


def dataset_check(
    settings: Settings, path: Path, config: PipelineConfig | None = None, *, estimate_poses: bool = False
) -> models.DatasetCheck:
    """:func:`leap_core.pipeline.preflight.check_dataset` of a sequence folder, worded for the app (its
    options, never a command-line flag), with the server's models folder. Cached per folder state
    (:func:`~leap_core.pipeline.preflight.dataset_stamp`: the mtimes of the folder and the entries it reads)
    and per setting that changes the answer, so the dataset list and project pages stay fast."""
    key = (
        dataset_stamp(path),
        None
        if config is None
        else (
            config.labeler,
            tuple(spec.models(spec.config_of(config)) for spec in LABELERS.values()),
            config.consistency.enabled,
        ),
        str(settings.models_dir),
        estimate_poses,
    )
    with _check_lock:
        hit = _check_cache.get(key)
    if hit is not None:
        return hit
    report = check_dataset(
        path, config=config, runtime=Runtime(models_dir=settings.models_dir), estimate_poses=estimate_poses
    )
    public = models.DatasetCheck.model_validate(report_dict(report, "app"))
    with _check_lock:
        if len(_check_cache) >= _CHECK_CACHE_SIZE:
            _check_cache.pop(next(iter(_check_cache)))
        _check_cache[key] = public
    return public


def check_problem(check: models.DatasetCheck) -> str:
    """One line for a dataset the pipeline cannot run on: each blocker with its fix."""
    blockers = [f for f in check.findings if f.severity == "blocker"]
    parts = [f"{f.message} ({f.fix})" if f.fix else f.message for f in blockers]
    return f"the pipeline cannot run on this dataset: {'; '.join(parts)}"


def dataset_candidate(settings: Settings, raw: str) -> models.DatasetCandidate:
    """A typed sequence folder with its check, as :func:`find_datasets` lists one.

    Raises:
        Forbidden, InvalidField: as :func:`resolve_dataset` (at ``[query, path]``).
    """
    _, folder = resolve_dataset(settings, models.DatasetRef(kind="folder", path=raw), loc=("query", "path"))
    check = dataset_check(settings, folder)
    return models.DatasetCandidate(
        path=str(folder),
        frames=check.frames,
        has_images=(folder / "image_2").is_dir(),
        has_ground_truth=(folder / "labels").is_dir(),
        check=check,
    )


def find_datasets(settings: Settings, max_depth: int = 4, limit: int = 200) -> list[models.DatasetCandidate]:
    """KITTI-layout sequence folders (with ``velodyne/``) inside the data roots, for the create form (the
    demo street and the farm drone demo too, once generated, when the work folder lies inside a data
    root)."""
    found: list[models.DatasetCandidate] = []
    seen: set[Path] = set()
    work = real_path_or_none(settings.work_dir) or settings.work_dir

    roots = list(settings.data_roots)

    def listable(folder: Path) -> bool:
        try:
            return escaping_entry(folder, roots) is None
        except UnusablePath:
            return False

    def visit(folder: Path, depth: int) -> None:
        if len(found) >= limit or depth > max_depth:
            return
        try:
            children = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
        except OSError:
            return
        if (folder / "velodyne").is_dir():
            real = real_path_or_none(folder)
            # A listed folder must be one a project can be created on (resolve_dataset's rules).
            if real is not None and real not in seen and listable(folder):
                seen.add(real)
                check = dataset_check(settings, folder)
                found.append(
                    models.DatasetCandidate(
                        path=str(folder),
                        frames=check.frames,
                        has_images=(folder / "image_2").is_dir(),
                        has_ground_truth=(folder / "labels").is_dir(),
                        check=check,
                    )
                )
            return
        for child in children:
            real = real_path_or_none(child)
            if real is None:  # a link that cannot be followed (a loop) leads to no dataset
                continue
            # The app's own work folder holds runs and caches, not datasets to label (of it only the
            # generated demo street, work_dir/demo/sequences/00, is offered); a link leading out of the
            # data roots is not followed (the listing would show folders nobody may use). The farm drone
            # demo, work_dir/demo-agri/sequences/00, is offered the same way.
            if real == work:
                for demo in (settings.demo_dataset, settings.demo_agri_dataset):
                    visit(child / demo.relative_to(settings.work_dir).parts[0], depth + 2)
                continue
            if not _inside(real, roots):
                continue
            visit(child, depth + 1)

    for root in settings.data_roots:
        if root.is_dir():
            visit(root, 0)
    return found


# --------------------------------------------------------------------------------------------- projects
def create_project(
    db: sqlite_utils.Database, settings: Settings, payload: models.ProjectCreate
) -> ProjectRow:
    """A new project with the classes and the ``pipeline:`` section of the built-in preset
    ``payload.schema_name`` (or the classes of ``payload.class_list`` and the default pipeline), the
    payload's ``pipeline`` overrides applied on top, on one sequence (``payload.dataset``) or several
    (``payload.sequences``, each confined and checked like one)."""
    kind, sequences = _project_sequences(settings, payload)
    if payload.class_list is not None:
        schema = _schema_of(payload.class_list)
        config = pipeline_config(payload.pipeline)
    else:
        try:
            preset = builtin_preset(payload.schema_name)
        except LeapError as exc:
            raise InvalidField(["body", "schema_name"], str(exc)) from None
        schema = preset.schema
        config = pipeline_config(payload.pipeline, preset.pipeline)
    if kind == "folder":
        for name, path, loc in sequences:
            check = dataset_check(settings, path, config, estimate_poses=payload.estimate_poses)
            if check.verdict == "none":
                what = f"dataset path {str(path)!r}" + (f" (sequence {name!r})" if len(sequences) > 1 else "")
                raise InvalidField(loc, f"{what}: {check_problem(check)}")
    return crud.create_project(
        db,
        name=payload.name,
        dataset_kind=kind,
        sequences=[(name, str(path)) for name, path, _ in sequences],
        schema=schema.to_dict(),
        pipeline=config_to_dict(config),
        estimate_poses=payload.estimate_poses,
    )


def _schema_of(class_list: models.ClassListCreate) -> Schema:
    """The validated schema of a payload's class list (the cross-class rules: unique names, export ids,
    ground-truth ids and prompts)."""
    doc = {
        "name": class_list.name,
        "description": class_list.description,
        "classes": [c.model_dump() for c in class_list.classes],
    }
    try:
        return Schema.from_dict(doc, source="class_list")
    except SchemaError as exc:
        raise InvalidField(["body", "class_list", *_class_field(exc)], str(exc)) from None


def _class_field(exc: SchemaError) -> list[str | int]:
    """A schema error's place in a class list as an API location: ``["classes", 3, "moving_id"]`` (the
    entry's index as a number), or ``["classes"]`` for the list as a whole."""
    path = exc.field or ("classes",)
    return [int(x) if x.isdigit() else x for x in path]


def class_list_public(schema: Schema) -> models.ClassListPublic:
    """A class list as the API answers it; ready to send back as ``ProjectCreate.class_list``."""
    return models.ClassListPublic(
        name=schema.name,
        # A request body's strings may hold no line breaks (app.api.types), so the list must come back
        # without any to be sent on.
        description=" ".join(schema.description.split()),
        classes=[models.ClassSpecPublic(**c.to_dict()) for c in schema.classes],
        count=schema.num_classes,
    )


def read_class_file(data: bytes) -> models.ClassListPublic:
    """An uploaded class-list file (the ``classes:`` part of a preset), validated.

    Raises:
        InvalidField: ``[body, <field in the file>]``, the message naming that field for people
            (``classes[3].prompts: must list at least one prompt``).
    """
    if len(data) > MAX_CLASS_LIST_BYTES:
        raise InvalidField(["body"], f"the file is larger than {MAX_CLASS_LIST_BYTES // 1024} KiB")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise InvalidField(["body"], "the file is not UTF-8 text (a YAML class list is)") from None
    try:
        schema = read_class_list(text)
    except ClassListError as exc:
        raise InvalidField(["body", *([exc.where] if exc.where else [])], str(exc)) from None
    return class_list_public(schema)


def _project_sequences(
    settings: Settings, payload: models.ProjectCreate
) -> tuple[DatasetKind, list[tuple[str, Path, tuple[str | int, ...]]]]:
    """(kind, [(name, resolved folder, payload field)]) of a new project's sequences.

    Raises:
        InvalidField: neither or both of ``dataset`` and ``sequences``; a folder that is not a sequence; a
            name that is not given and cannot come from the folder; two sequences with one name or one
            folder.
        Forbidden: a folder outside the data roots (:func:`resolve_dataset`).
    """
    if (payload.dataset is None) == (payload.sequences is None):
        field = "sequences" if payload.dataset is not None else "dataset"
        raise InvalidField(
            ["body", field],
            "give either dataset (one sequence folder, or the demo) or sequences (several folders), not both"
            if payload.dataset is not None
            else "dataset is required (or sequences, for several folders)",
        )
    if payload.dataset is not None:
        kind, path = resolve_dataset(settings, payload.dataset)
        return kind, [(default_sequence_name(str(path)), path, ("body", "dataset", "path"))]
    assert payload.sequences is not None
    out: list[tuple[str, Path, tuple[str | int, ...]]] = []
    names: dict[str, int] = {}
    folders: dict[Path, int] = {}
    for i, ref in enumerate(payload.sequences):
        loc: tuple[str | int, ...] = ("body", "sequences", i, "path")
        _, path = resolve_dataset(settings, models.DatasetRef(kind="folder", path=ref.path), loc)
        name = ref.name if ref.name is not None else path.name
        if not re.match(models.SEQUENCE_NAME_PATTERN, name):
            raise InvalidField(
                ("body", "sequences", i, "name"),
                f"folder name {name!r} cannot name a sequence (letters, digits, '_', '.', '-'; first a "
                "letter or digit); give a name",
            )
        if name in names:
            raise InvalidField(
                ("body", "sequences", i, "name"),
                f"sequence name {name!r} is taken by sequences[{names[name]}]; give each sequence its "
                "own name",
            )
        real = path  # resolved by resolve_dataset
        if real in folders:
            raise InvalidField(loc, f"dataset path {ref.path!r} is sequences[{folders[real]}] again")
        names[name], folders[real] = i, i
        out.append((name, path, loc))
    return "folder", out


def validate_form(form: Mapping[str, Any], base: PipelineConfig) -> PipelineConfig:
    """Apply the UI's flat parameters onto ``base``; errors name the flat field (``[body, form, k]``)."""
    unknown = [k for k in form if k not in FORM_FIELDS]
    if unknown:
        raise InvalidField(
            ["body", "form", unknown[0]],
            f"unknown parameter {unknown[0]!r} (known: {', '.join(FORM_FIELDS)})",
        )
    try:
        return config_from_dict(overrides_from_form(form), base)
    except LeapError as exc:
        dotted = ".".join(_below_pipeline(exc.field))
        flat = next((name for name, f in FORM_FIELDS.items() if f.path == dotted), None)
        loc = ["body", "form", flat] if flat else ["body", "pipeline", *_below_pipeline(exc.field)]
        raise InvalidField(loc, str(exc)) from None


def update_project(db: sqlite_utils.Database, project_id: int, payload: models.ProjectUpdate) -> ProjectRow:
    project = crud.require_project(db, project_id)
    config = None
    if payload.pipeline is not None or payload.form is not None:
        config = project_config(project)
        if payload.pipeline is not None:
            config = pipeline_config(payload.pipeline, config)
        if payload.form is not None:
            config = validate_form(payload.form, config)
    pipeline = None if config is None else config_to_dict(config)
    return crud.update_project(
        db, project_id, name=payload.name, pipeline=pipeline, estimate_poses=payload.estimate_poses
    )


def project_folders(settings: Settings, project_id: int) -> list[Path]:
    """The work folder's folders of one project: its runs (``runs/p<P>``) and its stage caches
    (``cache/p<P>``, the 2D labels its runs and run previews computed), its LiDAR-only models and their
    labelings (``lidar-models/p<P>``) and its object corrections' identities (``objects/p<P>``)."""
    return [
        settings.runs_dir / f"p{project_id}",
        settings.cache_dir / f"p{project_id}",
        settings.work_dir / "lidar-models" / f"p{project_id}",
        settings.work_dir / OBJECTS_FOLDER / f"p{project_id}",
    ]


OBJECTS_FOLDER = "objects"
"""Work-folder folder of the object corrections' identity files
(``objects/p<P>/r<R>-<sequence>-t<T>.npz``)."""


def object_corrections(
    corrections: Sequence[crud.Correction], names: list[str], work_dir: Path
) -> ObjectCorrections:
    """The object-scope corrections among ``corrections`` (in the order they were made) as a run with the
    classes ``names`` applies them, each identity read from its file under ``work_dir``; a relabel to a
    class the run does not have is left out.

    Raises:
        DatasetError: an identity file is missing or unreadable (naming it).
    """
    edits = []
    for c in corrections:
        if c.scope != "object" or not c.identity:
            continue
        identity = ObjectIdentity.load(work_dir / c.identity)
        if c.action == "merge" and c.other_identity:
            other = ObjectIdentity.load(work_dir / c.other_identity)
            edits.append(ObjectEdit(c.id, "merge", identity, other=other))
        elif c.action == "split" and c.split_frame:
            edits.append(ObjectEdit(c.id, "split", identity, frame_id=c.split_frame))
        elif c.action == "relabel" and (c.class_name == "" or c.class_name in names):
            index = UNLABELED if c.class_name == "" else names.index(c.class_name)
            edits.append(ObjectEdit(c.id, "relabel", identity, class_idx=index))
    return ObjectCorrections(tuple(edits))


def object_ref(  # noqa: PLR0913  the run's object, and what a merge or a split adds
    db: sqlite_utils.Database,
    settings: Settings,
    project_id: int,
    run_id: int,
    sequence: str,
    track_id: int,
    *,
    action: crud.ObjectAction = "relabel",
    other_track_id: int | None = None,
    frame: str | None = None,
) -> crud.ObjectRef:
    """Keep the object ``track_id`` of run ``run_id``'s sequence ``sequence`` for an object-scope
    correction, as the run's export shows it now (its tracks with the sequence's active object corrections
    on top, :class:`CorrectedTracks`: a merged object is both parts, a split-off part its own id): its point
    rows per scan go into a file of the work folder (written atomically, named by its content: the same
    points always get the same file). A merge keeps ``other_track_id`` the same way; a split checks that
    ``frame`` cuts the object (it has points before that scan and from it on).

    Raises:
        InvalidField: the run is not a finished run of the project that labeled ``sequence``, it has no
            objects (``tracks.npz``), it has no object ``track_id`` (or ``other_track_id``) with points, a
            merge names one object twice, a split's ``frame`` does not cut the object (each naming its
            field).
    """
    run = crud.get_run(db, run_id)
    if run is None or run.project_id != project_id:
        raise InvalidField(("body", "run_id"), f"project {project_id} has no run {run_id}")
    if run.status != "done":
        raise InvalidField(
            ("body", "run_id"), f"run {run.number} is {run.status}: objects come from a finished run"
        )
    if sequence not in [s.name for s in run.params.sequences]:
        raise InvalidField(("body", "sequence"), f"run {run.number} did not label sequence {sequence!r}")
    layout = run.sequence_layout(sequence)
    if not layout.tracks.is_file():
        raise InvalidField(
            ("body", "run_id"),
            f"run {run.number} has no objects (no tracks.npz in sequence {sequence}): "
            "turn tracking on and re-run",
        )
    schema = Schema.from_dict(run.params.schema, source=f"run {run.number} schema")
    active = crud.list_corrections(db, project_id, active_only=True, sequence=sequence)
    objects = CorrectedTracks.of(
        SequenceTracks.load(layout.tracks),
        object_corrections(active, schema.names, settings.work_dir),
        schema.things(),
    )

    def kept(object_id: int, field: str) -> str:
        if not 1 <= object_id <= objects.count:
            raise InvalidField(
                ("body", field), f"run {run.number} has objects 1..{objects.count}, not {object_id}"
            )
        identity = objects.identity(object_id)
        if identity.points == 0:
            # A static track whose points all keep a stuff class of the map, or an object merged into another.
            raise InvalidField(
                ("body", field), f"object {object_id} of run {run.number} has no points in its export"
            )
        digest = hashlib.sha256(identity.rows.tobytes() + identity.ptr.tobytes())
        digest.update("/".join(identity.frame_ids).encode())
        rel = (
            Path(OBJECTS_FOLDER)
            / f"p{project_id}"
            / f"r{run_id}-{sequence}-t{object_id}-{digest.hexdigest()[:16]}.npz"
        )
        identity.save(settings.work_dir / rel)
        return rel.as_posix()

    identity = kept(track_id, "track_id")
    other = None
    if action == "merge":
        if other_track_id is None or other_track_id == track_id:
            raise InvalidField(("body", "other_track_id"), f"a merge needs another object than {track_id}")
        other = kept(other_track_id, "other_track_id")
    if action == "split":
        scans = objects.object_scans(track_id)
        if frame is None or frame not in scans or frame == scans[0]:
            raise InvalidField(
                ("body", "frame"),
                f"object {track_id} of run {run.number} is in scans {scans[0]}..{scans[-1]}: a split names "
                f"one of them after its first, not {frame!r}",
            )
    return crud.ObjectRef(
        run_id=run_id,
        track_id=track_id,
        identity=identity,
        action=action,
        other_track_id=other_track_id if action == "merge" else None,
        other_identity=other,
        split_frame=frame if action == "split" else None,
    )


def delete_project(db: sqlite_utils.Database, settings: Settings, project_id: int) -> list[Path]:
    """Delete the project, its runs and corrections, and its folders under the work dir
    (:func:`project_folders`); returns those folders (the caller makes sure no background job writes
    into them again: :meth:`app.jobs.apply.CorrectionApplier.forget`).

    The dataset and anything exported into its ``predictions/`` folder are the user's and stay.
    """
    crud.require_project(db, project_id)
    active = crud.active_run(db, project_id)
    if active is not None:
        raise Conflict(
            f"Project {project_id} has run {active.number} (id {active.id}) {active.status}; cancel it first"
        )
    busy = crud.list_model_jobs(db, project_id, statuses=("queued", "running"))
    if busy:
        raise Conflict(f"Project {project_id} has model job {busy[0].id} {busy[0].status}; cancel it first")
    crud.delete_project(db, project_id)
    # After the rows are gone: a crash in between leaves orphan files, never rows pointing at nothing.
    folders = project_folders(settings, project_id)
    for folder in folders:
        remove_tree(folder)
    return folders


# -------------------------------------------------------------------------------------------- sequences
def _refuse_sequence_edit(db: sqlite_utils.Database, project: ProjectRow) -> None:
    """Sequence edits need a project on folders and no queued or running run (whose snapshot and run
    folder were made from the sequences as they were).

    Raises:
        Conflict: a run of the project is queued or running, or the project labels the built-in demo.
    """
    active = crud.active_run(db, project.id)
    if active is not None:
        raise Conflict(
            f"Project {project.id} has run {active.number} (id {active.id}) {active.status}; its sequences "
            "can change once it ends (or is cancelled)"
        )
    if project.dataset_kind == "demo":
        raise Conflict(
            f"Project {project.id} labels the built-in demo street, which is generated for it; create a "
            "project on sequence folders to label several"
        )


def add_sequence(
    db: sqlite_utils.Database, settings: Settings, project_id: int, payload: models.SequenceRef
) -> ProjectRow:
    """Append a sequence folder to an existing project, confined and checked as at creation
    (:func:`resolve_dataset`, the dataset check for the project's settings). A name not given is the
    folder's. The name of a removed sequence brings that sequence back only on its own folder.

    Raises:
        Conflict: see :func:`_refuse_sequence_edit`; the project already has ``MAX_SEQUENCES``.
        Forbidden: a folder outside the data roots or linking out of them.
        InvalidField: at ``[body, path]`` (not a sequence folder, one the pipeline cannot run on, one the
            project already has) or ``[body, name]`` (taken, or a folder name that cannot name one).
    """
    loc: tuple[str, ...] = ("body", "path")
    _, path = resolve_dataset(settings, models.DatasetRef(kind="folder", path=payload.path), loc)
    name = payload.name if payload.name is not None else path.name
    if not re.match(models.SEQUENCE_NAME_PATTERN, name):
        raise InvalidField(
            ("body", "name"),
            f"folder name {name!r} cannot name a sequence (letters, digits, '_', '.', '-'; first a letter or "
            "digit); give a name",
        )
    project = crud.require_project(db, project_id)
    # Checked before the write transaction, which a large folder's check would hold for long.
    check = dataset_check(settings, path, project_config(project), estimate_poses=project.estimate_poses)
    with transaction(db):
        project = crud.require_project(db, project_id)
        _refuse_sequence_edit(db, project)
        sequences = project.sequences
        if len(sequences) >= models.MAX_SEQUENCES:
            raise Conflict(f"Project {project_id} has {len(sequences)} sequences, the most one project holds")
        for s in sequences:
            if s.name == name:
                raise InvalidField(
                    ("body", "name"),
                    f"sequence name {name!r} is taken in project "
                    f"{project_id}; give the new sequence its own name",
                )
            if real_path_or_none(s.dataset_path) == path:
                raise InvalidField(
                    loc,
                    f"dataset path {payload.path!r} is sequence {s.name!r} of project {project_id} already",
                )
        removed = crud.removed_sequence(db, project_id, name)
        if removed is not None and real_path_or_none(removed.dataset_path) != path:
            raise InvalidField(
                ("body", "name"),
                f"sequence name {name!r} belonged to the removed sequence on {removed.dataset_path!r}, "
                "whose corrections and review marks are kept under that name; give this folder another name",
            )
        if check.verdict == "none":
            raise InvalidField(loc, f"dataset path {str(path)!r}: {check_problem(check)}")
        crud.add_sequence(db, project_id, name=name, dataset_path=str(path))
    return crud.require_project(db, project_id)


def remove_sequence(db: sqlite_utils.Database, project_id: int, name: str) -> ProjectRow:
    """Take a sequence out of a project. Nothing is deleted: the dataset, every run (their folders hold
    the removed sequence's results) and the sequence's corrections and review marks stay, the latter to
    come back if the same folder is added again under this name.

    Raises:
        NotFound: the project has no sequence ``name``.
        Conflict: see :func:`_refuse_sequence_edit`; ``name`` is the project's last sequence.
    """
    with transaction(db):
        project = crud.require_project(db, project_id)
        names = project.names
        if name not in names:
            raise NotFound(f"Project {project_id} has no sequence {name!r} (it has {', '.join(names)})")
        _refuse_sequence_edit(db, project)
        if len(names) == 1:
            raise Conflict(
                f"Sequence {name!r} is project {project_id}'s last; a project keeps one sequence "
                "at least (delete the project instead)"
            )
        crud.remove_sequence(db, project_id, name)
    return crud.require_project(db, project_id)


def _brief(run: RunRow | None) -> models.RunBrief | None:
    if run is None:
        return None
    metrics = overall(run)
    row = miou = None
    if metrics is not None and "camera" in metrics.tables:
        rows = metrics.tables["camera"]
        row = (metrics.rows or list(rows))[-1]
        miou = rows[row].miou if row in rows else None
    return models.RunBrief(
        id=run.id,
        number=run.number,
        status=run.status,
        created_at=run.created_at,
        finished_at=run.finished_at,
        miou=miou,
        miou_row=row,
    )


def project_check(settings: Settings, project: ProjectRow, path: str) -> models.DatasetCheck | None:
    """The dataset check of one of the project's sequence folders (``path``) for the project's own settings
    (None while the demo street is not generated)."""
    folder = Path(path)
    if project.dataset_kind == "demo" and not (folder / "velodyne").is_dir():
        return None
    return dataset_check(settings, folder, project_config(project), estimate_poses=project.estimate_poses)


def stale_results(project: ProjectRow, runs: list[RunRow]) -> models.StaleResults | None:
    """Whether the project's latest finished run (``runs``: newest first) labeled other sequences than
    the project has now (:func:`app.rows.labeled_sequences`), and how; None when it labeled exactly them,
    or when there is no finished run."""
    run = next((r for r in runs if r.status == "done"), None)
    if run is None:
        return None
    covered = [s.name for s in labeled_sequences(run, project.sequences)]
    added = [s.name for s in project.sequences if s.name not in covered]
    removed = [s.name for s in run.params.sequences if s.name not in covered]
    if not added and not removed:
        return None
    parts = ([f"added {', '.join(added)}"] if added else []) + (
        [f"removed {', '.join(removed)}"] if removed else []
    )
    message = (
        f"The sequences changed since run {run.number} ({'; '.join(parts)}): its results describe the "
        "sequences it labeled, not the project's now. Run the pipeline to label the current sequences."
    )
    return models.StaleResults(
        run_id=run.id, run_number=run.number, added=added, removed=removed, message=message
    )


def project_public(
    db: sqlite_utils.Database, project: ProjectRow, settings: Settings | None = None
) -> models.ProjectPublic:
    """A project row as the API shows it; with ``settings``, its datasets carry the dataset check."""
    runs = crud.list_runs(db, project.id)
    # One check per sequence folder (each is cached per folder state); the project's own is the first's.
    checks = [
        None if settings is None else project_check(settings, project, s.dataset_path)
        for s in project.sequences
    ]
    return models.ProjectPublic(
        id=project.id,
        name=project.name,
        dataset=dataset_public(project.dataset_kind, project.dataset_path, checks[0]),
        sequences=[
            models.SequencePublic(
                name=s.name, dataset=dataset_public(project.dataset_kind, s.dataset_path, check)
            )
            for s, check in zip(project.sequences, checks, strict=True)
        ],
        schema_name=project.schema["name"],
        num_classes=len(project.schema["classes"]),
        pipeline=project.pipeline,
        form=form_values(project_config(project)),
        estimate_poses=project.estimate_poses,
        is_demo=project.is_demo,
        created_at=project.created_at,
        updated_at=project.updated_at,
        active_run=_brief(next((r for r in runs if r.status in models.ACTIVE_STATUSES), None)),
        last_run=_brief(runs[0] if runs else None),
        runs_count=len(runs),
        stale=stale_results(project, runs),
    )


# ---------------------------------------------------------------------------------------------- classes
def _hex(color: list[int]) -> str:
    return "#" + "".join(f"{int(c):02x}" for c in color)


def next_color(classes: list[dict[str, Any]]) -> list[int]:
    """The colour a new class gets when it names none (:func:`leap_core.colors.distinct_color`)."""
    return list(distinct_color([c["color"] for c in classes]))


def classes_public(project: ProjectRow) -> models.ClassesPublic:
    # Through the schema, so a class stored before classes said thing / moving_id shows its defaults.
    schema = Schema.from_dict(project.schema, source=f"project {project.id}")
    classes = [c.to_dict() for c in schema.classes]
    data = [models.ClassPublic(index=i, hex=_hex(c["color"]), **c) for i, c in enumerate(classes)]
    return models.ClassesPublic(data=data, count=len(data), next_color=_hex(next_color(classes)))


def class_file(project: ProjectRow) -> str:
    """The project's classes as a class-list file: what ``POST /class-lists`` reads back into the same
    classes (to start another project with them, or keep them beside the data)."""
    return class_list_yaml(Schema.from_dict(project.schema, source=f"project {project.id}"))


def _class_position(classes: list[dict[str, Any]], name: str, project_id: int) -> int:
    for i, c in enumerate(classes):
        if c["name"] == name:
            return i
    raise NotFound(f"Class {name!r} not found in project {project_id}")


def save_classes(
    db: sqlite_utils.Database,
    project_id: int,
    classes: list[dict[str, Any]],
    *,
    loc: tuple[str | int, ...] = ("body",),
) -> ProjectRow:
    """Validate the whole class list with the pipeline's schema rules and store it.

    Raises:
        InvalidField: naming the class entry and the problem (duplicate name, prompt in two classes, ...).
    """
    project = crud.require_project(db, project_id)
    doc = {**project.schema, "classes": classes}
    try:
        schema = Schema.from_dict(doc, source="classes")
    except SchemaError as exc:
        raise InvalidField([*loc, *_class_field(exc)], str(exc)) from None
    return crud.update_project(db, project_id, schema=schema.to_dict())


def add_class(db: sqlite_utils.Database, project_id: int, payload: models.ClassCreate) -> ProjectRow:
    project = crud.require_project(db, project_id)
    classes = list(project.schema["classes"])
    entry = payload.model_dump(exclude={"position"})
    if entry["color"] is None:
        entry["color"] = next_color(classes)
    position = len(classes) if payload.position is None else min(payload.position, len(classes))
    classes.insert(position, entry)
    return save_classes(db, project_id, classes)


def update_class(
    db: sqlite_utils.Database, project_id: int, name: str, payload: models.ClassUpdate
) -> ProjectRow:
    project = crud.require_project(db, project_id)
    classes = [dict(c) for c in project.schema["classes"]]
    i = _class_position(classes, name, project_id)
    changes = payload.model_dump(exclude_unset=True, exclude={"position"})
    for key, value in changes.items():
        if value is None and key != "moving_id":  # a null moving id removes it
            raise InvalidField(["body", key], f"{key} may not be null")
        classes[i][key] = value
    if payload.position is not None:
        entry = classes.pop(i)
        classes.insert(min(payload.position, len(classes)), entry)
    return save_classes(db, project_id, classes)


def delete_class(db: sqlite_utils.Database, project_id: int, name: str) -> ProjectRow:
    project = crud.require_project(db, project_id)
    classes = list(project.schema["classes"])
    i = _class_position(classes, name, project_id)
    if len(classes) == 1:
        raise Conflict("A project needs at least one class; add another before removing this one")
    del classes[i]
    return save_classes(db, project_id, classes)


def replace_classes(db: sqlite_utils.Database, project_id: int, payload: models.SchemaReplace) -> ProjectRow:
    return save_classes(db, project_id, [c.model_dump() for c in payload.classes])


def set_prompts(db: sqlite_utils.Database, project_id: int, name: str, prompts: list[str]) -> ProjectRow:
    project = crud.require_project(db, project_id)
    classes = [dict(c) for c in project.schema["classes"]]
    i = _class_position(classes, name, project_id)
    classes[i]["prompts"] = prompts
    return save_classes(db, project_id, classes)


def add_prompt(db: sqlite_utils.Database, project_id: int, name: str, prompt: str) -> ProjectRow:
    project = crud.require_project(db, project_id)
    classes = project.schema["classes"]
    i = _class_position(classes, name, project_id)
    return set_prompts(db, project_id, name, [*classes[i]["prompts"], prompt.strip()])


def delete_prompt(db: sqlite_utils.Database, project_id: int, name: str, index: int) -> ProjectRow:
    project = crud.require_project(db, project_id)
    classes = project.schema["classes"]
    prompts = list(classes[_class_position(classes, name, project_id)]["prompts"])
    if not 0 <= index < len(prompts):
        raise NotFound(f"Prompt {index} not found in class {name!r}")
    if len(prompts) == 1:
        raise Conflict(f"Class {name!r} needs at least one prompt")
    del prompts[index]
    return set_prompts(db, project_id, name, prompts)


# ------------------------------------------------------------------------------------------------- runs
def run_progress(run: RunRow, live: dict[str, Any] | None) -> models.RunProgress:
    if live is not None and live["status"] == run.status:
        return models.RunProgress(**live)
    tracker = ProgressTracker.from_record(
        run.id,
        run.project_id,
        run.status,
        run.stages,
        run.params.stages,
        error=run.error,
        stamp=run.finished_at or run.started_at or run.created_at,
    )
    return models.RunProgress(**tracker.snapshot())


def metrics_summary(metrics: SequenceMetrics | None) -> dict[str, Any] | None:
    """{protocol: {row: mIoU}} for the run history table."""
    if metrics is None:
        return None
    return {protocol: {row: s.miou for row, s in rows.items()} for protocol, rows in metrics.tables.items()}


def metrics_public(metrics: SequenceMetrics | None) -> dict[str, Any] | None:
    """What the UI shows of a sequence's metrics or a run's ``overall`` (the confusion matrices dropped).

    Returns:
        ``{"protocols": {protocol: {row: {miou, category_miou, labeled_share, iou: {class: v}, ...}}},
        "descriptions": {protocol: text}, "rows": [...], "coverage_ratio": {row: x}, ...}``, or None
        without metrics or without any protocol's table. A protocol over merged classes (the paper's) has
        its classes in ``views`` ({protocol: {class_names, categories, merge: {class: [schema classes]}}});
        ``notes`` ({protocol: text}) says why a protocol is absent; ``objects`` the object scores
        (``camera`` / ``all`` → PQ, SQ, RQ, each ``_things`` / ``_stuff``; ``motion`` → ``mos_iou``,
        ``s_assoc``, ``moving_points``; ``moving_right_class``), null when the run tracked no objects.
    """
    if metrics is None or not metrics.tables:
        return None
    protocols = {
        protocol: {row: {k: v for k, v in s.to_dict().items() if k != "confusion"} for row, s in rows.items()}
        for protocol, rows in metrics.tables.items()
    }
    return {
        "protocols": protocols,
        "descriptions": dict(metrics.protocols),
        "rows": list(metrics.rows),
        "coverage_ratio": dict(metrics.coverage_ratio),
        "labeled_points": dict(metrics.labeled_points),
        "labeled_share_all_points": metrics.all_points_labeled_share(),
        "n_points": metrics.n_points,
        "n_points_in_view": metrics.n_points_in_view,
        "labeler": metrics.labeler,
        "views": (
            {PAPER: metrics.paper_view.to_dict()}
            if PAPER in protocols and metrics.paper_view is not None
            else {}
        ),
        "notes": dict(metrics.protocol_notes),
        "objects": None if metrics.objects is None else {k: dict(v) for k, v in metrics.objects.items()},
    }


def overall(run: RunRow) -> SequenceMetrics | None:
    """The run's own metrics: its sequences' confusion matrices summed."""
    return None if run.metrics is None else run.metrics.overall


def metrics_sequences(run: RunRow) -> list[str]:
    """The run's sequences with metrics of their own, in run order (the stored JSON's keys are sorted)."""
    if run.metrics is None:
        return []
    return [name for name in run.params.names if run.metrics.sequence(name) is not None]


def sequence_metrics(run: RunRow, sequence: str | None) -> dict[str, Any] | None:
    """The metrics table (:func:`metrics_public`) of one sequence of the run, or, with ``sequence`` None,
    the run's own (the sequences' confusion matrices summed).

    Raises:
        InvalidField: ``sequence`` is not one of the run's sequences (``[query, sequence]``).
    """
    if sequence is None:
        own = overall(run)
        names = metrics_sequences(run)
        if own is not None and own.objects is None and len(names) == 1 and run.metrics is not None:
            # Object scores are a sequence's (tracks do not span sequences): a run of one sequence shows
            # them as its own, a run of several per sequence.
            one = run.metrics.sequence(names[0])
            own = dataclasses.replace(own, objects=None if one is None else one.objects)
        return metrics_public(own)
    names = run.params.names
    if sequence not in names:
        raise InvalidField(
            ["query", "sequence"], f"run {run.id} has no sequence {sequence!r} (it has {', '.join(names)})"
        )
    return metrics_public(None if run.metrics is None else run.metrics.sequence(sequence))


def run_public(run: RunRow, live: dict[str, Any] | None) -> models.RunPublic:
    return models.RunPublic(
        id=run.id,
        project_id=run.project_id,
        number=run.number,
        status=run.status,
        created_at=run.created_at,
        started_at=run.started_at,
        finished_at=run.finished_at,
        attempts=run.attempts,
        error=run.error,
        params=run.params.public(),
        progress=run_progress(run, live),
        has_metrics=run.metrics is not None,
        has_export=run.status == "done"
        and all(run.sequence_layout(name).export_dir.is_dir() for name in run.params.names),
        resumable=run.status in models.RESUMABLE_STATUSES,
        fix_setting=setting_fix(run.error) if run.status == "failed" else None,
        summary=metrics_summary(overall(run)),
        note=run.note,
    )


# ------------------------------------------------------------------------------------ ground-truth ids
_RAW_ID_CACHE: dict[tuple[str, int, int], tuple[dict[int, int], int, int]] = {}
_RAW_ID_LOCK = threading.Lock()


def _labels_signature(labels: Path) -> tuple[int, int]:
    """(newest mtime_ns, file count) of a labels folder: changes when a file is added, replaced or removed."""
    newest, count = labels.stat().st_mtime_ns, 0
    with os.scandir(labels) as it:
        for e in it:
            if e.name.endswith(".label"):
                count += 1
                newest = max(newest, e.stat().st_mtime_ns)
    return newest, count


def raw_ids_public(project: ProjectRow) -> models.RawIdsPublic:
    """The raw ids in the project dataset's labels with their names and the classes mapping them.

    The scan (:func:`leap_core.datasets.raw_ids.scan_raw_ids`, at most 200 evenly spaced files) is cached
    per labels folder until a file in it changes.
    """
    folder = Path(project.dataset_path)
    labels = folder / "labels"
    names = raw_id_names(DEMO_EXTRA_RAW_IDS)
    if not labels.is_dir():
        return models.RawIdsPublic(
            data=[],
            count=0,
            has_ground_truth=False,
            frames_read=0,
            frames_total=0,
            names={str(k): v for k, v in names.items()},
        )
    try:
        real = real_path(labels)
    except UnusablePath as exc:
        raise InvalidField(["dataset", "labels"], f"{labels} {exc}; fix or remove it") from None
    key = (str(real), *_labels_signature(labels))
    with _RAW_ID_LOCK:
        cached = _RAW_ID_CACHE.get(key)
    if cached is None:
        try:
            scan = scan_raw_ids(folder)
        except LeapError as exc:
            raise InvalidField(["dataset", "labels"], str(exc)) from None
        cached = (scan.counts, scan.frames_read, scan.frames_total)
        with _RAW_ID_LOCK:
            _RAW_ID_CACHE[key] = cached
    counts, read, total = cached
    users: dict[int, list[str]] = {}
    for c in project.schema["classes"]:
        for g in c.get("gt_ids", []):
            users.setdefault(int(g), []).append(c["name"])
    data = [
        models.RawIdPublic(id=i, name=names.get(i), points=n, classes=users.get(i, []))
        for i, n in sorted(counts.items())
    ]
    return models.RawIdsPublic(
        data=data,
        count=len(data),
        has_ground_truth=True,
        frames_read=read,
        frames_total=total,
        names={str(k): v for k, v in names.items()},
    )
