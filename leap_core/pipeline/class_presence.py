"""Classes the 2D labeler (almost) never gave a pixel: their prompts may never fire.

A class whose prompts find nothing (on RELLIS-3D, ``other-ground``: IoU 0 on every seed) used to end a run
without a word. After the ``labels2d`` stage the run records each class's *pixels* over the run's frames
(:func:`class_pixels`, kept in the stage's ``stages.json`` record under :data:`RECORD_KEY`); at the end of
the run :func:`silent_classes` names each class whose share of them is below :data:`MIN_CLASS_SHARE`,
and the run logs one warning per class (:func:`warning_text`: the CLI prints it, the app shows it with the
run) and the export's ``summary.yaml`` lists them.

With 3D ground truth the check keeps to classes the ground truth holds (share ≥ :data:`MIN_CLASS_SHARE` of
its points): a class absent from the scene is not a prompt problem. Without it every silent class is named,
since the run cannot tell an absent class from one whose prompts never fire.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.labelers.base import SoftMasks

MIN_CLASS_SHARE = 1e-4
"""A class is *silent* below this share of all the run's mask pixels (0.01 %: a few dozen pixels per
KITTI frame); with ground truth, it must also hold at least this share of the ground-truth points."""

RECORD_KEY = "class_pixels"
"""Key of the per-class pixels in the ``labels2d`` stage record: ``{"frames": key, "count": frames,
"pixels": [...]}``."""

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.int64)


def class_pixels(soft: SoftMasks) -> npt.NDArray[np.float64]:
    """(C,) pixels of each class in one frame's soft masks: ``Σ_m area_m · 1[argmax_c p_m = c]``, the
    pixels of the masks whose most likely class it is (``area_m``: the pixels mask m covers; overlaps
    count once per mask: an indicator, not a per-pixel labeling). The argmax, not ``p_m(c)`` itself: a
    soft distribution gives every class a little of every mask, and a class no mask names is the point."""
    out = np.zeros(soft.num_classes, np.float64)
    if soft.num_masks == 0:
        return out
    area = _POPCOUNT[soft.bits].sum(axis=1).astype(np.float64)  # (M,)
    np.add.at(out, np.argmax(soft.probs, axis=1), area)
    return out


@dataclass(frozen=True)
class SilentClass:
    """A class with (almost) no pixels from the 2D labeler."""

    name: str
    prompts: tuple[str, ...]
    pixels: float
    """Its pixels over the run's frames (:func:`class_pixels`)."""
    share: float
    """``pixels`` / the pixels of all classes (0 when no class got any)."""
    frames: int
    """Frames the mass was summed over."""
    gt_points: int | None
    """Its ground-truth points in the run (None without ground truth)."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "class": self.name,
            "pixels": round(self.pixels),
            "share": float(f"{self.share:.3g}"),
            "frames": self.frames,
            "ground_truth_points": self.gt_points,
            "prompts": list(self.prompts),
        }


def silent_classes(
    names: Sequence[str],
    prompts: Sequence[Sequence[str]],
    pixels: Sequence[float],
    frames: int,
    gt_points: Sequence[int] | None = None,
    min_share: float = MIN_CLASS_SHARE,
) -> list[SilentClass]:
    """The classes whose pixel share is below ``min_share`` (all classes in schema order).

    Args:
        names, prompts: the classes and their prompts, in schema order.
        pixels: (C,) pixels per class (:func:`class_pixels` summed over the frames).
        frames: the frames summed.
        gt_points: (C,) ground-truth points per class, when the run has ground truth: then only classes
            holding at least ``min_share`` of them are named.
    """
    mass = np.asarray(pixels, np.float64)
    total = float(mass.sum())
    gt = None if gt_points is None else np.asarray(gt_points, np.int64)
    gt_total = 0 if gt is None else int(gt.sum())
    out = []
    for c, name in enumerate(names):
        share = float(mass[c]) / total if total > 0 else 0.0
        if share >= min_share:
            continue
        if gt is not None and (gt_total == 0 or gt[c] < min_share * gt_total):
            continue  # absent from the ground truth too: nothing to fix in its prompts
        out.append(
            SilentClass(
                name, tuple(prompts[c]), float(mass[c]), share, frames, None if gt is None else int(gt[c])
            )
        )
    return out


def warning_text(silent: SilentClass, sequence: str | None = None) -> str:
    """One line naming the class, what it got and what to change."""
    where = f"sequence {sequence}: " if sequence else ""
    got = "no pixels" if silent.pixels < 0.5 else f"almost no pixels ({100 * silent.share:.3f} % of all)"
    shown = ", ".join(f"'{p}'" for p in silent.prompts[:4]) + (", …" if len(silent.prompts) > 4 else "")
    truth = (
        f", though the ground truth has {silent.gt_points} of its points"
        if silent.gt_points
        else " (it may be absent from these images)"
        if silent.gt_points is None
        else ""
    )
    return (
        f"{where}class {silent.name!r} got {got} from the 2D labeler in {silent.frames} frames{truth}: "
        f"its prompts ({shown or 'none'}) may never fire; try other prompts for it (synonyms, what it "
        "looks like in these images) or check their spelling"
    )


__all__ = [
    "MIN_CLASS_SHARE",
    "RECORD_KEY",
    "SilentClass",
    "class_pixels",
    "silent_classes",
    "warning_text",
]
