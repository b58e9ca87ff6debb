"""Projects: a dataset, a class schema and pipeline parameters, with a history of runs."""

from __future__ import annotations

from fastapi import APIRouter, Request, status

from app import crud, models, services
from app.api.deps import DbDep, SettingsDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import ProjectId
from app.jobs.apply import applier

router = APIRouter(prefix="/projects", tags=["projects"], responses={**NOT_FOUND, **CONFLICT})


@router.get("", response_model=models.ProjectsPublic)
def list_projects(db: DbDep, settings: SettingsDep) -> models.ProjectsPublic:
    data = [services.project_public(db, p, settings) for p in crud.list_projects(db)]
    return models.ProjectsPublic(data=data, count=len(data))


@router.post("", response_model=models.ProjectPublic, status_code=status.HTTP_201_CREATED)
def create_project(payload: models.ProjectCreate, db: DbDep, settings: SettingsDep) -> models.ProjectPublic:
    return services.project_public(db, services.create_project(db, settings, payload), settings)


@router.get("/{project_id}", response_model=models.ProjectPublic)
def read_project(project_id: ProjectId, db: DbDep, settings: SettingsDep) -> models.ProjectPublic:
    return services.project_public(db, crud.require_project(db, project_id), settings)


@router.patch("/{project_id}", response_model=models.ProjectPublic)
def update_project(
    project_id: ProjectId, payload: models.ProjectUpdate, db: DbDep, settings: SettingsDep
) -> models.ProjectPublic:
    return services.project_public(db, services.update_project(db, project_id, payload), settings)


@router.delete("/{project_id}", response_model=models.Message)
def delete_project(
    project_id: ProjectId, request: Request, db: DbDep, settings: SettingsDep
) -> models.Message:
    folders = services.delete_project(db, settings, project_id)
    # A corrections pass in flight may still write into the run folder: it is removed again after it.
    applier(settings).forget(project_id, folders)
    viewers = getattr(request.app.state, "viewers", None)  # created on first viewer use only
    if viewers is not None:
        viewers.close(project_id)
    return models.Message(message="Project deleted")
