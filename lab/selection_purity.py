"""What the 3D-CN is taught: its reliable training labels against the ground truth, per class (a check
behind the Table 1 acceptance that the 3D-CN must lift the voxel row: it can only where it is taught right).

The 3D Consistency Network learns from the labels that the round selects (docs/METHOD.md, stage C: per class,
the ``consistency.share`` most confident points of the smoothed grid). Where those labels are wrong for most
of a class's points, the network learns the mistake, and fusing it back cannot lift that class above the
voxel row; where they are right but the voxel row is not, it can. This script makes the selection of a
finished run (the same function, settings and view counts as the round) and counts, per ground-truth class,
how many of its points were selected and which class they were taught as.

Usage (from the repository root; the run folder, ``leap run``'s ``--out``, needs the sequence's
``grid_smooth.npz`` and ``observations/`` in ``sequences/<name>/``, i.e. any finished run, with or without the
3D-CN)::

    .venv/bin/python -m lab.selection_purity DATA/demo/sequences/00 RUNS/street/base \\
        --project-file projects/semantickitti.yaml

Prints a Markdown table: per class with ground-truth points, its points, the share selected, the share of
those taught as the class itself (*right*), and the classes the others were taught as.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.consistency.selection import view_counts
from leap_core.consistency.stage import iter_reliable_targets
from leap_core.pipeline import SequenceSpec
from leap_core.pipeline.executor import RunJob, worker_context
from leap_core.pipeline.stages import observed_keys
from leap_core.presets import load_preset
from leap_core.run_layout import RunLayout
from leap_core.runtime import Runtime
from leap_core.smoothing import SmoothedGrid

ROOT = Path(__file__).resolve().parents[1]


def taught_counts(gt: npt.ArrayLike, targets: npt.ArrayLike, num_classes: int) -> npt.NDArray[np.int64]:
    """(C, C) counts ``T[g, t]``: points of ground-truth class g selected with training label t.

    Points without ground truth (``gt < 0``) or without a training label (``targets < 0``) are not counted.
    Example: gt [0, 0, 1, -1], targets [0, 1, 1, 0], C = 2 → [[1, 1], [0, 1]].
    """
    g = np.asarray(gt, np.int64)
    t = np.asarray(targets, np.int64)
    if g.shape != t.shape:
        raise ValueError(f"gt {g.shape} and targets {t.shape} differ in shape")
    keep = (g >= 0) & (t >= 0)
    flat = g[keep] * num_classes + t[keep]
    return np.bincount(flat, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def purity_lines(
    taught: npt.NDArray[np.int64], gt_points: npt.NDArray[np.int64], names: Sequence[str], top: int = 2
) -> list[str]:
    """The Markdown table of :func:`taught_counts` ``taught`` (C, C) and each class's ground-truth point
    count ``gt_points`` (C,): one row per class that has ground truth.

    Columns: class, ground-truth points, selected (% of them), right (% of the selected taught as the class
    itself), and up to ``top`` other classes they were taught as (% of the selected); "-" where none was
    selected.
    """
    lines = ["| class | points | selected | right | taught as instead |", "|---|---|---|---|---|"]
    for c, name in enumerate(names):
        n = int(gt_points[c])
        if n == 0:
            continue
        row = taught[c]
        sel = int(row.sum())
        if sel == 0:
            lines.append(f"| {name} | {n:,} | 0 | - | - |")
            continue
        others = [j for j in np.argsort(-row, kind="stable") if j != c and row[j] > 0][:top]
        instead = ", ".join(f"{names[j]} {100 * row[j] / sel:.0f} %" for j in others) or "-"
        lines.append(f"| {name} | {n:,} | {100 * sel / n:.1f} % | {100 * row[c] / sel:.1f} % | {instead} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", help="The run's sequence folder (with labels/).")
    ap.add_argument("run", help="A finished run folder of the sequence (`leap run --out`).")
    ap.add_argument(
        "--project-file",
        default=str(ROOT / "projects" / "semantickitti.yaml"),
        help="The run's project file (its classes and consistency settings).",
    )
    args = ap.parse_args()
    preset = load_preset(Path(args.project_file))
    schema, cfg = preset.schema, preset.pipeline
    if not RunLayout.is_run(Path(args.run)):
        sys.exit(f"{args.run}: not a run folder (no {RunLayout.SPEC}); give the --out of `leap run`")
    layout = RunLayout(Path(args.run)).sequence(SequenceSpec.of(args.sequence).name)
    if not layout.grid_smooth.is_file():
        sys.exit(f"{layout.grid_smooth}: missing (the run has not finished its smoothing stage)")
    seq = layout.open_sequence(Path(args.sequence))
    frames = range(len(seq))
    c = schema.num_classes
    cn = cfg.consistency
    views = None
    if cn.rank_by_views:  # the round's tie-break, from the run's own observations
        ctx = worker_context(
            RunJob(Path(args.sequence), schema, cfg, layout.folder, Runtime()),
            range(seq.frame_numbers[0], seq.frame_numbers[-1] + 1),
        )
        views = view_counts(keys for _, keys in observed_keys(ctx))
    smoothed = SmoothedGrid.load(layout.grid_smooth)
    taught = np.zeros((c, c), np.int64)
    gt_points = np.zeros(c, np.int64)
    for i, t in zip(
        frames, iter_reliable_targets(seq, smoothed, c, cn, cfg.fusion.voxel_size, frames, views), strict=True
    ):
        g = schema.map_gt(seq.frame(i).labels)
        gt_points += np.bincount(g[g >= 0], minlength=c)
        taught += taught_counts(g, t, c)
    tie = "views" if views is not None else "no view"
    print(
        f"3D-CN training labels of {args.run} (share {cn.share}, scope {cn.selection_scope}, {tie} "
        f"tie-break), against {args.sequence}'s ground truth:"
    )
    print("\n".join(purity_lines(taught, gt_points, schema.names)))
    right = np.trace(taught) / max(int(taught.sum()), 1)
    print(f"\nall classes: {int(taught.sum()):,} training labels, {100 * right:.1f} % right")


if __name__ == "__main__":
    main()
