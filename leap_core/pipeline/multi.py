"""Multi-sequence runs: several sequences (e.g. SemanticKITTI 00-10) labeled with one class schema and one
config into one run folder (:class:`~leap_core.run_layout.MultiRunLayout`).

Each sequence gets a complete ordinary run folder ``<root>/sequences/<name>/`` and goes through the usual
stage machinery (:func:`~leap_core.pipeline.runner.run_pipeline`: fingerprints, caching, resume). What is
joint:

- **The 3D-CN**, when enabled: every sequence runs up to ``smooth``; then each round trains ONE network
  on the reliable labels of all sequences and fuses its predictions back into each sequence's own grid
  (:func:`~leap_core.pipeline.stages.cn_rounds` over every sequence, the single-sequence stage being its
  one-sequence case). Checkpoints go to ``<root>/3dcn/``, each sequence's round grids to
  ``<root>/3dcn/rounds/<name>/``, from where the sequence's own ``3dcn`` stage hard-links them into its
  folder. Its ``3dcn_joint.json`` names the joint round (a fingerprint of the 3D-CN settings and of every
  sequence's ``smooth`` stage), and is part of its ``3dcn`` stage's fingerprint, so a change in any
  sequence reruns the 3D-CN and what follows in all of them. A joint run of one sequence gives the bytes
  of a single run's 3D-CN.
- **The metrics**: each sequence's ``metrics.json`` as usual, and ``<root>/metrics.json`` with
  ``{"overall": ..., "sequences": {name: ...}}``, overall = the metrics of the summed confusion matrices
  (:func:`~leap_core.pipeline.evaluation.overall_metrics`).

Without the 3D-CN nothing is joint but the overall metrics: each sequence's files are byte for byte those
of an ordinary run of that sequence.

Locally the sequences run one after another. With a Ray runtime they run at once, one driver thread each
sending its per-frame work to the one cluster (:class:`_Concurrently`); every sequence is still an
ordinary :func:`~leap_core.pipeline.runner.run_pipeline` in its own folder, so its files are the local
run's bytes, and the joint rounds' inference runs as Ray tasks too.

Exports keep SemanticKITTI's layout: :func:`export_sequences` writes ``<target>/sequences/<name>/
predictions/<frame>.label`` (through :func:`leap_core.export.write_export_folder`), :func:`export_zip` the
same layout into a zip with one label map and summary.
"""

from __future__ import annotations

import datetime
import json
import os
import threading
import time
import zipfile
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from leap_core.config import PipelineConfig, config_to_dict
from leap_core.consistency.config import fingerprint_form
from leap_core.errors import Cancelled, ConfigError, DatasetError, LeapError
from leap_core.export import (
    CONFIDENCES,
    LABEL_MAP_FILE,
    PREDICTIONS,
    SUMMARY_FILE,
    ExportConflict,
    existing_export_files,
    export_target_problem,
    label_map,
    label_map_yaml,
    write_export_folder,
    zip_member,
)
from leap_core.io_utils import atomic_write, atomic_write_json, remove_tree
from leap_core.pipeline.context import Ctx, hash_json, read_state
from leap_core.pipeline.evaluation import format_result_tables, overall_metrics, read_metrics_file
from leap_core.pipeline.executor import Executor, make_executor
from leap_core.pipeline.runner import (
    PIPELINE_VERSION,
    RunResult,
    require_poses,
    run_pipeline,
    stage_fingerprints,
)
from leap_core.pipeline.stages import STAGE_TABLE, STAGES, CnMember, cn_rounds, source_digest
from leap_core.run_layout import MultiRunLayout, RunLayout, sequence_name_problem
from leap_core.runtime import Runtime
from leap_core.schema import Schema

JOINT = "*"
"""The sequence name :func:`run_sequences` reports the joint 3D-CN's progress under (never a sequence's
name: not folder-safe)."""

MultiProgress = Callable[[str, str, int, int], None]
"""``progress(sequence_name, stage, done, total)`` (name :data:`JOINT` for the joint 3D-CN rounds); may
raise :class:`~leap_core.errors.Cancelled`."""


@dataclass(frozen=True)
class SequenceSpec:
    """One sequence of a multi-sequence run."""

    name: str
    """Its folder under ``<root>/sequences/`` and its name in tables and exports (``"00"``): 1-64 letters,
    digits, ``_``, ``-``, ``.``, starting with a letter or digit; unique in a run."""
    dataset: Path
    """The KITTI-layout sequence folder (``.../sequences/NN``)."""
    frames: range | None = None
    """Frame numbers to label (as ``run_pipeline(frames=)``); None = all."""

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
class MultiRunResult:
    """Outcome of :func:`run_sequences`."""

    root: Path
    per_sequence: dict[str, RunResult]
    """Per sequence (run order), its run's report (stages from both passes when the 3D-CN was joint)."""
    metrics: dict[str, Any] | None
    """Content of ``<root>/metrics.json`` (None when no sequence has ground truth or evaluation did not
    run)."""
    joint_seconds: float = 0.0
    """Wall time of the joint 3D-CN rounds in this call (≈ 0 when the 3D-CN is off or its rounds were
    kept from an earlier call); each sequence's own ``3dcn`` stage only links their grids."""


def check_specs(specs: Sequence[SequenceSpec]) -> None:
    """Refuse an empty list or two sequences with one name (a :class:`ConfigError` naming the entry)."""
    if not specs:
        raise ConfigError("a multi-sequence run needs at least one sequence", field=("sequences",))
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


def _check_root(out: Path) -> MultiRunLayout:
    if out.exists() and not out.is_dir():
        raise LeapError(f"{out}: run folder path exists and is not a folder")
    if (out / RunLayout.STATE).is_file():
        raise LeapError(f"{out}: a single-sequence run folder; give a multi-sequence run its own folder")
    return MultiRunLayout(out)


def _write_spec(layout: MultiRunLayout, specs: Sequence[SequenceSpec]) -> None:
    atomic_write_json(
        layout.spec,
        {
            "sequences": [
                {
                    "name": s.name,
                    "dataset": str(s.dataset.resolve()),
                    "frames": None if s.frames is None else [s.frames.start, s.frames.stop],
                }
                for s in specs
            ]
        },
    )


def run_sequences(
    specs: Sequence[SequenceSpec],
    schema: Schema,
    config: PipelineConfig,
    out: str | Path,
    *,
    progress: MultiProgress | None = None,
    runtime: Runtime | None = None,
    until: str | None = None,
) -> MultiRunResult:
    """Run (or resume) a multi-sequence run in ``out`` (module docstring).

    Every sequence runs up to ``smooth``; then, with the 3D-CN enabled, the joint rounds; then each
    sequence's 3D-CN link, point labels, evaluation and export. Finished frames, stages, rounds and
    checkpoints are reused as in a single run, so a run stopped by ``Cancelled`` resumes.

    Args:
        specs: the sequences (unique names).
        schema: the class schema (one for all).
        config: pipeline parameters (one for all).
        out: the multi-sequence run folder (created).
        progress: ``progress(sequence_name, stage, done, total)``.
        runtime: as for :func:`run_pipeline` (one 2D cache folder serves every sequence: its entries are
            keyed by the frame's input files).
        until: stop every sequence after this stage.

    Returns:
        :class:`MultiRunResult`.

    Raises:
        LeapError: bad specs (duplicate names), a folder that is not a sequence, a single-run ``out``.
        PosesMissingError: a sequence has no poses and a stage up to ``until`` needs them (before any
            work).
        Cancelled: raised by ``progress``.
    """
    if until is not None and until not in STAGES:
        raise LeapError(f"until: unknown stage {until!r} (stages: {', '.join(STAGES)})")
    last = STAGES.index(until) if until else len(STAGES) - 1
    check_specs(specs)
    layout = _check_root(Path(out))
    # Every sequence opened (and checked for poses) before any work, so a bad folder stops the run at once.
    for spec in specs:
        seq = layout.sequence(spec.name).open_sequence(spec.dataset)
        seq.select(spec.frames)
        require_poses(seq, config, STAGE_TABLE[: last + 1])
    layout.root.mkdir(parents=True, exist_ok=True)
    _write_spec(layout, specs)

    # On a Ray cluster the sequences run at once (one driver thread each, their per-frame work as tasks
    # of the one connection made here); locally one after another.
    executor = make_executor(runtime)
    each = _Concurrently(progress) if executor.name == "ray" and len(specs) > 1 else _InTurn(progress)

    def run(spec: SequenceSpec, stop: str) -> RunResult:
        return run_pipeline(
            spec.dataset,
            schema,
            config,
            layout.sequence(spec.name).run_dir,
            progress=each.progress(spec.name),
            frames=spec.frames,
            runtime=runtime,
            until=stop,
        )

    joint = config.consistency.enabled and last >= STAGES.index("3dcn")
    results: dict[str, RunResult] = {}
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
            results[spec.name] = RunResult(
                second.run_dir, stages, second.frames, second.export_dir, second.metrics
            )
    else:
        for spec in specs:
            # A joint record left by an earlier run with the 3D-CN on would make this folder's 3D-CN differ
            # from an ordinary run's; without the 3D-CN nothing is joint.
            layout.sequence(spec.name).joint_3dcn.unlink(missing_ok=True)
        results = each.run(specs, lambda spec: run(spec, STAGES[last]))
    metrics = None
    if last >= STAGES.index("evaluate"):
        metrics = write_metrics(layout, {n: r.metrics for n, r in results.items()})
    return MultiRunResult(layout.root, results, metrics, joint_seconds)


class _InTurn:
    """The sequences one after another (the local engine)."""

    def __init__(self, progress: MultiProgress | None) -> None:
        self._progress = progress

    def progress(self, name: str) -> Callable[[str, int, int], None] | None:
        report = self._progress
        if report is None:
            return None
        return lambda stage, done, total: report(name, stage, done, total)

    def run(
        self, specs: Sequence[SequenceSpec], fn: Callable[[SequenceSpec], RunResult]
    ) -> dict[str, RunResult]:
        return {spec.name: fn(spec) for spec in specs}


class _Concurrently(_InTurn):
    """The sequences at once, one thread each (the Ray engine: the threads mostly wait for tasks).

    Progress reports are passed on one at a time (the callback need not be thread-safe). When one
    sequence fails or is cancelled, or the waiting thread is interrupted, the others stop at their next
    report with :class:`Cancelled` (their stages recorded as cancelled: a rerun resumes them); the first
    error that is not such a consequence is raised once every thread has ended."""

    def __init__(self, progress: MultiProgress | None) -> None:
        super().__init__(progress)
        self._lock = threading.Lock()
        self._stop = threading.Event()

    def progress(self, name: str) -> Callable[[str, int, int], None]:
        def report(stage: str, done: int, total: int) -> None:
            if self._stop.is_set():
                raise Cancelled("stopped with the multi-sequence run")
            if self._progress is not None:
                with self._lock:
                    self._progress(name, stage, done, total)

        return report

    def run(
        self, specs: Sequence[SequenceSpec], fn: Callable[[SequenceSpec], RunResult]
    ) -> dict[str, RunResult]:
        def guarded(spec: SequenceSpec) -> RunResult:
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


def write_metrics(
    layout: MultiRunLayout, per_sequence: Mapping[str, Mapping[str, Any] | None]
) -> dict[str, Any] | None:
    """Write ``<root>/metrics.json`` = ``{"overall": overall_metrics(...), "sequences": per_sequence}``
    and return it; remove a stale one and return None when no sequence has metrics."""
    overall = overall_metrics(per_sequence)
    if overall is None:
        layout.metrics.unlink(missing_ok=True)
        return None
    data = {
        "overall": overall,
        "sequences": {n: (None if m is None else dict(m)) for n, m in per_sequence.items()},
    }
    atomic_write_json(layout.metrics, data)
    return data


# --------------------------------------------------------------------------------------- joint 3D-CN
def joint_fingerprint(
    specs: Sequence[SequenceSpec],
    schema: Schema,
    config: PipelineConfig,
    layout: MultiRunLayout,
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
    layout: MultiRunLayout,
    runtime: Runtime | None,
) -> tuple[str, dict[str, dict[str, str]]]:
    """:func:`joint_fingerprint` and every sequence's stage fingerprints (with its joint record as it is)."""
    members, fps = [], {}
    for spec in specs:
        fp = stage_fingerprints(
            spec.dataset,
            schema,
            config,
            layout.sequence(spec.name).run_dir,
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
    layout: MultiRunLayout,
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


def _joint_3dcn(  # noqa: PLR0917  the run's parts, each as run_sequences has it
    layout: MultiRunLayout,
    specs: Sequence[SequenceSpec],
    schema: Schema,
    config: PipelineConfig,
    runtime: Runtime | None,
    progress: MultiProgress | None,
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
        atomic_write_json(state, {**json.loads(state.read_text()), "ray_tasks": tasks})
    for spec in specs:
        note = _joint_note(fingerprint, spec.name, specs)
        path = layout.sequence(spec.name).joint_3dcn
        if _read_json(path) != note:
            atomic_write_json(path, note)


# --------------------------------------------------------------------------------------------- exports
def _members(out: str | Path, names: Sequence[str] | None) -> tuple[MultiRunLayout, list[str]]:
    layout = MultiRunLayout(Path(out))
    if not layout.is_multi_run(layout.root):
        raise LeapError(f"{layout.root}: not a multi-sequence run folder (no {MultiRunLayout.SPEC})")
    chosen = layout.names() if names is None else list(names)
    for name in chosen:
        export = layout.sequence(name).export_dir
        if not export.is_dir() or not any(export.glob("*.label")):
            raise LeapError(f"{export}: sequence {name} has no exported .label files (run it to the end)")
    return layout, chosen


def export_targets(
    target_dir: Path, names: Sequence[str], *, with_conf: bool = False
) -> dict[str, list[Path]]:
    """Per sequence, the folders :func:`export_sequences` writes: ``target_dir/sequences/<name>/predictions``
    (and ``confidences``)."""
    out: dict[str, list[Path]] = {}
    for name in names:
        base = target_dir / "sequences" / name
        out[name] = [base / PREDICTIONS, *([base / CONFIDENCES] if with_conf else [])]
    return out


def check_export_target(
    target_dir: Path, names: Sequence[str], *, with_conf: bool = False, overwrite: bool = False
) -> None:
    """Refuse, before writing anything, a target whose sequence folders may not receive an export
    (:func:`leap_core.export.export_target_problem`: a dataset's input folders, a run folder) or already
    hold files while ``overwrite`` is off."""
    target_dir = Path(target_dir).expanduser().resolve()
    for folders in export_targets(target_dir, names, with_conf=with_conf).values():
        for folder in folders:
            problem = export_target_problem(folder)
            if problem is not None:
                raise LeapError(problem)
            old = existing_export_files(folder)
            if old and not overwrite:
                raise ExportConflict(
                    f"{folder} already holds {len(old)} files (e.g. {old[0]}); nothing was "
                    "written. Export again with overwrite to replace them",
                    len(old),
                )


def export_sequences(
    out: str | Path,
    target_dir: str | Path,
    *,
    names: Sequence[str] | None = None,
    with_conf: bool = False,
    overwrite: bool = False,
) -> dict[str, int]:
    """Copy a multi-sequence run's ``.label`` files to ``target_dir/sequences/<name>/predictions/`` (and
    its ``.conf`` files to ``.../confidences/`` with ``with_conf``), the layout SemanticKITTI tools read.

    Each folder is written by :func:`leap_core.export.write_export_folder` (a fresh folder renamed into
    place). Every target is checked before anything is written (:func:`check_export_target`).

    Returns:
        Sequence name → files written.

    Raises:
        LeapError: ``out`` is not a finished multi-sequence run, or a target is a dataset's input folder
            or a run folder.
        ExportConflict: a target holds files and ``overwrite`` is off (nothing is written).
    """
    layout, chosen = _members(out, names)
    target = Path(target_dir).expanduser().resolve()
    check_export_target(target, chosen, with_conf=with_conf, overwrite=overwrite)
    written: dict[str, int] = {}
    for name, folders in export_targets(target, chosen, with_conf=with_conf).items():
        export = layout.sequence(name).export_dir
        n = 0
        for folder, suffix in zip(folders, (".label", ".conf"), strict=False):
            files = sorted(p for p in export.iterdir() if p.suffix == suffix and p.is_file())
            write_export_folder(folder, files, overwrite=overwrite)
            n += len(files)
        written[name] = n
    return written


def export_zip(  # noqa: PLR0913  # keyword-only: what goes in
    out: str | Path,
    path: str | Path,
    schema: Schema,
    *,
    config: PipelineConfig | None = None,
    names: Sequence[str] | None = None,
    with_conf: bool = False,
    overwrite: bool = False,
    raw_counts: Mapping[int, int] | None = None,
    version: str = "",
) -> int:
    """Write a multi-sequence run's export as one zip, atomically: ``sequences/<name>/predictions/
    <frame>.label`` (and ``confidences/<frame>.conf``) per sequence (:func:`leap_core.export.zip_member`),
    ``label-map.yaml`` (its ``split.valid`` lists every numeric sequence name) and ``summary.yaml``.

    Args:
        raw_counts: raw id → points over all sequences, for the label map's ``counts`` / ``content``.

    Returns:
        The number of frame files written.

    Raises:
        ExportConflict: ``path`` exists and ``overwrite`` is off.
    """
    layout, chosen = _members(out, names)
    path = Path(path)
    if path.exists() and not overwrite:
        raise ExportConflict(
            f"{path} already exists; nothing was written. Export again with overwrite to replace it", 1
        )
    suffixes = (".label", ".conf") if with_conf else (".label",)
    lmap = label_map(schema, raw_counts, name=schema.name)
    numbered = [int(n) for n in chosen if n.isdigit()]
    if numbered:
        lmap["split"] = {"train": [], "valid": numbered, "test": []}
    spec = {}
    if layout.spec.is_file():
        spec = {s["name"]: s for s in json.loads(layout.spec.read_text())["sequences"]}
    summary = {
        "run": {"folder": str(layout.root)},
        "sequences": [
            {
                "name": n,
                "dataset": spec.get(n, {}).get("dataset"),
                "frames": spec.get(n, {}).get("frames") or "all",
                "labels": f"sequences/{n}/{PREDICTIONS}/<frame>.label",
            }
            for n in chosen
        ],
        "label_map": LABEL_MAP_FILE,
        "settings": {"schema": schema.name, "pipeline": None if config is None else config_to_dict(config)},
        "leap_studio_version": version,
        "written_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    n = 0
    with (
        atomic_write(path, "wb") as fh,
        zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, compresslevel=6) as zf,
    ):
        for name in chosen:
            export = layout.sequence(name).export_dir
            for f in sorted(p for p in export.iterdir() if p.suffix in suffixes and p.is_file()):
                zf.write(f, zip_member(name, f.stem, f.suffix))
                n += 1
        zf.writestr(LABEL_MAP_FILE, label_map_yaml(lmap))
        zf.writestr(
            SUMMARY_FILE,
            "# LeAP Studio multi-sequence export summary.\n"
            + yaml.safe_dump(summary, sort_keys=False, allow_unicode=True),
        )
    return n


# ------------------------------------------------------------------------------------------ reading
def read_multi_metrics(out: str | Path) -> dict[str, Any] | None:
    """``<root>/metrics.json`` of a multi-sequence run (None when it has none)."""
    return read_metrics_file(MultiRunLayout(Path(out)).metrics)


def multi_result_tables(out: str | Path) -> str | None:
    """The result tables of every sequence, then the overall ones, as text (None without metrics)."""
    data = read_multi_metrics(out)
    if data is None:
        return None
    path = MultiRunLayout(Path(out)).metrics
    parts = []
    for name, m in data.get("sequences", {}).items():
        body = "no ground-truth labels: nothing to evaluate" if m is None else format_result_tables(m, path)
        parts.append(f"== sequence {name}\n{body}")
    overall = data.get("overall")
    if overall is not None:
        summed = ", ".join(overall.get("sequences", []))
        table = format_result_tables(overall, path)
        parts.append(f"== overall (confusion matrices of {summed} summed)\n{table}")
    return "\n\n".join(parts)


__all__ = [
    "JOINT",
    "MultiProgress",
    "MultiRunResult",
    "SequenceSpec",
    "check_export_target",
    "check_specs",
    "export_sequences",
    "export_targets",
    "export_zip",
    "joint_fingerprint",
    "multi_result_tables",
    "read_multi_metrics",
    "run_sequences",
    "write_metrics",
]
