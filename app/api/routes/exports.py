"""Exported labels of a finished run: a zip download, or a copy into a folder inside the data roots."""

from __future__ import annotations

import threading
import zipfile
from pathlib import Path
from typing import Any

from fastapi import APIRouter
from fastapi.responses import FileResponse

from app import crud, models
from app.api.deps import DbDep, SettingsDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.types import RunId
from app.core.config import Settings
from app.core.errors import Conflict, NotFound
from app.core.security import resolve_in_roots
from leap_core.io_utils import atomic_write, atomic_write_bytes
from leap_core.run_layout import RunLayout

router = APIRouter(
    prefix="/runs/{run_id}/export", tags=["exports"], responses={**NOT_FOUND, **CONFLICT}
)

_zip_lock = threading.Lock()


def _export_dir(run: dict[str, Any]) -> Path:
    folder = RunLayout(Path(run["run_dir"])).export_dir
    if run["status"] != "done":
        raise Conflict(f"Run {run['id']} is {run['status']}; only finished runs have exports")
    if not folder.is_dir():
        raise NotFound(f"Run {run['id']} has no export folder")
    return folder


def _files(folder: Path, include_confidence: bool) -> list[Path]:
    suffixes = (".label", ".conf") if include_confidence else (".label",)
    return sorted(p for p in folder.iterdir() if p.suffix in suffixes and p.is_file())


def build_zip(run: dict[str, Any], include_confidence: bool) -> Path:
    """The run's export zip (:meth:`RunLayout.export_zip`) with ``predictions/<frame>.label`` entries (built
    once, atomically).

    A finished run's export never changes, so the zip is cached beside it.
    """
    folder = _export_dir(run)
    target = RunLayout(Path(run["run_dir"])).export_zip(include_confidence)
    with _zip_lock:
        if not target.is_file():
            with (
                atomic_write(target, "wb") as fh,
                zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, compresslevel=6) as zf,
            ):
                for path in _files(folder, include_confidence):
                    zf.write(path, f"predictions/{path.name}")
    return target


@router.get(".zip", response_class=FileResponse, responses={200: {"content": {"application/zip": {}}}})
def download_export(run_id: RunId, db: DbDep, confidence: bool = False) -> FileResponse:
    """Zip of the run's ``.label`` files (SemanticKITTI raw ids); ``confidence=true`` adds ``.conf`` files."""
    run = crud.require_run(db, run_id)
    path = build_zip(run, confidence)
    project = crud.get_project(db, run["project_id"])
    stem = "".join(ch if ch.isalnum() or ch in "-_" else "-" for ch in (project or {}).get("name", "run"))[
        :40
    ]
    return FileResponse(path, media_type="application/zip", filename=f"{stem}-run{run['number']}-labels.zip")


def _allowed_roots(settings: Settings, project: dict[str, Any]) -> list[Path]:
    roots = list(settings.data_roots)
    if project["dataset_kind"] == "demo":
        # The built-in demo lives in the app's work folder; its own predictions/ folder is allowed too.
        roots.append(Path(project["dataset_path"]).resolve())
    return roots


@router.post("", response_model=models.ExportWritten)
def write_export(
    run_id: RunId, payload: models.ExportWrite, db: DbDep, settings: SettingsDep
) -> models.ExportWritten:
    """Copy the ``.label`` files into ``<dataset>/predictions`` (or ``path``), inside a data root."""
    run = crud.require_run(db, run_id)
    project = crud.require_project(db, run["project_id"])
    folder = _export_dir(run)
    raw = payload.path if payload.path else str(Path(project["dataset_path"]) / "predictions")
    target = resolve_in_roots(raw, _allowed_roots(settings, project), what="export path")
    files = _files(folder, payload.include_confidence)
    for path in files:
        atomic_write_bytes(target / path.name, path.read_bytes())
    return models.ExportWritten(run_id=run_id, path=str(target), files=len(files))
