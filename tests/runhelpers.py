"""Runs of one sequence for tests: :func:`leap_core.pipeline.run_pipeline` on one :class:`SequenceSpec`,
with the stage-level progress callback most tests watch.

A run folder holds its sequences under ``sequences/<name>/``; :func:`label` returns the sequence's
:class:`SequenceResult`, whose ``folder`` is where that sequence's files are.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from app.rows import RunParams, RunSequence
from leap_core.config import PipelineConfig
from leap_core.pipeline import JOINT, SequenceResult, SequenceSpec, run_pipeline
from leap_core.runtime import Runtime
from leap_core.schema import Schema


def label(
    dataset: Path,
    schema: Schema,
    config: PipelineConfig,
    out: Path,
    *,
    progress: Callable[[str, int, int], None] | None = None,
    frames: range | None = None,
    runtime: Runtime | None = None,
    until: str | None = None,
    name: str | None = None,
) -> SequenceResult:
    """Label ``dataset`` as a run of that one sequence (named after its folder unless ``name``) in the run
    folder ``out``; ``progress(stage, done, total)`` sees the sequence's stages and the 3D-CN rounds (as
    stage ``3dcn``)."""

    def report(sequence: str, stage: str, done: int, total: int) -> None:
        assert progress is not None
        if sequence in (JOINT, spec.name):
            progress(stage, done, total)

    spec = SequenceSpec.of(dataset, frames, name)
    result = run_pipeline(
        [spec],
        schema,
        config,
        out,
        progress=None if progress is None else report,
        runtime=runtime,
        until=until,
    )
    return result.only()


def run_params(schema: dict[str, Any], dataset: Path, name: str = "00") -> RunParams:
    """An app run's parameters of one sequence ``name`` on ``dataset`` with the class schema ``schema``
    (``Schema.to_dict`` form) and default settings."""
    return RunParams(
        sequences=(RunSequence(name, Path(dataset)),), dataset_kind="folder", schema=schema, pipeline={}
    )


def folder(out: Path, name: str = "00") -> Path:
    """The folder of sequence ``name`` in the run folder ``out``."""
    return Path(out) / "sequences" / name


__all__ = ["folder", "label", "run_params"]
