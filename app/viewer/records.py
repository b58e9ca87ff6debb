"""Records and protocols the parts of a review session share: what the viewer knows of runs, corrections and
review marks, the project store it steers (:class:`ProjectBackend`), what it tells its GUI panel
(:class:`SessionView`), its tunables (:class:`SessionConfig`) and the selection tools' settings.

No behaviour lives here; the session's rooms (:mod:`app.viewer.session`) import these names, and the app's
backend (:mod:`app.viewer.manager`) implements :class:`ProjectBackend`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol, TypedDict

import numpy as np
import numpy.typing as npt

from app.viewer import view_logic as vl
from app.viewer.data import ScanView
from app.viewer.lod import LodConfig
from app.viewer.region_logic import Region
from leap_core import selection as sel
from leap_core.bounds import check_bounds, within
from leap_core.object_review import ObjectQueueConfig
from leap_core.pipeline.object_corrections import ObjectCorrections
from leap_core.schema import Schema

QueueKind = Literal["confidence", "disagreement"]
ToolKind = Literal["lasso", "brush", "box"]
Target = Literal["map", "scan"]
"""What a selection tool picks from: voxels of the map, or points of the scan shown."""
ObjectAction = Literal["relabel", "merge", "split"]
"""What an object correction does (:class:`leap_core.pipeline.object_corrections.ObjectEdit`)."""
Scope = Literal["map", "scan"]
"""What a correction changes: all points in its voxels in every scan (``map``), or listed points of one
scan (``scan``)."""


class ViewChanges(TypedDict, total=False):
    """Fields of :class:`~app.viewer.view_logic.ViewState` to change
    (:meth:`~app.viewer.session.ReviewSession.set_state`)."""

    mode: vl.ColorMode
    class_index: int
    threshold: float
    enabled: tuple[bool, ...]
    max_points: int | None


@dataclass(frozen=True)
class RunInfo:
    """What the viewer needs to know about a run."""

    run_id: int
    """Run id."""
    number: int
    """Run number within its project (shown to the user)."""
    status: str
    """queued / running / done / failed / cancelled / interrupted."""
    percent: float
    """Overall progress 0..100."""
    stage: str | None
    """Stage in progress."""
    error: str | None
    """Failure message."""
    run_dir: Path
    """The run's folder of the sequence shown (its outputs)."""
    schema: Schema | None
    """Class schema the run was made with (its class indices index the run's grid)."""
    pipeline: dict[str, Any] | None = None
    """Pipeline parameters the run was made with (which grid is final)."""


@dataclass(frozen=True)
class CorrectionRecord:
    """A stored manual correction (see :class:`app.crud.Correction`)."""

    id: int
    """Row id."""
    class_name: str
    """Assigned class (``""`` = erase to unlabeled)."""
    voxel_size: float
    """Voxel edge of ``keys``."""
    keys: npt.NDArray[np.int64]
    """Packed voxel keys."""
    active: bool
    """False once undone."""
    created_at: str = ""
    """ISO UTC time it was made ("" when the store does not say)."""

    scope: Scope | Literal["object"] = "map"
    """``map``: every point in ``keys``' voxels; ``scan``: only ``points`` of scan ``frame_id``; ``object``:
    every point of one object in every scan (a run's track, matched to later runs' tracks)."""
    frame_id: str | None = None
    """Scan of a scan-scope correction."""
    points: npt.NDArray[np.int64] | None = None
    """Scan scope: indices into that scan's points."""
    run_id: int | None = None
    """Object scope: the run whose track it relabels."""
    track_id: int | None = None
    """Object scope: that track."""


@dataclass(frozen=True)
class Inspection:
    """What the panel shows of one clicked voxel
    (:meth:`~app.viewer.selection_tool.SelectionTool.inspect_ray`)."""

    row: int
    """Row of the voxel in the displayed grid."""
    key: int
    """Its packed voxel key."""
    centre: tuple[float, float, float]
    """Voxel centre (metres)."""
    probs: npt.NDArray[np.float32]
    """(C,) the grid's class distribution of the voxel (before corrections)."""
    label: int
    """Shown class index (after corrections), -1 unlabeled."""
    conf: float
    """Shown confidence (1 for a corrected voxel)."""
    corrected: bool
    """An active correction overrides the voxel."""
    views: int
    """Number of the run's scans that observed the voxel (:meth:`RunOutputs.view_counts`)."""
    history: tuple[CorrectionRecord, ...]
    """Every correction (active or undone) whose voxels include this one, oldest first."""
    distance: float
    """Distance from the click ray's origin (metres)."""


@dataclass(frozen=True)
class ObjectInfo:
    """The object (a track of the shown run) under a clicked point
    (:meth:`~app.viewer.selection_tool.SelectionTool.inspect_ray`)."""

    run_id: int
    """The run whose track it is."""
    track: int
    """Its id as the export shows it (the instance id in the upper 16 bits): the run's track id, or the new
    id of a part a split cut off; merged objects show the id of the one merged into."""
    class_index: int
    """The object's voted class (-1: none; a merged object's is the one merged into's)."""
    scans: int
    """Scans it was seen in."""
    moving: bool
    """Whether the track moves (docs/METHOD.md B.6, step 5)."""
    speed: float
    """Its speed (m/s): the norm of the least-squares velocity."""
    points: int
    """Its points in the shown scan."""
    frame_id: str
    """The shown scan."""
    corrected_to: int | None = None
    """The class an active object correction gives it (-1 erases), or None."""


@dataclass(frozen=True)
class ToolSettings:
    """The selection tools' settings (panel widgets and the viewer page's keys change them)."""

    tool: ToolKind | None = None
    """Armed tool: the next drag on the canvas draws its outline (None: the camera orbits)."""
    depth_mode: sel.DepthMode = "front"
    """``front``: only the first surface along each view ray (within ``distance``); ``through``: all."""
    distance: float = 0.5
    """Front-surface tolerance (m) behind the first hit."""
    class_filter: str | None = None
    """Select only what is currently labelled this class (None: any class)."""
    target: Target = "map"
    """Select voxels of the map or points of the scan shown."""
    scope: Scope = "map"
    """Scope of the corrections made from the selection."""
    brush_radius: float = 0.03
    """Brush radius as a share of the canvas height."""


@dataclass(frozen=True)
class ReviewMarkRecord:
    """A stored verdict on a review region (see :class:`app.crud.ReviewMark`)."""

    signature: str
    """Content signature the verdict was made on (:func:`leap_core.review.region_signatures`)."""
    state: str
    """``accepted`` or ``skipped``."""


class ProjectBackend(Protocol):
    """The project store the viewer reads and steers (the same data the web UI edits)."""

    project_id: int

    def project_name(self) -> str: ...

    def dataset_path(self) -> Path: ...

    def load_schema(self) -> Schema: ...

    def save_schema(self, schema: Schema) -> None: ...

    def latest_finished_run(self) -> RunInfo | None: ...

    def finished_run_before(self, run_id: int) -> RunInfo | None:
        """The newest finished run of the sequence before run ``run_id`` (the viewer's Δ view compares
        with it), or None."""
        ...

    def run_info(self, run_id: int) -> RunInfo: ...

    def active_run(self) -> RunInfo | None: ...

    def start_run(self) -> int: ...

    def labeler(self) -> str:
        """The project's 2D labeler (the next run's)."""
        ...

    def set_labeler(self, name: str) -> None:
        """Make ``name`` the project's 2D labeler, as the project page's form does."""
        ...

    def corrections(self) -> list[CorrectionRecord]: ...

    def add_correction(
        self,
        class_name: str,
        voxel_size: float,
        keys: npt.NDArray[np.int64],
        *,
        scope: Scope = "map",
        frame_id: str | None = None,
        points: npt.NDArray[np.int64] | None = None,
    ) -> int: ...

    def add_object_correction(
        self,
        class_name: str,
        run_id: int,
        track_id: int,
        *,
        action: ObjectAction = "relabel",
        other_track_id: int | None = None,
        frame: str | None = None,
    ) -> int:
        """Store an object-scope correction of object ``track_id`` of run ``run_id`` (as its export shows it
        now): a relabel to ``class_name``, a merge of ``other_track_id`` into it or a split at scan
        ``frame``; returns its id."""
        ...

    def object_corrections(self, names: list[str]) -> ObjectCorrections:
        """The sequence's active object corrections for a run with the classes ``names``."""
        ...

    def set_correction_active(self, correction_id: int, active: bool) -> None: ...

    def review_marks(self) -> dict[str, ReviewMarkRecord]: ...

    def set_review_mark(self, region: str, signature: str, state: str, run_id: int | None) -> None: ...

    def save_review_queue(self, kind: str, run_id: int | None, regions: list[tuple[str, str]]) -> None: ...


class SessionView(Protocol):
    """What the session tells its GUI panel (implemented by :class:`app.viewer.panel.ReviewPanel`)."""

    def set_status(self, text: str) -> None: ...

    def on_run_loaded(self) -> None: ...

    def on_drawn(self, *, shown: int, total: int, seconds: float) -> None: ...

    def on_scan(self, view: ScanView, pos: int, count: int) -> None: ...

    def on_region(self, region: Region, pos: int, count: int, kind: str) -> None: ...

    def on_focus_cleared(self) -> None: ...

    def on_queue(self, building: bool) -> None: ...

    def on_selection(self, count: int) -> None: ...

    def on_history(self) -> None: ...

    def on_schema(self) -> None: ...

    def on_run_progress(self, info: RunInfo) -> None: ...

    def on_inspect(self, inspection: Inspection) -> None: ...

    def on_object(self, found: ObjectInfo | None) -> None: ...

    def on_nav(self) -> None: ...


@dataclass(frozen=True)
class SessionConfig:
    """Tunables of a review session."""

    queue_share: float = 0.05
    """Share of voxels (lowest confidence / highest disagreement) clustered into review regions."""
    queue_cell: float = 4.0
    """Edge (m) of the cells review regions are clustered into."""
    queue_min_count: int = dataclasses.field(default=10, metadata=within(1, 100_000))
    """Minimum region size: cells with fewer candidate voxels are not regions (specks a few voxels large
    are not worth a person's time). The panel's *Min region size* changes it per session."""
    poll_interval_s: float = 0.5
    """How often a started run's progress is polled."""
    max_points: int = 200_000
    """Default of the panel's "Max points" (decimation applies only once the user ticks "Limit points")."""
    queue_scans: int = 12
    """A focused region's scan is the best observer (:func:`leap_core.review.best_observer`) among this many
    scans whose sensor positions lie nearest the region: counting every scan's points would cost a pass over
    the whole sequence per region."""
    play_interval_s: float = 1.0
    """Seconds between scans while playing through them."""
    follow_ego: bool = True
    """Whether the camera follows the ego pose on a scan change when the viewer starts (key ``g``)."""
    lod: LodConfig = dataclasses.field(default_factory=LodConfig)
    """Level of detail of maps with more voxels than its budget (:mod:`app.viewer.lod`)."""
    objects: ObjectQueueConfig = dataclasses.field(default_factory=ObjectQueueConfig)
    """Which objects the "Objects to review" queue holds (:mod:`app.viewer.object_queue`)."""

    def __post_init__(self) -> None:
        check_bounds(self)


@dataclass(frozen=True, eq=False)
class Selection:
    """What the selection tools selected (read by corrections, drawn by the renderer)."""

    rows: npt.NDArray[np.int64]
    """Rows of the grid (target ``map``) or indices of the shown scan's points (target ``scan``)."""
    target: Target = "map"
    """Whether ``rows`` index the grid or the shown scan's points."""
    frame_id: str | None = None
    """Scan the points belong to (target ``scan``)."""

    @classmethod
    def empty(cls) -> Selection:
        """Nothing selected."""
        return cls(np.zeros(0, np.int64))


__all__ = [
    "CorrectionRecord",
    "Inspection",
    "ObjectAction",
    "ObjectInfo",
    "ProjectBackend",
    "QueueKind",
    "ReviewMarkRecord",
    "RunInfo",
    "Scope",
    "Selection",
    "SessionConfig",
    "SessionView",
    "Target",
    "ToolKind",
    "ToolSettings",
    "ViewChanges",
]
