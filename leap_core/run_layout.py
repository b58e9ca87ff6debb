"""Every path of a run folder, in one place: the pipeline writes and the app, the viewer and the exports read
through :class:`RunLayout` and :class:`SequenceLayout`, so no other module spells a run-folder file name.

A run labels a list of sequences (often one) with one class schema and one config. Its folder::

    <root>/
      run.json                    the run's sequences: name, dataset folder, frames (in run order), and
                                  its settings (pipeline: the config it labels with)
      metrics.json                {"overall": metrics of the summed confusion matrices, "sequences": {...}}
      sequences/<name>/           one sequence's folder (below)
      3dcn/3dcn_iter{i}.pt        the 3D-CN's checkpoints (one network per round, trained on every sequence)
      3dcn/joint.json             the fingerprint the staged rounds below belong to (and ray_tasks: the
                                  inference tasks of the last rounds computed on Ray)
      3dcn/rounds/<name>/grid_3dcn{i}.npz, grid_smooth_3dcn{i}.npz
                                  round i's grids of each sequence, hard-linked into sequences/<name>/
      model.json                  the LiDAR-only model that labeled the run (`leap predict`), its card
      params.json, run.log, .lock, export.zip, export-conf.zip
                                  the app's files of this run

One sequence's folder::

    <root>/sequences/<name>/
      stages.json                 stage records (status, fingerprint, seconds, ...)
      labels2d/<frame_id>.npz     the 2D labeler's SoftMasks per frame
      observations/<frame_id>.npz projection + painting per frame
      motion.npz                  moving objects found before fusion (the motion stage; tracks.npz's format,
                                  moving tracks only): the points the fusion leaves out
      corrections.npz             map-scope manual corrections (keys (K,) int64, class_idx (K,), -1 = erase),
                                  fused into grid.npz, re-imposed on smoothed grids and on the points
      corrections_scan.npz        scan-scope corrections (leap_core.corrections.ScanCorrections), per point
      corrections_object.npz      object-scope corrections (leap_core.pipeline.object_corrections): per
                                  correction its class and the object's point rows per scan
      grid.npz                    fused VoxelGrid (keys, logp, voxel_size)
      grid_smooth.npz             SmoothedGrid (keys, probs float16, voxel_size) after kNN smoothing
      grid_3dcn{i}.npz            3D-CN round i: fused grid + network evidence
      grid_smooth_3dcn{i}.npz     ... smoothed (the final grid when the 3D-CN is on)
      3dcn_joint.json             with the 3D-CN on: the round its 3D-CN grids come from (its digest is part
                                  of the 3dcn stage's fingerprint)
      points/<frame_id>.npz       label, conf, point_label per point
      tracks.npz                  objects (the tracks stage): per scan the thing points' rows and track
                                  ids; per track its voted class, velocity, moving flag and scans seen
      metrics.json                result tables
      model-metrics.json          a LiDAR-only model's scores on the ground truth (`leap predict`)
      export/<frame_id>.label     raw export ids (a moving thing: its class's moving id), instance id << 16
      export/<frame_id>.conf      float32 per-point confidence
      export-coverage.json        the export's point counts (labeled, unlabeled by reason, per raw id)
      applied_corrections.npz, applied_corrections_scan.npz, applied_corrections_object.npz,
      frame_voxels.npz            the app's "apply corrections" job: the corrections the points and export
                                  now carry, and the voxel → frames index (leap_core.pipeline.apply)
      object_matches.json         per object correction the track it met and whether it applies
      poses/poses.txt, poses/poses_estimated.json
                                  estimated poses (KISS-ICP) the sequence uses because its dataset has none

Folders written before runs had this one shape (a single sequence's files directly in the run folder, or
``multi.json`` instead of ``run.json``) are moved into it by :func:`migrate_run_folder`.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import DatasetError, LeapError
from leap_core.io_utils import atomic_save_npz, atomic_write_json


class ConsistencySwitch(Protocol):
    """What the final-grid rule reads of :class:`~leap_core.consistency.config.ConsistencyConfig`."""

    @property
    def enabled(self) -> bool: ...

    @property
    def iterations(self) -> int: ...


_CN_GRID = re.compile(r"grid(_smooth)?_3dcn(\d+)\.npz")


@dataclass(frozen=True)
class SequenceLayout:
    """The paths of one sequence's folder in a run (nothing is created or read here, except
    :meth:`final_grid_on_disk`)."""

    folder: Path
    """The sequence's folder (``<run>/sequences/<name>``)."""

    STATE: ClassVar[str] = "stages.json"
    LABELS2D: ClassVar[str] = "labels2d"
    OBSERVATIONS: ClassVar[str] = "observations"
    POINTS: ClassVar[str] = "points"
    EXPORT: ClassVar[str] = "export"
    GRID: ClassVar[str] = "grid.npz"
    TRACKS: ClassVar[str] = "tracks.npz"
    MOTION: ClassVar[str] = "motion.npz"
    GRID_SMOOTH: ClassVar[str] = "grid_smooth.npz"
    METRICS: ClassVar[str] = "metrics.json"
    MODEL_METRICS: ClassVar[str] = "model-metrics.json"
    CORRECTIONS: ClassVar[str] = "corrections.npz"
    CORRECTIONS_SCAN: ClassVar[str] = "corrections_scan.npz"
    CORRECTIONS_OBJECT: ClassVar[str] = "corrections_object.npz"
    APPLIED_CORRECTIONS: ClassVar[str] = "applied_corrections.npz"
    APPLIED_CORRECTIONS_SCAN: ClassVar[str] = "applied_corrections_scan.npz"
    APPLIED_CORRECTIONS_OBJECT: ClassVar[str] = "applied_corrections_object.npz"
    OBJECT_MATCHES: ClassVar[str] = "object_matches.json"
    FRAME_VOXELS: ClassVar[str] = "frame_voxels.npz"
    EXPORT_COVERAGE: ClassVar[str] = "export-coverage.json"
    POSES_DIR: ClassVar[str] = "poses"
    JOINT_3DCN: ClassVar[str] = "3dcn_joint.json"
    RUN_OWN_FILES: ClassVar[frozenset[str]] = frozenset(
        {
            CORRECTIONS,
            CORRECTIONS_SCAN,
            CORRECTIONS_OBJECT,
            EXPORT_COVERAGE,
            APPLIED_CORRECTIONS,
            APPLIED_CORRECTIONS_SCAN,
            APPLIED_CORRECTIONS_OBJECT,
            FRAME_VOXELS,
        }
    )
    """Files of the folder that belong to one run only (never carried over into a later run's folder)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "folder", Path(self.folder))

    # ------------------------------------------------------------------------------- whole-run files
    def _file(self, name: str) -> Path:
        return self.folder / name

    @property
    def state(self) -> Path:
        return self._file(self.STATE)

    @property
    def tracks(self) -> Path:
        """The ``tracks`` stage's objects: per scan the thing points' track ids; per track class, motion."""
        return self._file(self.TRACKS)

    @property
    def motion(self) -> Path:
        """The ``motion`` stage's moving objects (the ``tracks.npz`` format, moving tracks only): the points
        the fusion leaves out."""
        return self._file(self.MOTION)

    @property
    def grid(self) -> Path:
        """The fused grid."""
        return self._file(self.GRID)

    @property
    def grid_smooth(self) -> Path:
        """The kNN-smoothed fused grid (the final grid without the 3D-CN)."""
        return self._file(self.GRID_SMOOTH)

    def grid_3dcn(self, iteration: int) -> Path:
        """The fused grid after 3D-CN round ``iteration`` (1-based)."""
        return self._file(f"grid_3dcn{iteration}.npz")

    def grid_smooth_3dcn(self, iteration: int) -> Path:
        """The smoothed grid after 3D-CN round ``iteration`` (1-based)."""
        return self._file(f"grid_smooth_3dcn{iteration}.npz")

    def cn_grids(self) -> list[Path]:
        """Every 3D-CN grid file present, of any round (fused and smoothed)."""
        if not self.folder.is_dir():
            return []
        return sorted(p for p in self.folder.iterdir() if _CN_GRID.fullmatch(p.name))

    @property
    def metrics(self) -> Path:
        return self._file(self.METRICS)

    @property
    def model_metrics(self) -> Path:
        """A model-labeled sequence's scores on its ground truth (``leap predict``)."""
        return self._file(self.MODEL_METRICS)

    @property
    def corrections(self) -> Path:
        """Map-scope corrections (:func:`save_corrections`)."""
        return self._file(self.CORRECTIONS)

    @property
    def corrections_scan(self) -> Path:
        """Scan-scope corrections (:class:`leap_core.corrections.ScanCorrections`)."""
        return self._file(self.CORRECTIONS_SCAN)

    @property
    def corrections_object(self) -> Path:
        """Object-scope corrections (:class:`leap_core.pipeline.object_corrections.ObjectCorrections`)."""
        return self._file(self.CORRECTIONS_OBJECT)

    @property
    def applied_corrections_object(self) -> Path:
        """Object-scope counterpart of :attr:`applied_corrections`."""
        return self._file(self.APPLIED_CORRECTIONS_OBJECT)

    @property
    def object_matches(self) -> Path:
        """Which track of the run each object correction met, and whether it applies (JSON, written by
        the export and the apply job: :meth:`CorrectedTracks.report
        <leap_core.pipeline.object_corrections.CorrectedTracks.report>`)."""
        return self._file(self.OBJECT_MATCHES)

    @property
    def applied_corrections(self) -> Path:
        """Map-scope corrections the points and export carry after the app's apply job (absent: the
        run's own :attr:`corrections`)."""
        return self._file(self.APPLIED_CORRECTIONS)

    @property
    def applied_corrections_scan(self) -> Path:
        """Scan-scope counterpart of :attr:`applied_corrections`."""
        return self._file(self.APPLIED_CORRECTIONS_SCAN)

    @property
    def frame_voxels(self) -> Path:
        """The voxel → frames index of the run's points (:class:`leap_core.corrections.FrameVoxelIndex`)."""
        return self._file(self.FRAME_VOXELS)

    @property
    def export_coverage(self) -> Path:
        """The export's cached point counts (labeled, unlabeled by reason, per raw id)."""
        return self._file(self.EXPORT_COVERAGE)

    @property
    def poses(self) -> Path:
        """Estimated poses (``poses/poses.txt``, the note beside it) for a dataset without its own, written
        by ``leap run --estimate-poses`` or the app's run of a project that estimates poses."""
        return self.folder / self.POSES_DIR / "poses.txt"

    @property
    def joint_3dcn(self) -> Path:
        """With the 3D-CN on: which round of the run's 3D-CN its 3D-CN grids come from
        (:mod:`leap_core.pipeline.run`)."""
        return self._file(self.JOINT_3DCN)

    def open_sequence(self, dataset: str | Path) -> KittiSequence:
        """The dataset as this run reads it: with the dataset's own ``poses.txt`` when it has one, else
        with the run's :attr:`poses` when present (the one rule the pipeline, the exports, the app's
        corrections and the viewer follow, so they all place the scans with the same poses)."""
        if not (Path(dataset) / "poses.txt").is_file() and self.poses.is_file():
            return KittiSequence(dataset, poses_path=self.poses)
        return KittiSequence(dataset)

    # ------------------------------------------------------------------------------- per-frame files
    def frame_folder(self, name: str) -> Path:
        """A per-frame folder (:attr:`LABELS2D`, :attr:`OBSERVATIONS`, :attr:`POINTS`, :attr:`EXPORT`)."""
        return self.folder / name

    def frame_file(self, folder: str, frame_id: str, suffix: str = ".npz") -> Path:
        """``<folder>/<per-frame folder>/<frame_id><suffix>``."""
        return self.folder / folder / f"{frame_id}{suffix}"

    def labels2d(self, frame_id: str, camera: str | None = None) -> Path:
        """A frame's 2D labels: ``labels2d/<frame_id>.npz`` for the rig's primary camera (``camera`` None),
        ``labels2d/<camera>/<frame_id>.npz`` for the camera folder ``camera`` of the others."""
        if camera is not None:
            return self.folder / self.LABELS2D / camera / f"{frame_id}.npz"
        return self.frame_file(self.LABELS2D, frame_id)

    def observation(self, frame_id: str) -> Path:
        return self.frame_file(self.OBSERVATIONS, frame_id)

    def points(self, frame_id: str) -> Path:
        return self.frame_file(self.POINTS, frame_id)

    @property
    def points_dir(self) -> Path:
        return self.frame_folder(self.POINTS)

    @property
    def export_dir(self) -> Path:
        return self.frame_folder(self.EXPORT)

    def export_label(self, frame_id: str) -> Path:
        return self.frame_file(self.EXPORT, frame_id, ".label")

    def export_conf(self, frame_id: str) -> Path:
        return self.frame_file(self.EXPORT, frame_id, ".conf")

    # ------------------------------------------------------------------------------- the final grid
    def final_grid(self, consistency: ConsistencySwitch) -> Path:
        """The grid the points take their labels from: the smoothed grid of the last 3D-CN round when the
        3D-CN is enabled, else ``grid_smooth.npz``."""
        if consistency.enabled:
            return self.grid_smooth_3dcn(consistency.iterations)
        return self.grid_smooth

    def final_grid_on_disk(self) -> Path:
        """:meth:`final_grid` for readers without the run's config: the smoothed grid of the highest 3D-CN
        round present in the folder, else ``grid_smooth.npz`` (which may not exist)."""
        rounds = [
            int(m.group(2)) for p in self.cn_grids() if (m := _CN_GRID.fullmatch(p.name)) and m.group(1)
        ]
        return self.grid_smooth_3dcn(max(rounds)) if rounds else self.grid_smooth


# ------------------------------------------------------------------------------------------- the run
_SEQUENCE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def sequence_name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a sequence of a run (a folder under ``sequences/``), or None: 1-64
    characters, letters, digits, ``_``, ``-`` and ``.``, starting with a letter or digit."""
    if not isinstance(name, str) or not _SEQUENCE_NAME.fullmatch(name):
        return (
            f"must be 1-64 letters, digits, '_', '-' or '.', starting with a letter or digit "
            f"(a folder name), got {name!r}"
        )
    return None


@dataclass(frozen=True)
class RunLayout:
    """The paths of a run folder (module docstring): one :class:`SequenceLayout` per sequence under
    ``sequences/``, the 3D-CN's files under ``3dcn/``, the overall metrics and the app's files."""

    root: Path
    """The run folder."""

    SPEC: ClassVar[str] = "run.json"
    SEQUENCES: ClassVar[str] = "sequences"
    METRICS: ClassVar[str] = "metrics.json"
    CN_DIR: ClassVar[str] = "3dcn"
    PARAMS: ClassVar[str] = "params.json"
    LOG: ClassVar[str] = "run.log"
    LOCK: ClassVar[str] = ".lock"
    EXPORT_ZIP: ClassVar[str] = "export.zip"
    EXPORT_CONF_ZIP: ClassVar[str] = "export-conf.zip"
    MODEL_NOTE: ClassVar[str] = "model.json"
    RUN_FILES: ClassVar[frozenset[str]] = frozenset(
        {SPEC, SEQUENCES, METRICS, CN_DIR, PARAMS, LOG, LOCK, EXPORT_ZIP, EXPORT_CONF_ZIP, MODEL_NOTE}
    )
    """The entries of the run folder itself (everything else lives in a sequence's folder)."""
    RUN_OWN_FILES: ClassVar[frozenset[str]] = frozenset({PARAMS, LOG, LOCK, EXPORT_ZIP, EXPORT_CONF_ZIP})
    """Top-level files that belong to one run only (never carried over into a later run's folder)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def spec(self) -> Path:
        """``run.json``: the run's sequences (name, dataset, frames), written when the run starts."""
        return self.root / self.SPEC

    @property
    def metrics(self) -> Path:
        """``metrics.json``: ``{"overall": ..., "sequences": {name: ...}}``
        (:func:`leap_core.pipeline.evaluation.overall_metrics`)."""
        return self.root / self.METRICS

    @property
    def sequences_dir(self) -> Path:
        return self.root / self.SEQUENCES

    def sequence(self, name: str) -> SequenceLayout:
        """The folder of sequence ``name`` (``root/sequences/<name>``).

        Raises:
            LeapError: ``name`` is not a folder-safe sequence name (:func:`sequence_name_problem`).
        """
        problem = sequence_name_problem(name)
        if problem is not None:
            raise LeapError(f"sequence name: {problem}", field=("name",))
        return SequenceLayout(self.sequences_dir / name)

    def names(self) -> list[str]:
        """The run's sequences: in ``run.json``'s order when it exists (those whose folder is present),
        else every sequence folder under ``sequences/`` in name order."""
        listed = self._listed()
        if listed is not None:
            return [n for n in listed if (self.sequences_dir / n).is_dir()]
        if not self.sequences_dir.is_dir():
            return []
        return sorted(
            p.name
            for p in self.sequences_dir.iterdir()
            if p.is_dir() and sequence_name_problem(p.name) is None
        )

    def _listed(self) -> list[str] | None:
        if not self.spec.is_file():
            return None
        try:
            data = json.loads(self.spec.read_text())
            return [str(s["name"]) for s in data["sequences"]]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DatasetError(self.spec, f"unreadable run record ({exc})") from exc

    def first(self) -> SequenceLayout:
        """The folder of the run's first sequence.

        Raises:
            LeapError: the run has no sequence folder.
        """
        names = self.names()
        if not names:
            raise LeapError(f"{self.root}: not a run folder (no sequences/ with a sequence in it)")
        return self.sequence(names[0])

    # ------------------------------------------------------------------------------- the 3D-CN
    @property
    def cn_dir(self) -> Path:
        """The 3D-CN's checkpoints (``3dcn_iter{i}.pt``)."""
        return self.root / self.CN_DIR

    @property
    def joint_state(self) -> Path:
        """``3dcn/joint.json``: the fingerprint of the 3D-CN round whose grids ``3dcn/rounds/`` holds."""
        return self.cn_dir / "joint.json"

    def joint_rounds(self, name: str) -> SequenceLayout:
        """Where the 3D-CN stages sequence ``name``'s round grids (``grid_3dcn{i}.npz``,
        ``grid_smooth_3dcn{i}.npz``) before its folder links them in."""
        self.sequence(name)  # checks the name
        return SequenceLayout(self.cn_dir / "rounds" / name)

    @property
    def model_note(self) -> Path:
        """``model.json`` of a run labeled by a LiDAR-only model (``leap predict``): the model's file,
        digest and card."""
        return self.root / self.MODEL_NOTE

    # ------------------------------------------------------------------------------- the app's files
    @property
    def params(self) -> Path:
        """The app's parameter snapshot of the run."""
        return self.root / self.PARAMS

    @property
    def log(self) -> Path:
        """The app worker's log of the run."""
        return self.root / self.LOG

    @property
    def lock(self) -> Path:
        """The file a process holds ``flock`` on while it works in this folder."""
        return self.root / self.LOCK

    def export_zip(self, with_confidence: bool = False) -> Path:
        """The cached zip of the export (``.label`` files, plus ``.conf`` files if asked)."""
        return self.root / (self.EXPORT_CONF_ZIP if with_confidence else self.EXPORT_ZIP)

    def holds_results(self) -> bool:
        """Whether the folder holds anything a run computed: False when it holds only what a run writes
        before its first stage finishes (the lock, ``run.json``, stage records of stages that did not
        finish, empty folders), so a run refused at its start may remove a folder it created."""
        for path in self.root.rglob("*"):
            if path.is_dir():
                continue
            rel = path.relative_to(self.root).parts
            if rel in ((self.LOCK,), (self.SPEC,)):
                continue
            if len(rel) == 3 and rel[0] == self.SEQUENCES and rel[2] == SequenceLayout.STATE:
                try:
                    state = json.loads(path.read_text())
                except (OSError, ValueError):
                    return True
                records = state.values() if isinstance(state, dict) else ()
                if any(not isinstance(r, dict) or r.get("status") in ("done", "skipped") for r in records):
                    return True
                continue
            return True
        return False

    @staticmethod
    def is_run(path: str | Path) -> bool:
        """True when ``path`` holds a run of this layout (its ``run.json``)."""
        return (Path(path) / RunLayout.SPEC).is_file()


def write_run_spec(
    layout: RunLayout,
    sequences: Sequence[tuple[str, Path | None, range | None]],
    *,
    pipeline: Mapping[str, Any] | None = None,
) -> None:
    """Write ``run.json``: (name, dataset folder or None when unknown, frame numbers or None = all) per
    sequence, in run order, and the run's settings when given (``pipeline``: ``config_to_dict`` of the
    config the run labels with, the labeler's seed included)."""
    data: dict[str, Any] = {
        "sequences": [
            {
                "name": name,
                "dataset": None if dataset is None else str(Path(dataset).resolve()),
                "frames": None if frames is None else [frames.start, frames.stop],
            }
            for name, dataset, frames in sequences
        ]
    }
    if pipeline is not None:
        data["pipeline"] = dict(pipeline)
    atomic_write_json(layout.spec, data)


def read_run_pipeline(layout: RunLayout) -> dict[str, Any] | None:
    """The settings ``run.json`` records (None for a run written before it recorded them, or none)."""
    if not layout.spec.is_file():
        return None
    try:
        data = json.loads(layout.spec.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(layout.spec, f"unreadable run record ({exc})") from exc
    pipeline = data.get("pipeline") if isinstance(data, dict) else None
    return pipeline if isinstance(pipeline, dict) else None


# -------------------------------------------------------------------------------------- old folders
FORMER_MULTI_SPEC = "multi.json"
"""What a former multi-sequence run folder called its :attr:`RunLayout.SPEC`."""


def former_layout(path: str | Path) -> str | None:
    """How an existing folder written before runs had one shape is laid out: ``"single"`` (one sequence's
    files directly in the folder, its ``stages.json`` at the top), ``"multi"`` (the sequences under
    ``sequences/`` and ``multi.json``), or None (this layout, an empty or a missing folder)."""
    path = Path(path)
    if (path / RunLayout.SPEC).is_file() or run_holding(path) is not None:
        return None
    if (path / SequenceLayout.STATE).is_file():
        return "single"
    if (path / FORMER_MULTI_SPEC).is_file():
        return "multi"
    return None


# ------------------------------------------------------------------------------------ corrections
def run_holding(path: str | Path) -> RunLayout | None:
    """The run whose sequence folder ``path`` is (``<run>/sequences/<name>``), or None."""
    path = Path(path)
    if path.parent.name == RunLayout.SEQUENCES and RunLayout.is_run(path.parent.parent):
        return RunLayout(path.parent.parent)
    return None


# ------------------------------------------------------------------------------------ corrections
def save_corrections(path: str | Path, keys: npt.ArrayLike, class_idx: npt.ArrayLike) -> None:
    """Write map-scope manual corrections: ``keys (K,)`` voxel keys and ``class_idx (K,)`` class indices
    (-1 = erase to unlabeled), in the order they were made (a later entry for the same voxel wins)."""
    atomic_save_npz(path, keys=np.asarray(keys), class_idx=np.asarray(class_idx))


def load_corrections(
    path: str | Path, num_classes: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Read corrections written by :func:`save_corrections` as ``(keys (K,) int64, class_idx (K,) int64)``.

    Raises:
        DatasetError: unreadable file, arrays of different length or rank, non-integer arrays, or a class
            index outside ``-1..num_classes-1`` (-1 erases).
    """
    try:
        with np.load(path) as z:
            keys, cls = np.asarray(z["keys"]), np.asarray(z["class_idx"])
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable corrections (need arrays 'keys', 'class_idx'): {exc}") from exc
    if keys.ndim != 1 or cls.shape != keys.shape:
        raise DatasetError(path, f"'keys' {keys.shape} and 'class_idx' {cls.shape} must be equal-length 1-D")
    if not (np.issubdtype(keys.dtype, np.integer) and np.issubdtype(cls.dtype, np.integer)):
        raise DatasetError(path, "'keys' and 'class_idx' must be integer arrays")
    if len(cls) and (cls.min() < -1 or cls.max() >= num_classes):
        raise DatasetError(path, f"'class_idx' must be in -1..{num_classes - 1} (-1 erases)")
    return keys.astype(np.int64), cls.astype(np.int64)


__all__ = [
    "FORMER_MULTI_SPEC",
    "ConsistencySwitch",
    "RunLayout",
    "SequenceLayout",
    "former_layout",
    "load_corrections",
    "read_run_pipeline",
    "run_holding",
    "save_corrections",
    "sequence_name_problem",
    "write_run_spec",
]
