"""Selection tools of the 3D viewer page: lasso, brush, box, their settings, assign / erase, undo / redo.

The viewer page (web/viewer/tools.js) draws a lasso or brush outline on a canvas over viser's and sends it
here in normalised screen coordinates; the selection is made server-side by the project's
:class:`~app.viewer.selection_tool.SelectionTool` with the camera of the browser that moved its camera
last (:meth:`~app.viewer.selection_tool.SelectionTool.latest_camera`): with several browsers on one viewer,
the one the user is drawing on. The settings (depth mode, distance, class filter, target, scope, armed
tool) live in the session, so the panel's widgets and the page's keys show and change the same values.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, status
from pydantic import BaseModel, ConfigDict, Field, Strict

from app.api.responses import CONFLICT, NOT_FOUND
from app.api.routes.viewer import ViewersDep, run_blocking, running_session
from app.api.types import CorrectionId, ProjectId
from app.viewer.records import ToolSettings
from app.viewer.session import ReviewSession

router = APIRouter(
    prefix="/projects/{project_id}/viewer/tools", tags=["viewer"], responses={**NOT_FOUND, **CONFLICT}
)

MAX_OUTLINE_POINTS = 20_000
"""Most points of one lasso or brush outline (a minute of dragging at 60 Hz stays below it)."""

ScreenPoint = Annotated[
    tuple[Annotated[float, Field(ge=-10.0, le=10.0)], Annotated[float, Field(ge=-10.0, le=10.0)]],
    Strict(False),  # a JSON array is a list: strict mode would take only a tuple; the numbers stay strict
]


class ToolsState(BaseModel):
    tool: Literal["lasso", "brush", "box"] | None = Field(description="armed tool (None: the camera orbits)")
    depth_mode: Literal["front", "through"] = Field(description="front surface only, or through")
    distance: float = Field(description="front-surface tolerance (m) behind the first hit")
    class_filter: str | None = Field(description="select only voxels/points currently of this class")
    target: Literal["map", "scan"] = Field(description="select voxels of the map or points of the shown scan")
    scope: Literal["map", "scan"] = Field(description="scope of corrections made from the selection")
    brush_radius: float = Field(description="brush radius as a share of the canvas height")
    selected: int = Field(description="size of the current selection")
    classes: list[str] = Field(description="class picker order: key n assigns classes[n-1]")


class ToolsPatch(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    tool: Literal["lasso", "brush", "box", "none"] | None = Field(
        default=None, description="arm a tool ('none' disarms)"
    )
    depth_mode: Literal["front", "through"] | None = None
    distance: float | None = Field(default=None, ge=0.0, le=100.0)
    class_filter: str | None = Field(default=None, max_length=200, description="class name, '' for any class")
    target: Literal["map", "scan"] | None = None
    scope: Literal["map", "scan"] | None = None
    brush_radius: float | None = Field(default=None, ge=0.001, le=0.5)


class SelectBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    tool: Literal["lasso", "brush", "box"] = Field(description="how to read `points`")
    points: list[ScreenPoint] = Field(
        min_length=1,
        max_length=MAX_OUTLINE_POINTS,
        description="normalised screen points (0,0 top-left; 1,1 bottom-right): lasso polygon, brush "
        "stroke, or the box's two corners",
    )
    add: bool = Field(default=False, description="add to the current selection instead of replacing it")


class SelectResult(BaseModel):
    count: int = Field(description="size of the selection")
    target: Literal["map", "scan"]


class AssignBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    slot: int | None = Field(default=None, ge=1, le=99, description="n-th class of the picker (keys 1-9)")
    erase: bool = Field(default=False, description="erase to unlabeled instead of assigning a class")


class EditResult(BaseModel):
    correction_id: int | None = Field(description="correction made, undone or redone (None: nothing to do)")


def _state(session: ReviewSession) -> ToolsState:
    t: ToolSettings = session.tools.settings
    return ToolsState(
        tool=t.tool,
        depth_mode=t.depth_mode,
        distance=t.distance,
        class_filter=t.class_filter,
        target=t.target,
        scope=t.scope,
        brush_radius=t.brush_radius,
        selected=int(session.tools.selection.rows.size),
        classes=session.class_names(),
    )


def _unprocessable(field: str, exc: Exception) -> HTTPException:
    return HTTPException(422, detail=f"{field}: {exc}")


@router.get("", response_model=ToolsState)
async def get_tools(project_id: ProjectId, viewers: ViewersDep) -> ToolsState:
    """The selection tools' settings and the selection's size."""
    return _state(running_session(viewers, project_id))


@router.patch("", response_model=ToolsState)
async def patch_tools(project_id: ProjectId, payload: ToolsPatch, viewers: ViewersDep) -> ToolsState:
    """Arm a tool or change the tools' settings (fields left out keep their value)."""
    session = running_session(viewers, project_id)
    changes = payload.model_dump(exclude_none=True)
    if changes.get("tool") == "none":
        changes["tool"] = None
    if "class_filter" in changes and changes["class_filter"] == "":
        changes["class_filter"] = None
    try:
        session.tools.set_tools(**changes)
    except ValueError as exc:
        raise _unprocessable("body", exc) from None
    return _state(session)


@router.post("/select", response_model=SelectResult)
async def select(project_id: ProjectId, payload: SelectBody, viewers: ViewersDep) -> SelectResult:
    """Select with a tool outline drawn on the canvas of the browser whose camera moved last."""
    session = running_session(viewers, project_id)
    try:
        camera = session.tools.latest_camera()
    except LookupError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, detail=str(exc)) from None
    try:
        count = await run_blocking(
            session.tools.select_screen, payload.tool, payload.points, camera, add=payload.add
        )
    except ValueError as exc:
        raise _unprocessable("points", exc) from None
    return SelectResult(count=count, target=session.tools.selection.target)


@router.post("/assign", response_model=EditResult)
async def assign(project_id: ProjectId, payload: AssignBody, viewers: ViewersDep) -> EditResult:
    """Correct the selection: the ``slot``-th class, or unlabeled (``erase``), in the tools' scope."""
    session = running_session(viewers, project_id)
    if payload.erase == (payload.slot is not None):
        raise HTTPException(422, detail="body: give either slot or erase")
    try:
        if payload.erase:
            cid = await run_blocking(session.corrections.assign_selection, "")
        else:
            assert payload.slot is not None
            cid = await run_blocking(session.corrections.assign_slot, payload.slot)
    except ValueError as exc:
        raise _unprocessable("slot" if payload.slot is not None else "erase", exc) from None
    return EditResult(correction_id=cid)


@router.post("/undo", response_model=EditResult)
async def undo(project_id: ProjectId, viewers: ViewersDep) -> EditResult:
    """Undo the viewer's last correction."""
    return EditResult(correction_id=await run_blocking(running_session(viewers, project_id).corrections.undo))


@router.post("/redo", response_model=EditResult)
async def redo(project_id: ProjectId, viewers: ViewersDep) -> EditResult:
    """Redo the last undone correction."""
    return EditResult(correction_id=await run_blocking(running_session(viewers, project_id).corrections.redo))


@router.post("/corrections/{correction_id}/show", response_model=ToolsState)
async def show_correction(
    project_id: ProjectId, correction_id: CorrectionId, viewers: ViewersDep
) -> ToolsState:
    """Jump to a stored correction (the project page's corrections list): select what it covers (its voxels,
    or its points in its scan, which is shown) and frame the camera on it."""
    session = running_session(viewers, project_id)
    try:
        await run_blocking(session.corrections.show_correction, correction_id)
    except LookupError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc)) from None
    except ValueError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, detail=str(exc)) from None
    return _state(session)


@router.post("/clear", response_model=ToolsState)
async def clear(project_id: ProjectId, viewers: ViewersDep) -> ToolsState:
    """Clear the selection and disarm the tool (the Escape key)."""
    session = running_session(viewers, project_id)
    session.tools.clear_selection()
    session.tools.set_tools(tool=None)
    return _state(session)
