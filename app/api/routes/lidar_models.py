"""A project's LiDAR-only models: train one on the latest finished run's labels (a background job), list
the models with their cards, label a sequence with one (a background job), follow, cancel and resume the
jobs, and download a labeling's zip (rules and shapes in :mod:`app.lidar_models`)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path, Request, status
from fastapi.responses import FileResponse

from app import crud, lidar_models, models
from app.api.deps import DbDep, SettingsDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import MAX_INT, ProjectId
from app.jobs.models import ModelJobs

router = APIRouter(prefix="/projects/{project_id}", tags=["models"], responses={**NOT_FOUND, **CONFLICT})

ModelId = Annotated[int, Path(ge=1, le=MAX_INT, description="model id (the job that trained it)")]
JobId = Annotated[int, Path(ge=1, le=MAX_INT, description="model job id")]


async def get_model_jobs(request: Request) -> ModelJobs:
    jobs: ModelJobs = request.app.state.model_jobs
    return jobs


ModelJobsDep = Annotated[ModelJobs, Depends(get_model_jobs)]


@router.post("/models", response_model=models.ModelJobPublic, status_code=status.HTTP_202_ACCEPTED)
def train_model(
    project_id: ProjectId, payload: models.ModelTrainCreate, db: DbDep, jobs: ModelJobsDep
) -> models.ModelJobPublic:
    """Queue a training on the final labels (corrections applied) of the project's latest finished run."""
    return lidar_models.job_public(lidar_models.start_training(db, jobs, project_id, payload), jobs)


@router.get("/models", response_model=models.ModelsPublic)
def list_models(project_id: ProjectId, db: DbDep, settings: SettingsDep) -> models.ModelsPublic:
    """The project's trained models, each with its card."""
    return lidar_models.list_models(db, settings, project_id)


@router.post(
    "/models/{model_id}/label", response_model=models.ModelJobPublic, status_code=status.HTTP_202_ACCEPTED
)
def label_with_model(
    project_id: ProjectId,
    model_id: ModelId,
    payload: models.ModelLabelCreate,
    db: DbDep,
    settings: SettingsDep,
    jobs: ModelJobsDep,
) -> models.ModelJobPublic:
    """Queue a labeling of one of the project's sequences with one of its models (LiDAR only)."""
    job = lidar_models.start_labeling(db, settings, jobs, project_id, model_id, payload)
    return lidar_models.job_public(job, jobs)


@router.get("/model-jobs", response_model=models.ModelJobsPublic)
def list_model_jobs(project_id: ProjectId, db: DbDep, jobs: ModelJobsDep) -> models.ModelJobsPublic:
    """The project's trainings and labelings, newest first, with live progress."""
    crud.require_project(db, project_id)
    data = [lidar_models.job_public(j, jobs) for j in crud.list_model_jobs(db, project_id)]
    return models.ModelJobsPublic(data=data, count=len(data))


@router.post("/model-jobs/{job_id}/cancel", response_model=models.ModelJobPublic)
def cancel_model_job(
    project_id: ProjectId, job_id: JobId, db: DbDep, jobs: ModelJobsDep
) -> models.ModelJobPublic:
    """Cancel a queued job, or a working one at its next step (a training keeps its last saved state)."""
    crud.require_model_job(db, job_id, project_id)
    jobs.cancel(job_id)
    return lidar_models.job_public(crud.require_model_job(db, job_id), jobs)


@router.post("/model-jobs/{job_id}/resume", response_model=models.ModelJobPublic)
def resume_model_job(
    project_id: ProjectId, job_id: JobId, db: DbDep, jobs: ModelJobsDep
) -> models.ModelJobPublic:
    """Queue a cancelled, failed or interrupted job again (a training continues from its saved state)."""
    crud.require_model_job(db, job_id, project_id)
    jobs.resume(job_id)
    return lidar_models.job_public(crud.require_model_job(db, job_id), jobs)


@router.get(
    "/model-jobs/{job_id}/labels.zip",
    response_class=FileResponse,
    responses={200: {"content": {"application/zip": {}}}},
)
def download_labels(project_id: ProjectId, job_id: JobId, db: DbDep, settings: SettingsDep) -> FileResponse:
    """A finished labeling's zip: ``sequences/<name>/predictions/*.label``, ``label-map.yaml`` and
    ``model-card.json``."""
    path = lidar_models.labels_zip(db, settings, project_id, job_id)
    job = crud.require_model_job(db, job_id, project_id)
    stem = "".join(ch if ch.isalnum() or ch in "-_" else "-" for ch in job.name)[:40]
    return FileResponse(path, media_type="application/zip", filename=f"{stem}-model{job.model_id}-labels.zip")
