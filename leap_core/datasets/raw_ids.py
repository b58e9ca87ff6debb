"""Raw ground-truth ids of a dataset's ``labels/*.label`` files: their names, and which ones a sequence holds.

A class's ``gt_ids`` are raw ids (the low 16 bits of a ``.label`` value). To let a person pick them by name,
:data:`SEMANTIC_KITTI_RAW_NAMES` names SemanticKITTI's raw ids (the ``labels:`` table of the dataset's
definition, PRBonn/semantic-kitti-api ``config/semantic-kitti.yaml``); :func:`raw_id_names` adds the names of
ids a dataset defines beyond those, which its caller passes as data (the app passes the generated demo
world's: 300 traffic-cone, 301 bench, 302 bollard, ``leap_core.synth.names.DEMO_EXTRA_RAW_IDS``).

:func:`scan_raw_ids` counts the raw ids in a sequence's labels. Reading every file of a long sequence costs
seconds (SemanticKITTI's sequence 00: 4,541 files, 2 GB), so it reads at most ``max_frames`` evenly spaced
files; objects present in a sequence appear in many consecutive scans, so a sample finds them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import read_label

SEMANTIC_KITTI_RAW_NAMES: Mapping[int, str] = MappingProxyType(
    {
        0: "unlabeled",
        1: "outlier",
        10: "car",
        11: "bicycle",
        13: "bus",
        15: "motorcycle",
        16: "on-rails",
        18: "truck",
        20: "other-vehicle",
        30: "person",
        31: "bicyclist",
        32: "motorcyclist",
        40: "road",
        44: "parking",
        48: "sidewalk",
        49: "other-ground",
        50: "building",
        51: "fence",
        52: "other-structure",
        60: "lane-marking",
        70: "vegetation",
        71: "trunk",
        72: "terrain",
        80: "pole",
        81: "traffic-sign",
        99: "other-object",
        252: "moving-car",
        253: "moving-bicyclist",
        254: "moving-person",
        255: "moving-motorcyclist",
        256: "moving-on-rails",
        257: "moving-bus",
        258: "moving-truck",
        259: "moving-other-vehicle",
    }
)
"""SemanticKITTI raw semantic id -> name (the dataset's 34 raw ids; 0 "unlabeled" and 1 "outlier" are
never evaluated)."""


def raw_id_names(extra: Mapping[int, str] | None = None) -> dict[int, str]:
    """SemanticKITTI's raw id names plus ``extra`` (raw id → name: the ids a dataset adds, e.g. the demo
    world's 300 traffic-cone); ``extra`` names win where both name an id."""
    return {**SEMANTIC_KITTI_RAW_NAMES, **(extra or {})}


@dataclass(frozen=True)
class RawIdScan:
    """What :func:`scan_raw_ids` found."""

    counts: dict[int, int]
    """Raw id -> number of points carrying it in the files read (ids with no point are absent)."""
    frames_read: int
    """Label files read."""
    frames_total: int
    """Label files the sequence has."""


def raw_id_counts(labels: npt.ArrayLike) -> dict[int, int]:
    """Point count per raw semantic id of one ``.label`` array (N,) uint32: the low 16 bits of each value.

    ``bincount`` over 65,536 ids: linear in N, no sort (``np.unique`` sorts).
    """
    sem = (np.asarray(labels, dtype=np.uint32) & 0xFFFF).astype(np.int64)
    counts = np.bincount(sem.ravel(), minlength=1)
    ids = np.flatnonzero(counts)
    return {int(i): int(counts[i]) for i in ids}


def sample_indices(total: int, max_frames: int) -> list[int]:
    """At most ``max_frames`` indices of ``0..total-1``, evenly spaced, first and last included.

    ``max_frames`` must be >= 1; every index when ``total <= max_frames``.
    """
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    if total <= max_frames:
        return list(range(total))
    if max_frames == 1:
        return [0]
    return sorted({round(k * (total - 1) / (max_frames - 1)) for k in range(max_frames)})


def scan_raw_ids(seq_root: str | Path, max_frames: int = 200) -> RawIdScan:
    """Raw ids in ``<seq_root>/labels/*.label`` (at most ``max_frames`` evenly spaced files).

    A sequence without a ``labels/`` folder has no ids (``frames_total`` 0).

    Raises:
        DatasetError: naming a ``.label`` file that cannot be read or is not a whole number of uint32.
    """
    folder = Path(seq_root) / "labels"
    files = sorted(folder.glob("*.label")) if folder.is_dir() else []
    totals: dict[int, int] = {}
    chosen = sample_indices(len(files), max_frames)
    for i in chosen:
        for raw_id, n in raw_id_counts(read_label(files[i])).items():
            totals[raw_id] = totals.get(raw_id, 0) + n
    return RawIdScan(counts=dict(sorted(totals.items())), frames_read=len(chosen), frames_total=len(files))


__all__ = [
    "SEMANTIC_KITTI_RAW_NAMES",
    "RawIdScan",
    "raw_id_counts",
    "raw_id_names",
    "sample_indices",
    "scan_raw_ids",
]
