"""The level-of-detail view's kept counts: per-block tables and overview colours of the shown grid.

A class toggle, a colour switch or a new focus only reads the per-block tables (:mod:`app.viewer.lod_plan`),
so they are counted once per labels / score / threshold and kept here; a correction or an undo moves only its
voxels in them and recolours only the blocks those lie in. Used by the drawing thread of
:class:`app.viewer.render.LodRenderer` only (one cache per shown grid).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import numpy.typing as npt

from app.viewer import lod_plan
from app.viewer import view_logic as vl
from app.viewer.lod import Blocks

Tables = tuple[tuple[Any, ...], npt.NDArray[np.float32], npt.NDArray[np.float32]]
"""Kept per-block tables: (what they were made from, counts, score sums)."""
BlockColors = tuple[tuple[Any, ...], npt.NDArray[np.uint8]]
"""Kept overview colours: ((tables, class columns, mode, palette), (B, 3) colours)."""


class LodCache:
    """Per-block tables and overview colours of one grid, kept while their inputs stay the same objects.

    Args:
        seconds: where the time of the last count is recorded (key ``tables``).
    """

    def __init__(self, seconds: dict[str, float]) -> None:
        self.seconds = seconds
        self.tables: Tables | None = None
        """The last tables and the inputs they were counted from."""
        self.table_inputs: tuple[npt.NDArray[np.int16], npt.NDArray[np.floating]] | None = None
        """Labels and scores the tables hold (to move only changed voxels after a correction)."""
        self.colors: BlockColors | None = None
        """The last overview colours and what they were made from."""

    def block_tables(
        self,
        blocks: Blocks,
        *,
        state: vl.ViewState,
        label: npt.NDArray[np.int16],
        conf: npt.NDArray[np.float32],
        corrected: npt.NDArray[np.bool_],
        score: npt.NDArray[np.floating],
        num_classes: int,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """Per block and class counts and score sums of the voxels passing the threshold, kept until the
        labels, the scored quantity or the threshold change (a class toggle or a new focus reuses them; the
        class and confidence views share one table: both threshold and sum the confidence)."""
        prob = state.mode == "class_probability"
        key = (
            blocks,
            label,
            conf,
            corrected if prob else None,
            state.class_index if prob else -1,
            state.threshold,
            # The disagreement view scores another column than the confidence views share.
            state.mode == "disagreement",
        )
        cached = self.tables
        if (
            cached is not None
            and len(cached[0]) == len(key)
            and all(
                a is b if isinstance(a, (np.ndarray, Blocks)) else a == b
                for a, b in zip(cached[0], key, strict=True)
            )
        ):
            return cached[1], cached[2]
        t0 = time.perf_counter()
        thr = np.float32(state.threshold)
        hist_ssum = self._tables_after_edit(blocks, key, label, score, thr, num_classes)
        if hist_ssum is None:
            hist, ssum = blocks.index.sorted_tables(
                blocks, label, num_classes, threshold=float(thr), score=score
            )
            assert ssum is not None
        else:
            hist, ssum = hist_ssum
        self.tables = (key, hist, ssum)
        self.table_inputs = (label, score)
        self.seconds["tables"] = time.perf_counter() - t0
        return hist, ssum

    def _tables_after_edit(
        self,
        blocks: Blocks,
        key: tuple[Any, ...],
        label: npt.NDArray[np.int16],
        score: npt.NDArray[np.floating],
        thr: np.float32,
        num_classes: int,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None:
        """The kept tables moved to new labels / scores when only those changed, and in few voxels (a
        correction, an undo); None when they must be counted afresh."""
        cached, inputs = self.tables, self.table_inputs
        if cached is None or inputs is None or cached[0][0] is not blocks or cached[0][4:] != key[4:]:
            return None
        old_label, old_score = inputs
        if old_label.shape != label.shape or old_score.shape != score.shape:
            return None
        rows = np.flatnonzero((old_label != label) | (old_score != score))
        if rows.size > label.shape[0] // 20:
            return None
        hist, ssum = cached[1], cached[2]  # updated in place, and the colours made from them
        counted_old = old_score[rows] >= thr if thr > 0 else np.ones(rows.size, bool)
        counted_new = score[rows] >= thr if thr > 0 else np.ones(rows.size, bool)
        changed = blocks.of_row[rows]
        lod_plan.update_tables(
            hist,
            ssum,
            changed,
            num_classes,
            (old_label[rows], old_score[rows], counted_old),
            (label[rows], score[rows], counted_new),
        )
        self._recolor_blocks(hist, ssum, np.unique(changed))
        return hist, ssum

    def _recolor_blocks(
        self, hist: npt.NDArray[np.float32], ssum: npt.NDArray[np.float32], changed: npt.NDArray[Any]
    ) -> None:
        """After an in-place table update, the kept overview colours of the ``changed`` blocks only (the
        other blocks' tables did not move): recolouring every block after a correction took 60-400 ms at
        10 M voxels, most of a correction's or an undo's time."""
        cached = self.colors
        if cached is None or cached[0][0] is not hist:
            return
        (_, columns_bytes, mode, palette), colors = cached
        columns = np.frombuffer(columns_bytes, np.float32)
        if mode == "class":
            colors[changed] = vl.class_colors(lod_plan.majority_class(hist, columns, changed), palette)
        elif mode == "objects":
            colors[changed] = vl.UNCHANGED_RGB
        else:
            colors[changed] = vl.scalar_colors(lod_plan.mean_score(hist, ssum, columns, changed))

    def block_colors(
        self,
        hist: npt.NDArray[np.float32],
        ssum: npt.NDArray[np.float32],
        columns: npt.NDArray[np.float32],
        mode: vl.ColorMode,
        palette: npt.NDArray[np.uint8],
    ) -> npt.NDArray[np.uint8]:
        """(B, 3) overview colour of every block (majority class or mean score of its visible voxels), kept
        until the tables, the class toggles, the mode or the palette change (a new focus reuses it)."""
        key = (hist, columns.tobytes(), mode, palette)
        cached = self.colors
        same = cached is not None and cached[0][0] is hist and cached[0][3] is palette
        if cached is not None and same and cached[0][1:3] == key[1:3]:
            return cached[1]
        if mode == "class":
            colors = vl.class_colors(lod_plan.majority_class(hist, columns), palette)
        elif mode == "objects":
            colors = np.tile(np.asarray(vl.UNCHANGED_RGB, np.uint8), (hist.shape[0], 1))
        else:
            colors = vl.scalar_colors(lod_plan.mean_score(hist, ssum, columns))
        self.colors = (key, colors)
        return colors


__all__ = ["BlockColors", "LodCache", "Tables"]
