"""Merged evaluation views: a schema's classes summed into fewer classes for one evaluation protocol.

A view is not a labeling schema: runs label and store the schema's own classes; only the evaluate stage
reads a view, summing the schema-class confusion matrix into the view's classes
(:func:`leap_core.metrics.merge_confusion`). docs/METHOD.md D.5.

:data:`PAPER_VIEW` is the paper's Table 1 (SemanticKITTI columns): the 19 SemanticKITTI classes merged
into 11 so that a model trained on nuScenes (16 classes) could be scored beside the pseudo-labels
(paper, Experiments, Metrics: "we rename and merge several classes to pair models trained on nuScenes
(16 classes) with SemanticKITTI (19 classes)"). The paper names the 11 columns but not the merge; each
entry's ``reason`` says what it rests on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.errors import SchemaError


@dataclass(frozen=True)
class MergedClass:
    """One class of a view: the schema classes it sums."""

    name: str
    """The view's class name (a Table 1 column)."""
    sources: tuple[str, ...]
    """Schema class names counted as this class, in ground truth and in predictions alike."""
    category: str
    """Category for the view's category mIoU (``ClassDef.category`` semantics)."""
    reason: str
    """Why these sources: what the paper says, or why we chose where it is silent."""


@dataclass(frozen=True)
class MergedView:
    """Classes of a schema merged into fewer ones; applies only to a schema whose class names are exactly
    the union of the sources (:meth:`mapping`)."""

    name: str
    """Identifier written to ``metrics.json`` (``paper_view.name``)."""
    classes: tuple[MergedClass, ...]
    """The view's classes in column order."""

    def __post_init__(self) -> None:
        seen: dict[str, str] = {}
        for mc in self.classes:
            for s in mc.sources:
                if s in seen:
                    raise SchemaError(f"view {self.name}: class {s!r} is in both {seen[s]!r} and {mc.name!r}")
                seen[s] = mc.name
        names = [mc.name for mc in self.classes]
        if len(set(names)) != len(names):
            raise SchemaError(f"view {self.name}: duplicate class names {names}")

    @property
    def names(self) -> list[str]:
        return [mc.name for mc in self.classes]

    @property
    def categories(self) -> list[str]:
        return [mc.category for mc in self.classes]

    def sources(self) -> set[str]:
        """Every schema class name the view merges."""
        return {s for mc in self.classes for s in mc.sources}

    def problem(self, class_names: Sequence[str]) -> str | None:
        """Why the view does not apply to a schema with ``class_names``, or None when it does.

        It applies when every schema class is a source of exactly one view class and every source is a
        schema class: a missing source would leave a view class partly counted, and an extra schema class
        (one the view does not know) would take ground-truth ids from a source or be predicted with no view
        class to count it in.
        """
        have = set(class_names)
        missing = sorted(self.sources() - have)
        extra = [n for n in class_names if n not in self.sources()]
        if not missing and not extra:
            return None
        parts = []
        if missing:
            parts.append(f"lacks {', '.join(missing)}")
        if extra:
            parts.append(f"has classes the merge does not know ({', '.join(extra)})")
        return f"the schema {' and '.join(parts)}; the {self.name} merge needs SemanticKITTI's 19 classes"

    def mapping(self, class_names: Sequence[str]) -> npt.NDArray[np.int64] | None:
        """(C,) int64: schema class index → view class index; None when :meth:`problem` is not None."""
        if self.problem(class_names) is not None:
            return None
        to_view = {s: j for j, mc in enumerate(self.classes) for s in mc.sources}
        return np.array([to_view[n] for n in class_names], np.int64)

    def to_dict(self) -> dict[str, Any]:
        """What ``metrics.json`` records of the view (``paper_view``) and the evaluate fingerprint hashes."""
        return {
            "name": self.name,
            "class_names": self.names,
            "categories": self.categories,
            "merge": {mc.name: list(mc.sources) for mc in self.classes},
        }


PAPER_VIEW = MergedView(
    name="semantickitti-11",
    classes=(
        MergedClass("car", ("car",), "vehicle", "a Table 1 column as is"),
        MergedClass(
            "bicycle",
            ("bicycle", "bicyclist"),
            "vehicle",
            "Table 1 has no bicyclist column and the paper does not say where it went; this is our reading. "
            "The merge pairs SemanticKITTI with nuScenes, whose bicycle annotations include the rider (its "
            "boxes enclose bicycle and rider), so a ridden bike is one bicycle there; and the paper's remark "
            "that the 2D models 'may split a moving bike into separate person and bicycle labels' "
            "(Experiments, Pseudo-label quality) reads as an error against one-class ground truth",
        ),
        MergedClass(
            "motorcycle",
            ("motorcycle", "motorcyclist"),
            "vehicle",
            "as bicycle: nuScenes' motorcycle annotations include the rider; Table 1 has no motorcyclist "
            "column",
        ),
        MergedClass(
            "other-vehicle",
            ("truck", "other-vehicle"),
            "vehicle",
            "Table 1 has no truck column; nuScenes' truck, bus, trailer and construction vehicle all pair "
            "with a non-car vehicle class, and the paper's prompt expansion already describes other-vehicle "
            "by its kinds (bus, train)",
        ),
        MergedClass("person", ("person",), "human", "a Table 1 column as is (nuScenes: pedestrian)"),
        MergedClass(
            "road",
            ("road", "parking"),
            "flat",
            "parking is not a Table 1 column and the paper is silent; nuScenes' driveable_surface covers "
            "parking lots, and Table 1's other-ground figures (0.0 for every method, 2.8 for the oracle in "
            "Table 2) are those of a class without parking, which models segment far better than that",
        ),
        MergedClass("sidewalk", ("sidewalk",), "flat", "a Table 1 column as is"),
        MergedClass(
            "other-ground",
            ("other-ground",),
            "flat",
            "a Table 1 column as is (nuScenes: other_flat); parking is in road, see there",
        ),
        MergedClass(
            "manmade",
            ("building", "fence", "pole", "traffic-sign"),
            "construction",
            "nuScenes' static.manmade covers buildings, walls, fences, poles and signs; Table 1 colours the "
            "column with SemanticKITTI's building colour. Its category: construction (KITTI-360's object "
            "category of pole and traffic-sign has no class of its own left)",
        ),
        MergedClass(
            "vegetation",
            ("vegetation", "trunk"),
            "nature",
            "nuScenes' vegetation includes tree trunks; Table 1 has no trunk column",
        ),
        MergedClass("terrain", ("terrain",), "nature", "a Table 1 column as is"),
    ),
)
"""The paper's 11 SemanticKITTI classes of Table 1, each with the 19-class sources it sums."""


__all__ = ["PAPER_VIEW", "MergedClass", "MergedView"]
