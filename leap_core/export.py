"""Export of per-point labels: SemanticKITTI ``.label`` files, a per-point confidence file, the label map
that reads them, and the rules for where an export may be written.

``.label``: uint32 per point, the class's raw export id (``Schema.export_ids``; a moving thing's points
its ``moving_id``) in the low 16 bits, the point's track id in the high 16 (unique over the sequence; 0
for stuff and untracked points), and 0 ("unlabeled") for points without a label.
``.conf``: float32 per point, the label's posterior probability, 0 where unlabeled.
Both are raw little-endian arrays in scan order, written atomically (temp file + rename). A run writes them
as ``export/<frame_id>.label`` / ``.conf`` (:class:`~leap_core.run_layout.SequenceLayout`).

A stand-alone export (zip) holds them in the SemanticKITTI folder layout (:func:`zip_member`) beside a
label-map YAML in the style of PRBonn/semantic-kitti-api's ``config/semantic-kitti.yaml``
(:func:`label_map`, :func:`load_label_map`; docs/METHOD.md, "Export").
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import shutil
import uuid
import zipfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from leap_core.datasets.kitti import write_label
from leap_core.errors import DatasetError, LeapError
from leap_core.io_utils import atomic_write, atomic_write_bytes
from leap_core.paths import UnusablePath, real_path
from leap_core.run_layout import RunLayout, SequenceLayout
from leap_core.schema import Schema
from leap_core.types import UNLABELED

PREDICTIONS = "predictions"
"""A sequence's folder for predicted ``.label`` files (beside its ground-truth ``labels/``)."""
CONFIDENCES = "confidences"
"""The zip's folder for the ``.conf`` files, beside ``predictions/`` (which evaluation tools read)."""
LABEL_MAP_FILE = "label-map.yaml"
SUMMARY_FILE = "summary.yaml"
EXPORT_SUFFIXES = (".label", ".conf")
"""What an export writes into a folder; nothing else is ever replaced there."""
DATASET_INPUT_FOLDERS = frozenset({"velodyne", "labels", "image_2", "image_3", "gt2d", "voxels"})
"""Folders of a KITTI / SemanticKITTI sequence that hold its input data or ground truth."""


def labels_to_raw(labels: npt.ArrayLike, export_ids: npt.ArrayLike) -> npt.NDArray[np.uint32]:
    """(N,) uint32 ``export_ids[label]``, 0 where ``label == UNLABELED``.

    Raises:
        ValueError: a label is outside ``-1..C-1`` or an export id does not fit 16 bits.
    """
    lab = np.asarray(labels).reshape(-1).astype(np.int64)
    ids = np.asarray(export_ids).reshape(-1).astype(np.int64)
    if ids.size and (ids.min() < 0 or ids.max() > 0xFFFF):
        raise ValueError("export ids must be in 0..65535 (the low 16 bits of a .label value)")
    if lab.size and (lab.min() < UNLABELED or lab.max() >= ids.size):
        raise ValueError(f"labels must be in {UNLABELED}..{ids.size - 1}, got {lab.min()}..{lab.max()}")
    lut = np.concatenate([ids, [0]]).astype(np.uint32)  # index -1 → the appended 0
    return lut[lab]


def export_labels(
    label_path: str | Path,
    conf_path: str | Path,
    labels: npt.ArrayLike,
    confidence: npt.ArrayLike,
    export_ids: npt.ArrayLike,
    *,
    instance: npt.ArrayLike | None = None,
    moving: npt.ArrayLike | None = None,
    moving_ids: npt.ArrayLike | None = None,
) -> None:
    """Write one scan's ``.label`` and ``.conf`` files, each atomically (folders created if missing).

    A label is ``raw | instance << 16`` (SemanticKITTI): ``raw`` is ``moving_ids[label]`` where ``moving``
    and ``export_ids[label]`` elsewhere, 0 where unlabeled.

    Args:
        label_path: the ``.label`` file.
        conf_path: the ``.conf`` file.
        labels: (N,) int16 class index per point, ``UNLABELED`` (-1) where none.
        confidence: (N,) float32 confidence per point (stored as 0 where unlabeled).
        export_ids: (C,) uint32 raw id per class index.
        instance: (N,) instance (track) id per point, 0..65535, 0 = none; None: all 0.
        moving: (N,) bool, the points whose track moves; None: none.
        moving_ids: (C,) raw id of a class's moving points (needed with ``moving``).
    """
    lab = np.asarray(labels).reshape(-1)
    conf = np.asarray(confidence, dtype=np.float32).reshape(-1)
    if conf.shape != lab.shape:
        raise ValueError(f"confidence has {conf.shape[0]} values for {lab.shape[0]} labels")
    raw = labels_to_raw(lab, export_ids)
    if moving is not None:
        if moving_ids is None:
            raise ValueError("moving points need moving_ids")
        raw = np.where(np.asarray(moving, bool).reshape(-1), labels_to_raw(lab, moving_ids), raw)
    inst = None
    if instance is not None:
        # Unlabeled points carry no instance: 0 is "unlabeled" as a whole value.
        inst = np.where(raw > 0, np.asarray(instance).reshape(-1), 0)
    conf = np.where(lab == UNLABELED, np.float32(0.0), conf).astype("<f4")
    write_label(label_path, raw, inst)
    atomic_write_bytes(conf_path, conf.tobytes())


def read_confidence(path: str | Path, num_points: int | None = None) -> npt.NDArray[np.float32]:
    """Read a ``.conf`` file as (N,) float32; check the count against the scan when given."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(path, f"cannot read confidences ({exc.strerror or exc})") from exc
    if len(raw) % 4:
        raise DatasetError(path, f"size {len(raw)} bytes is not a multiple of 4 (float32 per point)")
    conf = np.frombuffer(raw, dtype="<f4").astype(np.float32)
    if num_points is not None and conf.shape[0] != num_points:
        raise DatasetError(path, f"confidence count {conf.shape[0]} != point count {num_points} of its scan")
    return conf


# ------------------------------------------------------------------------------------- label map
def label_map(
    schema: Schema, counts: Mapping[int, int] | None = None, *, name: str = "", sequences: Sequence[str] = ()
) -> dict[str, Any]:
    """The label map of an export, as semantic-kitti-api's ``config/semantic-kitti.yaml`` lays one out.

    Keys (ids are the raw ids of ``.label`` files; learning ids are 0 = unlabeled, ``k + 1`` = class k):

    - ``labels``: raw id → name; 0 is ``unlabeled``, each class's export id its name, a thing's moving id
      ``moving-<name>``.
    - ``color_map``: raw id → ``[B, G, R]`` (BGR, as semantic-kitti-api stores colours; the schema's RGB
      reversed), unlabeled black.
    - ``content``: raw id → fraction of the exported points with that id (semantic-kitti-api's "ratio with
      the total number of points"); only with ``counts``.
    - ``counts``: raw id → number of exported points (LeAP's addition); only with ``counts``.
    - ``learning_map``: raw id → learning id, for 0, every export id and every class's ``gt_ids`` (the
      mapping the run was evaluated with); an id that is one class's export id and another's ``gt_id``
      maps to the class it is the export id of, because that is what the ``.label`` files mean.
    - ``learning_map_inv``: learning id → export id (0 → 0).
    - ``learning_ignore``: learning id → ignored in evaluation (only 0).
    - ``split``: ``{train: [], valid: [<sequence>, ...], test: []}`` listing the exported sequences whose
      names are numbers (``"00"``), so semantic-kitti-api's ``evaluate_semantics.py --split valid`` finds
      them.

    Args:
        schema: the run's classes.
        counts: raw id → points in the export (ids absent from it count 0).
        name: written as ``name`` (semantic-kitti-api's files carry one too).
        sequences: the exported sequences' names.
    """
    ids = [int(c.export_id) for c in schema.classes]
    labels: dict[int, str] = {0: "unlabeled"}
    colors: dict[int, list[int]] = {0: [0, 0, 0]}
    learning: dict[int, int] = {0: 0}
    for k, c in enumerate(schema.classes):
        for gid in c.gt_ids:
            learning[int(gid)] = k + 1
    for k, c in enumerate(schema.classes):  # after the gt ids: an export id keeps its own class
        labels[ids[k]] = c.name
        colors[ids[k]] = [int(c.color[2]), int(c.color[1]), int(c.color[0])]
        learning[ids[k]] = k + 1
        if c.moving_id is not None:
            labels[c.moving_id] = f"moving-{c.name}"
            colors[c.moving_id] = colors[ids[k]]
            learning[c.moving_id] = k + 1
    out: dict[str, Any] = {"name": name or schema.name, "labels": labels, "color_map": colors}
    if counts is not None:
        n = {raw: int(counts.get(raw, 0)) for raw in labels}
        total = sum(n.values())
        out["content"] = {raw: (v / total if total else 0.0) for raw, v in n.items()}
        out["counts"] = n
    out["learning_map"] = dict(sorted(learning.items()))
    out["learning_map_inv"] = {0: 0, **{k + 1: ids[k] for k in range(len(ids))}}
    out["learning_ignore"] = {0: True, **{k + 1: False for k in range(len(ids))}}
    numbered = [int(n) for n in sequences if n.isdigit()]
    if numbered:
        out["split"] = {"train": [], "valid": numbered, "test": []}
    return out


_LABEL_MAP_HEADER = """\
# Label map of a LeAP Studio export, in the layout of semantic-kitti-api's config/semantic-kitti.yaml.
# labels: raw id in the .label files (low 16 bits) -> class name; 0 = unlabeled.
# The upper 16 bits hold the point's track (instance) id, the same in every scan that sees the object;
# 0 for stuff classes and untracked points. A moving object's points carry its class's moving id.
# color_map: raw id -> [B, G, R] (BGR, like semantic-kitti-api's color_map).
# content / counts: share / number of the exported points with that id.
# learning_map: raw id -> learning id (0 = unlabeled, k = k-th class); learning_map_inv: the inverse.
"""


def label_map_yaml(mapping: Mapping[str, Any]) -> str:
    """:func:`label_map`'s result as YAML text (integer keys, key order kept), with a header comment."""
    return _LABEL_MAP_HEADER + yaml.safe_dump(
        dict(mapping), sort_keys=False, default_flow_style=None, allow_unicode=True
    )


@dataclass(frozen=True)
class LabelMap:
    """A label-map YAML read back: what a ``.label`` value means.

    Attributes:
        names: raw id → name (0 → ``unlabeled``).
        colors_rgb: raw id → (R, G, B) (the file's BGR reversed).
        learning_map: raw id → learning id.
        learning_map_inv: learning id → raw id.
        counts: raw id → points (empty when the file has none).
    """

    names: dict[int, str]
    colors_rgb: dict[int, tuple[int, int, int]]
    learning_map: dict[int, int]
    learning_map_inv: dict[int, int]
    counts: dict[int, int]

    def class_names(self) -> list[str]:
        """Names of the learning ids 1..K in order (the classes of the export)."""
        return [self.names[self.learning_map_inv[k]] for k in sorted(self.learning_map_inv) if k]


def load_label_map(text: str, source: str = "label map") -> LabelMap:
    """Parse a label-map YAML (:func:`label_map_yaml`, or semantic-kitti-api's own config file).

    Raises:
        DatasetError: naming ``source`` and the key at fault (not YAML, missing ``labels`` /
            ``color_map`` / ``learning_map`` / ``learning_map_inv``, a non-integer id, a colour that is not
            three 0..255 integers).
    """
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise DatasetError(source, f"not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(source, "expected a mapping with 'labels', 'color_map', 'learning_map'")

    def table(key: str, *, required: bool = True) -> dict[int, Any]:
        value = data.get(key)
        if value is None and not required:
            return {}
        if not isinstance(value, dict):
            raise DatasetError(source, f"'{key}' must be a mapping of integer ids")
        if not all(isinstance(k, int) and not isinstance(k, bool) for k in value):
            raise DatasetError(source, f"'{key}' has a key that is not an integer id")
        return dict(value)

    colors: dict[int, tuple[int, int, int]] = {}
    for raw, bgr in table("color_map").items():
        ok = isinstance(bgr, list) and len(bgr) == 3
        if not (ok and all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in bgr)):
            raise DatasetError(source, f"color_map[{raw}] must be [B, G, R] integers 0..255, got {bgr!r}")
        colors[raw] = (bgr[2], bgr[1], bgr[0])
    return LabelMap(
        names={k: str(v) for k, v in table("labels").items()},
        colors_rgb=colors,
        learning_map={k: int(v) for k, v in table("learning_map").items()},
        learning_map_inv={k: int(v) for k, v in table("learning_map_inv").items()},
        counts={k: int(v) for k, v in table("counts", required=False).items()},
    )


def raw_id_counts(raw_labels: Iterable[npt.ArrayLike]) -> dict[int, int]:
    """Points per raw id (low 16 bits) over ``.label`` arrays, ids in ascending order."""
    total: dict[int, int] = {}
    for raw in raw_labels:
        ids, n = np.unique(np.asarray(raw, dtype=np.uint32) & 0xFFFF, return_counts=True)
        for i, c in zip(ids.tolist(), n.tolist(), strict=True):
            total[i] = total.get(i, 0) + c
    return dict(sorted(total.items()))


def zip_member(sequence: str, frame_id: str, suffix: str) -> str:
    """Path of a frame's file inside an export zip: ``sequences/<seq>/predictions/<frame>.label`` (the
    SemanticKITTI layout evaluation tools read) or ``sequences/<seq>/confidences/<frame>.conf``."""
    folder = PREDICTIONS if suffix == ".label" else CONFIDENCES
    return f"sequences/{sequence}/{folder}/{frame_id}{suffix}"


@dataclass(frozen=True)
class ExportedSequence:
    """One sequence of a run's export: its name, its export folder and where its scans came from."""

    name: str
    """The sequence's name in the run (``sequences/<name>/`` in every export layout)."""
    export_dir: Path
    """Its ``.label`` / ``.conf`` files (``<run>/sequences/<name>/export``)."""
    dataset: Path | None = None
    """The dataset folder it labeled (None when unknown)."""
    frames: range | None = None
    """The frame numbers it labeled (None = all)."""

    def files(self, with_confidence: bool) -> list[Path]:
        """Its ``.label`` files (and ``.conf`` files), in name order."""
        suffixes = EXPORT_SUFFIXES if with_confidence else (".label",)
        return sorted(p for p in self.export_dir.iterdir() if p.suffix in suffixes and p.is_file())


def run_export(out: Path, names: Sequence[str] | None = None) -> list[ExportedSequence]:
    """The exported sequences of the run folder ``out`` (``names``, default all, in run order), read from
    its ``run.json``.

    Raises:
        LeapError: ``out`` is not a run folder, or a sequence has no exported ``.label`` files.
    """
    layout = RunLayout(Path(out))
    if not RunLayout.is_run(layout.root):
        raise LeapError(f"{layout.root}: not a run folder (no {RunLayout.SPEC})")
    listed = {str(e["name"]): e for e in _read_spec(layout)}
    chosen = layout.names() if names is None else list(names)
    out_list = []
    for name in chosen:
        export = layout.sequence(name).export_dir
        if not export.is_dir() or not any(export.glob("*.label")):
            raise LeapError(f"{export}: sequence {name} has no exported .label files (run it to the end)")
        entry = listed.get(name, {})
        dataset, frames = entry.get("dataset"), entry.get("frames")
        out_list.append(
            ExportedSequence(
                name,
                export,
                None if dataset is None else Path(dataset),
                None if frames is None else range(int(frames[0]), int(frames[1])),
            )
        )
    return out_list


def _read_spec(layout: RunLayout) -> list[dict[str, Any]]:
    try:
        data = json.loads(layout.spec.read_text())
        entries = list(data["sequences"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(layout.spec, f"unreadable run record ({exc})") from exc
    return [e for e in entries if isinstance(e, dict)]


def summary_yaml(  # noqa: PLR0913  # keyword-only: the parts of a summary
    *,
    sequences: Sequence[ExportedSequence],
    schema: Schema,
    pipeline: Mapping[str, Any],
    counts: Mapping[str, Any],
    with_confidence: bool,
    version: str,
    written_at: str,
    project: Mapping[str, Any] | None = None,
    run: Mapping[str, Any] | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> str:
    """An export's ``summary.yaml``: which project and run, each sequence's dataset and frames, where the
    files are, the point counts, the run's full settings (``pipeline``:
    :func:`~leap_core.config.config_to_dict`) and, when given, where the labels came from (``provenance``:
    :func:`leap_core.pipeline.provenance.run_provenance`: labeler and its weights, poses, corrections,
    classes the 2D labeler never found, code version).

    ``counts`` (summed over the sequences) holds ``scans``, ``points``, ``labeled``, ``unlabeled``,
    ``unlabeled_by_reason`` and ``raw_counts`` (raw id → points); ``per_class`` (class name → points) is
    derived here.
    """
    raw = {int(k): int(v) for k, v in counts["raw_counts"].items()}
    summary: dict[str, Any] = {}
    if project is not None:
        summary["project"] = dict(project)
    if run is not None:
        summary["run"] = dict(run)
    summary["sequences"] = [
        {
            "name": s.name,
            "dataset": None if s.dataset is None else str(s.dataset),
            "frames": "all" if s.frames is None else [s.frames.start, s.frames.stop],
        }
        for s in sequences
    ]
    summary["files"] = {
        "labels": f"sequences/<name>/{PREDICTIONS}/<frame>.label (uint32: raw id in the low 16 bits, "
        "a moving thing's moving id; track id in the upper 16, unique over the sequence, 0 = stuff or none)",
        "confidences": (
            f"sequences/<name>/{CONFIDENCES}/<frame>.conf (float32 per point)" if with_confidence else None
        ),
        "label_map": LABEL_MAP_FILE,
    }
    summary["counts"] = {
        **{k: counts[k] for k in ("scans", "points", "labeled", "unlabeled", "unlabeled_by_reason")},
        "per_class": {c.name: raw.get(int(c.export_id), 0) for c in schema.classes},
    }
    summary["settings"] = {"schema": schema.name, "pipeline": dict(pipeline)}
    if provenance is not None:
        summary["provenance"] = dict(provenance)
    summary["leap_studio_version"] = version
    summary["written_at"] = written_at
    return "# LeAP Studio export summary (README, 'Exports').\n" + yaml.safe_dump(
        summary, sort_keys=False, allow_unicode=True
    )


def write_export_zip(
    path: Path,
    sequences: Sequence[ExportedSequence],
    extra: Mapping[str, str],
    *,
    include_confidence: bool,
    overwrite: bool = False,
) -> int:
    """Write a stand-alone export zip atomically: each sequence's ``.label`` (and ``.conf``) files at
    :func:`zip_member`, plus ``extra`` (zip name → text, e.g. the label map and summary).

    Returns:
        The number of frame files written.

    Raises:
        ExportConflict: ``path`` exists and ``overwrite`` is off (nothing is written).
    """
    if path.exists() and not overwrite:
        raise ExportConflict(
            f"{path} already exists; nothing was written. Export again with overwrite to replace it", 1
        )
    n = 0
    with (
        atomic_write(path, "wb") as fh,
        zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, compresslevel=6) as zf,
    ):
        for seq in sequences:
            for f in seq.files(include_confidence):
                zf.write(f, zip_member(seq.name, f.stem, f.suffix))
                n += 1
        for name, text in extra.items():
            zf.writestr(name, text)
    return n


# ------------------------------------------------------------------------------- where exports go
class ExportConflict(LeapError):
    """An export would replace existing files (or files it did not write); nothing was written."""

    def __init__(self, message: str, existing: int) -> None:
        self.existing = existing
        super().__init__(message)


def export_target_problem(target: Path) -> str | None:
    """Why the folder ``target`` (absolute, resolved) may not receive an export, or None.

    Refused: a sequence folder itself, a sequence's input folders (:data:`DATASET_INPUT_FOLDERS`, e.g.
    ``labels/``, ``velodyne/``, ``image_2/``) and anything inside them, any folder deeper inside a sequence
    than its own ``predictions/`` and ``confidences/``, and any run folder (it holds ``run.json``), a
    sequence's folder in one (``stages.json``) or a folder inside them. A sequence is a folder with a
    ``velodyne/`` folder.
    """
    if (target / "velodyne").is_dir():
        return f"{target} is a dataset sequence folder; export into its {PREDICTIONS}/ folder"
    for folder in (target, *target.parents):
        if folder.name in DATASET_INPUT_FOLDERS and (folder.parent / "velodyne").is_dir():
            return f"{target} is inside the dataset folder {folder} (its input data or ground truth)"
        if (folder / SequenceLayout.STATE).is_file() or (folder / RunLayout.SPEC).is_file():
            return f"{target} is inside the pipeline run folder {folder}"
    for folder in target.parents[1:]:
        if (folder / "velodyne").is_dir():
            return (
                f"{target} is inside the dataset sequence folder {folder}; an export of a run goes into the "
                f"folder that holds sequences/ (or straight into {folder / PREDICTIONS})"
            )
    return None


def existing_export_files(target: Path) -> list[str]:
    """Names of the entries of the folder ``target`` (empty when it does not exist)."""
    if not target.is_dir():
        return []
    return sorted(p.name for p in target.iterdir())


def refuse_existing(target: Path, *, overwrite: bool) -> list[str]:
    """The entries of the folder ``target`` (:func:`existing_export_files`).

    Raises:
        ExportConflict: it holds some and ``overwrite`` is off.
    """
    old = existing_export_files(target)
    if old and not overwrite:
        raise ExportConflict(
            f"{target} already holds {len(old)} files (e.g. {old[0]}); nothing was written. "
            "Export again with overwrite to replace them",
            len(old),
        )
    return old


SCRATCH = re.compile(r"\.(?P<target>.+)\.leap-(?:new|old)-[0-9a-f]{8}")
"""The hidden siblings of an export's folder ``NAME``: ``.NAME.leap-new-XXXXXXXX``, where the export is
copied before it is renamed into place, and ``.NAME.leap-old-XXXXXXXX``, the folder it replaces, until it
is deleted (:func:`write_export_folder`)."""

_DIR_FLAGS = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_CLOEXEC", 0)


@contextlib.contextmanager
def _folder_lock(folder: Path, *, wait: bool = True) -> Iterator[bool]:
    """Hold an exclusive ``flock`` on the folder ``folder`` while the block runs; yields False without
    waiting when ``wait`` is off and another open of it holds the lock (then ``folder`` may not be a link
    either: only a scratch folder is tried so). The lock follows the folder through renames and dies with
    its process, kill -9 included: a scratch folder nobody holds is a dead export's."""
    fd = os.open(folder, _DIR_FLAGS if wait else _DIR_FLAGS | os.O_NOFOLLOW)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            yield False
            return
        yield True
    finally:
        os.close(fd)


def _only_export_files(folder: Path) -> bool:
    """Whether ``folder`` holds nothing but regular ``.label`` / ``.conf`` files (what an export copies)."""
    try:
        with os.scandir(folder) as it:
            return all(e.is_file(follow_symlinks=False) and e.name.endswith(EXPORT_SUFFIXES) for e in it)
    except OSError:
        return False


def remove_export_leftovers(target: Path) -> list[str]:
    """Delete what exports into the folder ``target`` left beside it when they were killed: its scratch
    siblings (:data:`SCRATCH`) that no running export holds. Nothing else is touched: a sibling named
    otherwise, a link, a folder holding anything but ``.label`` / ``.conf`` files (a user's own folder
    that happens to carry such a name) or the scratch folder of an export still running stays.

    Returns:
        The names deleted.
    """
    parent = target.parent
    try:
        with os.scandir(parent) as it:
            names = sorted(
                e.name
                for e in it
                if e.is_dir(follow_symlinks=False)
                and (m := SCRATCH.fullmatch(e.name)) is not None
                and m["target"] == target.name
            )
    except OSError:
        return []
    removed = []
    for name in names:
        folder = parent / name
        try:
            with _folder_lock(folder, wait=False) as mine:
                if mine and _only_export_files(folder):
                    shutil.rmtree(folder)
                    removed.append(name)
        except OSError:
            continue  # gone meanwhile, or not ours to open: left as it is
    return removed


def write_export_folder(target: Path, files: Sequence[Path], *, overwrite: bool = False) -> int:
    """Copy ``files`` into the folder ``target``: written into a fresh hidden sibling folder, then renamed
    into place, so ``target`` never holds a half-written export.

    An existing ``target`` is replaced only when it is empty, or with ``overwrite`` when it holds nothing
    but ``.label`` / ``.conf`` files (what an export writes); the old folder is removed after the swap.

    An export killed on the way (kill -9, a power cut) cannot clean up after itself: its hidden sibling
    folders (:data:`SCRATCH`) stay, and the next export to ``target`` deletes them
    (:func:`remove_export_leftovers`). Each export holds a lock on its scratch folders, so one still running
    is never taken for dead; the lock on ``target``'s parent covers the moment a scratch folder is made.

    Returns:
        The number of files the previous ``target`` held (0 when it was new or empty).

    Raises:
        ExportConflict: ``target`` holds files and ``overwrite`` is off, or holds something an export does
            not write (then even ``overwrite`` refuses).
    """
    if target.parent.is_dir():
        with _folder_lock(target.parent):
            remove_export_leftovers(target)
    old = refuse_existing(target, overwrite=overwrite)
    foreign = [n for n in old if not (n.endswith(EXPORT_SUFFIXES) and (target / n).is_file())]
    if foreign:
        raise ExportConflict(
            f"{target} holds {foreign[0]!r}, which an export does not write; nothing was written "
            "(move it away, or export elsewhere)",
            len(old),
        )
    if target.exists() and not target.is_dir():
        raise ExportConflict(f"{target} is a file, not a folder; nothing was written", 1)
    target.parent.mkdir(parents=True, exist_ok=True)
    tag = uuid.uuid4().hex[:8]
    fresh = target.parent / f".{target.name}.leap-new-{tag}"
    with contextlib.ExitStack() as held:
        # Made and locked in one step under the parent's lock, so no other export's clean-up sees it unheld.
        with _folder_lock(target.parent):
            fresh.mkdir()
            held.enter_context(_folder_lock(fresh))
        _fill_and_swap(target, fresh, files, old, tag)
    return len(old)


def _fill_and_swap(target: Path, fresh: Path, files: Sequence[Path], old: Sequence[str], tag: str) -> None:
    """Copy ``files`` into the (locked) folder ``fresh``, then rename it to ``target``; an ``old`` target is
    renamed aside (locked, so it is not taken for a dead export's) and deleted after the swap."""
    try:
        for path in files:
            shutil.copyfile(path, fresh / path.name)
        with contextlib.suppress(OSError):  # a best effort: the copies are flushed before the rename
            for path in fresh.iterdir():
                fd = os.open(path, os.O_RDONLY)
                os.fsync(fd)
                os.close(fd)
        if old:
            stale = target.parent / f".{target.name}.leap-old-{tag}"
            with _folder_lock(target):
                os.rename(target, stale)
                try:
                    os.rename(fresh, target)
                except OSError:
                    os.rename(stale, target)
                    raise
                shutil.rmtree(stale, ignore_errors=True)
        else:
            try:
                # rename() replaces an empty folder and fails on a non-empty one (someone wrote there since).
                os.rename(fresh, target)
            except OSError as exc:
                raise ExportConflict(
                    f"{target} changed while exporting ({exc.strerror}); nothing written",
                    len(existing_export_files(target)),
                ) from None
    finally:
        if fresh.exists():
            shutil.rmtree(fresh, ignore_errors=True)


def export_targets(
    target_dir: Path, names: Sequence[str], *, with_conf: bool = False
) -> dict[str, list[Path]]:
    """Per sequence, the folders of an export into ``target_dir`` in the layout SemanticKITTI tools read:
    ``target_dir/sequences/<name>/predictions`` (and ``confidences``; for :func:`write_run_export`)."""
    out: dict[str, list[Path]] = {}
    for name in names:
        base = Path(target_dir) / "sequences" / name
        out[name] = [base / PREDICTIONS, *([base / CONFIDENCES] if with_conf else [])]
    return out


def check_export_targets(targets: Mapping[str, Sequence[Path]], *, overwrite: bool = False) -> None:
    """Refuse, before writing anything, export folders (sequence name → its folders, as
    :func:`export_targets` gives them) that may not receive an export (:func:`export_target_problem`: a
    dataset's input folders, a run folder) or already hold files while ``overwrite`` is off.

    Raises:
        LeapError: naming the folder refused.
        ExportConflict: a folder holds files and ``overwrite`` is off.
    """
    for folders in targets.values():
        for folder in folders:
            try:
                resolved = real_path(folder)
            except UnusablePath as exc:
                raise LeapError(f"export folder {str(folder)!r} {exc}") from None
            problem = export_target_problem(resolved)
            if problem is not None:
                raise LeapError(problem)
            refuse_existing(Path(folder), overwrite=overwrite)


@dataclass(frozen=True)
class RunExportWritten:
    """What :func:`write_run_export` wrote."""

    files: dict[str, int]
    """Sequence name → files written."""
    replaced: int
    """Files the target folders held before (0 unless ``overwrite``)."""


def write_run_export(
    targets: Mapping[str, Sequence[Path]],
    sequences: Sequence[ExportedSequence],
    *,
    with_conf: bool = False,
    overwrite: bool = False,
) -> RunExportWritten:
    """Copy each sequence's ``.label`` files into the first of its ``targets`` folders (and its ``.conf``
    files into the second, with ``with_conf``): ``<dir>/sequences/<name>/predictions/`` for the folders of
    :func:`export_targets`. Each folder is written by :func:`write_export_folder` (a fresh folder renamed
    into place); every folder is checked before anything is written (:func:`check_export_targets`).

    Raises:
        LeapError: a target is a dataset's input folder or a run folder.
        ExportConflict: a target holds files and ``overwrite`` is off (nothing is written).
    """
    check_export_targets(targets, overwrite=overwrite)
    written: dict[str, int] = {}
    replaced = 0
    for seq in sequences:
        n = 0
        for folder, suffix in zip(targets[seq.name], EXPORT_SUFFIXES, strict=False):
            files = [f for f in seq.files(with_conf) if f.suffix == suffix]
            replaced += write_export_folder(Path(folder), files, overwrite=overwrite)
            n += len(files)
        written[seq.name] = n
    return RunExportWritten(written, replaced)


__all__ = [
    "CONFIDENCES",
    "DATASET_INPUT_FOLDERS",
    "EXPORT_SUFFIXES",
    "LABEL_MAP_FILE",
    "PREDICTIONS",
    "SCRATCH",
    "SUMMARY_FILE",
    "ExportConflict",
    "ExportedSequence",
    "LabelMap",
    "RunExportWritten",
    "check_export_targets",
    "existing_export_files",
    "export_labels",
    "export_target_problem",
    "export_targets",
    "label_map",
    "label_map_yaml",
    "labels_to_raw",
    "load_label_map",
    "raw_id_counts",
    "read_confidence",
    "refuse_existing",
    "remove_export_leftovers",
    "run_export",
    "summary_yaml",
    "write_export_folder",
    "write_export_zip",
    "write_run_export",
    "zip_member",
]
