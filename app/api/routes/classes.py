"""A project's classes (name, color, prompts, export id, ground-truth ids) and each class's prompt list,
and the raw ground-truth ids of the project's dataset (to pick a class's ground-truth ids from).

Classes are addressed by name; every change is validated against the whole schema (unique names, export
ids and prompts) and answers with the full, ordered class list. A class created without a colour gets
``next_color`` of that list: the unused colour most distinct from the others and from unlabeled grey.
"""

from __future__ import annotations

from fastapi import APIRouter, status
from fastapi.responses import PlainTextResponse

from app import crud, models, services
from app.api.deps import DbDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import ClassName, ProjectId, PromptIndex

router = APIRouter(
    prefix="/projects/{project_id}/classes", tags=["classes"], responses={**NOT_FOUND, **CONFLICT}
)
ids_router = APIRouter(prefix="/projects/{project_id}", tags=["classes"], responses={**NOT_FOUND})


@ids_router.get("/gt-ids", response_model=models.RawIdsPublic)
def list_gt_ids(project_id: ProjectId, db: DbDep) -> models.RawIdsPublic:
    """The raw ids in the dataset's ``labels/`` (at most 200 evenly spaced files are read; cached until
    the folder changes), each with its SemanticKITTI or demo name and the classes that map it."""
    return services.raw_ids_public(crud.require_project(db, project_id))


@ids_router.get(
    "/classes.yaml",
    response_class=PlainTextResponse,
    responses={200: {"content": {"application/yaml": {}}}},
)
def download_class_list(project_id: ProjectId, db: DbDep) -> PlainTextResponse:
    """The project's classes as a class-list file, which ``POST /class-lists`` (the create form's upload)
    reads back into the same classes."""
    project = crud.require_project(db, project_id)
    # The file name is the project id's, not its name: a name is free text, a header value is not.
    return PlainTextResponse(
        services.class_file(project),
        media_type="application/yaml",
        headers={"Content-Disposition": f'attachment; filename="project-{project_id}-classes.yaml"'},
    )


@router.get("", response_model=models.ClassesPublic)
def list_classes(project_id: ProjectId, db: DbDep) -> models.ClassesPublic:
    return services.classes_public(crud.require_project(db, project_id))


@router.put("", response_model=models.ClassesPublic)
def replace_classes(project_id: ProjectId, payload: models.SchemaReplace, db: DbDep) -> models.ClassesPublic:
    return services.classes_public(services.replace_classes(db, project_id, payload))


@router.post("", response_model=models.ClassesPublic, status_code=status.HTTP_201_CREATED)
def create_class(project_id: ProjectId, payload: models.ClassCreate, db: DbDep) -> models.ClassesPublic:
    return services.classes_public(services.add_class(db, project_id, payload))


@router.patch("/{name}", response_model=models.ClassesPublic)
def update_class(
    project_id: ProjectId, name: ClassName, payload: models.ClassUpdate, db: DbDep
) -> models.ClassesPublic:
    return services.classes_public(services.update_class(db, project_id, name, payload))


@router.delete("/{name}", response_model=models.ClassesPublic)
def delete_class(project_id: ProjectId, name: ClassName, db: DbDep) -> models.ClassesPublic:
    return services.classes_public(services.delete_class(db, project_id, name))


@router.put("/{name}/prompts", response_model=models.ClassesPublic)
def replace_prompts(
    project_id: ProjectId, name: ClassName, payload: models.PromptsReplace, db: DbDep
) -> models.ClassesPublic:
    return services.classes_public(services.set_prompts(db, project_id, name, payload.prompts))


@router.post("/{name}/prompts", response_model=models.ClassesPublic, status_code=status.HTTP_201_CREATED)
def add_prompt(
    project_id: ProjectId, name: ClassName, payload: models.PromptCreate, db: DbDep
) -> models.ClassesPublic:
    return services.classes_public(services.add_prompt(db, project_id, name, payload.prompt))


@router.delete("/{name}/prompts/{index}", response_model=models.ClassesPublic)
def delete_prompt(
    project_id: ProjectId, name: ClassName, index: PromptIndex, db: DbDep
) -> models.ClassesPublic:
    return services.classes_public(services.delete_prompt(db, project_id, name, index))
