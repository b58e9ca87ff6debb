"""A project's sequences after creation: list them, add a sequence folder, remove one.

A folder is confined to the data roots and checked exactly as at creation; names are unique within the
project. Edits wait for the project's queued or running run to end (409), a project keeps one sequence
at least (409), and removing a sequence deletes nothing: its dataset, every run folder and its
corrections and review marks stay. After an edit the latest run's results describe other sequences than
the project's: ``ProjectPublic.stale`` says so until a new run labels the current ones. Each answer is
the whole project, every sequence with its dataset check.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, status

from app import crud, models, services
from app.api.deps import DbDep, SettingsDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import ProjectId, SequenceName

router = APIRouter(
    prefix="/projects/{project_id}/sequences", tags=["sequences"], responses={**NOT_FOUND, **CONFLICT}
)


def _close_viewer(request: Request, project_id: int) -> None:
    # The project's viewer was opened on the sequences as they were (which one it shows, how review marks
    # are keyed); the next "Open 3D viewer" starts it on the current ones.
    viewers = getattr(request.app.state, "viewers", None)  # created on first viewer use only
    if viewers is not None:
        viewers.close(project_id)


@router.get("", response_model=models.SequencesPublic)
def list_sequences(project_id: ProjectId, db: DbDep, settings: SettingsDep) -> models.SequencesPublic:
    """The project's sequences in run order, each with its dataset check, and whether the latest run's
    results describe other sequences."""
    project = services.project_public(db, crud.require_project(db, project_id), settings)
    return models.SequencesPublic(data=project.sequences, count=len(project.sequences), stale=project.stale)


@router.post("", response_model=models.ProjectPublic, status_code=status.HTTP_201_CREATED)
def add_sequence(
    project_id: ProjectId, payload: models.SequenceRef, request: Request, db: DbDep, settings: SettingsDep
) -> models.ProjectPublic:
    """Append a sequence folder (inside a data root, one the pipeline can run on); ``name`` defaults to
    the folder's name. The name of a removed sequence brings it back (with its corrections and review
    marks) only on its own folder."""
    project = services.add_sequence(db, settings, project_id, payload)
    _close_viewer(request, project_id)
    return services.project_public(db, project, settings)


@router.delete("/{name}", response_model=models.ProjectPublic)
def remove_sequence(
    project_id: ProjectId, name: SequenceName, request: Request, db: DbDep, settings: SettingsDep
) -> models.ProjectPublic:
    """Take a sequence out of the project; nothing on disk or in its history is deleted."""
    project = services.remove_sequence(db, project_id, name)
    _close_viewer(request, project_id)
    return services.project_public(db, project, settings)
