"""Class-list files: the ``classes:`` part of a preset (``projects/*.yaml``) as a file of its own, to start
a project with classes of one's own (the create form uploads one) and to take a project's classes along
(``GET /projects/{id}/classes.yaml``, in :mod:`app.api.routes.classes`).

An upload is the file's bytes as the request body (``application/yaml``), not a JSON string: the YAML's
line breaks are control characters that no JSON string of a request may hold (:mod:`app.api.types`).
It is only read and validated here, never stored; the answer is what ``ProjectCreate.class_list`` takes.
"""

from __future__ import annotations

from fastapi import APIRouter, Request

from app import models, services
from leap_core.schema import MAX_CLASS_LIST_BYTES

router = APIRouter(prefix="/class-lists", tags=["classes"])


@router.post(
    "",
    response_model=models.ClassListPublic,
    openapi_extra={
        "requestBody": {
            "required": True,
            "description": f"a class-list YAML file (at most {MAX_CLASS_LIST_BYTES // 1024} KiB)",
            "content": {"application/yaml": {"schema": {"type": "string"}}},
        }
    },
)
async def read_class_list(request: Request) -> models.ClassListPublic:
    """Validate an uploaded class list; a bad file answers 422 naming the field at fault in the file
    (``classes[3].prompts: must list at least one prompt``)."""
    # The server's body limit (LEAP_MAX_BODY_BYTES) has bounded the read; the file's own, smaller limit
    # is read_class_file's.
    return services.read_class_file(await request.body())
