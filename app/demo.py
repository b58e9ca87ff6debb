"""The built-in demo: a generated street sequence and a ready project on it.

The demo sequence is generated once into ``work_dir/demo`` (inside a temp folder renamed into place, under
a file lock, so two runs never generate it at the same time or see half of it). The demo project is the
built-in ``semantickitti`` preset (its classes, and its pipeline: the simulated labeler), so it needs no
model weights.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from app import crud
from app.core.config import Settings
from app.core.db import open_db, transaction
from app.core.demo_synth import synth_config
from leap_core.config import config_to_dict
from leap_core.presets import builtin_preset
from leap_core.synth import SYNTH_VERSION, default_workers, generate_sequence, synth_version

DEMO_PROJECT_NAME = "Demo street (simulated labeler)"
SEEDED_KEY = "demo_seeded"
SYNTH_STAGE = "generate demo"

log = logging.getLogger("leap.demo")


@contextlib.contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def demo_exists(dataset: Path) -> bool:
    """A complete demo sequence written by this generator version (an older one is generated again)."""
    return (
        (dataset / "poses.txt").is_file()
        and (dataset / "velodyne").is_dir()
        and synth_version(dataset) == SYNTH_VERSION
    )


def ensure_demo_sequence(
    dataset: Path,
    synth_overrides: dict[str, Any],
    *,
    progress: Callable[[str, int, int], None] | None = None,
    log: logging.Logger | None = None,
) -> Path:
    """Generate the demo sequence at ``dataset`` (a ``.../sequences/NN`` folder) unless it exists.

    Args:
        dataset: the sequence folder to create.
        synth_overrides: ``SynthConfig`` overrides (see :func:`synth_config`), e.g. fewer frames for tests.
        progress: called as ``progress("generate demo", done, total)`` after each frame.
    """
    dataset = Path(dataset)
    if demo_exists(dataset):
        return dataset
    config = synth_config(synth_overrides)
    with _file_lock(dataset.parent.parent / ".generate.lock"):
        if demo_exists(dataset):
            return dataset
        if log is not None:
            log.info("generating the demo sequence (%d frames) into %s", config.frames, dataset)
        # Generated beside its final place and renamed in, so nobody ever sees half a sequence.
        partial = dataset.parent.parent / ".partial"
        shutil.rmtree(partial, ignore_errors=True)

        def report(done: int, total: int) -> None:
            if progress is not None:
                progress(SYNTH_STAGE, done, total)

        report(0, config.frames)
        generate_sequence(
            partial, config, dataset.name, force=True, workers=default_workers(), progress=report
        )
        shutil.rmtree(dataset, ignore_errors=True)
        dataset.parent.mkdir(parents=True, exist_ok=True)
        os.replace(partial / "sequences" / dataset.name, dataset)
        shutil.rmtree(partial, ignore_errors=True)
    return dataset


def seed_demo_project(settings: Settings, jobs: Any | None = None) -> dict[str, Any] | None:
    """On first start, create the demo project (and queue its first run when ``jobs`` is given).

    Returns the new project, or None when the demo was seeded before (also when the user deleted it).
    """
    preset = builtin_preset("semantickitti")
    with open_db(settings.database) as db, transaction(db):
        if crud.get_meta(db, SEEDED_KEY) is not None:
            return None
        project = crud.create_project(
            db,
            name=DEMO_PROJECT_NAME,
            dataset_kind="demo",
            dataset_path=str(settings.demo_dataset),
            schema=preset.schema.to_dict(),
            pipeline=config_to_dict(preset.pipeline),
            is_demo=True,
        )
        crud.set_meta(db, SEEDED_KEY, str(project["id"]))
    log.info("seeded the demo project (id %d)", project["id"])
    if jobs is not None:
        finished = None
        with open_db(settings.database) as db:
            finished = crud.last_finished_run(db, project["id"])
        if finished is None:
            jobs.start_run(project["id"])
    return project
