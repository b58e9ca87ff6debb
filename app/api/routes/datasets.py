"""Dataset folders found inside the configured data roots (for the create-project form), and the check of
one folder the user typed (the form shows it before *Create*, as it does for a listed one)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from app import models, services
from app.api.deps import SettingsDep
from app.api.responses import FORBIDDEN, INVALID

router = APIRouter(prefix="/datasets", tags=["datasets"])


@router.get("", response_model=models.DatasetsPublic)
def list_datasets(settings: SettingsDep) -> models.DatasetsPublic:
    data = services.find_datasets(settings)
    return models.DatasetsPublic(data=data, count=len(data), roots=[str(r) for r in settings.data_roots])


@router.get("/check", response_model=models.DatasetCandidate, responses={**FORBIDDEN, **INVALID})
def check_dataset_path(
    settings: SettingsDep,
    path: Annotated[
        str, Query(min_length=1, max_length=4096, description="sequence folder inside a data root")
    ],
) -> models.DatasetCandidate:
    """The dataset check of one folder, confined and refused exactly as a new project's (403 outside the
    data roots, naming them; 422 at ``[query, path]`` for a folder that is no KITTI sequence)."""
    return services.dataset_candidate(settings, path)
