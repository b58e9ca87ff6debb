"""What every stage works with: the stage record type, the run context, fingerprint hashing helpers and the
readers of per-frame files that several stages share."""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import os
from collections import deque
from collections.abc import Callable, Generator, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt

from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import KittiSequence
from leap_core.datasets.rig import FRAME_TR_FOLDER, GT2D_KINDS, RIG_FILE
from leap_core.errors import DatasetError
from leap_core.io_utils import atomic_write_json, file_digest, read_npz
from leap_core.labelers import make_labeler
from leap_core.projection import Painted
from leap_core.run_layout import SequenceLayout
from leap_core.runtime import Runtime
from leap_core.schema import Schema

if TYPE_CHECKING:
    from leap_core.labelers.base import Labeler

_R = TypeVar("_R")


def ordered_map(fn: Callable[[int], _R], items: Iterable[int], threads: int) -> Generator[_R, None, None]:
    """``fn(i)`` for each item, yielded in item order, with up to ``threads`` calls in flight on a thread
    pool (``threads`` ≤ 1: one after the other, in this thread).

    The next item starts only when the consumer asks for the next result, so a consumer that raises (or
    closes the generator: use :func:`contextlib.closing`) starts no further items; the calls already
    running are waited for and those not started are cancelled. An exception of ``fn`` is raised at its
    item's turn. Overlaps the reads of frame files (disk, page faults) with other frames' numpy work,
    which releases the GIL.
    """
    if threads <= 1:
        for i in items:
            yield fn(i)
        return
    queue = iter(items)
    with ThreadPoolExecutor(threads, thread_name_prefix="leap-frames") as pool:
        in_flight = deque(pool.submit(fn, i) for i in itertools.islice(queue, threads))
        try:
            while in_flight:
                result = in_flight.popleft().result()
                yield result
                nxt = next(queue, None)
                if nxt is not None:
                    in_flight.append(pool.submit(fn, nxt))
        except BaseException:
            for fut in in_flight:
                fut.cancel()
            raise


ProgressCallback = Callable[[str, int, int], None]
"""``progress(stage, done, total)``; may raise :class:`~leap_core.errors.Cancelled`."""

StageFn = Callable[["Ctx"], dict[str, Any]]
"""A stage: computes its outputs into the run folder; returns extra fields for its ``stages.json`` record
(``{"status": "skipped", "note": ...}`` when it had nothing to do)."""


def _no_files(_layout: SequenceLayout, _cfg: PipelineConfig) -> tuple[Path, ...]:
    return ()


@dataclass(frozen=True)
class FrameFiles:
    """Where a per-frame stage writes: ``<sequence folder>/<folder>/<frame_id><suffix>`` for every suffix."""

    folder: str
    """A :class:`~leap_core.run_layout.SequenceLayout` per-frame folder name."""
    suffixes: tuple[str, ...] = (".npz",)
    """One file per suffix and frame; a frame is done when all exist."""


@dataclass(frozen=True)
class StageInfo:
    """One stage of the pipeline: what the app shows, what it runs, what it reads and what it writes.

    The runner derives everything from these records: the order (the table's), the fingerprint (config
    sections read + upstream fingerprints + other inputs), when a stage is current (fingerprint matches and
    outputs exist), what is cleared when its inputs change, and frame-by-frame resumption.
    """

    name: str
    """Key in ``stages.json``, progress messages and the API."""
    label: str
    """Short human name ("Voxel fusion")."""
    description: str
    """One line: what the stage computes and writes."""
    per_frame: bool
    """True when the stage works (and resumes) frame by frame (then :attr:`frame_files` is set)."""
    run: StageFn = field(repr=False, compare=False)
    """The stage function."""
    reads: tuple[str, ...] = ()
    """:class:`~leap_core.config.PipelineConfig` sections (top-level keys of ``config_to_dict``) hashed into
    the fingerprint."""
    upstream: tuple[str, ...] = ()
    """Stages whose outputs this one reads; their fingerprints are part of this one's (all earlier in the
    table)."""
    frame_files: FrameFiles | None = None
    """Per-frame stages: their files (the folder is removed when the fingerprint changes)."""
    outputs: Callable[[SequenceLayout, PipelineConfig], tuple[Path, ...]] = field(
        default=_no_files, repr=False, compare=False
    )
    """Whole-run stages: the files a finished run of the stage has (a stage recorded as skipped has none)."""
    stale: Callable[[SequenceLayout], Iterable[Path]] | None = field(default=None, repr=False, compare=False)
    """Files removed when the fingerprint changes; None = :attr:`outputs` (for the current config)."""
    inputs: Callable[[Ctx], Any] | None = field(default=None, repr=False, compare=False)
    """Other fingerprint parts (JSON-able): labeler identity, dataset identity, frames, corrections, schema
    parts."""
    switch: str | None = None
    """Dotted :class:`~leap_core.config.PipelineConfig` path of the boolean that turns the stage on
    (``"consistency.enabled"``); None = no switch. The app greys out the settings of a switched-off stage
    (:mod:`leap_core.pipeline.steering`), so the switch is data, not only code."""
    needs_poses: bool = False
    """True when the stage places scans in the world (``frame.pose``): a run that reaches it on a sequence
    without poses is refused before any stage runs (:func:`~leap_core.pipeline.runner.require_poses`)."""
    enabled: Callable[[PipelineConfig], bool] | None = field(default=None, repr=False, compare=False)
    """Any further condition; the stage runs when its :attr:`switch` (if any) is on and this (if any)
    returns True, else it is recorded as skipped (and its fingerprint then ignores :attr:`reads` and
    :attr:`inputs`)."""

    def __post_init__(self) -> None:
        if self.per_frame != (self.frame_files is not None):
            raise ValueError(f"stage {self.name}: per_frame and frame_files disagree")

    def is_enabled(self, cfg: PipelineConfig) -> bool:
        if self.switch is not None and not config_value(cfg, self.switch):
            return False
        return self.enabled is None or self.enabled(cfg)


def config_value(cfg: PipelineConfig, path: str) -> Any:
    """The value at a dotted path of ``cfg``'s dict form (``"consistency.enabled"``,
    ``"grounded_sam.box_threshold"``: a labeler's section is a top-level key)."""
    first, *rest = path.split(".")
    node: Any = cfg.labelers[first] if first in cfg.labelers else getattr(cfg, first)
    for part in rest:
        node = getattr(node, part)
    return node


# ------------------------------------------------------------------------------------------ context
@dataclass
class Ctx:
    """One sequence of a run in one :func:`~leap_core.pipeline.runner.run_sequence` call: inputs, its folder,
    records, progress."""

    seq: KittiSequence
    schema: Schema
    cfg: PipelineConfig
    layout: SequenceLayout
    frames: range
    runtime: Runtime | None
    progress: ProgressCallback | None
    table: Mapping[str, StageInfo]
    state: dict[str, dict[str, Any]] = field(default_factory=dict)
    """``stages.json`` as read at the start, updated as stages run."""
    fp: dict[str, str] = field(default_factory=dict)
    """Each stage's fingerprint for this call."""
    _labeler: Labeler | None = None

    @property
    def cache_dir(self) -> Path | None:
        """The shared 2D cache folder (:attr:`Runtime.cache_dir`), if any."""
        return None if self.runtime is None else self.runtime.cache_dir

    def fid(self, index: int) -> str:
        """Frame id (file stem) of frame ``index``."""
        return self.seq.frame_ids[index]

    def frame_ids(self) -> list[str]:
        """The ids of the run's frames, in order: what fingerprints name (never their positions, which
        shift when scans are added or removed)."""
        return [self.fid(i) for i in self.frames]

    def tick(self, stage: str, done: int, total: int) -> None:
        if self.progress is not None:
            self.progress(stage, done, total)

    def save_state(self) -> None:
        atomic_write_json(self.layout.state, self.state)

    def labeler(self) -> Labeler:
        if self._labeler is None:
            self._labeler = make_labeler(self.cfg, self.runtime)
        return self._labeler

    def missing_frames(self, stage: str) -> list[int]:
        """Frames (in order) that lack one of the per-frame stage's files."""
        files = self.table[stage].frame_files
        if files is None:
            raise ValueError(f"stage {stage} is not per-frame")
        return [
            i
            for i in self.frames
            if not all(self.layout.frame_file(files.folder, self.fid(i), s).is_file() for s in files.suffixes)
        ]

    @property
    def frame_threads(self) -> int:
        """Frames a parallel :meth:`each_frame` computes at a time (:attr:`Runtime.frame_threads`)."""
        return (self.runtime or Runtime()).frame_threads

    def each_frame(
        self, stage: str, work: Callable[[int], None], *, parallel: bool = False
    ) -> dict[str, Any]:
        """Run ``work(i)`` on the frames that lack the stage's files, reporting progress over all frames.

        With ``parallel``, up to :attr:`frame_threads` frames are in flight on a thread pool; ``work`` must
        then only read shared state. Frames are started and their completions reported in frame order, so
        the progress calls are those of the one-by-one loop. An exception (a frame's error, or
        :class:`~leap_core.errors.Cancelled` from the progress callback) stops further frames from starting,
        waits for those already running (their files are whole: atomic writes) and is raised.
        """
        todo = self.missing_frames(stage)
        total = len(self.frames)
        done = total - len(todo)
        self.tick(stage, done, total)
        threads = min(self.frame_threads, len(todo)) if parallel else 1
        with contextlib.closing(ordered_map(work, todo, threads)) as results:
            for _ in results:
                done += 1
                self.tick(stage, done, total)  # before the next frame starts: Cancelled stops it
        return {"frames_done": total, "frames_computed": len(todo)}


def read_state(layout: SequenceLayout) -> dict[str, dict[str, Any]]:
    """``stages.json`` ({} when the run has none)."""
    path = layout.state
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"unreadable stage record ({exc}); delete it to recompute the run") from exc
    if not isinstance(data, dict):
        raise DatasetError(path, "stage record must be a JSON object")
    return data


# ------------------------------------------------------------------------------------- fingerprints
def hash_json(obj: Any) -> str:
    """24 hex digits of the SHA-256 of ``obj``'s sorted-key JSON."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:24]


def dataset_identity(seq: KittiSequence) -> str:
    """Hash of a sequence's location, calibration, poses (the file it reads them from, which may lie in a
    run folder: estimated poses) and the size + mtime of every per-frame file."""
    root = seq.root.resolve()
    poses = file_digest(seq.poses_path) if seq.has_poses else None
    parts: list[Any] = [str(root), file_digest(root / "calib.txt"), poses]
    folders = ["velodyne", "labels", "image_2", "gt2d/semantic", "gt2d/instance", "gt2d/name"]
    # A newer optional folder counts only where present, so older sequences keep their identity.
    if (root / "gt2d" / "cell").is_dir():
        folders.append("gt2d/cell")
    if len(seq.cameras) > 1 or seq.rig_source != "calib.txt":
        rig = root / RIG_FILE
        parts.append(["rig", file_digest(rig) if rig.is_file() else None])
        folders += [f for f in seq.camera_folders() if (root / f).is_dir()]
        if (root / FRAME_TR_FOLDER).is_dir():
            folders.append(FRAME_TR_FOLDER)
    for name in folders:
        folder = root / name
        if not folder.is_dir():
            parts.append([name, None])
            continue
        with os.scandir(folder) as it:
            entries = sorted((e.name, e.stat().st_size, e.stat().st_mtime_ns) for e in it if e.is_file())
        parts.append([name, entries])
    return hash_json(parts)


def frame_input_digest(seq: KittiSequence, index: int, camera: int = 0) -> str:
    """Content digest of what a 2D labeler reads for one frame of one camera: its frame number and id (what
    seeds depend on), the camera's name (for cameras after the primary one), its image and 2D ground
    truth, if any."""
    key = f"{seq.frame_numbers[index]}|{seq.frame_ids[index]}"
    if camera:
        key += f"|{seq.cameras[camera].name}"
    h = hashlib.sha256(key.encode())
    frame = seq.frame(index, camera)
    paths = [seq.image_path(index, camera), *(frame.gt2d_path(kind) for kind in GT2D_KINDS)]
    for p in paths:
        if p is not None and p.is_file():
            h.update(p.name.encode())
            h.update(file_digest(seq.confined(p)).encode())
    return h.hexdigest()[:32]


# ------------------------------------------------------------------------------------- shared readers
def load_observation(path: Path) -> tuple[Painted, int, npt.NDArray[np.bool_]]:
    """An ``observations/`` file: the painted points, the scan's point count and its in-image mask (N,)
    (one read of the file)."""
    arrays = _read_observation(path, None)
    n, in_view = _view_of(path, arrays)
    return Painted.from_arrays(path, arrays), n, in_view


def load_view(path: Path) -> tuple[int, npt.NDArray[np.bool_]]:
    """An ``observations/`` file's scan point count and in-image mask (N,), without its painted points
    (two small members of the file read, for the stages that only count and mask points)."""
    return _view_of(path, _read_observation(path, ("n_points", "in_view")))


def _read_observation(path: Path, names: tuple[str, ...] | None) -> dict[str, npt.NDArray[Any]]:
    try:
        return read_npz(path, names)
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable observation file ({exc})") from exc


def _view_of(path: Path, arrays: dict[str, npt.NDArray[Any]]) -> tuple[int, npt.NDArray[np.bool_]]:
    try:
        n = int(arrays["n_points"])
        in_view = np.unpackbits(arrays["in_view"], count=n).astype(bool)
    except (KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable observation file ({exc})") from exc
    return n, in_view


__all__ = [
    "Ctx",
    "FrameFiles",
    "ProgressCallback",
    "StageFn",
    "StageInfo",
    "config_value",
    "dataset_identity",
    "file_digest",
    "frame_input_digest",
    "hash_json",
    "load_observation",
    "load_view",
    "read_state",
]
