"""Run folders written by earlier versions, moved into today's layout when the app starts.

The database migration to one run shape rewrote every run's parameters (a list of sequences); its folder
follows here (:func:`leap_core.pipeline.migration.migrate_run_folder`), with its ``params.json``
snapshot, so the viewer, the exports and a resume read one layout only.
"""

from __future__ import annotations

import logging
from pathlib import Path

from app import crud
from app.core.db import open_db
from app.jobs.worker import RunDirBusy, run_dir_lock
from leap_core.errors import LeapError
from leap_core.io_utils import atomic_write_json
from leap_core.pipeline.migration import migrate_run_folder
from leap_core.run_layout import former_layout

log = logging.getLogger("leap.jobs")


def migrate_run_folders(database: Path) -> int:
    """Move every run folder of the database that an earlier version wrote into today's layout; returns
    how many moved. A folder that cannot move (another process works in it, or an entry is in the way)
    keeps its layout, with a warning naming it and why."""
    with open_db(database) as db:
        runs = crud.all_runs(db)
    moved = 0
    for run in runs:
        if former_layout(run.run_dir) is None:
            continue
        first = run.params.sequences[0]
        try:
            with run_dir_lock(run.run_dir):
                migrate_run_folder(run.run_dir, first.name, first.dataset, first.frame_range)
                atomic_write_json(run.layout.params, run.params.to_dict())
        except (LeapError, OSError, RunDirBusy) as exc:
            log.warning("run folder %s keeps its former layout: %s", run.run_dir, exc)
            continue
        moved += 1
    if moved:
        log.info("moved %d run folder(s) into the layout of runs of sequences", moved)
    return moved


__all__ = ["migrate_run_folders"]
