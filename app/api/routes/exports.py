"""Exported labels of a finished run: what the export holds, a stand-alone zip download, or a copy into
each sequence's ``predictions/`` folder (policy and file work in :mod:`app.exports`)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse

from app import crud, exports, models
from app.api.deps import DbDep, SettingsDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import RunId

router = APIRouter(prefix="/runs/{run_id}/export", tags=["exports"], responses={**NOT_FOUND, **CONFLICT})


@router.get("", response_model=models.ExportInfo)
def export_info(run_id: RunId, db: DbDep, settings: SettingsDep) -> models.ExportInfo:
    """Point counts of the export (labeled, unlabeled by reason, per class) and each sequence's default
    target folder."""
    run = crud.require_run(db, run_id)
    project = crud.require_project(db, run.project_id)
    return exports.export_info(settings, run, project)


@router.get(".zip", response_class=FileResponse, responses={200: {"content": {"application/zip": {}}}})
def download_export(run_id: RunId, db: DbDep, confidence: bool = False) -> FileResponse:
    """Stand-alone zip: ``sequences/<seq>/predictions/*.label`` (SemanticKITTI raw ids), ``label-map.yaml``
    (semantic-kitti-api layout), ``summary.yaml``; ``confidence=true`` adds ``confidences/*.conf``."""
    run = crud.require_run(db, run_id)
    project = crud.require_project(db, run.project_id)
    path = exports.build_zip(run, project, confidence)
    stem = "".join(ch if ch.isalnum() or ch in "-_" else "-" for ch in project.name)[:40]
    return FileResponse(path, media_type="application/zip", filename=f"{stem}-run{run.number}-labels.zip")


@router.post("", response_model=models.ExportWritten)
def write_export(
    run_id: RunId, payload: models.ExportWrite, db: DbDep, settings: SettingsDep
) -> models.ExportWritten:
    """Copy each sequence's ``.label`` files into its dataset's ``predictions/`` (or, with ``path``, into
    ``<path>/sequences/<name>/predictions/``: the datasets' common root, or a folder inside the app's export
    folder). A folder that already holds files is refused with 409 unless ``overwrite`` is true; dataset
    inputs, run folders and the work folder: 403."""
    run = crud.require_run(db, run_id)
    project = crud.require_project(db, run.project_id)
    return exports.write_export(settings, run, project, payload)
