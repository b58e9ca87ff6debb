"""A run's progress stages: ``<sequence>/<stage>`` for each sequence of the run (``00/fuse``), and
``*/3dcn`` for the 3D-CN's rounds, which train one network on every sequence at once.

:func:`run_stages` lists them in the order a run reaches them, so the run panel and the run log show each
sequence's stages; the web UI leaves the sequence out of the label in a run of one sequence.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from leap_core.errors import LeapError
from leap_core.pipeline.stages import STAGE_TABLE
from leap_core.run_layout import RunLayout

SEPARATOR = "/"
"""Between a sequence's name and a stage's in a progress stage name (never in a sequence name)."""

JOINT = "*"
"""The "sequence" the 3D-CN rounds report under (``leap_core.pipeline.JOINT``)."""

POSES = "estimate poses"
"""The per-sequence pose estimation's stage (``app.jobs.poses``)."""

SYNTH = "generate demo"
"""The demo sequence's generation (``app.demo.SYNTH_STAGE``), before its run's pipeline."""


UNIT_SECONDS: dict[str, float] = {
    "labels2d": 0.13,
    "project": 0.025,
    "motion": 0.006,
    "fuse": 0.005,
    "smooth": 0.003,
    "3dcn": 0.0,
    "label_points": 0.008,
    "tracks": 0.004,
    "evaluate": 0.004,
    "export": 0.003,
    POSES: 0.05,
    SYNTH: 0.9,
}
"""Expected seconds per progress unit (a frame; a scan for the pose estimation) of each stage before a run has
measured its own, from a demo run (60 frames, the simulated labeler: labels2d 8.0 s, project 1.5 s, motion
(with ``tracking.exclude_moving``) about 0.35 s, fuse 0.28 s, smooth 0.16 s, label_points 0.49 s, tracks about
0.25 s, evaluate 0.23 s, export 0.15 s; a sequence's own ``3dcn`` stage only links the rounds' grids). Only
their ratios matter until a stage has finished."""

LABELS2D_UNIT_SECONDS: dict[str, float] = {"gt2d": 0.13, "images": 2.0}
"""``labels2d`` per frame by what the labeler reads: 2D ground truth (the simulated labelers) or camera
images (Grounding DINO + SAM: about 2 s a frame on a CPU)."""

JOINT_UNIT_SECONDS = 0.02
"""The 3D-CN rounds (``*/3dcn``) report thousandths of a round: ≈ 20 s a round (a small demo run)."""

OTHER_UNIT_SECONDS = 0.01
"""A stage this table does not know."""


def unit_seconds(name: str, labeler_input: str | None = None) -> float:
    """Expected seconds per progress unit of the progress stage ``name`` (:data:`UNIT_SECONDS`), its
    ``labels2d`` by the labeler's input (:data:`LABELS2D_UNIT_SECONDS`: ``gt2d`` or ``images``)."""
    sequence, stage = split_stage(name)
    if sequence == JOINT:
        return JOINT_UNIT_SECONDS
    if stage == "labels2d" and labeler_input in LABELS2D_UNIT_SECONDS:
        return LABELS2D_UNIT_SECONDS[labeler_input]
    return UNIT_SECONDS.get(stage, OTHER_UNIT_SECONDS)


def stage_name(sequence: str, stage: str) -> str:
    """``<sequence>/<stage>``: one stage of one sequence in a run's progress."""
    return f"{sequence}{SEPARATOR}{stage}"


def split_stage(name: str) -> tuple[str | None, str]:
    """(sequence, stage) of a progress stage name; (None, name) for a name without a sequence (a run
    stored before every run had sequences)."""
    sequence, sep, stage = name.partition(SEPARATOR)
    return (sequence, stage) if sep else (None, name)


def stage_words(name: str, several: bool = False) -> str:
    """A progress stage's name for people, as the project page's run panel words it: the stage's label
    (``"00/labels2d"`` → ``"2D labels"``), after the sequence when the run has ``several``
    (``"01 · Voxel fusion"``, ``"all · 3D-CN"`` for the 3D-CN's rounds); a stage outside the pipeline
    (``"00/estimate poses"``) keeps its words."""
    sequence, stage = split_stage(name)
    label = next((s.label for s in STAGE_TABLE if s.name == stage), stage)
    if sequence is None or not several:
        return label
    return f"{'all' if sequence == JOINT else sequence} · {label}"


def run_stages(
    names: Sequence[str],
    stages: Sequence[str],
    *,
    joint_3dcn: bool,
    estimate: Sequence[str] = (),
    generate: Sequence[str] = (),
) -> list[str]:
    """A run's progress stages in the order it reaches them.

    Args:
        names: the sequences, in order.
        stages: the pipeline's stages (``leap_core.pipeline.STAGES``).
        joint_3dcn: the 3D-CN is on: every sequence goes up to ``smooth``, then the rounds (``*/3dcn``),
            then each sequence from ``3dcn`` (linking the rounds' grids) to the end.
        estimate: the sequences whose poses are estimated first.
        generate: the sequences generated first (the demo's).
    """
    out = [stage_name(n, SYNTH) for n in generate] + [stage_name(n, POSES) for n in estimate]
    if joint_3dcn and "3dcn" in stages:
        cut = list(stages).index("3dcn")
        out += [stage_name(n, s) for n in names for s in stages[:cut]]
        out.append(stage_name(JOINT, "3dcn"))
        out += [stage_name(n, s) for n in names for s in stages[cut:]]
    else:
        out += [stage_name(n, s) for n in names for s in stages]
    return out


def stage_folder(run_dir: Path, name: str) -> tuple[Path, str] | None:
    """(sequence folder, stage) whose ``stages.json`` says whether the progress stage ``name`` computed
    anything; None for the 3D-CN rounds, the pose estimation and the demo's generation."""
    sequence, stage = split_stage(name)
    if sequence is None or sequence == JOINT or stage in (POSES, SYNTH):
        return None
    try:
        return RunLayout(run_dir).sequence(sequence).folder, stage
    except LeapError:
        return None


def skipped_stages(run_dir: Path, names: Sequence[str]) -> dict[str, str | None]:
    """The stages each of the run's sequences ``names`` recorded as skipped, named ``<sequence>/<stage>``,
    with their note."""
    from leap_core.pipeline import stage_status  # noqa: PLC0415  # the pipeline, on demand

    out: dict[str, str | None] = {}
    layout = RunLayout(run_dir)
    for name in names:
        try:
            state = stage_status(layout.sequence(name).folder)
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
    "JOINT_UNIT_SECONDS",
    "LABELS2D_UNIT_SECONDS",
    "OTHER_UNIT_SECONDS",
    "POSES",
    "SEPARATOR",
    "SYNTH",
    "UNIT_SECONDS",
    "run_stages",
    "skipped_stages",
    "split_stage",
    "stage_folder",
    "stage_name",
    "stage_words",
    "unit_seconds",
]
