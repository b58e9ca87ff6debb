"""The built-in demos: a generated street sequence and a ready project on it, and a second one, a farm
seen from a survey drone (``leap synth --domain agri-uav``).

A demo sequence is generated once into ``work_dir/demo`` (street) or ``work_dir/demo-agri`` (farm), inside a
temp folder renamed into place, under a file lock, so two runs never generate it at the same time or see
half of it; which one a folder holds follows from its path (:func:`demo_domain`). The street demo project
is the built-in ``semantickitti`` preset (its classes, and its pipeline: the simulated labeler), the farm
one the ``agri_uav`` preset with the simulated labeler instead of grounded-sam, so neither needs model
weights.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import logging
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from app import crud
from app.core.config import Settings
from app.core.db import default_sequence_name, open_db, transaction
from app.core.demo_synth import synth_config
from app.jobs.stages import SYNTH
from app.rows import ProjectRow
from leap_core.config import config_to_dict
from leap_core.presets import builtin_preset
from leap_core.synth import SYNTH_VERSION, SynthConfig, default_workers, generate_sequence, synth_version
from leap_core.synth.agri import AGRI_SYNTH_STAMP, AgriSynthConfig
from leap_core.synth.generator import synth_stamp

DEMO_PROJECT_NAME = "Demo street (simulated labeler)"
SEEDED_KEY = "demo_seeded"
AGRI_DEMO_PROJECT_NAME = "Demo farm drone (simulated labeler)"
AGRI_SEEDED_KEY = "demo_agri_seeded"
AGRI_DEMO_FOLDER = "demo-agri"
"""The farm demo's folder in the work folder (``Settings.demo_agri_dataset``)."""
AGRI_DEMO_FRAMES = 20
"""Frames of the farm demo (24 m of flight at 5 Hz): its first run stays short."""

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


def demo_domain(dataset: Path) -> str:
    """``agri-uav`` for a sequence folder under ``<work_dir>/demo-agri``, else ``street``."""
    return "agri-uav" if Path(dataset).parent.parent.name == AGRI_DEMO_FOLDER else "street"


def demo_exists(dataset: Path) -> bool:
    """A complete demo sequence written by this generator version (an older one is generated again)."""
    current = (
        synth_stamp(dataset) == AGRI_SYNTH_STAMP
        if demo_domain(dataset) == "agri-uav"
        else synth_version(dataset) == SYNTH_VERSION
    )
    return (dataset / "poses.txt").is_file() and (dataset / "velodyne").is_dir() and current


def demo_config(dataset: Path, synth_overrides: dict[str, Any]) -> SynthConfig | AgriSynthConfig:
    """The generator config of the demo at ``dataset``: the street with ``synth_overrides``
    (:func:`synth_config`), or the farm with :data:`AGRI_DEMO_FRAMES` frames (fewer when the overrides'
    ``frames`` is smaller, so tests make both demos short)."""
    if demo_domain(dataset) == "agri-uav":
        frames = min(int(synth_overrides.get("frames", AGRI_DEMO_FRAMES)), AGRI_DEMO_FRAMES)
        return AgriSynthConfig(frames=frames)
    return synth_config(synth_overrides)


def ensure_demo_sequence(
    dataset: Path,
    synth_overrides: dict[str, Any],
    *,
    progress: Callable[[str, int, int], None] | None = None,
    log: logging.Logger | None = None,
) -> Path:
    """Generate the demo sequence at ``dataset`` (a ``.../sequences/NN`` folder) unless it exists.

    Args:
        dataset: the sequence folder to create (its path picks the street or the farm, :func:`demo_domain`).
        synth_overrides: ``SynthConfig`` overrides (see :func:`demo_config`), e.g. fewer frames for tests.
        progress: called as ``progress("generate demo", done, total)`` after each frame.
    """
    dataset = Path(dataset)
    if demo_exists(dataset):
        return dataset
    config = demo_config(dataset, synth_overrides)
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
                progress(SYNTH, done, total)

        report(0, config.frames)
        generate_sequence(
            partial, config, dataset.name, force=True, workers=default_workers(), progress=report
        )
        shutil.rmtree(dataset, ignore_errors=True)
        dataset.parent.mkdir(parents=True, exist_ok=True)
        os.replace(partial / "sequences" / dataset.name, dataset)
        shutil.rmtree(partial, ignore_errors=True)
    return dataset


def seed_demo_project(settings: Settings, jobs: Any | None = None) -> ProjectRow | None:
    """On first start, create the demo project (and queue its first run when ``jobs`` is given).

    Returns the new project, or None when the demo was seeded before (also when the user deleted it).
    """
    preset = builtin_preset("semantickitti")
    return _seed(
        settings,
        jobs,
        SEEDED_KEY,
        DEMO_PROJECT_NAME,
        settings.demo_dataset,
        schema=preset.schema.to_dict(),
        pipeline=config_to_dict(preset.pipeline),
    )


def seed_agri_demo_project(settings: Settings, jobs: Any | None = None) -> ProjectRow | None:
    """On first start, create the farm drone demo project (and queue its first run, which generates the
    sequence, when ``jobs`` is given): the ``agri_uav`` preset with the simulated labeler.

    Returns the new project, or None when it was seeded before (also when the user deleted it).
    """
    preset = builtin_preset("agri_uav")
    pipeline = dataclasses.replace(preset.pipeline, labeler="simulated")
    return _seed(
        settings,
        jobs,
        AGRI_SEEDED_KEY,
        AGRI_DEMO_PROJECT_NAME,
        settings.demo_agri_dataset,
        schema=preset.schema.to_dict(),
        pipeline=config_to_dict(pipeline),
    )


def _seed(
    settings: Settings,
    jobs: Any | None,
    key: str,
    name: str,
    dataset: Path,
    *,
    schema: dict[str, Any],
    pipeline: dict[str, Any],
) -> ProjectRow | None:
    """Create a demo project once (``key`` in the meta table remembers it) and queue its first run."""
    with open_db(settings.database) as db, transaction(db):
        if crud.get_meta(db, key) is not None:
            return None
        project = crud.create_project(
            db,
            name=name,
            dataset_kind="demo",
            sequences=[(default_sequence_name(str(dataset)), str(dataset))],
            schema=schema,
            pipeline=pipeline,
            is_demo=True,
        )
        crud.set_meta(db, key, str(project.id))
    log.info("seeded the demo project %r (id %d)", name, project.id)
    if jobs is not None:
        finished = None
        with open_db(settings.database) as db:
            finished = crud.last_finished_run(db, project.id)
        if finished is None:
            jobs.start_run(project.id)
    return project
