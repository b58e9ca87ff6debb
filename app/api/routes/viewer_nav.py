"""Scan navigation of the running viewer, for the page's keys (web/viewer/nav.js).

The viser panel's Browse / Fit view / Follow ego / Enlarge image widgets call the same
:class:`~app.viewer.player.ScanPlayer` methods, so keys and widgets act on one state. The camera moves
of every browser showing the viewer follow (viser's ``client.camera``).
"""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, HTTPException, Response, status
from pydantic import BaseModel, ConfigDict, Field

from app.api.deps import AuthDep
from app.api.responses import CONFLICT, NOT_FOUND
from app.api.routes.viewer import ViewersDep, run_blocking, running_session
from app.api.types import ProjectId
from app.viewer.session import ReviewSession

router = APIRouter(
    prefix="/projects/{project_id}/viewer/nav", tags=["viewer"], responses={**NOT_FOUND, **CONFLICT}
)


class NavState(BaseModel):
    pos: int = Field(description="position of the shown scan among the run's labelled scans (0-based)")
    count: int = Field(description="number of labelled scans")
    frame_id: str | None = Field(description="file stem of the shown scan")
    follow: bool = Field(description="the camera follows the ego pose on a scan change")
    playing: bool = Field(description="playing through the scans")
    image_open: bool = Field(description="the page shows the scan's image enlarged")
    has_image: bool = Field(description="the shown scan has a camera image")
    camera: str | None = Field(default=None, description="the rig camera whose image is shown (its folder)")
    zoomed: bool = Field(
        default=False, description="the image is the focused review region's crop, zoomed on it"
    )


class StepBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    step: int = Field(ge=-10_000, le=10_000, description="scans to move (< 0: back), clipped at the ends")


class ToggleBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    on: bool | None = Field(default=None, description="true / false, or null to toggle")


class FitBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    target: Literal["scan", "map"] = Field(description="frame the shown scan or the whole voxel map")


def _session(viewers: ViewersDep, project_id: int) -> ReviewSession:
    session = running_session(viewers, project_id)
    if session.grid is None:
        raise HTTPException(status.HTTP_409_CONFLICT, detail="The viewer has no finished run loaded yet")
    return session


def _state(session: ReviewSession) -> NavState:
    player = session.player
    view = player.scan_view
    return NavState(
        pos=player.frame_pos,
        count=player.scan_count,
        frame_id=None if view is None else view.frame_id,
        follow=player.follow_ego,
        playing=player.playing,
        image_open=player.image_open,
        has_image=view is not None and view.overlay is not None,
        camera=None if view is None else view.camera,
        zoomed=player.is_zoomed(view),
    )


@router.get("", response_model=NavState, dependencies=[AuthDep])
async def nav_state(project_id: ProjectId, viewers: ViewersDep) -> NavState:
    """Where the viewer is: shown scan, follow / play / enlarged-image state."""
    return _state(_session(viewers, project_id))


@router.post("/step", response_model=NavState, dependencies=[AuthDep])
async def step_scan(project_id: ProjectId, body: StepBody, viewers: ViewersDep) -> NavState:
    """Show the next (``step`` > 0) or previous scan; the camera follows the ego pose when following."""
    session = _session(viewers, project_id)
    await run_blocking(session.player.step_scan, body.step)
    return _state(session)


@router.post("/play", response_model=NavState, dependencies=[AuthDep])
async def play(project_id: ProjectId, body: ToggleBody, viewers: ViewersDep) -> NavState:
    """Play through the scans or pause."""
    session = _session(viewers, project_id)
    await run_blocking(session.player.set_playing, body.on)
    return _state(session)


@router.post("/follow", response_model=NavState, dependencies=[AuthDep])
async def follow(project_id: ProjectId, body: ToggleBody, viewers: ViewersDep) -> NavState:
    """Make the camera follow the ego pose on scan changes (turning it on moves the camera now)."""
    session = _session(viewers, project_id)
    await run_blocking(session.player.set_follow, body.on)
    return _state(session)


@router.post("/fit", response_model=NavState, dependencies=[AuthDep])
async def fit(project_id: ProjectId, body: FitBody, viewers: ViewersDep) -> NavState:
    """Move the camera to show the whole shown scan or the whole map."""
    session = _session(viewers, project_id)
    player = session.player
    await run_blocking(player.fit_scan if body.target == "scan" else player.fit_map)
    return _state(session)


@router.post("/image", response_model=NavState, dependencies=[AuthDep])
async def image_open(project_id: ProjectId, body: ToggleBody, viewers: ViewersDep) -> NavState:
    """Show or hide the enlarged image of the shown scan in the page."""
    session = _session(viewers, project_id)
    session.player.set_image_open(body.on)
    return _state(session)


@router.get(
    "/image",
    dependencies=[AuthDep],
    response_class=Response,
    responses={200: {"content": {"image/jpeg": {}}, "description": "the shown scan's labelled image"}},
)
async def scan_image(project_id: ProjectId, viewers: ViewersDep) -> Response:
    """The shown scan's camera image with its labels drawn over it, as JPEG (404 when it has none)."""
    session = _session(viewers, project_id)
    data = await run_blocking(session.player.scan_image_jpeg)
    if data is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail="The shown scan has no camera image")
    return Response(data, media_type="image/jpeg", headers={"Cache-Control": "no-store"})
