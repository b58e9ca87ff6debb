"""API schemas (pydantic): the only shapes that leave the API. Database rows are :mod:`app.rows`
(:mod:`app.crud`).

Per resource: ``XCreate`` / ``XUpdate`` inputs, ``XPublic`` outputs and ``XsPublic(data, count)`` lists.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from app.rows import DatasetKind, RunStatus
from leap_core.object_review import ReasonCode
from leap_core.schema import class_name_problem

StageStatus = Literal["pending", "running", "done", "skipped", "failed", "cancelled"]

ACTIVE_STATUSES: tuple[str, ...] = ("queued", "running")
RESUMABLE_STATUSES: tuple[str, ...] = ("interrupted", "cancelled", "failed")

_HEX = re.compile(r"^#[0-9a-fA-F]{6}$")
_BAD_NAME_CHARS = re.compile(r"[/\\\x00-\x1f\x7f]")


class _Input(BaseModel):
    """Base of every request body. Ids, strings and numbers inside bodies are bounded for every route by
    :func:`app.api.deps.require_plain_body` (64-bit integers, finite numbers, no control characters).

    Strict: a value must have its field's JSON type (``true`` is no integer, ``"3"`` no number, ``1`` no
    boolean); an integer is accepted where a number is meant."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True, allow_inf_nan=False, strict=True)


# --------------------------------------------------------------------------------------------- classes
def _check_class_name(value: str) -> str:
    if _BAD_NAME_CHARS.search(value):
        raise ValueError("class names may not contain '/', '\\' or control characters")
    problem = class_name_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return value


def _check_color(value: Any) -> list[int]:
    if isinstance(value, str):
        if not _HEX.match(value.strip()):
            raise ValueError("color must be '#rrggbb' or 3 integers 0..255")
        h = value.strip()[1:]
        return [int(h[i : i + 2], 16) for i in (0, 2, 4)]
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ValueError("color must be '#rrggbb' or 3 integers 0..255")
    if not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in value):
        raise ValueError("color must be '#rrggbb' or 3 integers 0..255")
    return [int(v) for v in value]


def _check_prompts(value: list[str]) -> list[str]:
    out = [p.strip() for p in value]
    for i, p in enumerate(out):
        if not p:
            raise ValueError(f"prompt {i} is empty")
        if len(p) > 200:
            raise ValueError(f"prompt {i} is longer than 200 characters")
    return out


class ClassBase(_Input):
    name: str = Field(min_length=1, max_length=64)
    color: Any = Field(description="'#rrggbb' or [r, g, b] with 0..255", examples=["#6496f5"])
    prompts: list[str] = Field(min_length=1, max_length=64)
    export_id: int = Field(ge=1, le=65535, description="raw id written to exported .label files")
    gt_ids: list[int] = Field(default_factory=list, max_length=256)
    category: str = Field(default="other", min_length=1, max_length=64)
    negative_prompts: list[str] = Field(default_factory=list, max_length=64)
    thing: bool | None = Field(
        default=None,
        description="a countable object, tracked with instance ids; absent: SemanticKITTI's things by "
        "name and export id, else stuff",
    )
    moving_id: int | None = Field(
        default=None, ge=1, le=65535, description="raw id exported for its points while it moves (a thing)"
    )

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        return _check_class_name(v)

    @field_validator("color")
    @classmethod
    def _color(cls, v: Any) -> list[int] | None:  # None only where a subclass allows it (ClassCreate)
        return _check_color(v)

    @field_validator("prompts", "negative_prompts")
    @classmethod
    def _prompts(cls, v: list[str]) -> list[str]:
        return _check_prompts(v)


class ClassCreate(ClassBase):
    color: Any = Field(
        default=None,
        description="'#rrggbb' or [r, g, b]; absent = the unused colour most distinct from the project's "
        "other classes and from unlabeled grey (`ClassesPublic.next_color`)",
        examples=["#6496f5"],
    )
    position: int | None = Field(default=None, ge=0, description="insert at this index (default: append)")

    @field_validator("color")
    @classmethod
    def _color(cls, v: Any) -> list[int] | None:
        return None if v is None else _check_color(v)


class ClassUpdate(_Input):
    """Fields to change; absent fields keep their value. ``name`` renames the class."""

    name: str | None = Field(default=None, min_length=1, max_length=64)
    color: Any = None
    prompts: list[str] | None = Field(default=None, min_length=1, max_length=64)
    export_id: int | None = Field(default=None, ge=1, le=65535)
    gt_ids: list[int] | None = Field(default=None, max_length=256)
    category: str | None = Field(default=None, min_length=1, max_length=64)
    negative_prompts: list[str] | None = Field(default=None, max_length=64)
    thing: bool | None = None
    moving_id: int | None = Field(default=None, ge=1, le=65535, description="null: no moving id")
    position: int | None = Field(default=None, ge=0, description="move the class to this index")

    @field_validator("name")
    @classmethod
    def _name(cls, v: str | None) -> str | None:
        return None if v is None else _check_class_name(v)

    @field_validator("color")
    @classmethod
    def _color(cls, v: Any) -> list[int] | None:
        return None if v is None else _check_color(v)

    @field_validator("prompts", "negative_prompts")
    @classmethod
    def _prompts(cls, v: list[str] | None) -> list[str] | None:
        return None if v is None else _check_prompts(v)


class ClassPublic(BaseModel):
    index: int
    name: str
    color: list[int]
    hex: str
    prompts: list[str]
    export_id: int
    gt_ids: list[int]
    category: str
    negative_prompts: list[str]
    thing: bool
    moving_id: int | None


class ClassesPublic(BaseModel):
    data: list[ClassPublic]
    count: int
    next_color: str = Field(
        description="'#rrggbb' a new class gets when it names none: the candidate colour farthest (CIELAB) "
        "from every class colour and from the viewer's unlabeled grey"
    )


class RawIdPublic(BaseModel):
    id: int = Field(description="raw semantic id (low 16 bits of a .label value)")
    name: str | None = Field(description="SemanticKITTI's or the demo's name for it; null when unknown")
    points: int = Field(description="points carrying it in the label files read")
    classes: list[str] = Field(description="classes of the project whose ground-truth ids include it")


class RawIdsPublic(BaseModel):
    """The raw ground-truth ids of a project's dataset, for picking a class's ground-truth ids."""

    data: list[RawIdPublic] = Field(description="ids present in the dataset's labels, ascending")
    count: int
    has_ground_truth: bool = Field(description="the dataset has a labels/ folder")
    frames_read: int = Field(description="label files read (evenly spaced when the dataset has many)")
    frames_total: int
    names: dict[str, str] = Field(description="every raw id this program can name (id as a string -> name)")


class PromptCreate(_Input):
    prompt: str = Field(min_length=1, max_length=200)


class PromptsReplace(_Input):
    prompts: list[str] = Field(min_length=1, max_length=64)

    @field_validator("prompts")
    @classmethod
    def _prompts(cls, v: list[str]) -> list[str]:
        return _check_prompts(v)


class SchemaReplace(_Input):
    """The whole ordered class list at once (what the editor saves)."""

    classes: list[ClassBase] = Field(min_length=1, max_length=256)


class ClassListCreate(_Input):
    """A whole class list for a new project: what ``POST /class-lists`` answers for an uploaded file."""

    name: str = Field(default="uploaded", min_length=1, max_length=64, description="the class list's name")
    description: str = Field(default="", max_length=4000)
    classes: list[ClassBase] = Field(min_length=1, max_length=256)


class ClassSpecPublic(BaseModel):
    """One class as a class-list file holds it (the fields of ClassBase, normalised)."""

    name: str
    color: list[int]
    prompts: list[str]
    export_id: int
    gt_ids: list[int]
    category: str
    negative_prompts: list[str]
    thing: bool
    moving_id: int | None


class ClassListPublic(BaseModel):
    """An uploaded class-list file, validated; send it back as ``ProjectCreate.class_list``."""

    name: str
    description: str = Field(description="on one line (a file's line breaks become spaces)")
    classes: list[ClassSpecPublic]
    count: int


# -------------------------------------------------------------------------------------------- projects
class DatasetRef(_Input):
    kind: DatasetKind = "folder"
    path: str | None = Field(default=None, max_length=4096, description="sequence folder inside a data root")

    @model_validator(mode="after")
    def _path_for_folder(self) -> DatasetRef:
        if self.kind == "folder" and not self.path:
            raise ValueError("path is required when kind is 'folder'")
        return self


SEQUENCE_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
"""A sequence's name: it names the run's ``sequences/<name>/`` folder and the export's, so no ``/``, no
leading dot."""

MAX_SEQUENCES = 64
"""Most sequences one project may hold."""


class SequenceRef(_Input):
    """One sequence of a multi-sequence project: a KITTI sequence folder inside a data root."""

    path: str = Field(min_length=1, max_length=4096, description="sequence folder inside a data root")
    name: str | None = Field(
        default=None,
        pattern=SEQUENCE_NAME_PATTERN,
        description="name in runs, metrics and exports (default: the folder's name, e.g. `00`)",
    )


class ProjectCreate(_Input):
    name: str = Field(min_length=1, max_length=120)
    dataset: DatasetRef | None = Field(
        default=None,
        description="the project's one sequence (or the built-in demo); give this or `sequences`",
    )
    sequences: list[SequenceRef] | None = Field(
        default=None,
        min_length=1,
        max_length=MAX_SEQUENCES,
        description="several sequence folders labeled with one class schema (e.g. SemanticKITTI 00-10); a "
        "run labels them all, metrics come per sequence and overall; give this or `dataset`",
    )
    schema_name: str = Field(
        default="semantickitti", min_length=1, max_length=64, description="built-in schema"
    )
    class_list: ClassListCreate | None = Field(
        default=None,
        description="the project's classes, instead of a built-in schema (`schema_name`): e.g. an uploaded "
        "file as `POST /class-lists` answers it; the pipeline starts from the defaults",
    )
    pipeline: dict[str, Any] = Field(
        default_factory=dict, description="overrides of the default pipeline configuration"
    )
    estimate_poses: bool = Field(
        default=False,
        description="when the dataset has no poses.txt, runs first estimate poses with KISS-ICP LiDAR "
        "odometry into the work folder (the dataset is never written)",
    )

    @model_validator(mode="after")
    def _one_class_source(self) -> ProjectCreate:
        if self.class_list is not None and "schema_name" in self.model_fields_set:
            raise ValueError("give schema_name (a built-in schema) or class_list, not both")
        return self


class ProjectUpdate(_Input):
    name: str | None = Field(default=None, min_length=1, max_length=120)
    estimate_poses: bool | None = Field(
        default=None, description="estimate poses with KISS-ICP when the dataset has none"
    )
    pipeline: dict[str, Any] | None = Field(
        default=None, description="partial pipeline configuration, merged into the current one"
    )
    form: dict[str, Any] | None = Field(
        default=None,
        description="the UI's flat parameters (labeler, threshold, voxel_size, k, cluster_gap, consistency, "
        "share, temperature, iterations), merged after `pipeline`",
    )


class CheckCoverage(BaseModel):
    present: int = Field(description="scans that have the file")
    total: int = Field(description="scans in velodyne/")
    kind: Literal["all", "some", "none"]


class CheckCamera(BaseModel):
    """One camera of the dataset's rig (docs/IMPORT.md, "Several cameras")."""

    name: str = Field(description="its image folder (image_2, CAM_FRONT)")
    source: str = Field(description="where its projection was read (calib.txt P2, cameras.yaml)")
    images: CheckCoverage
    gt2d: CheckCoverage


class CheckCalib(BaseModel):
    present: bool
    valid: bool
    problem: str | None = None


class CheckPoses(BaseModel):
    source: Literal["file", "estimated", "missing", "invalid", "will-estimate"]
    path: str
    lines: int | None = None
    method: str | None = None


class CheckFinding(BaseModel):
    code: str = Field(description="stable identifier (leap_core.pipeline.preflight.REASONS)")
    severity: Literal["blocker", "warning", "info"]
    path: str | None = None
    detail: str
    frames: list[str] = Field(default_factory=list, description="the first frames concerned")
    count: int = Field(default=0, description="frames concerned in all")
    message: str = Field(description="the finding in one line (file, problem, frames)")
    fix: str = Field(description="what to do, worded for this app ('' when nothing)")


class CheckLabeler(BaseModel):
    name: str
    label: str
    can_run: bool
    reasons: list[str] = Field(default_factory=list)
    reason: str = ""


class CheckStage(BaseModel):
    name: str
    label: str
    state: Literal["runs", "skipped", "blocked"]
    reasons: list[str] = Field(default_factory=list)
    reason: str = ""


class DatasetCheck(BaseModel):
    """What the pipeline can do with a dataset (leap_core.pipeline.preflight; `leap check` prints it)."""

    root: str
    verdict: Literal["full", "partial", "none"]
    summary: str
    frames: int
    first_frame: str | None = None
    last_frame: str | None = None
    images: CheckCoverage
    ground_truth: CheckCoverage
    gt2d: CheckCoverage
    calib: CheckCalib
    poses: CheckPoses
    labeler: str = Field(description="the labeler the stages were judged for")
    labeler_chosen: bool
    labelers: list[CheckLabeler]
    stages: list[CheckStage]
    findings: list[CheckFinding]
    cameras: list[CheckCamera] = Field(default=[], description="the rig's cameras, the primary one first")


class DatasetPublic(BaseModel):
    kind: DatasetKind
    path: str
    exists: bool
    frames: int | None = None
    has_ground_truth: bool = False
    check: DatasetCheck | None = Field(
        default=None,
        description="what the project's pipeline can do with the dataset (None: not generated yet)",
    )


class SequencePublic(BaseModel):
    name: str = Field(description="the sequence's name in runs, metrics and exports")
    dataset: DatasetPublic


class StaleResults(BaseModel):
    """The project's sequences changed since its latest finished run: that run's results describe other
    sequences than the project's now, and a re-run labels the current ones together."""

    run_id: int
    run_number: int
    added: list[str] = Field(description="project sequences the run did not label (added since)")
    removed: list[str] = Field(
        description="sequences the run labeled that the project no longer has (their run folders stay)"
    )
    message: str = Field(description="one line for the user")


class SequencesPublic(BaseModel):
    data: list[SequencePublic] = Field(description="the project's sequences in run order")
    count: int
    stale: StaleResults | None = Field(
        default=None, description="set when sequences were added or removed since the latest finished run"
    )


class RunBrief(BaseModel):
    id: int
    number: int
    status: RunStatus
    created_at: str
    finished_at: str | None = None
    miou: float | None = Field(
        default=None, description="camera-view mIoU of the run's final labels (last result row)"
    )
    miou_row: str | None = Field(
        default=None, description="which result row `miou` is (voxel, +3D-CN x1, ...)"
    )


class ProjectPublic(BaseModel):
    id: int
    name: str
    dataset: DatasetPublic = Field(description="the project's (first) sequence")
    sequences: list[SequencePublic] = Field(
        default_factory=list, description="every sequence, in order (one for a single-sequence project)"
    )
    schema_name: str
    num_classes: int
    pipeline: dict[str, Any]
    form: dict[str, Any] = Field(description="the flat parameters the UI edits (see ProjectUpdate.form)")
    estimate_poses: bool = Field(
        default=False, description="runs estimate poses with KISS-ICP when the dataset has none"
    )
    is_demo: bool
    created_at: str
    updated_at: str
    active_run: RunBrief | None = None
    last_run: RunBrief | None = None
    runs_count: int = 0
    stale: StaleResults | None = Field(
        default=None,
        description="set when sequences were added or removed since the latest finished run (re-run)",
    )


class ProjectsPublic(BaseModel):
    data: list[ProjectPublic]
    count: int


class DatasetCandidate(BaseModel):
    path: str
    frames: int
    has_images: bool
    has_ground_truth: bool
    check: DatasetCheck = Field(description="what a new project's pipeline could do with it")


class DatasetsPublic(BaseModel):
    data: list[DatasetCandidate]
    count: int
    roots: list[str]


# ------------------------------------------------------------------------------------------------ runs
class FrameRange(_Input):
    """Frame numbers start..stop-1 (scan ``000010.bin`` is frame 10), as ``leap run --frames A:B``."""

    start: int = Field(default=0, ge=0, description="first frame number")
    stop: int = Field(ge=1, description="frame number after the last one (exclusive)")

    @model_validator(mode="after")
    def _order(self) -> FrameRange:
        if self.stop <= self.start:
            raise ValueError("stop must be greater than start")
        return self


RUN_NOTE_MAX = 500
"""Longest run note, in characters."""


class RunCreate(_Input):
    frames: FrameRange | None = Field(default=None, description="label only these frames (default: all)")
    note: str | None = Field(default=None, max_length=RUN_NOTE_MAX, description="free text kept with the run")


class RunUpdate(_Input):
    note: str | None = Field(max_length=RUN_NOTE_MAX, description="the run's note; null or '' clears it")


class StagePublic(BaseModel):
    name: str
    status: StageStatus = "pending"
    done: int = 0
    total: int = 0
    seconds: float | None = None
    eta_s: float | None = None
    percent: float = 0.0
    note: str | None = Field(default=None, description="why a skipped stage computed nothing")
    expected_s: float | None = Field(
        default=None,
        description="the stage's expected seconds in all, its weight in the run's percent: what it took "
        "(done), its own rate's projection (running), the previous run's time or its expected cost (to "
        "come); 0 when skipped",
    )


class RunProgress(BaseModel):
    """Live state of one run (what the progress stream sends)."""

    run_id: int
    project_id: int
    status: RunStatus
    stage: str | None = None
    percent: float = Field(
        default=0.0, description="Σ expected_s · stage percent / Σ expected_s: stages weighted by their cost"
    )
    eta_s: float | None = Field(
        default=None,
        description="seconds left: the running stages' own rates plus the expected_s of those to come; "
        "null until some stage has a rate",
    )
    stages: list[StagePublic] = Field(default_factory=list)
    error: str | None = None
    warnings: list[str] = Field(
        default_factory=list, description="what the pipeline warned about (e.g. frames without an image)"
    )
    updated_at: str
    version: int = 0


class RunPublic(BaseModel):
    id: int
    project_id: int
    number: int
    status: RunStatus
    created_at: str
    started_at: str | None
    finished_at: str | None
    attempts: int
    error: str | None
    params: dict[str, Any]
    progress: RunProgress
    has_metrics: bool
    has_export: bool
    resumable: bool
    fix_setting: str | None = Field(
        default=None,
        description="a failed run whose fix is a project setting: that setting as the web UI names it (e.g. "
        '"Estimate poses (KISS-ICP)"). Resume keeps the run\'s own settings, so after changing it start a '
        "new run (POST /projects/{id}/runs) instead",
    )
    summary: dict[str, Any] | None = Field(default=None, description="headline metrics (mIoU per result row)")
    note: str | None = Field(default=None, description="the note given when the run was started or later")


class RunsPublic(BaseModel):
    data: list[RunPublic]
    count: int


class MetricsPublic(BaseModel):
    run_id: int
    class_names: list[str]
    metrics: dict[str, Any]
    before_corrections: bool = Field(
        default=False,
        description="the run's export now carries corrections applied after its evaluation (the "
        "apply-corrections job); these figures describe the labels before them until a re-run",
    )
    sequence: str | None = Field(
        default=None,
        description="the sequence these figures are of (null: the run's own, overall for a "
        "run of several sequences)",
    )
    sequences: list[str] = Field(
        default_factory=list,
        description="the run's sequences with metrics of their own (`?sequence=`), in run order: "
        "one name for a run of one sequence, whose own figures are that sequence's",
    )


class ChangePublic(BaseModel):
    """One difference between two runs' inputs (or between the latest run and the project now)."""

    kind: Literal["dataset", "frames", "class", "parameter", "correction", "poses"]
    subject: str = Field(
        description="class name, dotted parameter path, sequence name, correction id or `estimate_poses`"
    )
    text: str = Field(description="one line for people")
    ignored: str | None = Field(
        default=None, description="a parameter the newer configuration ignores: why (it changed nothing)"
    )
    field: str | None = Field(
        default=None,
        description="a change of one class's field: which (`prompts`, `gt_ids`, `export_id`, `thing`, "
        "`moving_id`, ...); null for a class added, removed or reordered and for the other kinds",
    )


class ClassDelta(BaseModel):
    name: str
    iou: float | None = Field(description="IoU in the run (null: not evaluated in it)")
    base_iou: float | None = Field(description="IoU in the base run (null: not evaluated in it)")
    delta: float | None = Field(description="iou - base_iou, when both exist")


class RowDelta(BaseModel):
    protocol: str
    row: str
    miou: float | None
    base_miou: float | None
    delta: float | None
    classes: list[ClassDelta] = Field(description="the run's classes, then the base run's others")


class ComparePublic(BaseModel):
    """A run against an earlier one: the Δ per class and result row, and what changed in between."""

    run_id: int
    base_run_id: int
    changes: list[ChangePublic] = Field(
        description="base run → run: dataset, frames, pose estimation, classes, parameters, corrections"
    )
    rows: list[RowDelta] = Field(description="per protocol, the result rows both runs have")


class StagePlanPublic(BaseModel):
    name: str
    label: str
    action: Literal["recompute", "reuse", "off"]
    reason: str


class RunBasis(BaseModel):
    id: int
    number: int


class RunPreview(BaseModel):
    """What the next run of the project will recompute and why."""

    base_run: RunBasis | None = Field(
        description="the finished run whose outputs the next run starts from (null: it starts empty)"
    )
    stages: list[StagePlanPublic]
    recompute: list[str] = Field(description="names of the stages the next run recomputes")
    changes: list[ChangePublic] = Field(description="the base run → the project's current settings")
    problem: str | None = Field(default=None, description="why the fingerprints could not be computed")
    stale: StaleResults | None = Field(
        default=None, description="the sequences changed since the latest finished run (nothing reused)"
    )


class LogPublic(BaseModel):
    run_id: int
    text: str
    truncated: bool


# --------------------------------------------------------------------------------------------- exports
class ExportWrite(_Input):
    path: str | None = Field(
        default=None,
        max_length=4096,
        description="a folder that receives <path>/sequences/<name>/predictions/ for each sequence of the "
        "run (SemanticKITTI's layout): the datasets' common root (each sequence's own predictions/) or a "
        "folder inside the app's export folder (<work_dir>/exports); default: each sequence's own "
        "predictions/ folder, beside its velodyne/",
    )
    include_confidence: bool = Field(default=False, description="also copy the .conf files")
    overwrite: bool = Field(
        default=False,
        description="replace the .label/.conf files a previous export left there; without it a folder that "
        "holds files is refused (409) and nothing is written",
    )


class ExportWritten(BaseModel):
    run_id: int
    path: str = Field(description="the folder given, or the first sequence's predictions/ folder")
    files: int = Field(description="files written")
    replaced: int = Field(description="files the folder held before (0 unless overwrite was set)")


class UnlabeledReason(BaseModel):
    key: str = Field(description="`outside_view` or `no_mask` (README, 'Exports')")
    label: str
    points: int
    explanation: str


class ExportClassCount(BaseModel):
    name: str
    export_id: int
    color: str
    points: int


class ExportTargetPublic(BaseModel):
    sequence: str
    path: str
    existing: int = Field(description="entries it holds now (writing them needs overwrite)")


class ExportInfo(BaseModel):
    """A finished run's export: point counts, why points stay unlabeled, and the default target folder."""

    run_id: int
    frames: int
    points: int
    labeled: int
    unlabeled: int
    reasons: list[UnlabeledReason] = Field(description="unlabeled points by reason; they sum to `unlabeled`")
    threshold_note: str = Field(description="why there is no 'below threshold' count")
    classes: list[ExportClassCount]
    targets: list[ExportTargetPublic] = Field(
        description="per sequence of the run, its own predictions/ folder (where an export without a path "
        "writes)"
    )
    predictions_allowed: bool = Field(description="whether those folders may receive an export")
    provenance: dict[str, Any] = Field(
        default_factory=dict,
        description="where the labels came from, as the zip's summary.yaml records it: the labeler and "
        "whether its weights are real or random test models, each sequence's poses (file or estimated, and "
        "how), the corrections applied (counts and a digest), classes the 2D labeler never found, the code "
        "version",
    )
    provenance_lines: list[str] = Field(default_factory=list, description="`provenance` in a few lines")


# -------------------------------------------------------------------------------------------- pipeline
class StageInfoPublic(BaseModel):
    """One stage a run goes through, in execution order."""

    name: str = Field(description="stage name, as in a run's progress (`RunProgress.stages[].name`)")
    label: str = Field(description="short human label")
    description: str = Field(description="one line on what the stage computes")
    per_frame: bool = Field(description="works frame by frame (resumable per frame; progress counts frames)")
    switch: str | None = Field(
        default=None, description="flat name of the form field that turns the stage on (`consistency`)"
    )


class FormChoice(BaseModel):
    value: str
    label: str


class FormFieldPublic(BaseModel):
    """One parameter of the project form (the flat `ProjectPublic.form` / `ProjectUpdate.form` values)."""

    name: str = Field(description="flat name in `ProjectPublic.form` and `ProjectUpdate.form`")
    path: str = Field(description="dotted path in the pipeline configuration (`fusion.voxel_size`)")
    label: str
    kind: Literal["select", "number", "integer", "checkbox"] = Field(description="input widget")
    help: str = Field(description="one line on what the setting changes")
    minimum: float | None = None
    maximum: float | None = None
    step: float | None = None
    choices: list[FormChoice] = Field(default_factory=list, description="`select` only")
    labeler: str | None = Field(
        default=None, description="only this labeler reads the setting; the others ignore it"
    )
    stage: str | None = Field(
        default=None, description="only this stage reads the setting; ignored while its `switch` is off"
    )


class LabelerPublic(BaseModel):
    name: str = Field(description="value of the pipeline's `labeler` setting")
    label: str


class RunStatusesPublic(BaseModel):
    active: list[RunStatus] = Field(description="a run in these states is queued or working")
    terminal: list[RunStatus] = Field(description="a run in these states has ended")
    resumable: list[RunStatus] = Field(description="a run in these states can be resumed")


class PresetPublic(BaseModel):
    name: str = Field(description="value of ProjectCreate.schema_name")
    classes: list[str] = Field(description="the preset's class names, in order")


class PipelinePublic(BaseModel):
    """What the web UI shows of the pipeline: its stages, the parameter form and the 2D labelers."""

    stages: list[StageInfoPublic] = Field(
        description="every stage a run can report, in order (the demo generation first: it runs before the "
        "pipeline when a demo project's sequence does not exist yet)"
    )
    form: list[FormFieldPublic] = Field(description="the project form's parameters, in display order")
    labelers: list[LabelerPublic]
    run_statuses: RunStatusesPublic
    presets: list[PresetPublic] = Field(
        default_factory=list,
        description="the built-in class presets a project can be created from (projects/*.yaml), by name",
    )


# ---------------------------------------------------------------------------------------------- health
class HealthPublic(BaseModel):
    status: Literal["ok", "degraded"] = Field(description="degraded when `problems` is not empty")
    version: str
    db_schema_version: int
    queued: int
    running: int
    viewer: bool
    auth_required: bool
    workers: int = Field(description="job threads the server started (settings.max_parallel_runs)")
    workers_alive: int = Field(description="job threads still alive (fewer means runs cannot execute)")
    unsaved_runs: list[int] = Field(description="ended runs whose end the database refused so far")
    disk_free_mb: float | None = Field(description="free MiB on the work folder's file system")
    min_free_disk_mb: float = Field(description="below this free space no run starts")
    problems: list[str] = Field(description="what needs attention, one sentence each")


class Message(BaseModel):
    message: str


# ----------------------------------------------------------------------------------------- corrections
CORRECTION_MAX_ITEMS = 5_000_000
"""Most voxel keys or point indices one correction may list (the request body limit applies too)."""


class CorrectionCreate(_Input):
    """A manual correction made through the API (author "api"); the viewer makes them itself."""

    class_name: str | None = Field(
        default=None,
        max_length=64,
        description="class to assign; '' erases to unlabeled (export id 0); required but for an object's "
        "merge or split, which take none",
    )
    voxel_size: float = Field(gt=0, le=100, description="voxel edge (m) the keys were computed with")
    keys: list[Annotated[int, Field(ge=0, le=2**63 - 1)]] = Field(
        default_factory=list, max_length=CORRECTION_MAX_ITEMS, description="packed voxel keys covered"
    )
    scope: Literal["map", "scan", "object"] = Field(
        default="map",
        description="'map': all scans' points in the voxels; 'scan': listed points of one scan; 'object': "
        "every point of one object (a run's track) in every scan",
    )
    frame_id: str | None = Field(
        default=None,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.-]+$",
        description="scan scope: the scan's frame id (file stem)",
    )
    points: list[Annotated[int, Field(ge=0, le=2**31 - 1)]] | None = Field(
        default=None,
        max_length=CORRECTION_MAX_ITEMS,
        description="scan scope: indices into the scan's points",
    )
    sequence: str | None = Field(
        default=None,
        pattern=SEQUENCE_NAME_PATTERN,
        description="the project sequence it corrects (default: the first; keys and frame ids are per "
        "sequence)",
    )
    run_id: int | None = Field(default=None, ge=1, le=2**62, description="object scope: the run whose track")
    track_id: int | None = Field(
        default=None,
        ge=1,
        le=0xFFFF,
        description="object scope: the object (instance id) of that run, as its export shows it now",
    )
    action: Literal["relabel", "merge", "split"] = Field(
        default="relabel",
        description="object scope: 'relabel' gives class_name to the object; 'merge' joins the object "
        "other_track_id into track_id (one id, one class); 'split' gives the object's points from scan "
        "frame on a new id",
    )
    other_track_id: int | None = Field(
        default=None, ge=1, le=0xFFFF, description="object merge: the object merged into track_id"
    )
    frame: str | None = Field(
        default=None,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.-]+$",
        description="object split: the frame id of the first scan the new object holds",
    )

    @field_validator("class_name")
    @classmethod
    def _class(cls, value: str | None) -> str | None:
        return value if value is None or value == "" else _check_class_name(value)

    @model_validator(mode="after")
    def _scope(self) -> CorrectionCreate:
        if self.scope == "scan" and (self.frame_id is None or self.points is None):
            raise ValueError("a scan-scope correction needs frame_id and points")
        if self.scope != "scan" and (self.frame_id is not None or self.points is not None):
            raise ValueError("frame_id and points are only for scan-scope corrections")
        if (self.scope == "object") != (self.run_id is not None and self.track_id is not None):
            raise ValueError("an object-scope correction, and only one, needs run_id and track_id")
        if self.action != "relabel" and self.scope != "object":
            raise ValueError(f"action {self.action!r} is for object-scope corrections")
        if (self.action == "relabel") == (self.class_name is None):
            raise ValueError("class_name is required, but for an object's merge or split, which take none")
        if (self.action == "merge") != (self.other_track_id is not None):
            raise ValueError("other_track_id is for a merge, which needs it")
        if (self.action == "split") != (self.frame is not None):
            raise ValueError("frame is for a split, which needs it")
        return self


class CorrectionUpdate(_Input):
    active: bool = Field(description="false undoes the correction, true redoes it")


class ObjectMatch(BaseModel):
    """Where an object-scope correction lands in a run (docs/METHOD.md B.6, "Object corrections")."""

    run_id: int
    run_number: int
    track: int = Field(description="the run's track of highest overlap (0: none shares a point)")
    iou: float = Field(description="its IoU with the corrected object")
    applied: bool = Field(
        description="false: it changes nothing (an IoU not above 0.5: it no longer matches an object; a "
        "merge whose objects are one, a split whose scan the run did not label)"
    )
    other_track: int | None = Field(default=None, description="merge: the object met by the one merged in")
    other_iou: float | None = Field(default=None, description="merge: its IoU")
    new_track: int | None = Field(default=None, description="split: the new object's id (0: not applied)")


class CorrectionPublic(BaseModel):
    id: int
    created_at: str
    class_name: str = Field(description="assigned class; '' = erased to unlabeled")
    scope: Literal["map", "scan", "object"]
    frame_id: str | None = Field(description="scan scope: the scan")
    voxels: int = Field(description="voxels covered")
    points: int | None = Field(description="scan scope: points covered")
    author: str | None = Field(description="'viewer', 'api', or null for corrections older than authors")
    active: bool
    sequence: str | None = Field(default=None, description="the project sequence it corrects")
    reviewer: str | None = Field(default=None, description="the reviewer's name given to the viewer tab")
    run_id: int | None = Field(default=None, description="object scope: the run it was made on")
    track_id: int | None = Field(default=None, description="object scope: that run's object")
    action: Literal["relabel", "merge", "split"] | None = Field(
        default=None, description="object scope: what it does (null for map and scan scope)"
    )
    other_track_id: int | None = Field(default=None, description="object merge: the object merged in")
    split_frame: str | None = Field(default=None, description="object split: the new object's first scan")
    match: ObjectMatch | None = Field(
        default=None, description="object scope: the track of the latest finished run it meets, if known"
    )


class CorrectionClassCount(BaseModel):
    class_name: str
    corrections: int = Field(description="active corrections assigning this class")
    voxels: int = Field(description="voxels they cover (a voxel corrected twice counts twice)")


class CorrectionApply(BaseModel):
    """The "apply corrections" job (app/jobs/apply.py ApplyState)."""

    status: Literal["idle", "running", "done", "failed", "no_run"]
    run_id: int | None
    run_number: int | None
    frames: int
    changed_voxels: int
    baked_reverts: int
    seconds: float
    error: str | None
    finished_at: str | None


class CorrectionList(BaseModel):
    corrections: list[CorrectionPublic]
    per_class: list[CorrectionClassCount]
    apply: CorrectionApply
    latest_run_objects: bool | None = Field(
        default=None,
        description="whether the latest finished run tracked objects in this sequence (its tracks are what "
        "object corrections reach); null when the project has no finished run of the sequence",
    )


# ------------------------------------------------------------------------------ LiDAR-only models
MODEL_NAME_MAX = 80
MODEL_STEPS_MAX = 100_000
"""The app's cap on a training's steps (the CLI allows more): a job holds the server's one model thread."""


class ModelTrainCreate(_Input):
    """Train a LiDAR-only model on the project's latest finished run's final labels (corrections win)."""

    name: str = Field(
        default="model", min_length=1, max_length=MODEL_NAME_MAX, description="the model's name"
    )
    steps: int = Field(default=200, ge=1, le=MODEL_STEPS_MAX, description="optimisation steps")
    points_per_scan: int = Field(
        default=8192, ge=256, le=1_000_000, description="points drawn from a scan per step (time and memory)"
    )
    validation: Literal["block", "sequence"] = Field(
        default="block",
        description="held apart for validation: every val_every-th block of val_block frames of each "
        "sequence, or one whole sequence (validation_sequence)",
    )
    validation_sequence: str | None = Field(
        default=None, max_length=200, description="the sequence held apart (validation = 'sequence')"
    )
    val_block: int = Field(default=10, ge=1, le=100_000, description="frames per validation block")
    val_every: int = Field(default=5, ge=2, le=1000, description="every this-many-th block validates")
    seed: int = Field(default=0, ge=0, le=2**32 - 1, description="seed of weights, order, draws")

    @field_validator("name")
    @classmethod
    def _model_name(cls, v: str) -> str:
        if _BAD_NAME_CHARS.search(v):
            raise ValueError("model names may not contain '/', '\\' or control characters")
        return v


class ModelLabelCreate(_Input):
    """Label one of the project's sequences, or a sequence folder inside a data root, with a model of the
    project (give one of ``sequence`` and ``dataset``)."""

    sequence: str | None = Field(
        default=None, min_length=1, max_length=200, description="the project's sequence to label"
    )
    dataset: str | None = Field(
        default=None,
        min_length=1,
        max_length=4096,
        description="a KITTI-layout sequence folder inside a data root to label instead (LiDAR only)",
    )

    @model_validator(mode="after")
    def _one_target(self) -> ModelLabelCreate:
        if (self.sequence is None) == (self.dataset is None):
            raise ValueError("give one of 'sequence' (the project's) or 'dataset' (a folder in a data root)")
        return self


class ModelJobPublic(BaseModel):
    id: int
    project_id: int
    kind: Literal["train", "label"]
    status: str
    name: str
    model_id: int | None
    done: int
    total: int
    error: str | None
    created_at: str
    started_at: str | None
    finished_at: str | None
    download: str | None = Field(default=None, description="the labels' zip (a finished labeling)")


class ModelJobsPublic(BaseModel):
    data: list[ModelJobPublic]
    count: int


class ModelPublic(BaseModel):
    id: int = Field(description="the id of the job that trained it")
    name: str
    card: dict[str, Any] = Field(description="classes, data and runs seen, settings, validation, code, when")


class ModelsPublic(BaseModel):
    data: list[ModelPublic]
    count: int


# ------------------------------------------------------------------------------------------- objects
class ObjectPublic(BaseModel):
    """One object (track) of a finished run's sequence (``tracks.npz``; docs/METHOD.md B.6)."""

    id: int = Field(description="track id: the instance id in the export's upper 16 bits")
    class_name: str = Field(description="its voted class")
    scans: int = Field(description="scans in which it has points")
    first_frame: str | None = Field(description="frame id of the first of them (null: none)")
    last_frame: str | None = Field(description="frame id of the last of them (null: none)")
    gaps: int = Field(description="scans between the first and the last without its points")
    moving: bool
    speed: float = Field(description="m/s, the norm of its least-squares velocity")
    vote_share: float = Field(description="the voted class's share of the class vote over its scans, 0..1")
    runner_up: str | None = Field(description="the class with the next most votes (null: no other)")
    runner_up_share: float = Field(description="its share of the vote, 0..1")
    queued: list[ReasonCode] = Field(
        description="why the object review queue holds it, in priority order (empty: not queued)"
    )
    reason: str = Field(description="the same for a person: 'car 48 % vs truck 41 %; 3 gaps'")


class ObjectsPublic(BaseModel):
    """A page of a run's objects: every object by id, or (``queued=true``) the review queue in order."""

    run_id: int
    sequence: str
    data: list[ObjectPublic]
    count: int = Field(description="objects matching the filter, over all pages")
    offset: int
    limit: int
