"""Dataset folders found inside the configured data roots (for the create-project form)."""

from __future__ import annotations

from fastapi import APIRouter

from app import models, services
from app.api.deps import SettingsDep

router = APIRouter(prefix="/datasets", tags=["datasets"])


@router.get("", response_model=models.DatasetsPublic)
def list_datasets(settings: SettingsDep) -> models.DatasetsPublic:
    data = services.find_datasets(settings)
    return models.DatasetsPublic(data=data, count=len(data), roots=[str(r) for r in settings.data_roots])
