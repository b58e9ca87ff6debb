"""Run folders written before every run had one shape, moved into it in place.

Earlier versions wrote two shapes: a run of one sequence kept that sequence's files directly in the run
folder (its ``stages.json`` at the top), a run of several kept them under ``sequences/<name>/`` beside a
``multi.json``. Today a run folder always holds ``run.json`` and ``sequences/<name>/``
(:mod:`leap_core.run_layout`). :func:`migrate_run_folder` moves an old folder once; the pipeline calls it
on the folder it is given, the app on every run folder when it starts.
"""

from __future__ import annotations

import os
from pathlib import Path

from leap_core.errors import LeapError
from leap_core.pipeline.evaluation import read_metrics_json, write_run_metrics
from leap_core.run_layout import FORMER_MULTI_SPEC, RunLayout, SequenceLayout, former_layout, write_run_spec


def migrate_run_folder(
    path: str | Path, name: str, dataset: Path | None = None, frames: range | None = None
) -> bool:
    """Move a run folder of a former layout (:func:`~leap_core.run_layout.former_layout`) into this one,
    in place; True when it moved something, False for a folder already in this layout (or none).

    A former one-sequence folder's entries go to ``sequences/<name>/``, except the run's own (the app's
    parameter snapshot, log, lock and zips, and ``3dcn/``, whose checkpoints belong to the run); its
    ``metrics.json`` goes with them, the run's overall ``metrics.json`` is written beside ``sequences/``
    and ``run.json`` names the sequence (with ``dataset`` and ``frames`` when the caller knows them). A
    former folder of several sequences only has its ``multi.json`` renamed to ``run.json``.

    Every entry moves with one rename and ``stages.json`` last, so a migration stopped half-way leaves a
    former one-sequence folder that the next call finishes. ``name``, ``dataset`` and ``frames`` are only
    read for a one-sequence folder.

    Raises:
        LeapError: ``name`` is not a folder-safe sequence name, or ``sequences/<name>/`` already holds an
            entry of the name of one to move.
        DatasetError: the folder's ``metrics.json`` is unreadable.
    """
    root = Path(path)
    kind = former_layout(root)
    if kind is None:
        return False
    layout = RunLayout(root)
    if kind == "multi":
        os.replace(root / FORMER_MULTI_SPEC, layout.spec)
        return True
    seq = layout.sequence(name)
    seq.folder.mkdir(parents=True, exist_ok=True)
    moving = [
        entry
        for entry in sorted(root.iterdir())
        if entry.name not in RunLayout.RUN_FILES and entry.name != SequenceLayout.STATE
    ]
    if layout.metrics.is_file() and not seq.metrics.is_file():
        # The sequence's tables (once they moved, a file here is the run's, written below).
        moving.append(layout.metrics)
    for entry in moving:
        target = seq.folder / entry.name
        if target.exists() or target.is_symlink():
            raise LeapError(
                f"{root}: cannot move {entry.name} into {seq.folder}, which already has one; move one of "
                "them away, then run again"
            )
        os.replace(entry, target)
    metrics = read_metrics_json(seq.folder)
    if metrics is not None:
        write_run_metrics(layout, {name: metrics})
    os.replace(root / SequenceLayout.STATE, seq.state)
    write_run_spec(layout, [(name, dataset, frames)])
    return True


__all__ = ["migrate_run_folder"]
