"""Where a LiDAR-only model's training labels come from, and which scans are held apart for validation.

Two kinds of labeled sequence:

- a **run's sequence** (``<run>/sequences/<name>``): its final labels, i.e. ``points/<frame_id>.npz``'s
  ``label``: the final grid's label of every point with the manual corrections on top (map scope, then
  scan scope: the ``label_points`` stage, rewritten by the app's "apply corrections"), so corrections win
  over the pipeline's labels, exactly as in the run's export;
- a **ground-truth sequence** (a dataset folder with ``labels/``): every point's ground-truth class
  (``Schema.map_gt``), for a source network trained on another domain or the oracle.

Scans are read one at a time when a step needs them (:meth:`LabeledScans.load`); nothing is held.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import DatasetError, LeapError
from leap_core.io_utils import read_npz
from leap_core.run_layout import RunLayout, SequenceLayout, run_holding
from leap_core.schema import Schema


@dataclass(frozen=True)
class LabeledSequence:
    """One sequence whose scans carry labels, and which of its scans take part."""

    kind: Literal["run", "truth"]
    """``run``: a run's final labels; ``truth``: the dataset's ground truth."""
    seq: KittiSequence
    """The dataset the scans are read from."""
    indices: tuple[int, ...]
    """The scan indices (into ``seq``) that have labels of this kind."""
    layout: SequenceLayout | None = None
    """The run's sequence folder (``kind == "run"``)."""

    @property
    def where(self) -> str:
        """The folder the labels come from (a run's sequence folder, or the dataset)."""
        return str(self.layout.folder if self.layout is not None else self.seq.root)

    def labels(self, index: int, schema: Schema) -> npt.NDArray[np.int16]:
        """(N,) class per point of scan ``index`` (``UNLABELED`` = -1 where none).

        Raises:
            DatasetError: naming the file, when it is unreadable or its count is not the scan's.
        """
        if self.layout is None:
            return schema.map_gt(self.seq.frame(index).labels)
        path = self.layout.points(self.seq.frame_ids[index])
        try:
            label = np.asarray(read_npz(path, ("label",))["label"], np.int16)
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(path, f"unreadable point labels ({exc})") from exc
        if label.size and (label.min() < -1 or label.max() >= schema.num_classes):
            raise DatasetError(
                path, f"labels outside -1..{schema.num_classes - 1}: was the run made with these classes?"
            )
        return label


def run_sequences(run: str | Path, names: Sequence[str] | None = None) -> list[LabeledSequence]:
    """The labeled sequences of a run folder (``names``, default all), or of one run sequence folder.

    Raises:
        LeapError: not a run folder, an unknown sequence name, or a sequence without point labels (the
            run did not reach its ``label_points`` stage).
    """
    path = Path(run)
    held = run_holding(path)
    if held is not None:
        layout, chosen = held, [path.name]
    elif RunLayout.is_run(path):
        layout = RunLayout(path)
        chosen = list(names) if names else layout.names()
    else:
        raise LeapError(f"{path}: not a run folder (no {RunLayout.SPEC}) nor a run's sequence folder")
    try:
        entries = {e["name"]: e for e in json.loads(layout.spec.read_text())["sequences"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(layout.spec, f"unreadable run record ({exc})") from exc
    out = []
    for name in chosen:
        entry = entries.get(name)
        if entry is None or entry.get("dataset") is None:
            raise LeapError(f"{layout.root}: no sequence {name!r} with a known dataset in {RunLayout.SPEC}")
        lay = layout.sequence(name)
        seq = lay.open_sequence(entry["dataset"])
        frames = entry.get("frames")
        chosen_idx = seq.select(None if frames is None else range(int(frames[0]), int(frames[1])))
        idx = tuple(i for i in chosen_idx if lay.points(seq.frame_ids[i]).is_file())
        if not idx:
            raise LeapError(f"{lay.folder}: no point labels (points/*.npz); run it to the end first")
        out.append(LabeledSequence("run", seq, idx, lay))
    return out


def truth_sequence(dataset: str | Path) -> LabeledSequence:
    """A dataset's ground truth as training labels.

    Raises:
        DatasetError: a scan without its ``.label`` file.
    """
    seq = KittiSequence(dataset)
    for i in range(len(seq)):
        if not seq.label_path(i).is_file():
            raise DatasetError(seq.label_path(i), "missing ground-truth label file")
    return LabeledSequence("truth", seq, tuple(range(len(seq))))


def labeled_sequences(paths: Sequence[str | Path]) -> list[LabeledSequence]:
    """Each path's labeled sequences: a run (every sequence), a run's sequence folder, or a dataset with
    ground truth (``labels/``)."""
    out: list[LabeledSequence] = []
    for p in paths:
        path = Path(p)
        if RunLayout.is_run(path) or run_holding(path) is not None:
            out += run_sequences(path)
        elif (path / "velodyne").is_dir():
            out.append(truth_sequence(path))
        else:
            raise LeapError(f"{path}: neither a run folder, a run's sequence folder nor a dataset sequence")
    return out


def block_split(count: int, block: int, every: int) -> npt.NDArray[np.bool_]:
    """(count,) True for the positions held apart for validation: position ``k`` is in block
    ``k // block``, and blocks ``every - 1``, ``2·every - 1``, ... are held apart (all False when
    ``block`` is 0). Example: count 10, block 2, every 2 → positions 2, 3, 6, 7."""
    if block <= 0:
        return np.zeros(count, bool)
    held: npt.NDArray[np.bool_] = np.arange(count) // block % every == every - 1
    return held


@dataclass(frozen=True)
class LabeledScans:
    """Scans to train on or validate on: (sequence, scan index) pairs, read one at a time."""

    sequences: tuple[LabeledSequence, ...]
    scans: tuple[tuple[int, int], ...]
    """(position in ``sequences``, scan index) of every scan, in order."""

    def load(self, j: int, schema: Schema) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int16]]:
        """Scan ``j``'s ``(points (N, 4), label (N,))``.

        Raises:
            DatasetError: the label count differs from the scan's point count.
        """
        s, i = self.scans[j]
        part = self.sequences[s]
        points = part.seq.frame(i).points
        label = part.labels(i, schema)
        if label.shape != (points.shape[0],):
            raise DatasetError(
                part.seq.scan_path(i), f"{points.shape[0]} points but {label.shape[0]} labels in {part.where}"
            )
        return points, label


def split_scans(
    train: Sequence[LabeledSequence], apart: Sequence[LabeledSequence], block: int, every: int
) -> tuple[LabeledScans, LabeledScans]:
    """``(training, validation)`` scans: the ``apart`` sequences validate whole; of the ``train``
    sequences, each one's :func:`block_split` blocks validate and the rest trains.

    Raises:
        LeapError: a sequence is both in ``train`` and ``apart``, or no scan is left to train on.
    """
    trained = {(p.where, p.seq.root.resolve()) for p in train}
    for p in apart:
        if (p.where, p.seq.root.resolve()) in trained:
            raise LeapError(f"{p.where}: given both to train on and apart for validation; give it once")
    parts = (*train, *apart)
    tr: list[tuple[int, int]] = []
    va: list[tuple[int, int]] = []
    for s, part in enumerate(train):
        held = block_split(len(part.indices), block, every)
        for k, i in enumerate(part.indices):
            (va if held[k] else tr).append((s, i))
    for s, part in enumerate(apart, start=len(train)):
        va += [(s, i) for i in part.indices]
    if not tr:
        raise LeapError("no scan left to train on: give more frames, or a smaller val_block")
    return LabeledScans(parts, tuple(tr)), LabeledScans(parts, tuple(va))


__all__ = [
    "LabeledScans",
    "LabeledSequence",
    "block_split",
    "labeled_sequences",
    "run_sequences",
    "split_scans",
    "truth_sequence",
]
