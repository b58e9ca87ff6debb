"""``metrics.json`` as typed objects that round-trip it: :class:`SequenceMetrics` (a sequence's file, and a
run's ``overall`` entry) and :class:`RunMetrics` (a run's file, ``{"overall": ..., "sequences": {...}}``).

A sequence's file holds, per *protocol* (``camera``, ``common``, ``all``, and ``paper`` for SemanticKITTI's
classes; :data:`leap_core.pipeline.evaluation.PROTOCOLS`) and *row* (``point``, ``voxel``, ``+3D-CN xN``),
the scores of :class:`leap_core.metrics.Metrics` with their confusion matrix (:class:`RowScores`), plus the
point counts every row shares. ``from_dict(data).to_dict() == data`` for every file the evaluate stage
writes (files written before a field existed lack it: ``common``, ``labeled_share_all_points``), so a reader
never reshapes the JSON itself; the writers build these objects and store :meth:`to_dict`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError
from leap_core.metrics import Metrics

_RESERVED = frozenset(
    {
        "class_names",
        "categories",
        "rows",
        "protocols",
        "frames",
        "n_points",
        "n_points_in_view",
        "labeled_points",
        "labeled_share_all_points",
        "labeler",
        "coverage_ratio",
        "paper_view",
        "protocol_notes",
        "sequences",
        "objects",
    }
)
"""Keys of a sequence's ``metrics.json`` that are not a protocol's table."""


def _opt_float(value: Any) -> float | None:
    return None if value is None else float(value)


@dataclass(frozen=True)
class RowScores:
    """One row's scores under one protocol (:meth:`leap_core.metrics.Metrics.to_dict`); absent values
    (a class neither in the ground truth nor predicted) are None."""

    miou: float | None
    miou_all_classes: float | None
    category_miou: float | None
    labeled_share: float | None
    n_points: int
    ignore_unlabeled_pred: bool
    iou: dict[str, float | None]
    """Class name → IoU."""
    category_iou: dict[str, float | None]
    confusion: list[list[int]] = field(repr=False)
    """(C, C+1): ground truth × prediction, the last column predicted unlabeled."""

    @property
    def confusion_matrix(self) -> npt.NDArray[np.int64]:
        return np.asarray(self.confusion, np.int64)

    def to_dict(self) -> dict[str, Any]:
        return {
            "miou": self.miou,
            "miou_all_classes": self.miou_all_classes,
            "category_miou": self.category_miou,
            "labeled_share": self.labeled_share,
            "n_points": self.n_points,
            "ignore_unlabeled_pred": self.ignore_unlabeled_pred,
            "iou": dict(self.iou),
            "category_iou": dict(self.category_iou),
            "confusion": [list(r) for r in self.confusion],
        }

    @classmethod
    def of(cls, metrics: Metrics) -> RowScores:
        """The scores of an evaluation (its :meth:`~leap_core.metrics.Metrics.to_dict`)."""
        return cls.from_dict(metrics.to_dict())

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RowScores:
        return cls(
            miou=_opt_float(data["miou"]),
            miou_all_classes=_opt_float(data.get("miou_all_classes")),
            category_miou=_opt_float(data.get("category_miou")),
            labeled_share=_opt_float(data.get("labeled_share")),
            n_points=int(data["n_points"]),
            ignore_unlabeled_pred=bool(data["ignore_unlabeled_pred"]),
            iou={str(k): _opt_float(v) for k, v in data["iou"].items()},
            category_iou={str(k): _opt_float(v) for k, v in data.get("category_iou", {}).items()},
            confusion=[[int(x) for x in r] for r in data["confusion"]],
        )


@dataclass(frozen=True)
class ViewSpec:
    """A protocol over merged classes (the paper's ``paper_view``): its classes and what each merges."""

    name: str
    class_names: list[str]
    categories: list[str]
    merge: dict[str, list[str]]
    """Merged class → the schema's classes it sums."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "class_names": list(self.class_names),
            "categories": list(self.categories),
            "merge": {k: list(v) for k, v in self.merge.items()},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ViewSpec:
        return cls(
            name=str(data["name"]),
            class_names=[str(n) for n in data["class_names"]],
            categories=[str(c) for c in data["categories"]],
            merge={str(k): [str(s) for s in v] for k, v in data["merge"].items()},
        )


Frames = list[int] | dict[str, list[int] | None]
"""A sequence's frame numbers ``[first, last + 1]``; in a run's ``overall``, each sequence's."""


@dataclass(frozen=True)
class SequenceMetrics:
    """A sequence's ``metrics.json`` (or a run's ``overall``: the sequences' confusion matrices summed,
    :func:`leap_core.pipeline.evaluation.overall_metrics`)."""

    class_names: list[str]
    categories: list[str]
    """Each class's category, in class order."""
    rows: list[str]
    """Result rows in order: ``point``, ``voxel``, ``+3D-CN x1`` ..."""
    protocols: dict[str, str]
    """Protocol key → what it measures (the keys of :attr:`tables`)."""
    tables: dict[str, dict[str, RowScores]]
    """Protocol → row → scores."""
    frames: Frames | None
    n_points: int
    n_points_in_view: int
    labeled_points: dict[str, int]
    """Row → points (ground truth or not) it labeled."""
    coverage_ratio: dict[str, float | None]
    """Row → labeled points over the point row's."""
    labeler: str | None = None
    labeled_share_all_points: dict[str, float | None] | None = None
    """Row → labeled share of all points (None in files written before it was stored)."""
    paper_view: ViewSpec | None = None
    protocol_notes: dict[str, str] = field(default_factory=dict)
    """Protocol → why it was not computed."""
    sequences: list[str] | None = None
    """A run's ``overall``: the sequences summed (None in a sequence's file)."""
    objects: dict[str, dict[str, float | None]] | None = None
    """Object scores (:mod:`leap_core.panoptic`, docs/METHOD.md D.6), when the run tracked objects:
    ``camera`` and ``all`` → ``PQ``, ``SQ``, ``RQ`` and each with ``_things`` / ``_stuff``; ``motion`` →
    ``mos_iou`` (moving-object IoU, all points), ``s_assoc`` (LSTQ's association score) and
    ``moving_points``; ``moving_right_class`` → class → share of its ground-truth moving points exported
    with that class. A sequence's file only (a run's ``overall`` has none)."""

    def table(self, protocol: str) -> dict[str, RowScores]:
        """Row → scores of ``protocol``.

        Raises:
            KeyError: naming the protocols the file has.
        """
        if protocol not in self.tables:
            raise KeyError(f"no protocol {protocol!r} (has {', '.join(self.tables)})")
        return self.tables[protocol]

    def miou(self, protocol: str, row: str) -> float | None:
        return self.table(protocol)[row].miou

    def all_points_labeled_share(self) -> dict[str, float | None]:
        """Row → share of all points of the evaluated scans that got a label (as an exported ``.label``
        counts them); computed from the counts for files written before it was stored."""
        if self.labeled_share_all_points is not None:
            return dict(self.labeled_share_all_points)
        n = self.n_points
        return {r: (v / n if n > 0 else None) for r, v in self.labeled_points.items()}

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (:meth:`from_dict` reads it back)."""
        out: dict[str, Any] = {
            "class_names": list(self.class_names),
            "categories": list(self.categories),
            "rows": list(self.rows),
            "protocols": dict(self.protocols),
            "n_points": self.n_points,
            "n_points_in_view": self.n_points_in_view,
            "labeled_points": dict(self.labeled_points),
            "coverage_ratio": dict(self.coverage_ratio),
        }
        if self.frames is not None:
            out["frames"] = dict(self.frames) if isinstance(self.frames, dict) else list(self.frames)
        if self.labeler is not None:
            out["labeler"] = self.labeler
        if self.labeled_share_all_points is not None:
            out["labeled_share_all_points"] = dict(self.labeled_share_all_points)
        for protocol, rows in self.tables.items():
            out[protocol] = {r: s.to_dict() for r, s in rows.items()}
        if self.paper_view is not None:
            out["paper_view"] = self.paper_view.to_dict()
        if self.protocol_notes:
            out["protocol_notes"] = dict(self.protocol_notes)
        if self.sequences is not None:
            out["sequences"] = list(self.sequences)
        if self.objects is not None:
            out["objects"] = {k: dict(v) for k, v in self.objects.items()}
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str | Path = "metrics") -> SequenceMetrics:
        """The object of a ``metrics.json``'s content.

        Raises:
            DatasetError: naming ``source`` and the key at fault.
        """
        try:
            protocols = {str(k): str(v) for k, v in data["protocols"].items()}
            tables = {
                p: {str(r): RowScores.from_dict(s) for r, s in data[p].items()}
                for p in protocols
                if p in data and p not in _RESERVED
            }
            frames = data.get("frames")
            shares = data.get("labeled_share_all_points")
            view = data.get("paper_view")
            listed = data.get("sequences")
            return cls(
                class_names=[str(n) for n in data["class_names"]],
                categories=[str(c) for c in data["categories"]],
                rows=[str(r) for r in data["rows"]],
                protocols=protocols,
                tables=tables,
                frames=(
                    {str(k): (None if v is None else [int(x) for x in v]) for k, v in frames.items()}
                    if isinstance(frames, Mapping)
                    else (None if frames is None else [int(x) for x in frames])
                ),
                n_points=int(data.get("n_points", 0)),
                n_points_in_view=int(data.get("n_points_in_view", 0)),
                labeled_points={str(k): int(v) for k, v in (data.get("labeled_points") or {}).items()},
                coverage_ratio={str(k): _opt_float(v) for k, v in (data.get("coverage_ratio") or {}).items()},
                labeler=None if data.get("labeler") is None else str(data["labeler"]),
                labeled_share_all_points=(
                    None if shares is None else {str(k): _opt_float(v) for k, v in shares.items()}
                ),
                paper_view=None if view is None else ViewSpec.from_dict(view),
                protocol_notes={str(k): str(v) for k, v in (data.get("protocol_notes") or {}).items()},
                sequences=None if listed is None else [str(s) for s in listed],
                objects=(
                    None
                    if data.get("objects") is None
                    else {
                        str(k): {str(n): _opt_float(v) for n, v in part.items()}
                        for k, part in data["objects"].items()
                    }
                ),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise DatasetError(source, f"unreadable metrics ({type(exc).__name__}: {exc})") from exc


@dataclass(frozen=True)
class RunMetrics:
    """A run's ``metrics.json``: the sequences' confusion matrices summed (``overall``) and each
    sequence's own metrics (None for a sequence without ground truth)."""

    overall: SequenceMetrics
    sequences: dict[str, SequenceMetrics | None]

    def sequence(self, name: str) -> SequenceMetrics | None:
        return self.sequences.get(name)

    def to_dict(self) -> dict[str, Any]:
        return {
            "overall": self.overall.to_dict(),
            "sequences": {n: (None if m is None else m.to_dict()) for n, m in self.sequences.items()},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str | Path = "metrics") -> RunMetrics:
        """Raises:
        DatasetError: naming ``source`` and the key at fault."""
        try:
            overall, per = data["overall"], data["sequences"]
            if not isinstance(overall, Mapping) or not isinstance(per, Mapping):
                raise TypeError("'overall' and 'sequences' must be objects")
        except (KeyError, TypeError) as exc:
            raise DatasetError(source, f"unreadable run metrics ({exc})") from exc
        return cls(
            overall=SequenceMetrics.from_dict(overall, source),
            sequences={
                str(n): (None if m is None else SequenceMetrics.from_dict(m, source)) for n, m in per.items()
            },
        )


__all__ = ["Frames", "RowScores", "RunMetrics", "SequenceMetrics", "ViewSpec"]
