"""The run-vs-run Δ of the viewer's ``delta`` colour mode: which voxels changed class since the finished
run before the shown one.

The earlier run's final grid is read once per shown run (:meth:`ReviewGrid.load`, as the viewer reads the
shown run's) and its classes are matched to the shown run's by name, so a class added, removed or moved
between the runs compares correctly; the column itself is :func:`app.viewer.view_logic.delta_column`.
"""

from __future__ import annotations

import logging
import threading

import numpy as np
import numpy.typing as npt

from app.viewer import view_logic as vl
from app.viewer.data import ReviewGrid
from app.viewer.records import ProjectBackend, RunInfo
from leap_core.errors import LeapError

log = logging.getLogger(__name__)


def class_index_map(base_names: list[str], names: list[str]) -> npt.NDArray[np.int64]:
    """(C_base,) each earlier class's index among ``names``, -2 when this run has no class of that name."""
    where = {n: i for i, n in enumerate(names)}
    return np.array([where.get(n, -2) for n in base_names], np.int64)


class RunDelta:
    """The ``delta`` column of the shown run against the finished run before it (None: no such run)."""

    def __init__(self, backend: ProjectBackend) -> None:
        self.backend = backend
        self._lock = threading.Lock()
        self._base: tuple[int, RunInfo | None, ReviewGrid | None] | None = None
        self._column: tuple[object, object, npt.NDArray[np.float32]] | None = None

    def base_run(self, run: RunInfo) -> RunInfo | None:
        """The finished run the shown ``run`` is compared with (read once per shown run)."""
        return self._load(run)[0]

    def _load(self, run: RunInfo) -> tuple[RunInfo | None, ReviewGrid | None]:
        with self._lock:
            if self._base is not None and self._base[0] == run.run_id:
                return self._base[1], self._base[2]
            base = self.backend.finished_run_before(run.run_id)
            grid = None
            if base is not None:
                try:
                    grid = ReviewGrid.load(base.run_dir, base.pipeline)
                except LeapError as exc:  # its folder was removed: nothing to compare with
                    log.warning("run %d's grid for the Δ view: %s", base.number, exc)
                    base = None
            self._base = (run.run_id, base, grid)
            self._column = None
            return base, grid

    def column(
        self, run: RunInfo, grid: ReviewGrid, label: npt.NDArray[np.int16], names: list[str]
    ) -> npt.NDArray[np.float32]:
        """(V,) 1 where the voxel's class (corrections applied) differs from the earlier run's, else 0; all 0
        without an earlier run (nothing is shown as changed). Kept until the grid or the labels change."""
        base, base_grid = self._load(run)
        if base is None or base_grid is None:
            return np.zeros(grid.num_voxels, np.float32)
        with self._lock:
            cached = self._column
            if cached is not None and cached[0] is grid and cached[1] is label:
                return cached[2]
        base_names = [c.name for c in base.schema.classes] if base.schema is not None else []
        mapping = class_index_map(base_names, names)
        if mapping.shape[0] < base_grid.num_classes:  # a schema that does not describe the grid
            mapping = np.arange(base_grid.num_classes, dtype=np.int64)
        col = vl.delta_column(grid.keys, label, base_grid.keys, base_grid.label, mapping)
        with self._lock:
            self._column = (grid, label, col)
        return col


__all__ = ["RunDelta", "class_index_map"]
