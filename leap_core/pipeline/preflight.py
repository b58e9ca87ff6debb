"""What a sequence folder holds and what the pipeline can do with it, before a run (``leap check``, the
app's project creation and dataset list).

:func:`check_dataset` is a pure inspection: it lists the folder's entries, reads ``calib.txt`` and the
poses, opens the folder with :class:`~leap_core.datasets.kitti.KittiSequence` (the reader every run uses,
so the check refuses exactly what a run would refuse) and never raises for a bad folder: every problem
becomes a :class:`Finding` with a code, the file it concerns and a neutral description. Each per-frame
file is looked at without being read: a link leading outside the sequence folder or a pipe is named (the
reader refuses the folder), as is a directory in place of a file. Scans are not read (only their sizes
are checked) and of the camera images only the header and the last bytes (a truncated PNG or JPEG, an
image of another size than the others), so the check costs a few directory listings and small reads
whatever the sequence length.

It judges the pipeline's stages (:data:`~leap_core.pipeline.stages.STAGE_TABLE`) and labelers
(:data:`~leap_core.labelers.LABELERS`) against the folder, so it lives with the pipeline. Its results are
neutral: finding codes (:data:`REASONS`), the files concerned and what is wrong. How to fix a finding is
worded by whoever shows it: ``leap check`` and the app (``app/advice.py``: the CLI's advice names
``leap`` commands and flags, the app's names its own options, never a command-line flag).

Verdict (:attr:`DatasetReport.verdict`):

- ``"none"``: nothing can run (no folder, no scans, bad calibration, a file the reader refuses, or no
  input any 2D labeler reads: neither camera images nor 2D ground truth);
- ``"partial"``: some stages cannot run (e.g. no poses: the 3D stages; the chosen labeler lacks its
  input or its models);
- ``"full"``: every stage can run (a stage that is merely skipped, evaluation without ground truth or a
  switched-off 3D-CN, does not count against it).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal

from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import (
    FRAME_FOLDERS,
    IMAGE_SUFFIXES,
    LINK_OUTSIDE,
    NOT_REGULAR,
    POSES_NOTE,
    KittiSequence,
    folder_problems,
    image_size,
    read_calib,
    read_poses,
    sequence_roots,
)
from leap_core.datasets.rig import gt2d_folder
from leap_core.errors import DatasetError, ModelLoadError
from leap_core.labelers import LABELERS
from leap_core.labelers.grounded_sam import model_folder_name, resolve_model_folder
from leap_core.labelers.tiny_models import is_tiny_random
from leap_core.pipeline.stages import STAGE_TABLE
from leap_core.runtime import Runtime

Severity = Literal["blocker", "warning", "info"]
"""``blocker``: nothing can run; ``warning``: something cannot run or will be wrong; ``info``: a fact."""
Verdict = Literal["full", "partial", "none"]
StageState = Literal["runs", "skipped", "blocked"]
"""``runs``: the stage can compute; ``skipped``: it will run as a no-op (evaluation without ground truth,
3D-CN switched off); ``blocked``: it cannot run on this dataset."""
PoseSource = Literal["file", "estimated", "missing", "invalid", "will-estimate"]

SHOWN_FRAMES = 5
"""Frame ids a finding names (the rest are counted)."""
POSES_STAGES = ("motion", "fuse", "smooth", "3dcn", "label_points", "tracks", "evaluate", "export")
"""Stages that place scans in the world (they read ``frame.pose``); ``labels2d`` and ``project`` do not."""


# ------------------------------------------------------------------------------------------ records
@dataclass(frozen=True)
class Finding:
    """One fact about the folder that limits what can run (or that a user should know)."""

    code: str
    """Stable identifier (``poses_missing``, ``calib_invalid``, ...: the keys of :data:`REASONS`)."""
    severity: Severity
    path: str | None
    """The file or folder it concerns."""
    detail: str
    """What is wrong, neutral (no advice: the place it is shown adds that)."""
    frames: tuple[str, ...] = ()
    """Frame ids concerned (the first :data:`SHOWN_FRAMES`), when per frame."""
    count: int = 0
    """How many frames are concerned in all (0 when not per frame)."""


@dataclass(frozen=True)
class FrameCoverage:
    """How many of the sequence's scans have a per-frame file of one kind."""

    present: int
    """Scans with the file."""
    total: int
    """Scans in ``velodyne/``."""

    @property
    def kind(self) -> Literal["all", "some", "none"]:
        if self.total and self.present >= self.total:
            return "all"
        return "some" if self.present else "none"


@dataclass(frozen=True)
class CalibCheck:
    present: bool
    """``calib.txt`` exists."""
    valid: bool
    """It has a usable P2 and Tr."""
    problem: str | None = None
    """What the reader refused (the file's problem), when not valid."""


@dataclass(frozen=True)
class CameraCheck:
    """One camera of the sequence's rig (:attr:`~leap_core.datasets.kitti.KittiSequence.cameras`)."""

    name: str
    """Its image folder (``image_2``, ``CAM_FRONT``)."""
    source: str
    """Where its projection was read (``calib.txt P3``, ``cameras.yaml``)."""
    images: FrameCoverage
    """Scans with an image of this camera."""
    gt2d: FrameCoverage
    """Scans with this camera's 2D ground truth (semantic and instance masks)."""


@dataclass(frozen=True)
class PosesCheck:
    source: PoseSource
    """``file`` / ``estimated`` (:data:`~leap_core.datasets.kitti.POSES_NOTE` beside it, as
    ``KittiSequence.pose_source``), ``missing``, ``invalid`` (unreadable) or ``will-estimate`` (missing,
    and the caller estimates them before the 3D stages)."""
    path: str
    """The poses file the sequence reads."""
    lines: int | None = None
    """Poses in the file (None when missing or unreadable)."""
    method: str | None = None
    """For estimated poses: the note's ``method`` (``kiss-icp``)."""


@dataclass(frozen=True)
class LabelerCheck:
    name: str
    """Registry name (``leap_core.labelers.LABELERS``)."""
    label: str
    """Its human name (the app's choice)."""
    can_run: bool
    reasons: tuple[str, ...] = ()
    """Codes of the findings that stop it."""


@dataclass(frozen=True)
class StageCheck:
    name: str
    """Stage name (``leap_core.pipeline.STAGES``)."""
    label: str
    state: StageState
    reasons: tuple[str, ...] = ()
    """Codes of the findings (or ``needs:<stage>``, ``off``) behind a skipped or blocked state."""


@dataclass(frozen=True)
class DatasetReport:
    """The result of :func:`check_dataset`."""

    root: str
    verdict: Verdict
    frames: int
    """Scans in ``velodyne/``."""
    first_frame: str | None
    last_frame: str | None
    images: FrameCoverage
    ground_truth: FrameCoverage
    """``labels/<frame>.label`` per scan (3D ground truth)."""
    gt2d: FrameCoverage
    """``gt2d/semantic`` + ``gt2d/instance`` masks per scan (2D ground truth)."""
    calib: CalibCheck
    poses: PosesCheck
    labeler: str
    """The labeler the stages were judged for."""
    labeler_chosen: bool
    """True when the caller named the labeler; False when the check picked the first one that can run."""
    labelers: tuple[LabelerCheck, ...]
    stages: tuple[StageCheck, ...]
    findings: tuple[Finding, ...]
    cameras: tuple[CameraCheck, ...] = ()
    """The rig's cameras, primary first (empty when the reader cannot open the folder)."""

    def finding(self, code: str) -> Finding | None:
        return next((f for f in self.findings if f.code == code), None)

    @property
    def blocked_stages(self) -> list[str]:
        return [s.name for s in self.stages if s.state == "blocked"]


GT2D_MASKS = ("semantic", "instance")
"""The 2D ground-truth masks a frame's camera needs for the simulated labeler."""


def _camera_checks(seq: KittiSequence) -> tuple[CameraCheck, ...]:
    """Per camera of the rig: where its calibration came from, and how many scans have its image and
    its 2D ground truth."""
    out = []
    n = len(seq)
    for k, cam in enumerate(seq.cameras):
        images = sum(seq.image_path(i, k) is not None for i in range(n))
        masks = [
            _stems(seq.root / gt2d_folder(seq.cameras, k, kind), (".png",))
            for kind in ("semantic", "instance")
        ]
        gt2d = len(set(seq.frame_ids) & masks[0] & masks[1])
        out.append(CameraCheck(cam.name, cam.source, FrameCoverage(images, n), FrameCoverage(gt2d, n)))
    return tuple(out)


# ----------------------------------------------------------------------------------------- listing
def _stems(folder: Path, suffixes: Iterable[str]) -> set[str]:
    if not folder.is_dir():
        return set()
    allowed = tuple(suffixes)
    try:
        with os.scandir(folder) as it:
            return {os.path.splitext(e.name)[0] for e in it if e.name.lower().endswith(allowed)}
    except OSError:
        return set()


def _entry_findings(root: Path) -> tuple[list[Finding], dict[str, set[str]]]:
    """Findings on the per-frame files the reader may not read (:func:`~leap_core.datasets.kitti.
    folder_problems`), one per folder and kind, and per folder the stems of those files (they count as
    absent).

    ``linked_outside`` (a blocker): links leading outside the sequence's roots. ``not_a_file``: a pipe,
    socket or device anywhere, or a scan that is not a file, blocks (the reader refuses the sequence);
    a directory or dangling link in place of a label, image or 2D mask is a warning (that frame lacks it).
    """
    roots = sequence_roots(root)
    findings: list[Finding] = []
    unusable: dict[str, set[str]] = {}
    for name, suffixes in FRAME_FOLDERS.items():
        problems = folder_problems(root / name, suffixes, roots)
        unusable[name] = {os.path.splitext(entry)[0] for entry, _ in problems}
        outside = [(e, p) for e, p in problems if p == LINK_OUTSIDE]
        other = [(e, p) for e, p in problems if p != LINK_OUTSIDE]
        if outside:
            findings.append(_files_finding("linked_outside", "blocker", root / name, outside))
        if other:
            blocks = name == "velodyne" or any(p == NOT_REGULAR for _, p in other)
            findings.append(
                _files_finding("not_a_file", "blocker" if blocks else "warning", root / name, other)
            )
    return findings, unusable


def _files_finding(code: str, severity: Severity, folder: Path, items: list[tuple[str, str]]) -> Finding:
    """A finding naming each file of ``folder`` and what it is (the first :data:`SHOWN_FRAMES`)."""
    shown = "; ".join(f"{entry} is {problem}" for entry, problem in items[:SHOWN_FRAMES])
    more = f"; and {len(items) - SHOWN_FRAMES} more" if len(items) > SHOWN_FRAMES else ""
    stems = [os.path.splitext(entry)[0] for entry, _ in items]
    return Finding(code, severity, str(folder), shown + more, tuple(stems[:SHOWN_FRAMES]), len(stems))


def _image_files(folder: Path, frames: Iterable[str], skip: set[str]) -> dict[str, Path]:
    """Frame id → its camera image in ``folder`` (as the reader indexes them), for ``frames`` not in
    ``skip``."""
    wanted = set(frames) - skip
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return {}
    return {p.stem: p for p in entries if p.suffix.lower() in IMAGE_SUFFIXES and p.stem in wanted}


def _image_findings(folder: Path, images: dict[str, Path]) -> list[Finding]:
    """``images_damaged``: images whose header the reader refuses (not a PNG or JPEG, truncated);
    ``images_size``: images of another size than most of the sequence's (the calibration projects into
    one image size). Only headers and the files' last bytes are read."""
    sizes: dict[str, tuple[int, int]] = {}
    damaged: list[tuple[str, str]] = []
    for fid, path in images.items():
        try:
            sizes[fid] = image_size(path)
        except DatasetError as exc:
            damaged.append((path.name, exc.problem.removeprefix("unreadable image: ")))
    out = []
    if damaged:
        out.append(_files_finding("images_damaged", "warning", folder, damaged))
    if sizes:
        counts: dict[tuple[int, int], int] = {}
        for size in sizes.values():
            counts[size] = counts.get(size, 0) + 1
        usual = max(counts, key=lambda k: counts[k])  # the most common; ties: the first frame's
        odd = [
            (images[fid].name, f"{w}×{h} pixels, the sequence's other images {usual[0]}×{usual[1]}")
            for fid, (w, h) in sizes.items()
            if (w, h) != usual
        ]
        if odd:
            out.append(_files_finding("images_size", "warning", folder, odd))
    return out


def _scan_sizes(vel: Path) -> dict[str, int]:
    out: dict[str, int] = {}
    try:
        with os.scandir(vel) as it:
            for e in it:
                if e.name.endswith(".bin"):
                    try:
                        out[e.name[:-4]] = e.stat().st_size
                    except OSError:
                        out[e.name[:-4]] = -1
    except OSError:
        pass
    return out


def _ordered(ids: Iterable[str]) -> list[str]:
    items = list(ids)
    if all(s.isdigit() for s in items):
        return sorted(items, key=lambda s: (int(s), s))
    return sorted(items)


def _missing(frames: list[str], have: set[str]) -> list[str]:
    return [f for f in frames if f not in have]


def _per_frame(code: str, severity: Severity, path: Path, detail: str, frames: list[str]) -> Finding:
    return Finding(code, severity, str(path), detail, tuple(frames[:SHOWN_FRAMES]), len(frames))


def dataset_stamp(root: str | Path, poses_path: str | Path | None = None) -> tuple[Any, ...]:
    """A cheap key that changes when :func:`check_dataset`'s answer may change: the modification time
    and size of the folder and of every entry it reads (a file added to or removed from a folder changes
    the folder's mtime). For caching reports (the app's dataset list)."""
    root = Path(root)
    names = (
        "",
        "velodyne",
        "image_2",
        "labels",
        "gt2d",
        "gt2d/semantic",
        "gt2d/instance",
        "calib.txt",
        "poses.txt",
        "times.txt",
        POSES_NOTE,
    )
    paths = [root / n if n else root for n in names]
    if poses_path is not None:
        paths += [Path(poses_path), Path(poses_path).parent / POSES_NOTE]
    stamp: list[Any] = [str(root)]
    for p in paths:
        try:
            st = p.stat()
            stamp.append((st.st_mtime_ns, st.st_size, st.st_ino))
        except OSError:
            stamp.append(None)
    return tuple(stamp)


# ------------------------------------------------------------------------------------------- check
def check_dataset(  # noqa: PLR0912, PLR0915  # one pass over the folder's parts, in the order they matter
    root: str | Path,
    *,
    config: PipelineConfig | None = None,
    runtime: Runtime | None = None,
    poses_path: str | Path | None = None,
    estimate_poses: bool = False,
    check_models: bool = True,
    labeler_named: bool | None = None,
) -> DatasetReport:
    """Inspect a KITTI-layout sequence folder; never raises for a bad folder.

    Args:
        root: the sequence folder (``.../sequences/NN``).
        config: the pipeline settings the run would use (its labeler, model ids, 3D-CN switch). None =
            the defaults, with the first labeler (registry order) that can run on the folder.
        runtime: where models are looked for (``models_dir``; None = the Hugging Face cache).
        poses_path: read the poses from this file instead of ``root/poses.txt`` (as ``KittiSequence``).
        estimate_poses: missing poses will be estimated before the 3D stages (the app's "Estimate poses
            (KISS-ICP)" option, ``leap run --estimate-poses``): the 3D stages are then not blocked by them.
        check_models: look for the model labelers' folders (skip for a listing that must stay cheap).
        labeler_named: whether the user named ``config.labeler`` (``--labeler``, or a ``labeler:`` in the
            project file); when not, the check judges the labeler :func:`pick_labeler` picks, as ``leap
            run`` does. None = named whenever ``config`` is given (the app's projects name theirs).

    Returns:
        The :class:`DatasetReport`.
    """
    root = Path(root)
    chosen = config is not None if labeler_named is None else labeler_named
    cfg = config or PipelineConfig()
    rt = runtime or Runtime()
    poses_file = Path(poses_path) if poses_path is not None else root / "poses.txt"
    findings: list[Finding] = []
    empty = FrameCoverage(0, 0)

    def early(code: str, path: Path, detail: str) -> DatasetReport:
        findings.append(Finding(code, "blocker", str(path), detail))
        return _assemble(
            root,
            [],
            empty,
            empty,
            empty,
            CalibCheck(False, False),
            PosesCheck("missing", str(poses_file)),
            cfg,
            chosen,
            findings,
            {},
            {},
        )

    if not root.is_dir():
        return early("not_a_folder", root, "no such folder" if not root.exists() else "not a folder")
    vel = root / "velodyne"
    if not vel.is_dir():
        inner = sorted(p.parent.name for p in root.glob("sequences/*/velodyne") if p.is_dir())
        inner += sorted(p.parent.name for p in root.glob("*/velodyne") if p.is_dir())
        hint = f"; it holds sequence folders: {', '.join(inner[:5])}" if inner else ""
        return early(
            "not_a_sequence", vel, f"no velodyne/ folder, so this is not a KITTI sequence folder{hint}"
        )
    sizes = _scan_sizes(vel)
    frames = _ordered(sizes)
    if not frames:
        return early("no_scans", vel, "no .bin scans")
    entry_findings, unusable = _entry_findings(root)
    findings += entry_findings
    damaged = [f for f in frames if f not in unusable["velodyne"] and (sizes[f] < 0 or sizes[f] % 16)]
    if damaged:
        findings.append(
            _per_frame(
                "scans_damaged",
                "blocker",
                vel,
                "scans whose size is not a whole number of points (16 bytes: float32 x, y, z, remission)",
                damaged,
            )
        )

    images = _stems(root / "image_2", IMAGE_SUFFIXES) - unusable["image_2"]
    labels = _stems(root / "labels", (".label",)) - unusable["labels"]
    gt2d = (_stems(root / "gt2d" / "semantic", (".png",)) - unusable["gt2d/semantic"]) & (
        _stems(root / "gt2d" / "instance", (".png",)) - unusable["gt2d/instance"]
    )
    findings += _image_findings(root / "image_2", _image_files(root / "image_2", frames, unusable["image_2"]))
    cover_img = FrameCoverage(len(set(frames) & images), len(frames))
    cover_gt = FrameCoverage(len(set(frames) & labels), len(frames))
    cover_2d = FrameCoverage(len(set(frames) & gt2d), len(frames))

    # Calibration: needed by every stage from the projection on (and by the reader to open the folder).
    calib_path = root / "calib.txt"
    if not calib_path.is_file():
        calib = CalibCheck(False, False, "missing")
        findings.append(Finding("calib_missing", "blocker", str(calib_path), "no calibration file"))
    else:
        try:
            read_calib(calib_path)
            calib = CalibCheck(True, True)
        except DatasetError as exc:
            calib = CalibCheck(True, False, exc.problem)
            findings.append(Finding("calib_invalid", "blocker", str(calib_path), exc.problem))

    # The reader every run uses decides what opens; its own poses reading gives pose_source.
    poses: PosesCheck | None = None
    cameras: tuple[CameraCheck, ...] = ()
    try:
        seq = KittiSequence(root, poses_path=poses_file)
    except (DatasetError, OSError, ValueError) as exc:
        where = Path(getattr(exc, "path", root))
        problem = getattr(exc, "problem", str(exc))
        said = {Path(f.path) for f in findings if f.severity == "blocker" and f.path is not None}
        if where == poses_file:
            findings.append(Finding("poses_unreadable", "blocker", str(poses_file), problem))
        elif where not in said and where.parent not in said:  # a file a finding above names already
            findings.append(Finding("unreadable", "blocker", str(where), problem))
    else:
        cameras = _camera_checks(seq)
        for cam in seq.cameras[1:]:  # the primary camera's images are checked above
            folder = root / cam.name
            findings += _image_findings(folder, _image_files(folder, frames, set()))
        if seq.has_poses:
            source = seq.pose_source
            method = _note_method(poses_file) if source == "estimated" else None
            poses = PosesCheck(
                "estimated" if source == "estimated" else "file", str(poses_file), seq.pose_lines, method
            )
        else:
            poses = PosesCheck("missing", str(poses_file))
    if poses is None:  # the reader stopped before (or without) reading the poses: read them here
        if not poses_file.is_file():
            poses = PosesCheck("missing", str(poses_file))
        else:
            try:
                poses = PosesCheck("file", str(poses_file), len(read_poses(poses_file)))
            except DatasetError as exc:
                poses = PosesCheck("invalid", str(poses_file))
                if not any(f.path == str(poses_file) for f in findings):  # the reader's refusal says it
                    findings.append(Finding("poses_invalid", "warning", str(poses_file), exc.problem))
    if poses.source == "missing":
        if estimate_poses:
            poses = PosesCheck("will-estimate", str(poses_file))
            findings.append(
                Finding(
                    "poses_will_estimate",
                    "info",
                    str(poses_file),
                    "no poses file: the poses will be estimated (KISS-ICP) before the 3D stages",
                )
            )
        else:
            findings.append(
                Finding(
                    "poses_missing",
                    "warning",
                    str(poses_file),
                    "no poses file: the 3D stages need one pose per scan",
                )
            )
    elif poses.lines is not None:
        # A scan NNNNNN takes pose line NNNNNN (the frame's number), so the file may hold more lines than
        # there are scans (a subset copied out of a sequence) but not fewer than the highest number + 1.
        numbered = all(f.isdigit() for f in frames)
        beyond = (
            [f for f in frames if int(f) >= poses.lines]
            if numbered
            else (frames[poses.lines :] if poses.lines < len(frames) else [])
        )
        if beyond:
            findings.append(
                _per_frame(
                    "poses_short",
                    "warning",
                    poses_file,
                    f"{poses.lines} poses, but scans are numbered up to {frames[-1]}: "
                    "frames past the last line have no pose",
                    beyond,
                )
            )
        elif poses.lines > len(frames):
            findings.append(
                Finding(
                    "poses_extra",
                    "info",
                    str(poses_file),
                    f"{poses.lines} poses for {len(frames)} scans: scan NNNNNN takes pose "
                    "line NNNNNN (counted from 0)",
                )
            )
        if poses.source == "estimated":
            findings.append(
                Finding(
                    "poses_estimated",
                    "info",
                    str(poses_file),
                    f"estimated poses ({poses.method or 'method not recorded'}; note {POSES_NOTE})",
                )
            )

    # 2D inputs: camera images (grounded-sam, sam3), 2D ground truth (simulated).
    if cover_img.kind == "none":
        findings.append(Finding("images_missing", "warning", str(root / "image_2"), "no camera images"))
    elif cover_img.kind == "some":
        findings.append(
            _per_frame(
                "images_partial",
                "warning",
                root / "image_2",
                "scans without a camera image of the same number",
                _missing(frames, images),
            )
        )
    if cover_2d.kind == "none":
        findings.append(Finding("gt2d_missing", "info", str(root / "gt2d"), "no 2D ground truth"))
    elif cover_2d.kind == "some":
        findings.append(
            _per_frame(
                "gt2d_partial",
                "warning",
                root / "gt2d",
                "scans without 2D ground truth (gt2d/semantic and gt2d/instance)",
                _missing(frames, gt2d),
            )
        )
    if cover_img.kind == "none" and cover_2d.kind == "none":
        findings.append(
            Finding(
                "no_2d_input",
                "blocker",
                str(root),
                "neither camera images (image_2/) nor 2D ground truth (gt2d/): no 2D labeler "
                "has anything to label",
            )
        )
    if cover_gt.kind == "none":
        findings.append(
            Finding(
                "labels_missing",
                "info",
                str(root / "labels"),
                "no ground-truth labels: the run is not evaluated",
            )
        )
    elif cover_gt.kind == "some":
        findings.append(
            _per_frame(
                "labels_partial",
                "warning",
                root / "labels",
                "scans without a ground-truth .label file: the run is not evaluated",
                _missing(frames, labels),
            )
        )
    model_findings: dict[str, list[Finding]] = {}
    model_codes = _check_models(cfg, rt, model_findings) if check_models else {}
    report = _assemble(
        root,
        frames,
        cover_img,
        cover_gt,
        cover_2d,
        calib,
        poses,
        cfg,
        chosen,
        findings,
        model_codes,
        model_findings,
    )
    return replace(report, cameras=cameras)


def _note_method(poses_file: Path) -> str | None:
    try:
        note = json.loads((poses_file.parent / POSES_NOTE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    method = note.get("method") if isinstance(note, dict) else None
    return str(method) if method else None


def _check_models(
    cfg: PipelineConfig, rt: Runtime, findings: dict[str, list[Finding]]
) -> dict[str, tuple[str, ...]]:
    """Findings on the model folders of every labeler that loads models, into ``findings[labeler]``;
    returns {labeler: codes that stop it}."""
    out: dict[str, tuple[str, ...]] = {}
    for spec in LABELERS.values():
        ids = spec.models(spec.config_of(cfg))
        if ids:
            out[spec.name] = _check_model_folders(spec.name, ids, rt, findings.setdefault(spec.name, []))
    return out


def _check_model_folders(
    labeler: str, model_ids: Sequence[str], rt: Runtime, findings: list[Finding]
) -> tuple[str, ...]:
    missing: list[str] = []
    for model_id in model_ids:
        try:
            folder = resolve_model_folder(model_id, rt.models_dir, allow_download=False)
        except ModelLoadError:
            missing.append(model_id)
            continue
        if is_tiny_random(folder):
            findings.append(
                Finding(
                    "models_random",
                    "warning",
                    str(folder),
                    f"{model_id}: a tiny RANDOM-weight test model; its labels are meaningless",
                )
            )
    if not missing:
        return ()
    if rt.models_dir is not None:
        names = ", ".join(f"{model_folder_name(m)}/ ({m})" for m in missing)
        findings.append(
            Finding(
                "models_missing",
                "warning",
                str(rt.models_dir),
                f"no model folder with a config.json for {names}, which the {labeler} labeler loads",
            )
        )
    else:
        findings.append(
            Finding(
                "models_missing",
                "warning",
                None,
                f"no models folder is set and {', '.join(missing)} "
                f"{'is' if len(missing) == 1 else 'are'} not in the Hugging Face cache "
                f"(the {labeler} labeler loads {'it' if len(missing) == 1 else 'them'})",
            )
        )
    return ("models_missing",)


IMAGE_CODES = ("images_damaged", "images_size")
"""Findings on the camera images that stop a labeler reading them (a damaged image fails its frame; one of
another size is projected with the calibration of the others, so its labels land on the wrong points)."""


def _labeler_checks(
    frames: list[str],
    img: FrameCoverage,
    gt2d: FrameCoverage,
    model_codes: dict[str, tuple[str, ...]],
    image_codes: tuple[str, ...] = (),
) -> tuple[LabelerCheck, ...]:
    out = []
    for name, spec in LABELERS.items():
        cover = img if spec.needs == "images" else gt2d
        if not frames:
            reasons: tuple[str, ...] = ("no_scans",)
        elif cover.kind == "none":
            reasons = ("images_missing",) if spec.needs == "images" else ("gt2d_missing",)
        elif cover.kind == "some":
            reasons = ("images_partial",) if spec.needs == "images" else ("gt2d_partial",)
        else:
            reasons = ()
        if spec.needs == "images":
            reasons += image_codes
        reasons += model_codes.get(name, ())
        out.append(LabelerCheck(name, spec.label, not reasons, reasons))
    return tuple(out)


def _alternative(labelers: Iterable[LabelerCheck], besides: str | None) -> LabelerCheck | None:
    """The labeler to suggest: the first (registry order) that can run, else the first whose input the
    folder has and that lacks only its models."""
    others = [lab for lab in labelers if lab.name != besides]
    return next((lab for lab in others if lab.can_run), None) or next(
        (lab for lab in others if set(lab.reasons) <= {"models_missing"}), None
    )


def pick_labeler(per_sequence: Sequence[Sequence[LabelerCheck]], named: str | None = None) -> str | None:
    """The 2D labeler a run uses, the one rule ``leap check`` and ``leap run`` share.

    Args:
        per_sequence: each sequence's :attr:`DatasetReport.labelers` (one entry for a run of one).
        named: the labeler the user named (``--labeler``, a project file's ``labeler:``), if any.

    Returns:
        ``named`` when given; else the first labeler (registry order) that can run on every sequence;
        else the first that lacks nothing but its models on any of them (the run then says which folder
        to give); else None (nothing fits: the config's own labeler stays, and the check says why).
    """
    if named is not None:
        return named
    if not per_sequence:
        return None
    names = [lab.name for lab in per_sequence[0]]
    by_seq = [{lab.name: lab for lab in labs} for labs in per_sequence]

    def fits(name: str, allowed: set[str]) -> bool:
        return all(name in labs and set(labs[name].reasons) <= allowed for labs in by_seq)

    return next((n for n in names if fits(n, set())), None) or next(
        (n for n in names if fits(n, {"models_missing"})), None
    )


def _assemble(  # noqa: PLR0912, PLR0913, PLR0917  # the parts check_dataset gathered
    root: Path,
    frames: list[str],
    img: FrameCoverage,
    gt: FrameCoverage,
    gt2d: FrameCoverage,
    calib: CalibCheck,
    poses: PosesCheck,
    cfg: PipelineConfig,
    chosen: bool,
    findings: list[Finding],
    model_codes: dict[str, tuple[str, ...]],
    model_findings: dict[str, list[Finding]],
) -> DatasetReport:
    image_codes = tuple(c for c in IMAGE_CODES if any(f.code == c for f in findings))
    labelers = _labeler_checks(frames, img, gt2d, model_codes, image_codes)
    by_name = {lab.name: lab for lab in labelers}
    labeler = pick_labeler([labelers], cfg.labeler if chosen else None) or cfg.labeler
    alt = _alternative(labelers, labeler)
    # The models of the labeler that runs (or of the one suggested instead) are what the user acts on;
    # the others' are a fact, not a warning.
    acting = labeler if by_name[labeler].can_run or alt is None else alt.name
    for name, found in model_findings.items():
        findings += found if name == acting else [replace(f, severity="info") for f in found]
    blockers = [f.code for f in findings if f.severity == "blocker"]
    if not by_name[labeler].can_run and not blockers and alt is not None:
        # Only with another labeler to suggest: otherwise the findings behind it carry the fixes.
        why = ", ".join(reason_text(r) for r in by_name[labeler].reasons)
        findings.append(
            Finding(
                "labeler_cannot_run",
                "warning",
                None,
                f"the {labeler} labeler cannot run ({why})"
                + (
                    f"; the {alt.name} labeler can"
                    if alt.can_run
                    else f"; the {alt.name} labeler could, given its models"
                ),
            )
        )
    codes = {f.code for f in findings}
    pose_codes = tuple(c for c in ("poses_missing", "poses_invalid", "poses_short") if c in codes)
    stages: list[StageCheck] = []
    state: dict[str, StageState] = {}
    for info in STAGE_TABLE:
        reasons: list[str] = []
        if blockers:
            reasons = blockers
        else:
            if info.name == "labels2d" and not by_name[labeler].can_run:
                reasons = ["labeler_cannot_run", *by_name[labeler].reasons]
            if info.name in POSES_STAGES:
                reasons += pose_codes
            if not reasons:  # its own reasons already say why; "needs X" only when it has none
                reasons = [f"needs:{u}" for u in info.upstream if state.get(u) == "blocked"]
        if reasons:
            st: StageState = "blocked"
        elif not info.is_enabled(cfg):
            st, reasons = "skipped", ["off"]
        elif info.name == "evaluate" and gt.kind != "all":
            st, reasons = "skipped", ["labels_missing" if gt.kind == "none" else "labels_partial"]
        else:
            st = "runs"
        state[info.name] = st
        stages.append(StageCheck(info.name, info.label, st, tuple(dict.fromkeys(reasons))))
    if blockers:
        verdict: Verdict = "none"
    elif any(s.state == "blocked" for s in stages):
        verdict = "partial"
    else:
        verdict = "full"
    return DatasetReport(
        root=str(root),
        verdict=verdict,
        frames=len(frames),
        first_frame=frames[0] if frames else None,
        last_frame=frames[-1] if frames else None,
        images=img,
        ground_truth=gt,
        gt2d=gt2d,
        calib=calib,
        poses=poses,
        labeler=labeler,
        labeler_chosen=chosen,
        labelers=labelers,
        stages=tuple(stages),
        findings=tuple(findings),
    )


# ------------------------------------------------------------------------------------------ wording
REASONS: dict[str, str] = {
    "not_a_folder": "no such folder",
    "not_a_sequence": "not a sequence folder",
    "no_scans": "no scans",
    "scans_damaged": "damaged scans",
    "calib_missing": "no calibration",
    "calib_invalid": "unusable calibration",
    "unreadable": "a file the reader refuses",
    "linked_outside": "files linked outside the sequence folder",
    "not_a_file": "entries that are not files",
    "images_damaged": "damaged camera images",
    "images_size": "camera images of another size",
    "no_2d_input": "nothing to label from",
    "images_missing": "no camera images",
    "images_partial": "frames without a camera image",
    "gt2d_missing": "no 2D ground truth",
    "gt2d_partial": "frames without 2D ground truth",
    "labels_missing": "no ground truth",
    "labels_partial": "ground truth for only some scans",
    "poses_missing": "no poses",
    "poses_will_estimate": "",
    "poses_invalid": "unreadable poses",
    "poses_unreadable": "unreadable poses",
    "poses_short": "frames without a pose",
    "poses_extra": "",
    "poses_estimated": "",
    "models_missing": "its models are not found",
    "models_random": "",
    "labeler_cannot_run": "the chosen labeler cannot run",
    "off": "3D-CN off",
}
"""Every finding code (:attr:`Finding.code`; also the reason codes of stages and labelers), with a short
neutral phrase for a stage or labeler that it stops (``"no poses"``; empty where the code never stops
one). How to fix a finding depends on where it is shown (a command-line flag, an option of the app), so
that wording is the caller's: the ``leap`` CLI's and the app's live in ``app/advice.py``."""


def describe(finding: Finding) -> str:
    """The finding in one line: its file, what is wrong and the frames concerned."""
    text = f"{finding.path}: {finding.detail}" if finding.path else finding.detail
    if finding.count:
        shown = ", ".join(finding.frames) + (", …" if finding.count > len(finding.frames) else "")
        text += f" ({finding.count} frame{'s' if finding.count != 1 else ''}: {shown})"
    return text


def reason_text(code: str) -> str:
    """A stage's or labeler's reason code as a short phrase."""
    if code.startswith("needs:"):
        return f"needs {code.split(':', 1)[1]}"
    return REASONS.get(code) or code.replace("_", " ")


VERDICT_TEXT: dict[Verdict, str] = {
    "full": "every stage can run",
    "partial": "only some stages can run",
    "none": "the pipeline cannot run on this folder",
}


def summary_text(report: DatasetReport) -> str:
    """The verdict in words, as it agrees with the stage list: :data:`VERDICT_TEXT`, except that a
    ``partial`` verdict counts the stages that cannot run, and says so when that is all of them (the
    folder is usable, but not as set up: another labeler, its models or poses would unblock them)."""
    blocked = report.blocked_stages
    if report.verdict != "partial" or not blocked:
        return VERDICT_TEXT[report.verdict]
    total = len(report.stages)
    if len(blocked) == total:
        return f"no stage can run as set up (all {total} cannot run; the findings say what unblocks them)"
    return f"only some stages can run ({len(blocked)} of {total} cannot run: {', '.join(blocked)})"


def stage_line(stage: StageCheck) -> str:
    """``runs`` / ``skipped (no ground truth)`` / ``cannot run (no poses)``."""
    why = ", ".join(reason_text(r) for r in stage.reasons)
    if stage.state == "runs":
        return "runs"
    return f"skipped ({why})" if stage.state == "skipped" else f"cannot run ({why})"


def alternative_labeler(report: DatasetReport) -> LabelerCheck | None:
    """The labeler to suggest instead of the report's (:func:`_alternative`), or None."""
    return _alternative(report.labelers, report.labeler)


def report_data(report: DatasetReport) -> dict[str, Any]:
    """The report as plain JSON-able data: each finding with its one-line ``message``
    (:func:`describe`), each stage and labeler with its ``reason`` (:func:`reason_text`), the verdict's
    ``summary`` and each coverage's ``kind``. A caller adds the fixes in its own words."""
    data = asdict(report)
    data["summary"] = summary_text(report)
    for cover in ("images", "ground_truth", "gt2d"):
        data[cover]["kind"] = getattr(report, cover).kind
    for cam, entry in zip(report.cameras, data["cameras"], strict=True):
        entry["images"]["kind"] = cam.images.kind
        entry["gt2d"]["kind"] = cam.gt2d.kind
    data["findings"] = [{**asdict(f), "message": describe(f)} for f in report.findings]
    data["stages"] = [
        {**asdict(s), "reason": "" if s.state == "runs" else ", ".join(map(reason_text, s.reasons))}
        for s in report.stages
    ]
    data["labelers"] = [
        {**asdict(lab), "reason": ", ".join(map(reason_text, lab.reasons))} for lab in report.labelers
    ]
    return data


__all__ = [
    "POSES_STAGES",
    "REASONS",
    "VERDICT_TEXT",
    "CalibCheck",
    "CameraCheck",
    "DatasetReport",
    "Finding",
    "FrameCoverage",
    "LabelerCheck",
    "PosesCheck",
    "StageCheck",
    "Verdict",
    "alternative_labeler",
    "check_dataset",
    "dataset_stamp",
    "describe",
    "pick_labeler",
    "reason_text",
    "report_data",
    "stage_line",
    "summary_text",
]
