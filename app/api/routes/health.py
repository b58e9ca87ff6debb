"""Liveness, the job manager's state, free disk space and a few counters."""

from __future__ import annotations

import importlib.util

from fastapi import APIRouter

from app import models
from app.api.deps import DbDep, JobsDep, SettingsDep
from app.core.db import current_version
from leap_core import __version__

router = APIRouter(prefix="/health", tags=["health"])


@router.get("", response_model=models.HealthPublic)
def health(db: DbDep, jobs: JobsDep, settings: SettingsDep) -> models.HealthPublic:
    queued, running = jobs.counts()
    state = jobs.health()
    return models.HealthPublic(
        status="degraded" if state["problems"] else "ok",
        version=__version__,
        db_schema_version=current_version(db),
        queued=queued,
        running=running,
        viewer=settings.viewer_enabled and importlib.util.find_spec("app.api.routes.viewer") is not None,
        auth_required=settings.token is not None,
        **state,
    )
