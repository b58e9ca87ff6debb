"""A project's LiDAR-only models in the app: what a train or label request may ask (checked here, at the
edge, each error naming its field), the public shapes of jobs and models, and a labeling's zip.

The jobs themselves run in :mod:`app.jobs.models`. A model and a labeling belong to one project: every
lookup takes the project id, so one project's requests never reach another's models or labels.
"""

from __future__ import annotations

import threading
from pathlib import Path

import sqlite_utils

from app import crud, models, services
from app.core.config import Settings
from app.core.errors import Conflict, InvalidField, NotFound
from app.jobs.models import ModelJobs, label_folder, model_file
from app.rows import ModelJobRow
from leap_core.errors import ConfigError, LeapError, ModelLoadError
from leap_core.lidar_model.card import read_card
from leap_core.lidar_model.config import LidarModelConfig, model_config_to_dict
from leap_core.run_layout import sequence_name_problem
from leap_core.schema import Schema

ZIP_NAME = "labels.zip"
_zip_lock = threading.Lock()


def checkpoint_every(steps: int) -> int:
    """Steps between saved training states: a tenth of the training (1..100), so a cancel or a restart
    loses at most that much."""
    return max(1, min(100, steps // 10))


def start_training(
    db: sqlite_utils.Database, jobs: ModelJobs, project_id: int, payload: models.ModelTrainCreate
) -> ModelJobRow:
    """Queue a ``train`` job on the project's latest finished run.

    Raises:
        Conflict: the project has no finished run.
        InvalidField: ``validation_sequence`` missing or not one of the run's sequences, or a sequence
            split that leaves nothing to train on.
    """
    project = crud.require_project(db, project_id)
    run = crud.last_finished_run(db, project.id)
    if run is None:
        raise Conflict(
            f"Project {project_id} has no finished run: run the pipeline first, then train on its labels"
        )
    names = run.params.names
    if payload.validation == "sequence":
        if payload.validation_sequence not in names:
            raise InvalidField(
                ("body", "validation_sequence"),
                f"give one of run {run.number}'s sequences ({', '.join(names)}) to hold apart for validation",
            )
        if len(names) < 2:
            raise InvalidField(
                ("body", "validation"),
                f"run {run.number} labeled one sequence: hold frame blocks apart (validation 'block')",
            )
    try:
        cfg = LidarModelConfig(
            steps=payload.steps,
            points_per_scan=payload.points_per_scan,
            val_block=payload.val_block if payload.validation == "block" else 0,
            val_every=payload.val_every,
            seed=payload.seed,
            checkpoint_every=checkpoint_every(payload.steps),
        )
    except ConfigError as exc:
        raise InvalidField(("body", *exc.field), str(exc)) from None
    params = {
        "run_id": run.id,
        "run_number": run.number,
        "settings": model_config_to_dict(cfg),
        "validation": {"by": payload.validation, "sequence": payload.validation_sequence},
    }
    job = crud.create_model_job(db, project_id=project.id, kind="train", name=payload.name, params=params)
    jobs.submit(job)
    return job


def start_labeling(
    db: sqlite_utils.Database,
    settings: Settings,
    jobs: ModelJobs,
    project_id: int,
    model_id: int,
    payload: models.ModelLabelCreate,
) -> ModelJobRow:
    """Queue a ``label`` job: the project's sequence ``payload.sequence``, or the sequence folder
    ``payload.dataset`` inside a data root (checked as a project's dataset is), with its model ``model_id``.

    Raises:
        NotFound: no such model in this project.
        Conflict: the model's training has not finished.
        InvalidField: ``sequence`` is not one of the project's sequences, or ``dataset`` no sequence folder.
        Forbidden: ``dataset`` outside the data roots (or linking out of them).
    """
    project = crud.require_project(db, project_id)
    trained = crud.require_model_job(db, model_id, project.id)
    if trained.kind != "train":
        raise NotFound(f"Model {model_id} not found in project {project_id}")
    if trained.status != "done" or not model_file(settings, project.id, model_id).is_file():
        raise Conflict(f"Model {model_id} is {trained.status}; label with a finished model")
    if payload.dataset is not None:
        ref = models.DatasetRef(kind="folder", path=payload.dataset)
        _kind, folder = services.resolve_dataset(settings, ref, loc=("body", "dataset"))
        name = folder.name if sequence_name_problem(folder.name) is None else "00"
        dataset = str(folder)
    else:
        seq = project.sequence(payload.sequence or "")
        if seq is None:
            raise InvalidField(
                ("body", "sequence"),
                f"not a sequence of this project; give one of {', '.join(project.names)}",
            )
        name, dataset = seq.name, seq.dataset_path
    job = crud.create_model_job(
        db,
        project_id=project.id,
        kind="label",
        name=name,
        model_id=model_id,
        params={"dataset": dataset, "frames": None},
    )
    jobs.submit(job)
    return job


def job_public(job: ModelJobRow, jobs: ModelJobs) -> models.ModelJobPublic:
    done, total = jobs.progress(job)
    download = (
        f"/projects/{job.project_id}/model-jobs/{job.id}/labels.zip"
        if job.kind == "label" and job.status == "done"
        else None
    )
    return models.ModelJobPublic(
        id=job.id,
        project_id=job.project_id,
        kind=job.kind,
        status=job.status,
        name=job.name,
        model_id=job.model_id,
        done=done,
        total=total,
        error=job.error,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
        download=download,
    )


def list_models(db: sqlite_utils.Database, settings: Settings, project_id: int) -> models.ModelsPublic:
    """The project's trained models with their cards (read from ``m<J>.card.json``; no torch)."""
    crud.require_project(db, project_id)
    out = []
    for job in crud.list_model_jobs(db, project_id, statuses=("done",)):
        if job.kind != "train":
            continue
        try:
            card = read_card(model_file(settings, project_id, job.id))
        except ModelLoadError:
            continue  # its files were removed by hand: nothing to offer
        out.append(models.ModelPublic(id=job.id, name=job.name, card=card))
    return models.ModelsPublic(data=out, count=len(out))


def labels_zip(db: sqlite_utils.Database, settings: Settings, project_id: int, job_id: int) -> Path:
    """A finished labeling's zip (built once, kept in its folder): ``sequences/<name>/predictions/*.label``,
    ``label-map.yaml`` and ``model-card.json`` (the layout of ``leap predict --zip``).

    Raises:
        NotFound: no such labeling in this project; Conflict: it has not finished.
    """
    # The zip and label map are leap_core's export code, as a run's export; imported when asked for.
    import json  # noqa: PLC0415

    from leap_core.export import (  # noqa: PLC0415
        LABEL_MAP_FILE,
        label_map,
        label_map_yaml,
        run_export,
        write_export_zip,
    )

    job = crud.require_model_job(db, job_id, project_id)
    if job.kind != "label":
        raise NotFound(f"Model job {job_id} is a training; only labelings have labels to download")
    if job.status != "done":
        raise Conflict(f"Labeling {job_id} is {job.status}; only finished labelings have a download")
    folder = label_folder(settings, project_id, job_id)
    target = folder / ZIP_NAME
    with _zip_lock:
        if target.is_file():
            return target
        assert job.model_id is not None
        card = read_card(model_file(settings, project_id, job.model_id))
        schema = Schema.from_dict(card["schema"], source=f"model {job.model_id} card")
        try:
            exported = run_export(folder)
        except LeapError as exc:
            raise Conflict(f"Labeling {job_id}: {exc}") from None
        counts = {int(k): int(v) for k, v in job.params.get("raw_counts", {}).items()}
        lmap = label_map(
            schema, counts, name=f"{job.name} labeled by model {job.model_id}", sequences=[job.name]
        )
        extra = {LABEL_MAP_FILE: label_map_yaml(lmap), "model-card.json": json.dumps(card, indent=2)}
        write_export_zip(target, exported, extra, include_confidence=False, overwrite=True)
    return target


__all__ = ["checkpoint_every", "job_public", "labels_zip", "list_models", "start_labeling", "start_training"]
