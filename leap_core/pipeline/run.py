"""A run: one or several sequences (e.g. SemanticKITTI 00-10, often just one) labeled with one class schema
and one config into one run folder (:class:`~leap_core.run_layout.RunLayout`). :func:`run_pipeline` is the
pipeline's entry point.

Each sequence gets its folder ``<root>/sequences/<name>/`` and goes through the stage machinery
(:func:`~leap_core.pipeline.runner.run_sequence`: fingerprints, caching, resume). What spans the run:

- **The 3D-CN**, when enabled: every sequence runs up to ``smooth``; then each round trains ONE network
  on the reliable labels of all sequences and fuses its predictions back into each sequence's own grid
  (:func:`~leap_core.pipeline.stages.cn_rounds`). Checkpoints go to ``<root>/3dcn/``, each sequence's
  round grids to ``<root>/3dcn/rounds/<name>/``, from where the sequence's own ``3dcn`` stage hard-links
  them into its folder. Its ``3dcn_joint.json`` names the round (a fingerprint of the 3D-CN settings and
  of every sequence's ``smooth`` stage), and is part of its ``3dcn`` stage's fingerprint, so a change in
  any sequence reruns the 3D-CN and what follows in all of them.
- **The metrics**: each sequence's ``metrics.json``, and ``<root>/metrics.json`` with
  ``{"overall": ..., "sequences": {name: ...}}``, overall = the metrics of the summed confusion matrices
  (:func:`~leap_core.pipeline.evaluation.overall_metrics`).

Without the 3D-CN nothing but the overall metrics spans the run: each sequence's files are those of a run
of that sequence alone.

Locally the sequences run one after another. With a Ray runtime they run at once, one driver thread each
sending its per-frame work to the one cluster (:class:`_Concurrently`); every sequence is still an
ordinary :func:`~leap_core.pipeline.runner.run_sequence` in its own folder, so its files are the local
run's bytes, and the 3D-CN rounds' inference runs as Ray tasks too.

Exports keep SemanticKITTI's layout (:mod:`leap_core.export`: ``<target>/sequences/<name>/predictions/
<frame>.label``).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from leap_core.config import PipelineConfig, config_to_dict
from leap_core.consistency.config import fingerprint_form
from leap_core.errors import Cancelled, ConfigError, DatasetError, LeapError
from leap_core.io_utils import atomic_write_json, remove_tree
from leap_core.pipeline.context import Ctx, hash_json, read_state
from leap_core.pipeline.evaluation import format_result_tables, read_metrics_file, write_run_metrics
from leap_core.pipeline.executor import Executor, make_executor
from leap_core.pipeline.metrics_file import RunMetrics
from leap_core.pipeline.migration import migrate_run_folder
from leap_core.pipeline.runner import (
    PIPELINE_VERSION,
    SequenceResult,
    require_poses,
    run_sequence,
    stage_fingerprints,
)
from leap_core.pipeline.stages import STAGE_TABLE, STAGES, CnMember, cn_rounds, source_digest
from leap_core.run_layout import RunLayout, former_layout, run_holding, sequence_name_problem, write_run_spec
from leap_core.runtime import Runtime
from leap_core.schema import Schema

JOINT = "*"
"""The sequence name :func:`run_pipeline` reports the 3D-CN rounds' progress under (never a sequence's
name: not folder-safe)."""

RunProgress = Callable[[str, str, int, int], None]
"""``progress(sequence_name, stage, done, total)`` (name :data:`JOINT` for the 3D-CN rounds); may raise
:class:`~leap_core.errors.Cancelled`."""


@dataclass(frozen=True)
class SequenceSpec:
    """One sequence of a run."""

    name: str
    """Its folder under ``<root>/sequences/`` and its name in tables and exports (``"00"``): 1-64 letters,
    digits, ``_``, ``-``, ``.``, starting with a letter or digit; unique in a run."""
    dataset: Path
    """The KITTI-layout sequence folder (``.../sequences/NN``)."""
    frames: range | None = None
    """Frame numbers to label (``range(10, 20)`` = scans 000010..000019, gaps allowed;
    :meth:`~leap_core.datasets.kitti.KittiSequence.select`); None = all."""

    def __post_init__(self) -> None:
        problem = sequence_name_problem(self.name)
        if problem is not None:
            raise ConfigError(problem, field=("name",))
        object.__setattr__(self, "dataset", Path(self.dataset))
        if self.frames is not None and not isinstance(self.frames, range):
            raise ConfigError(
                f"must be a range of frame numbers or None, got {self.frames!r}", field=("frames",)
            )

    @classmethod
    def of(cls, dataset: str | Path, frames: range | None = None, name: str | None = None) -> SequenceSpec:
        """A spec named after the sequence folder (``.../sequences/00`` → ``"00"``) unless ``name`` is
        given."""
        path = Path(dataset)
        # abspath, not resolve: a sequence folder that is a link keeps the name it is given under.
        return cls(Path(os.path.abspath(path)).name if name is None else name, path, frames)


@dataclass(frozen=True)
class RunResult:
    """Outcome of :func:`run_pipeline`."""

    root: Path
    """The run folder."""
    sequences: dict[str, SequenceResult]
    """Per sequence (run order), what its stages did (from both passes when the 3D-CN was on)."""
    metrics: RunMetrics | None
    """``<root>/metrics.json`` (None when no sequence has ground truth or evaluation did not run)."""
    joint_seconds: float = 0.0
    """Wall time of the 3D-CN rounds in this call (≈ 0 when the 3D-CN is off or its rounds were kept from
    an earlier call); each sequence's own ``3dcn`` stage only links their grids."""

    def only(self) -> SequenceResult:
        """The result of a run of one sequence.

        Raises:
            LeapError: the run has several sequences.
        """
        if len(self.sequences) != 1:
            raise LeapError(f"{self.root}: a run of {len(self.sequences)} sequences, not one")
        return next(iter(self.sequences.values()))


def check_specs(specs: Sequence[SequenceSpec]) -> None:
    """Refuse an empty list or two sequences with one name (a :class:`ConfigError` naming the entry)."""
    if not specs:
        raise ConfigError("a run needs at least one sequence", field=("sequences",))
    seen: dict[str, SequenceSpec] = {}
    for k, spec in enumerate(specs):
        if not isinstance(spec, SequenceSpec):
            raise ConfigError(
                f"must be a SequenceSpec, got {type(spec).__name__}", field=("sequences", str(k))
            )
        if spec.name in seen:
            raise ConfigError(
                f"duplicate sequence name {spec.name!r} ({seen[spec.name].dataset} and {spec.dataset}); "
                "give each sequence its own name",
                field=("sequences", str(k), "name"),
            )
        seen[spec.name] = spec


def open_run_folder(out: Path, specs: Sequence[SequenceSpec]) -> RunLayout:
    """The run folder ``out`` of a run of ``specs``, moved into this layout first when an earlier version
    wrote it (:func:`~leap_core.pipeline.migration.migrate_run_folder`; a folder of one sequence takes
    the name of the run's one sequence).

    Raises:
        LeapError: bad specs (:func:`check_specs`), ``out`` is a file or a sequence's folder of a run, or a
            former one-sequence folder given several sequences.
    """
    check_specs(specs)
    if out.exists() and not out.is_dir():
        raise LeapError(f"{out}: run folder path exists and is not a folder")
    holder = run_holding(out)
    if holder is not None:
        raise LeapError(
            f"{out}: the folder of sequence {out.name} of the run {holder.root}; give the run folder "
            f"({holder.root}) instead"
        )
    if former_layout(out) == "single" and len(specs) != 1:
        raise LeapError(
            f"{out}: a run folder of one sequence written by an earlier version; run it with its one "
            "sequence, or give this run its own folder"
        )
    first = specs[0]
    migrate_run_folder(out, first.name, first.dataset, first.frames)
    return RunLayout(out)


def run_pipeline(
    specs: Sequence[SequenceSpec],
    schema: Schema,
    config: PipelineConfig,
    out: str | Path,
    *,
    progress: RunProgress | None = None,
    runtime: Runtime | None = None,
    until: str | None = None,
) -> RunResult:
    """Run (or resume) a run of ``specs`` in the run folder ``out`` (module docstring).

    Every sequence runs up to ``smooth``; then, with the 3D-CN enabled, its rounds over every sequence;
    then each sequence's 3D-CN link, point labels, evaluation and export. Finished frames, stages, rounds
    and checkpoints are reused, so a run stopped by ``Cancelled`` (or killed) resumes byte for byte.

    Args:
        specs: the sequences (unique names).
        schema: the class schema (one for all).
        config: pipeline parameters (one for all).
        out: the run folder (created; a folder an earlier version wrote is moved into this layout).
        progress: ``progress(sequence_name, stage, done, total)`` after each unit of work; raising
            :class:`~leap_core.errors.Cancelled` stops the run cleanly (finished frames are kept).
        runtime: where the run executes: models folder, shared 2D cache folder (``cache_dir``; its entries
            are keyed by the frame's input files, so it serves every sequence), device, and the engine
            (``ray_address``: per-frame stages and fusion as Ray tasks, same bytes;
            :mod:`leap_core.pipeline.executor`). None = defaults, no shared cache, this process only.
        until: stop every sequence after this stage (e.g. "smooth" to only build the grids).

    Returns:
        :class:`RunResult`.

    Raises:
        LeapError: bad specs (duplicate names), a folder that is not a sequence, a bad run folder (one
            line, naming the file or field).
        PosesMissingError: a sequence has no poses and a stage up to ``until`` needs them (before any
            work).
        Cancelled: raised by ``progress``; the stage is recorded as "cancelled" and a rerun resumes.
    """
    if until is not None and until not in STAGES:
        raise LeapError(f"until: unknown stage {until!r} (stages: {', '.join(STAGES)})")
    last = STAGES.index(until) if until else len(STAGES) - 1
    check_specs(specs)
    layout = open_run_folder(Path(out), specs)
    # Every sequence opened (and checked for poses) before any work, so a bad folder stops the run at once.
    for spec in specs:
        seq = layout.sequence(spec.name).open_sequence(spec.dataset)
        seq.select(spec.frames)
        require_poses(seq, config, STAGE_TABLE[: last + 1])
    layout.root.mkdir(parents=True, exist_ok=True)
    write_run_spec(layout, [(s.name, s.dataset, s.frames) for s in specs], pipeline=config_to_dict(config))

    # On a Ray cluster the sequences run at once (one driver thread each, their per-frame work as tasks
    # of the one connection made here); locally one after another.
    executor = make_executor(runtime)
    each = _Concurrently(progress) if executor.name == "ray" and len(specs) > 1 else _InTurn(progress)

    def run(spec: SequenceSpec, stop: str) -> SequenceResult:
        return run_sequence(
            spec.dataset,
            schema,
            config,
            layout.sequence(spec.name).folder,
            progress=each.progress(spec.name),
            frames=spec.frames,
            runtime=runtime,
            until=stop,
        )

    joint = config.consistency.enabled and last >= STAGES.index("3dcn")
    results: dict[str, SequenceResult] = {}
    joint_seconds = 0.0
    if joint:
        first = each.run(specs, lambda spec: run(spec, "smooth"))
        t0 = time.perf_counter()
        _joint_3dcn(layout, specs, schema, config, runtime, progress, executor)
        joint_seconds = time.perf_counter() - t0
        seconds = each.run(specs, lambda spec: run(spec, STAGES[last]))
        for spec in specs:
            second = seconds[spec.name]
            stages = {
                **first[spec.name].stages,
                **{k: v for k, v in second.stages.items() if k not in first[spec.name].stages},
            }
            results[spec.name] = SequenceResult(
                second.folder, stages, second.frames, second.export_dir, second.metrics
            )
    else:
        for spec in specs:
            # A 3D-CN record left by an earlier run with the 3D-CN on belongs to that run's rounds.
            layout.sequence(spec.name).joint_3dcn.unlink(missing_ok=True)
        results = each.run(specs, lambda spec: run(spec, STAGES[last]))
    metrics = None
    if last >= STAGES.index("evaluate"):
        metrics = write_run_metrics(layout, {n: r.metrics for n, r in results.items()})
    return RunResult(layout.root, results, metrics, joint_seconds)


class _InTurn:
    """The sequences one after another (the local engine)."""

    def __init__(self, progress: RunProgress | None) -> None:
        self._progress = progress

    def progress(self, name: str) -> Callable[[str, int, int], None] | None:
        report = self._progress
        if report is None:
            return None
        return lambda stage, done, total: report(name, stage, done, total)

    def run(
        self, specs: Sequence[SequenceSpec], fn: Callable[[SequenceSpec], SequenceResult]
    ) -> dict[str, SequenceResult]:
        return {spec.name: fn(spec) for spec in specs}


class _Concurrently(_InTurn):
    """The sequences at once, one thread each (the Ray engine: the threads mostly wait for tasks).

    Progress reports are passed on one at a time (the callback need not be thread-safe). When one
    sequence fails or is cancelled, or the waiting thread is interrupted, the others stop at their next
    report with :class:`Cancelled` (their stages recorded as cancelled: a rerun resumes them); the first
    error that is not such a consequence is raised once every thread has ended."""

    def __init__(self, progress: RunProgress | None) -> None:
        super().__init__(progress)
        self._lock = threading.Lock()
        self._stop = threading.Event()

    def progress(self, name: str) -> Callable[[str, int, int], None]:
        def report(stage: str, done: int, total: int) -> None:
            if self._stop.is_set():
                raise Cancelled("stopped with the run")
            if self._progress is not None:
                with self._lock:
                    self._progress(name, stage, done, total)

        return report

    def run(
        self, specs: Sequence[SequenceSpec], fn: Callable[[SequenceSpec], SequenceResult]
    ) -> dict[str, SequenceResult]:
        def guarded(spec: SequenceSpec) -> SequenceResult:
            try:
                return fn(spec)
            except BaseException:
                self._stop.set()
                raise

        with ThreadPoolExecutor(len(specs), thread_name_prefix="leap-sequence") as pool:
            futures = [pool.submit(guarded, spec) for spec in specs]
            try:
                wait(futures)
            except BaseException:  # e.g. Ctrl-C in the CLI: the threads stop at their next report
                self._stop.set()
                raise
        errors = [e for f in futures if (e := f.exception()) is not None]
        if errors:
            raise next((e for e in errors if not isinstance(e, Cancelled)), errors[0])
        return {spec.name: f.result() for spec, f in zip(specs, futures, strict=True)}


# --------------------------------------------------------------------------------------- joint 3D-CN
def joint_fingerprint(
    specs: Sequence[SequenceSpec],
    schema: Schema,
    config: PipelineConfig,
    layout: RunLayout,
    runtime: Runtime | None,
) -> str:
    """What the joint 3D-CN rounds depend on: the 3D-CN settings, C, and each sequence's name and
    ``smooth`` / ``project`` fingerprints (which cover its 2D labels, frames, fusion, corrections and
    smoothing); reads no stage output."""
    return _joint_fingerprints(specs, schema, config, layout, runtime)[0]


def _joint_fingerprints(
    specs: Sequence[SequenceSpec],
    schema: Schema,
    config: PipelineConfig,
    layout: RunLayout,
    runtime: Runtime | None,
) -> tuple[str, dict[str, dict[str, str]]]:
    """:func:`joint_fingerprint` and every sequence's stage fingerprints (with its joint record as it is)."""
    members, fps = [], {}
    for spec in specs:
        fp = stage_fingerprints(
            spec.dataset,
            schema,
            config,
            layout.sequence(spec.name).folder,
            frames=spec.frames,
            runtime=runtime,
        )
        fps[spec.name] = fp
        members.append([spec.name, fp["project"], fp["smooth"]])
    head: dict[str, Any] = {
        "v": PIPELINE_VERSION,
        "C": schema.num_classes,
        "consistency": fingerprint_form(config_to_dict(config)["consistency"]),
        "members": members,
    }
    if runtime is not None and runtime.init_3dcn is not None:
        head["source"] = source_digest(runtime.init_3dcn)
    joint = hash_json(head)
    return joint, fps


def _joint_note(fingerprint: str, name: str, specs: Sequence[SequenceSpec]) -> dict[str, Any]:
    """A sequence's ``3dcn_joint.json``."""
    return {"fingerprint": fingerprint, "name": name, "sequences": [s.name for s in specs]}


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text()) if path.is_file() else None
    except (OSError, ValueError) as exc:
        raise DatasetError(path, f"unreadable joint 3D-CN record ({exc}); delete it to recompute") from exc


def _all_linked(
    layout: RunLayout,
    specs: Sequence[SequenceSpec],
    config: PipelineConfig,
    fingerprint: str,
    fps: Mapping[str, Mapping[str, str]],
) -> bool:
    """True when every sequence already holds this joint round's 3D-CN: its record names it, its 3dcn
    stage is done under the fingerprint that record gives, and its round grids exist. (A run folder seeded
    from an earlier run, e.g. by the app, then needs neither the staged grids nor the checkpoints.)"""
    for spec in specs:
        lay = layout.sequence(spec.name)
        if _read_json(lay.joint_3dcn) != _joint_note(fingerprint, spec.name, specs):
            return False
        record = read_state(lay).get("3dcn", {})
        if record.get("status") != "done" or record.get("fingerprint") != fps[spec.name]["3dcn"]:
            return False
        rounds = range(1, config.consistency.iterations + 1)
        if not all(lay.grid_3dcn(i).is_file() and lay.grid_smooth_3dcn(i).is_file() for i in rounds):
            return False
    return True


def _joint_3dcn(  # noqa: PLR0917  the run's parts, each as run_pipeline has it
    layout: RunLayout,
    specs: Sequence[SequenceSpec],
    schema: Schema,
    config: PipelineConfig,
    runtime: Runtime | None,
    progress: RunProgress | None,
    executor: Executor,
) -> None:
    """The joint rounds into ``<root>/3dcn/rounds/<name>/`` (their inference where ``executor`` puts it),
    then each sequence's ``3dcn_joint.json``."""
    fingerprint, fps = _joint_fingerprints(specs, schema, config, layout, runtime)
    tick = None if progress is None else (lambda done, total: progress(JOINT, "3dcn", done, total))
    if _all_linked(layout, specs, config, fingerprint, fps):
        if tick is not None:
            tick(1, 1)
        return
    state = layout.joint_state
    old = _read_json(state)
    if not isinstance(old, dict) or old.get("fingerprint") != fingerprint:
        # Staged grids of other settings; checkpoints stay (each is reused only when its fingerprint
        # matches, e.g. after a temperature change).
        remove_tree(layout.cn_dir / "rounds")
        atomic_write_json(state, {"fingerprint": fingerprint, "sequences": [s.name for s in specs]})
    members = []
    for spec in specs:
        lay = layout.sequence(spec.name)
        seq = lay.open_sequence(spec.dataset)
        ctx = Ctx(
            seq, schema, config, lay, seq.select(spec.frames), runtime, None, {s.name: s for s in STAGE_TABLE}
        )
        members.append(CnMember(ctx, layout.joint_rounds(spec.name), spec.name))
    predict = executor.predictor(config)
    cn_rounds(members, layout.cn_dir, tick, predict)
    tasks = getattr(predict, "tasks", 0)
    if tasks:  # how many inference tasks ran on Ray (the rounds' own record: sequences only link them)
        gpus = getattr(predict, "gpus", 0)
        extra = {"ray_tasks": tasks, **({"ray_gpus_per_task": gpus} if gpus else {})}
        atomic_write_json(state, {**json.loads(state.read_text()), **extra})
    for spec in specs:
        note = _joint_note(fingerprint, spec.name, specs)
        path = layout.sequence(spec.name).joint_3dcn
        if _read_json(path) != note:
            atomic_write_json(path, note)


# ------------------------------------------------------------------------------------------ reading
def read_run_metrics(out: str | Path) -> RunMetrics | None:
    """``<root>/metrics.json`` of a run (None when it has none).

    Raises:
        DatasetError: the file is unreadable.
    """
    path = RunLayout(Path(out)).metrics
    data = read_metrics_file(path)
    return None if data is None else RunMetrics.from_dict(data, path)


def run_result_tables(out: str | Path) -> str | None:
    """The result tables of a run as text (None without metrics): a run of one sequence its tables; a run
    of several every sequence's, then the overall ones."""
    data = read_run_metrics(out)
    if data is None:
        return None
    if len(data.sequences) == 1:
        only = next(iter(data.sequences.values()))
        return None if only is None else format_result_tables(only)
    parts = []
    for name, m in data.sequences.items():
        body = "no ground-truth labels: nothing to evaluate" if m is None else format_result_tables(m)
        parts.append(f"== sequence {name}\n{body}")
    summed = ", ".join(data.overall.sequences or [])
    parts.append(f"== overall (confusion matrices of {summed} summed)\n{format_result_tables(data.overall)}")
    return "\n\n".join(parts)


__all__ = [
    "JOINT",
    "RunProgress",
    "RunResult",
    "SequenceSpec",
    "check_specs",
    "joint_fingerprint",
    "open_run_folder",
    "read_run_metrics",
    "run_pipeline",
    "run_result_tables",
]
