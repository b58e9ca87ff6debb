"""The API router: every resource router, all behind the access-token check and the body check
(:func:`app.api.deps.require_plain_body`), with the error answers every route can give declared once."""

from __future__ import annotations

import importlib
import importlib.util

from fastapi import APIRouter

from app.api.deps import AuthDep, PlainBodyDep
from app.api.responses import COMMON_RESPONSES
from app.api.routes import (
    class_lists,
    classes,
    corrections,
    datasets,
    exports,
    health,
    lidar_models,
    objects,
    pipeline,
    projects,
    reviewers,
    runs,
    sequences,
)

api_router = APIRouter(dependencies=[AuthDep, PlainBodyDep], responses=COMMON_RESPONSES)
api_router.include_router(health.router)
api_router.include_router(pipeline.router)
api_router.include_router(datasets.router)
api_router.include_router(projects.router)
api_router.include_router(sequences.router)
api_router.include_router(classes.router)
api_router.include_router(classes.ids_router)
api_router.include_router(class_lists.router)
api_router.include_router(runs.router)
api_router.include_router(objects.router)
api_router.include_router(exports.router)
api_router.include_router(corrections.router)
api_router.include_router(reviewers.router)
api_router.include_router(lidar_models.router)

if importlib.util.find_spec("app.api.routes.viewer") is not None:
    # The 3D review viewer is an optional module of its own (app/viewer, app/api/routes/viewer.py).
    api_router.include_router(importlib.import_module("app.api.routes.viewer").router)
    api_router.include_router(importlib.import_module("app.api.routes.viewer_nav").router)
    api_router.include_router(importlib.import_module("app.api.routes.viewer_tools").router)
    api_router.include_router(importlib.import_module("app.api.routes.viewer_review").router)
