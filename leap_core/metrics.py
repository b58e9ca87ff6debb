"""Segmentation metrics: confusion matrix, per-class IoU, mIoU, category mIoU, labeled share.

Two protocols (docs/METHOD.md "Evaluation"):

- ``ignore_unlabeled_pred=True``, the paper's pseudo-label protocol: points the method left unlabeled are
  ignored (neither false positive nor false negative). Callers restrict points to the camera view.
- ``ignore_unlabeled_pred=False``, the all-points protocol: an unlabeled prediction is a false negative of
  its ground-truth class. Its per-class IoU equals PRBonn/semantic-kitti-api ``evaluate_semantics.py``
  (``iouEval``: conf[pred, gt], ignored class 0 zeroes the gt-0 column, tp = diag, fp = row sum - tp,
  fn = column sum - tp, IoU = tp / (tp + fp + fn + 1e-15)) for the predictions exported as raw ids with
  unlabeled → 0, which that evaluator maps to its ignored class 0.

In both, points whose ground truth is ``UNLABELED`` (-1, raw id mapped to nothing) are ignored.

Averages: ``miou`` is the mean IoU over the classes present in ground truth or prediction (IoU defined);
absent classes are NaN and excluded. ``miou_all_classes`` averages all C classes with absent ones counted
as 0, which is what ``evaluate_semantics.py`` prints (it averages all 19 classes, present or not).

Merged classes (the paper's 11 SemanticKITTI classes, ``leap_core.eval_view``): :func:`merge_confusion`
sums the (C, C+1) matrix into the merged classes; IoU is then computed on the merged matrix.

Category IoU (KITTI-360 style): the confusion matrix is summed into groups of classes that share a
category, then IoU is computed per group. The grouping is the schema's ``ClassDef.category`` per class
(for SemanticKITTI: vehicle, human, flat, construction, nature, object).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.types import UNLABELED


def confusion_matrix(gt: npt.ArrayLike, pred: npt.ArrayLike, num_classes: int) -> npt.NDArray[np.int64]:
    """(C, C+1) int64 counts: row = ground-truth class, column = predicted class, last column = predicted
    ``UNLABELED``. Points with ground truth ``UNLABELED`` are not counted.

    Raises:
        ValueError: lengths differ or a label is outside ``-1..C-1``.
    """
    g = np.asarray(gt).reshape(-1).astype(np.int64)
    p = np.asarray(pred).reshape(-1).astype(np.int64)
    c = int(num_classes)
    if g.shape != p.shape:
        raise ValueError(f"gt has {g.shape[0]} points but pred has {p.shape[0]}")
    for name, a in (("gt", g), ("pred", p)):
        if a.size and (a.min() < UNLABELED or a.max() >= c):
            raise ValueError(f"{name} labels must be in {UNLABELED}..{c - 1}, got {a.min()}..{a.max()}")
    keep = g != UNLABELED
    g, p = g[keep], p[keep]
    p = np.where(p == UNLABELED, c, p)
    return np.bincount(g * (c + 1) + p, minlength=c * (c + 1)).reshape(c, c + 1).astype(np.int64)


def iou_from_confusion(conf: npt.ArrayLike, *, ignore_unlabeled_pred: bool) -> npt.NDArray[np.float64]:
    """Per-class IoU ``tp / (tp + fp + fn)`` from a (C, C+1) confusion matrix; NaN where tp+fp+fn = 0.

    ``tp = conf[i, i]``, ``fp = Σ_{g≠i} conf[g, i]``, ``fn = Σ_{j≠i, j<C} conf[i, j]`` plus, when
    ``ignore_unlabeled_pred`` is False, ``conf[i, C]`` (unlabeled predictions are misses).
    """
    cm = np.asarray(conf, dtype=np.float64)
    c = cm.shape[0]
    if cm.shape != (c, c + 1):
        raise ValueError(f"confusion matrix must be (C, C+1), got {cm.shape}")
    tp = np.diag(cm[:, :c])
    fp = cm[:, :c].sum(axis=0) - tp
    fn = cm[:, :c].sum(axis=1) - tp
    if not ignore_unlabeled_pred:
        fn = fn + cm[:, c]
    den = tp + fp + fn
    iou = np.full(c, np.nan)
    np.divide(tp, den, out=iou, where=den > 0)
    return iou


def merge_confusion(conf: npt.ArrayLike, mapping: npt.ArrayLike, num_merged: int) -> npt.NDArray[np.int64]:
    """Sum a (C, C+1) confusion matrix into (M, M+1) merged classes.

    ``out[mapping[g], mapping[p]] = Σ conf[g, p]`` over g, p < C, and ``out[mapping[g], M] = Σ conf[g, C]``
    (predicted ``UNLABELED`` stays unlabeled): with B the (C, M) one-hot of ``mapping``,
    ``out[:, :M] = Bᵀ · conf[:, :C] · B`` and ``out[:, M] = Bᵀ · conf[:, C]``. It equals the confusion
    matrix of the labels mapped through ``mapping`` (ground truth and prediction alike), so per-class IoU
    of the merged classes needs no per-point pass.

    Args:
        conf: (C, C+1) integer counts, rows ground truth, last column predicted ``UNLABELED``.
        mapping: (C,) integers in 0..M-1: the merged class of each class (every class is in one).
        num_merged: M.

    Raises:
        ValueError: shapes disagree or a mapping entry is outside 0..M-1.
    """
    cm = np.asarray(conf, dtype=np.int64)
    to = np.asarray(mapping).reshape(-1).astype(np.int64)
    c, m = to.shape[0], int(num_merged)
    if cm.shape != (c, c + 1):
        raise ValueError(
            f"confusion {cm.shape} does not match a mapping of {c} classes (needs ({c}, {c + 1}))"
        )
    if c and (to.min() < 0 or to.max() >= m):
        raise ValueError(f"mapping entries must be in 0..{m - 1}, got {to.min()}..{to.max()}")
    onehot = np.zeros((c, m), np.int64)
    onehot[np.arange(c), to] = 1
    out = np.zeros((m, m + 1), np.int64)
    out[:, :m] = onehot.T @ cm[:, :c] @ onehot
    out[:, m] = onehot.T @ cm[:, c]
    return out


def _nanmean(x: npt.NDArray[np.float64]) -> float:
    finite = x[~np.isnan(x)]
    return float(finite.mean()) if finite.size else math.nan


@dataclass
class Metrics:
    """Evaluation of one method's labels against ground truth.

    Attributes:
        class_names: the C class names, in index order.
        iou: (C,) float64 IoU per class, NaN where the class is absent from both gt and pred.
        miou: mean IoU over classes with a defined IoU.
        miou_all_classes: mean over all C classes with absent ones counted as 0 (the semantic-kitti-api
            printout's averaging).
        category_iou: IoU per category (classes merged by ``ClassDef.category``), NaN where absent.
        category_miou: mean of the defined category IoUs.
        labeled_share: share of ground-truth-labeled points that received a prediction.
        n_points: number of ground-truth-labeled points evaluated.
        confusion: (C, C+1) int64 confusion matrix (last column: predicted unlabeled).
        ignore_unlabeled_pred: which protocol produced these numbers.
    """

    class_names: tuple[str, ...]
    iou: npt.NDArray[np.float64]
    miou: float
    miou_all_classes: float
    category_iou: dict[str, float]
    category_miou: float
    labeled_share: float
    n_points: int
    confusion: npt.NDArray[np.int64] = field(repr=False)
    ignore_unlabeled_pred: bool = True

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping; NaN becomes None."""

        def num(x: float) -> float | None:
            return None if math.isnan(x) else float(x)

        return {
            "miou": num(self.miou),
            "miou_all_classes": num(self.miou_all_classes),
            "category_miou": num(self.category_miou),
            "labeled_share": num(self.labeled_share),
            "n_points": int(self.n_points),
            "ignore_unlabeled_pred": self.ignore_unlabeled_pred,
            "iou": {n: num(v) for n, v in zip(self.class_names, self.iou, strict=True)},
            "category_iou": {k: num(v) for k, v in self.category_iou.items()},
            "confusion": self.confusion.tolist(),
        }


def evaluate(
    gt: npt.ArrayLike,
    pred: npt.ArrayLike,
    class_names: Sequence[str],
    categories: Sequence[str],
    *,
    ignore_unlabeled_pred: bool,
) -> Metrics:
    """Compare predicted class indices with ground truth (both (N,) int16, ``UNLABELED`` = -1).

    Args:
        gt: (N,) ground-truth class index per point.
        pred: (N,) predicted class index per point.
        class_names: C names.
        categories: C category names (``ClassDef.category`` per class), in class order.
        ignore_unlabeled_pred: True = paper protocol (unlabeled predictions ignored); False = all-points
            protocol (unlabeled predictions are false negatives), see the module docstring.
    """
    if len(tuple(categories)) != len(tuple(class_names)):
        raise ValueError(f"{len(tuple(categories))} categories given for {len(tuple(class_names))} classes")
    conf = confusion_matrix(gt, pred, len(tuple(class_names)))
    return metrics_from_confusion(conf, class_names, categories, ignore_unlabeled_pred=ignore_unlabeled_pred)


def metrics_from_confusion(
    conf: npt.ArrayLike,
    class_names: Sequence[str],
    categories: Sequence[str],
    *,
    ignore_unlabeled_pred: bool,
) -> Metrics:
    """:class:`Metrics` from a (C, C+1) confusion matrix (rows gt, last column = unlabeled prediction).

    Confusion matrices add up, so per-scan matrices can be summed instead of holding every point.
    Category IoU merges the matrix by category (:func:`merge_confusion` with the class→category map).
    """
    cm = np.asarray(conf, dtype=np.int64)
    names = tuple(class_names)
    cats = tuple(categories)
    c = len(names)
    if len(cats) != c or cm.shape != (c, c + 1):
        raise ValueError(f"confusion {cm.shape} / {len(cats)} categories do not match {c} classes")
    iou = iou_from_confusion(cm, ignore_unlabeled_pred=ignore_unlabeled_pred)

    groups = list(dict.fromkeys(cats))
    group_of = np.array([groups.index(x) for x in cats], dtype=np.int64)
    gconf = merge_confusion(cm, group_of, len(groups))
    giou = iou_from_confusion(gconf, ignore_unlabeled_pred=ignore_unlabeled_pred)

    n = int(cm.sum())
    return Metrics(
        class_names=names,
        iou=iou,
        miou=_nanmean(iou),
        miou_all_classes=float(np.nan_to_num(iou, nan=0.0).mean()) if c else math.nan,
        category_iou={g: float(v) for g, v in zip(groups, giou, strict=True)},
        category_miou=_nanmean(giou),
        labeled_share=float(cm[:, :c].sum() / n) if n else math.nan,
        n_points=n,
        confusion=cm,
        ignore_unlabeled_pred=ignore_unlabeled_pred,
    )


def format_table(rows: dict[str, Metrics], class_names: Sequence[str]) -> str:
    """Text table with one column per method (point, voxel, +3D-CN ...) and one line per figure: mIoU,
    category mIoU, labeled share, then the IoU of each class (all in %).

    Classes run down the lines, so the width grows with the number of methods, never with the number of
    classes (19 SemanticKITTI classes across fit a terminal only at over 200 columns). A class absent
    from both gt and pred prints ``-``.
    """
    names = list(class_names)
    methods = list(rows)

    def pct(x: float) -> str:
        return "-" if math.isnan(x) else f"{100 * x:.1f}"

    for method, m in rows.items():
        if len(m.iou) != len(names):
            raise ValueError(f"method {method!r} has {len(m.iou)} classes, table has {len(names)}")
    lines: list[list[str]] = [
        ["mIoU", *(pct(rows[k].miou) for k in methods)],
        ["cat-mIoU", *(pct(rows[k].category_miou) for k in methods)],
        ["labeled", *(pct(rows[k].labeled_share) for k in methods)],
    ]
    lines += [[name, *(pct(rows[k].iou[c]) for k in methods)] for c, name in enumerate(names)]
    head = ["%", *methods]
    widths = [max(len(h), *(len(r[i]) for r in lines)) for i, h in enumerate(head)]

    def row(cells: Sequence[str]) -> str:
        pairs = enumerate(zip(cells, widths, strict=True))
        return "  ".join(v.ljust(w) if i == 0 else v.rjust(w) for i, (v, w) in pairs)

    out = [row(head), "  ".join("-" * w for w in widths)]
    out += [row(r) for r in lines[:3]]
    out.append("  ".join("-" * w for w in widths))
    out += [row(r) for r in lines[3:]]
    return "\n".join(out)


__all__ = [
    "Metrics",
    "confusion_matrix",
    "evaluate",
    "format_table",
    "iou_from_confusion",
    "merge_confusion",
    "metrics_from_confusion",
]
