"""Export of per-point labels: SemanticKITTI ``.label`` files plus a per-point confidence file.

``.label``: uint32 per point, the class's raw export id (``Schema.export_ids``) in the low 16 bits,
instance 0 in the high 16, and 0 ("unlabeled") for points without a label.
``.conf``: float32 per point, the label's posterior probability, 0 where unlabeled.
Both are raw little-endian arrays in scan order, written atomically (temp file + rename). A run writes them
as ``export/<frame_id>.label`` / ``.conf`` (:class:`~leap_core.run_layout.RunLayout`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import write_label
from leap_core.errors import DatasetError
from leap_core.io_utils import atomic_write_bytes
from leap_core.types import UNLABELED


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
) -> None:
    """Write one scan's ``.label`` and ``.conf`` files, each atomically (folders created if missing).

    Args:
        label_path: the ``.label`` file.
        conf_path: the ``.conf`` file.
        labels: (N,) int16 class index per point, ``UNLABELED`` (-1) where none.
        confidence: (N,) float32 confidence per point (stored as 0 where unlabeled).
        export_ids: (C,) uint32 raw id per class index.
    """
    lab = np.asarray(labels).reshape(-1)
    conf = np.asarray(confidence, dtype=np.float32).reshape(-1)
    if conf.shape != lab.shape:
        raise ValueError(f"confidence has {conf.shape[0]} values for {lab.shape[0]} labels")
    raw = labels_to_raw(lab, export_ids)
    conf = np.where(lab == UNLABELED, np.float32(0.0), conf).astype("<f4")
    write_label(label_path, raw)
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


__all__ = ["export_labels", "labels_to_raw", "read_confidence"]
