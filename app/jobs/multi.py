"""Runs of a project with several sequences (e.g. SemanticKITTI 00-10 under one class schema).

Such a run works in a multi-sequence run folder (:class:`leap_core.run_layout.MultiRunLayout`): one ordinary
run folder per sequence under ``run_dir/sequences/<name>/`` and the overall ``metrics.json``, filled by
:func:`leap_core.pipeline.multi.run_sequences`. A project with one sequence runs exactly as before
(``run_pipeline`` in ``run_dir`` itself); everything here is used only when the run's parameter snapshot
lists ``sequences`` (:func:`snapshot_sequences`, two or more).

Progress stages are named ``<sequence>/<stage>`` (``00/fuse``; ``*/3dcn`` for the 3D-CN rounds trained on
every sequence at once), listed in the order the run reaches them (:func:`run_stages`), so the run panel and
the run log show each sequence's stages.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from leap_core.errors import LeapError
from leap_core.run_layout import MultiRunLayout, RunLayout

SEPARATOR = "/"
"""Between a sequence's name and a stage's in a progress stage name (never in a sequence name)."""

JOINT = "*"
"""The "sequence" the joint 3D-CN rounds report under (``leap_core.pipeline.multi.JOINT``)."""

POSES = "estimate poses"
"""The per-sequence pose estimation's stage (``app.jobs.poses.POSES_STAGE``)."""


def stage_name(sequence: str, stage: str) -> str:
    """``<sequence>/<stage>``: one stage of one sequence in a multi-sequence run's progress."""
    return f"{sequence}{SEPARATOR}{stage}"


def split_stage(name: str) -> tuple[str | None, str]:
    """(sequence, stage) of a progress stage name; (None, name) for a single-sequence run's stage."""
    sequence, sep, stage = name.partition(SEPARATOR)
    return (sequence, stage) if sep else (None, name)


def snapshot_sequences(sequences: Sequence[Mapping[str, Any]]) -> list[dict[str, str]] | None:
    """The ``sequences`` entry of a run's parameter snapshot: ``[{"name", "dataset"}]`` in order for a
    project with several sequences; None for one (its snapshot stays as it always was)."""
    if len(sequences) <= 1:
        return None
    return [{"name": str(s["name"]), "dataset": str(s["dataset_path"])} for s in sequences]


def run_sequences_of(params: Mapping[str, Any]) -> list[tuple[str, Path]] | None:
    """(name, dataset) per sequence of a run's parameter snapshot; None for a single-sequence run."""
    listed = params.get("sequences")
    if not listed:
        return None
    return [(str(s["name"]), Path(s["dataset"])) for s in listed]


def run_stages(
    names: Sequence[str], stages: Sequence[str], *, joint_3dcn: bool, estimate: Sequence[str] = ()
) -> list[str]:
    """A multi-sequence run's progress stages in the order it reaches them.

    Args:
        names: the sequences, in order.
        stages: the pipeline's stages (``leap_core.pipeline.STAGES``).
        joint_3dcn: the 3D-CN is on: every sequence goes up to ``smooth``, then the joint rounds
            (``*/3dcn``), then each sequence from ``3dcn`` (linking the rounds' grids) to the end.
        estimate: the sequences whose poses are estimated first.
    """
    out = [stage_name(n, POSES) for n in estimate]
    if joint_3dcn and "3dcn" in stages:
        cut = list(stages).index("3dcn")
        out += [stage_name(n, s) for n in names for s in stages[:cut]]
        out.append(stage_name(JOINT, "3dcn"))
        out += [stage_name(n, s) for n in names for s in stages[cut:]]
    else:
        out += [stage_name(n, s) for n in names for s in stages]
    return out


def run_sequence_folders(params: Mapping[str, Any]) -> list[tuple[str | None, str]]:
    """(name, dataset folder) per sequence a run labeled; a single-sequence run's one has no name in its
    snapshot (None)."""
    listed = run_sequences_of(params)
    if listed is None:
        return [(None, str(params.get("dataset")))]
    return [(name, str(dataset)) for name, dataset in listed]


def covered_sequences(params: Mapping[str, Any], sequences: Sequence[Mapping[str, Any]]) -> list[str]:
    """The names of the project's current ``sequences`` (``{"name", "dataset_path"}`` rows) that a run
    labeled: a multi-sequence run's listed sequences still in the project on the same folder, a
    single-sequence run's folder (its snapshot names none). Sequences added or re-pointed since the run
    are not covered, so its results are never shown or corrected as theirs."""
    labeled = run_sequence_folders(params)
    out = []
    for s in sequences:
        name, folder = str(s["name"]), str(s["dataset_path"])
        if any(folder == f and n in (None, name) for n, f in labeled):
            out.append(name)
            if labeled[0][0] is None:
                break  # a single-sequence run labeled one folder: one project sequence at most
    return out


def sequence_run_dir(run_dir: Path, params: Mapping[str, Any], sequence: str | None) -> Path:
    """The run folder of one sequence of a run: ``run_dir/sequences/<name>`` for a multi-sequence run
    (None: its first sequence), ``run_dir`` itself for a single-sequence run (whatever ``sequence`` says).

    Raises:
        KeyError: ``sequence`` is not one of the run's sequences.
    """
    listed = run_sequences_of(params)
    if listed is None:  # the project's one sequence (the caller checked the name against the project)
        return run_dir
    names = [n for n, _ in listed]
    name = names[0] if sequence is None else sequence
    if name not in names:
        raise KeyError(sequence)
    return MultiRunLayout(run_dir).sequence(name).run_dir


# ------------------------------------------------------------------------------- the worker's side
def execute_sequences(  # one keyword per part of the run spec it reads
    run_dir: Path,
    sequences: Mapping[str, Path],
    schema_doc: dict[str, Any],
    pipeline: dict[str, Any],
    reporter: Any,
    *,
    runtime: Any,
    estimate_poses: bool,
    poses_cache: Path | None,
) -> None:
    """The worker's part of a multi-sequence run (``app.jobs.worker``): poses per sequence, then
    :func:`leap_core.pipeline.multi.run_sequences` with each report renamed ``<sequence>/<stage>``.

    ``reporter`` is the worker's progress callback (``reporter(stage, done, total)``); its ``stage_dir``
    hook is pointed at each sequence's run folder so a stage that computed nothing reads "skipped".
    """
    from app.jobs.poses import prepare_run_poses  # noqa: PLC0415  # the worker's own import order
    from leap_core.config import config_from_dict  # noqa: PLC0415
    from leap_core.pipeline.multi import SequenceSpec, run_sequences  # noqa: PLC0415  # loads torch
    from leap_core.schema import Schema  # noqa: PLC0415

    layout = MultiRunLayout(run_dir)
    for name, dataset in sequences.items():
        prepare_run_poses(
            dataset,
            layout.sequence(name).run_dir,
            estimate=estimate_poses,
            cache_root=poses_cache,
            progress=lambda done, total, n=name: reporter(stage_name(n, POSES), done, total),
        )
    schema = Schema.from_dict(schema_doc, source="project schema")
    config = config_from_dict(pipeline)
    specs = [SequenceSpec(name, dataset) for name, dataset in sequences.items()]
    run_sequences(
        specs,
        schema,
        config,
        run_dir,
        progress=lambda seq, stage, done, total: reporter(stage_name(seq, stage), done, total),
        runtime=runtime,
    )


def stage_dir(run_dir: Path, name: str) -> tuple[Path, str] | None:
    """(sequence run folder, stage) whose ``stages.json`` says whether the progress stage ``name`` of a
    multi-sequence run computed anything; None for the joint rounds and the pose estimation."""
    sequence, stage = split_stage(name)
    if sequence is None or sequence == JOINT or stage == POSES:
        return None
    try:
        return MultiRunLayout(run_dir).sequence(sequence).run_dir, stage
    except LeapError:
        return None


# ------------------------------------------------------------------------------- the server's side
def sequence_layouts(run_dir: Path, params: Mapping[str, Any]) -> list[tuple[str, Path, RunLayout]]:
    """(name, dataset, run layout) per sequence of a multi-sequence run."""
    listed = run_sequences_of(params) or []
    layout = MultiRunLayout(run_dir)
    return [(name, dataset, layout.sequence(name)) for name, dataset in listed]


def read_run_metrics(run_dir: Path) -> dict[str, Any] | None:
    """A multi-sequence run's ``metrics.json`` (``{"overall", "sequences"}``), None when absent or
    unreadable."""
    from leap_core.pipeline.multi import read_multi_metrics  # noqa: PLC0415  # the pipeline, on demand

    try:
        return read_multi_metrics(run_dir)
    except LeapError:
        return None


def skipped_stages(run_dir: Path, params: Mapping[str, Any]) -> dict[str, str | None]:
    """The stages each sequence recorded as skipped, named ``<sequence>/<stage>``."""
    from leap_core.pipeline import stage_status  # noqa: PLC0415  # the pipeline, on demand

    out: dict[str, str | None] = {}
    for name, _, lay in sequence_layouts(run_dir, params):
        try:
            state = stage_status(lay.run_dir)
        except LeapError:
            continue
        out.update(
            {
                stage_name(name, stage): rec.get("note")
                for stage, rec in state.items()
                if rec.get("status") == "skipped"
            }
        )
    return out


__all__ = [
    "JOINT",
    "SEPARATOR",
    "covered_sequences",
    "execute_sequences",
    "read_run_metrics",
    "run_sequence_folders",
    "run_sequences_of",
    "run_stages",
    "sequence_layouts",
    "sequence_run_dir",
    "skipped_stages",
    "snapshot_sequences",
    "split_stage",
    "stage_dir",
    "stage_name",
]
