"""The ``leap`` command line.

It lives in ``app`` because ``serve`` and ``demo`` start the web app, and leap_core stays free of web code.
Configs, presets and the labeler registry are imported at the top (they import no torch); the pipeline,
the models, the synthesiser and the web app stay inside the commands that use them, so ``leap --help``
stays fast."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import typer

from app.cli_import import import_cli
from leap_core.config import PipelineConfig, config_from_dict
from leap_core.datasets.kitti import Frame, KittiSequence
from leap_core.errors import Cancelled, ConfigError, DatasetError, LeapError, PosesMissingError
from leap_core.labelers import LABELERS
from leap_core.labelers.cache import default_cache_dir
from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
from leap_core.paths import UnusablePath, real_path
from leap_core.presets import Preset, load_preset
from leap_core.runtime import Runtime
from leap_core.schema import Schema
from leap_core.synth.domains import DOMAINS as SYNTH_DOMAINS

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

    import numpy as np
    import numpy.typing as npt
    from pydantic import SecretStr
    from tqdm import tqdm

    from app.core.config import Settings
    from app.core.instance import ServerLock
    from app.rows import RunRow
    from leap_core.lidar_model.config import LidarModelConfig
    from leap_core.pipeline.preflight import Verdict
    from leap_core.pipeline.run import RunResult, SequenceSpec
    from leap_core.progress import ProgressFn

cli = typer.Typer(
    name="leap",
    help="LeAP Studio: open-vocabulary 3D point labeling from camera + LiDAR sequences.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)
cli.add_typer(import_cli, name="import")


class StageBars:
    """One tqdm bar per pipeline stage, opened when the stage first reports (``progress(stage, done, total)``)
    and closing the previous stage's bar; use as a context manager so every bar is closed and log lines
    (the pipeline's warnings) are written above the bars instead of onto them.

    The pipeline reports a stage it does not compute (cached from an earlier run, or disabled) as complete
    at once. With ``folder`` (the sequence's folder in the run) given, such a stage is held back until the
    pipeline has recorded it, then printed as one ``skipped`` line instead of a full bar (a stage that
    really computed in one step still gets its bar).
    """

    def __init__(self, folder: Path | None = None, label: str = "") -> None:
        import time

        self.bars: dict[str, tqdm[Any]] = {}
        self.folder = folder
        self.label = label
        """Put before each stage's name (a sequence's bars among others')."""
        self.started = time.time()
        self._held: tuple[str, int] | None = None
        self._redirect: Any = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if self._held is not None and self._held[0] != stage:
            self._settle()
        bar = self.bars.get(stage)
        if bar is None:
            if self.folder is not None and total > 0 and done >= total and self._held is None:
                self._close_bars()
                self._held = (stage, total)
                return
            self._close_bars()
            unit = "step" if stage in ("3dcn", "synth") else "frame"
            bar = self.bars[stage] = tqdm(
                total=total, desc=f"{self.label}{stage:<12}", unit=unit, leave=True, dynamic_ncols=True
            )
        bar.total = total
        bar.n = done
        bar.refresh()

    def _settle(self) -> None:
        """Print the held stage as skipped, or as the full bar of a stage that computed in one step."""
        from tqdm import tqdm

        from leap_core.pipeline.runner import UNCHANGED, skip_reason

        assert self._held is not None and self.folder is not None
        stage, total = self._held
        self._held = None
        reason = skip_reason(self.folder, stage, self.started)
        if reason == UNCHANGED:
            reason += " in this folder"
        if reason is not None:
            tqdm.write(f"{self.label}{stage:<12} skipped ({reason})", file=sys.stderr)
        else:
            unit = "step" if stage in ("3dcn", "synth") else "frame"
            with tqdm(
                total=total, initial=total, desc=f"{self.label}{stage:<12}", unit=unit, dynamic_ncols=True
            ):
                pass

    def _close_bars(self) -> None:
        for bar in self.bars.values():
            bar.close()
        self.bars.clear()

    def close(self) -> None:
        if self._held is not None:
            self._settle()
        self._close_bars()

    def __enter__(self) -> StageBars:
        from tqdm.contrib.logging import logging_redirect_tqdm

        self._redirect = logging_redirect_tqdm()
        self._redirect.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
        if self._redirect is not None:
            self._redirect.__exit__(None, None, None)
            self._redirect = None


@contextlib.contextmanager
def _run_errors(out: str | Path) -> Iterator[None]:
    """A `leap run`'s one-line endings: interrupted or cancelled (run again to resume), no poses (naming
    `leap poses` on that sequence and --estimate-poses), any other LeapError."""
    try:
        yield
    except KeyboardInterrupt:
        raise fail(f"interrupted; run the same command again to resume from {out}") from None
    except Cancelled:
        raise fail(f"cancelled; run the same command again to resume from {out}") from None
    except PosesMissingError as exc:
        sequence = Path(exc.path).parent
        raise fail(f"{exc}; run `leap poses {sequence}` or pass --estimate-poses") from None
    except LeapError as exc:
        raise fail(str(exc)) from None


@contextlib.contextmanager
def _run_folder_lock(out: Path) -> Iterator[None]:
    """Hold the run folder's lock while ``leap run`` works in it: the app's worker takes the same ``flock``,
    and two processes in one folder would each delete the other's temporaries and stage outputs.

    A run that fails before any stage finished (a refused labeler, a model that does not load, no poses)
    leaves no folder behind when it created the folder; a folder that existed before is never removed."""
    from app.jobs.worker import RunDirBusy, run_dir_lock
    from leap_core.io_utils import remove_tree
    from leap_core.run_layout import RunLayout

    created = not out.exists()
    failed = True
    try:
        with run_dir_lock(out):
            yield
        failed = False
    except RunDirBusy as exc:
        created = False  # another process made it, or works in it
        raise LeapError(
            f"{exc} (another `leap run`, or the app's worker); wait for it to finish, or give "
            "this run another --out"
        ) from None
    finally:
        if created and failed and out.is_dir() and not RunLayout(out).holds_results():
            with contextlib.suppress(OSError):
                remove_tree(out)


def _cli_path(raw: str | Path, option: str) -> Path:
    """The path an option names, resolved (:func:`leap_core.paths.real_path`).

    Raises:
        LeapError: ``option`` and why the path cannot be used (a symlink loop, ...), printed as one line.
    """
    try:
        return real_path(raw)
    except UnusablePath as exc:
        raise LeapError(f"{option}: path {str(raw)!r} {exc}") from None


def fail(message: str) -> typer.Exit:
    """Print a one-line error to stderr and return the exit to raise (``raise fail(...)``)."""
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    return typer.Exit(code=2)


def _runtime(
    models: str | None,
    cache: str | Path | None,
    device: str,
    allow_download: bool,
    ray: str | None = None,
    ray_cpus: int | None = None,
    *,
    frame_threads: int = Runtime.frame_threads,
    init_3dcn: str | None = None,
) -> Runtime:
    """The run's deployment values from the command-line flags (one-line error for a bad ``--device``,
    ``--frame-threads`` or a ``--3dcn-init`` that is not a file)."""
    if init_3dcn is not None and not Path(init_3dcn).is_file():
        raise LeapError(
            f"--3dcn-init {init_3dcn}: no such file (give a 3D-CN checkpoint a run wrote, "
            "e.g. RUN/3dcn/3dcn_iter1.pt)"
        )
    try:
        return Runtime(
            models_dir=None if models is None else Path(models),
            cache_dir=None if cache is None else Path(cache),
            device=device,  # type: ignore[arg-type]  # any string: Runtime rejects a bad one (error below)
            allow_download=allow_download,
            ray_address=ray,
            ray_cpus=ray_cpus,
            frame_threads=frame_threads,
            init_3dcn=None if init_3dcn is None else Path(init_3dcn),
        )
    except ConfigError as exc:
        raise LeapError(f"--{exc.field[-1].replace('_', '-')} {exc.problem}") from None


def _preset(option: str, name_or_path: str, base: PipelineConfig | None = None) -> Preset:
    """:func:`load_preset`, its errors prefixed with the option that named the file
    (``--schema nope: no such file, ...``)."""
    try:
        return load_preset(name_or_path, base)
    except LeapError as exc:
        raise LeapError(f"{option} {exc}", field=exc.field) from None


_MODELS_HELP = "Folder with one subfolder per model (grounding-dino-tiny/, sam-vit-base/, sam3/)."
_DEVICE_HELP = "Where the 2D labeler's models run: auto (CUDA when available), cpu or cuda."
_DOWNLOAD_HELP = "Without --models: download a model missing from the Hugging Face cache."
_RAY_HELP = (
    "Run the per-frame work as Ray tasks: 'auto' joins this machine's Ray cluster (`ray start --head`) or "
    "starts a local one; or a cluster address (host:6379). The run folder and dataset must be on storage "
    "every node sees at the same path. Same output bytes as without it."
)
_RAY_CPUS_HELP = "CPUs of the local Ray instance --ray auto starts when no cluster runs (default: all cores)."


LABELS2D_THRESHOLD = {"grounded-sam": "box_threshold", "sam3": "score_threshold"}
"""The setting ``leap labels2d --threshold`` sets, per model labeler."""


@cli.command("labels2d")
def labels2d(  # noqa: PLR0913  # typer: one parameter per command-line option
    dataset: str = typer.Argument(..., help="Sequence folder in KITTI layout (.../sequences/NN)."),
    *,
    labeler_name: str = typer.Option(
        "grounded-sam",
        "--labeler",
        help="The model labeler whose labels to precompute: grounded-sam or sam3.",
    ),
    schema: str = typer.Option(
        "semantickitti", "--schema", help="Project/schema YAML file, or a built-in name in projects/."
    ),
    models: str | None = typer.Option(None, "--models", help=_MODELS_HELP),
    mode: str | None = typer.Option(
        None, "--mode", help="grounded-sam: joint (all prompts in one text) or per-class."
    ),
    batch_size: int | None = typer.Option(None, "--batch-size", min=1, help="Images per forward pass."),
    cache: str | None = typer.Option(
        None, "--cache", help="Shared cache folder, as `leap run --cache` (default: <dataset>/leap_cache)."
    ),
    threshold: float | None = typer.Option(
        None,
        "--threshold",
        help="Box (grounded-sam) or instance score (sam3) threshold (default: project's).",
    ),
    device: str = typer.Option("auto", "--device", help=_DEVICE_HELP),
    allow_download: bool = typer.Option(False, "--allow-download", help=_DOWNLOAD_HELP),
    ray: str | None = typer.Option(None, "--ray", metavar="auto|ADDRESS", help=_RAY_HELP),
    ray_cpus: int | None = typer.Option(None, "--ray-cpus", min=1, help=_RAY_CPUS_HELP),
) -> None:
    """Precompute a model labeler's 2D labels (Grounding DINO + SAM, or SAM 3) of every frame into the 2D
    cache (resumable: frames already in the cache are skipped, so an interrupted run continues where it
    stopped).

    `leap run DATASET --labeler grounded-sam|sam3 --cache <same folder>` then reads them instead of
    running the models."""
    from tqdm import tqdm

    from leap_core.labelers import model_labeler
    from leap_core.labelers.base import passes_text

    try:
        if labeler_name not in LABELS2D_THRESHOLD:
            raise LeapError(
                f"--labeler {labeler_name}: labels2d precomputes a model labeler's labels: "
                f"use {' or '.join(LABELS2D_THRESHOLD)}"
            )
        if mode is not None and labeler_name != "grounded-sam":
            raise LeapError(f"--mode is a grounded-sam setting; the {labeler_name} labeler has no modes")
        seq = KittiSequence(dataset)
        preset = _preset("--schema", schema)
        sch = preset.schema
        spec = LABELERS[labeler_name]
        flags = {"mode": mode, "batch_size": batch_size, LABELS2D_THRESHOLD[labeler_name]: threshold}
        config = config_from_dict(
            {"labeler": labeler_name, spec.section: {k: v for k, v in flags.items() if v is not None}},
            preset.pipeline,
        )
        runtime = _runtime(
            models, cache if cache else default_cache_dir(seq.root), device, allow_download, ray, ray_cpus
        )
        labeler, batch = model_labeler(config, runtime)
        # Each camera's image of each frame (a rig's cameras after the first: docs/IMPORT.md).
        frames = [v for f in seq for v in f.cameras() if v.has_image]
        unit = "frame" if len(seq.cameras) == 1 else "image"

        def cached(frame: Frame) -> bool:
            hit = labeler.is_cached(frame.image, sch)
            frame.__dict__.pop("image", None)  # a long sequence's decoded images would not fit in memory
            return hit

        todo = [f for f in tqdm(frames, desc="checking cache", unit=unit, leave=False) if not cached(f)]
        what = f"{len(frames)} frames with images ({len(seq) - len(frames)} without)"
        if len(seq.cameras) > 1:
            what = f"{len(frames)} images of {len(seq)} frames from {len(seq.cameras)} cameras"
        typer.echo(
            f"{what}, {len(frames) - len(todo)} cached, {len(todo)} to label; "
            f"{labeler.work_per_image(sch)}, cache {runtime.cache_dir}"
        )
        if runtime.ray_address is not None:
            # A task labels every camera's image of its frames (the cached ones are read back).
            ids = list(dict.fromkeys(f.frame_id for f in todo))
            with tqdm(total=len(ids), desc="labels2d (ray)", unit="frame") as bar:
                calls = _labels2d_on_ray(Path(dataset), sch, config, runtime, ids, bar.update)
            typer.echo(f"done: {len(ids)} frames labeled, {passes_text(calls)} (Ray tasks)")
            return
        with tqdm(total=len(todo), desc="labels2d", unit=unit) as bar:
            for start in range(0, len(todo), batch):
                chunk = todo[start : start + batch]
                labeler.label_frames(chunk, sch)
                for f in chunk:
                    f.__dict__.pop("image", None)  # frames keep their decoded image otherwise
                bar.update(len(chunk))
    except LeapError as exc:
        raise fail(str(exc)) from None
    typer.echo(f"done: {len(todo)} {unit}s labeled, {passes_text(labeler.forward_passes())}")


def _labels2d_on_ray(
    dataset: Path,
    sch: Schema,
    cfg: PipelineConfig,
    runtime: Runtime,
    frame_ids: list[str],
    update: Callable[[int], Any],
) -> dict[str, int]:
    """``leap labels2d --ray``: the frames to label as Ray tasks (a GPU each when the cluster has GPUs)."""
    from leap_core.pipeline.executor import RayExecutor  # the pipeline (and ray) only when asked for

    assert runtime.ray_address is not None
    return RayExecutor(runtime.ray_address, runtime.ray_cpus).label_cache(
        dataset, sch, cfg, runtime, frame_ids, update
    )


@cli.command("make-tiny-models")
def make_tiny_models_cmd(
    folder: str = typer.Argument(..., help="Where to write grounding-dino-tiny/, sam-vit-base/ and sam3/."),
    seed: int = typer.Option(0, "--seed", help="Seed of the random weights."),
) -> None:
    """Write tiny RANDOM-weight Grounding DINO + SAM and SAM 3 models (for trying the code paths without
    weights).

    Their labels are meaningless: they only exercise the grounded-sam and sam3 code paths. Use them with
    --models FOLDER; see the README section 'Real 2D labels' for the real weights."""
    paths = make_tiny_models(folder, TinyModelsConfig(seed=seed))
    typer.echo(f"wrote {paths.detector}, {paths.segmenter} and {paths.sam3}")
    typer.secho(
        "these models have RANDOM weights: their labels exercise the code path only and are meaningless",
        fg=typer.colors.YELLOW,
    )


CHECK_EXIT_CODES: dict[Verdict, int] = {"full": 0, "partial": 1, "none": 3}
"""``leap check``'s exit code per verdict (2 stays typer's usage error and this CLI's one-line errors)."""


@cli.command("check")
def check_cmd(
    dataset: str = typer.Argument(..., help="Sequence folder in KITTI layout (.../sequences/NN)."),
    *,
    labeler: str | None = typer.Option(
        None,
        "--labeler",
        help="Judge the stages for this 2D labeler (default: the project file's, else the "
        "first labeler that can run).",
        autocompletion=lambda: list(LABELERS),
    ),
    project_file: str | None = typer.Option(
        None, "--project-file", help="Project YAML whose 'pipeline:' section the run would use."
    ),
    models: str | None = typer.Option(None, "--models", help=_MODELS_HELP),
    estimate_poses: bool = typer.Option(
        False, "--estimate-poses", help="Judge a run with --estimate-poses (missing poses estimated first)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the report as JSON."),
) -> None:
    """Check a sequence folder before a run: frames, camera images, calibration, poses (file, estimated or
    missing), ground truth, 2D ground truth, and which labelers and stages can run, each problem with
    its fix.

    Exit codes: 0 every stage can run (evaluation without ground truth and a switched-off 3D-CN count as
    runnable); 1 only some stages can run (see the findings); 3 the pipeline cannot run on this folder at
    all; 2 a usage error."""
    import json

    from app.advice import render_cli, report_dict
    from leap_core.pipeline.preflight import check_dataset

    try:
        # The config `leap run` would use with these options, and the same rule for its labeler.
        _, config, named = _run_choice(None, project_file, labeler, None)
        runtime = _runtime(models, None, "auto", False)
    except LeapError as exc:
        raise fail(str(exc)) from None
    report = check_dataset(
        dataset, config=config, runtime=runtime, estimate_poses=estimate_poses, labeler_named=named
    )
    if as_json:
        typer.echo(json.dumps(report_dict(report, "cli"), indent=2))
    else:
        typer.echo(render_cli(report, CHECK_EXIT_CODES))
    raise typer.Exit(code=CHECK_EXIT_CODES[report.verdict])


def _labeler_help() -> str:
    return (
        "2D labeler: "
        + "; ".join(f"{name} ({spec.description})" for name, spec in LABELERS.items())
        + ". Default: the project file's, else the first that can run on every sequence (as `leap check` "
        "picks)."
    )


def _presets_help() -> str:
    return "; ".join(f"{name}: {', '.join(spec.presets)}" for name, spec in LABELERS.items() if spec.presets)


@cli.command("run")
def run_cmd(  # noqa: PLR0913  # typer: one parameter per command-line option
    datasets: list[str] = typer.Argument(
        ...,
        help="Sequence folder in KITTI layout (.../sequences/NN), or several: one run of them all (one "
        "schema and config; each sequence named after its folder, names must differ).",
        metavar="DATASET...",
    ),
    *,
    out: str = typer.Option(
        ...,
        "--out",
        help="Run folder (created; rerunning on it resumes / reuses stages): OUT/sequences/<name>/ per "
        "sequence. A folder an earlier version wrote is moved into this layout.",
    ),
    schema: str | None = typer.Option(
        None,
        "--schema",
        help="Schema/project YAML file, or a built-in name in projects/ (default semantickitti).",
    ),
    labeler: str | None = typer.Option(
        None,
        "--labeler",
        help=_labeler_help(),
        # Checked by PipelineConfig against the same registry, so a bad name is the usual one-line error.
        autocompletion=lambda: list(LABELERS),
    ),
    project_file: str | None = typer.Option(
        None, "--project-file", help="Project YAML: classes plus a 'pipeline:' section of config overrides."
    ),
    labeler_preset: str | None = typer.Option(
        None,
        "--labeler-preset",
        help="A named setting of the chosen labeler's config section, replacing the project's settings of "
        f"it (pipeline.<section>.preset): {_presets_help()}.",
        autocompletion=lambda: sorted({p for spec in LABELERS.values() for p in spec.presets}),
    ),
    consistency: bool | None = typer.Option(
        None, "--3dcn/--no-3dcn", help="Run the 3D Consistency Network (default: the project's setting, off)."
    ),
    cn_iterations: int | None = typer.Option(
        None,
        "--3dcn-iterations",
        help="3D-CN rounds, 1 or 2 (pipeline.consistency.iterations; default: the project's setting, 1). "
        "Implies --3dcn; the result table gets one '+3D-CN xN' column per round.",
    ),
    frames: str | None = typer.Option(
        None, "--frames", help="Frame numbers A:B (B exclusive; scan 000010.bin is frame 10), e.g. 0:20."
    ),
    cache: str | None = typer.Option(None, "--cache", help="Shared 2D cache folder reused across runs."),
    models: str | None = typer.Option(None, "--models", help=_MODELS_HELP),
    device: str = typer.Option("auto", "--device", help=_DEVICE_HELP),
    allow_download: bool = typer.Option(False, "--allow-download", help=_DOWNLOAD_HELP),
    export_to: str | None = typer.Option(
        None,
        "--export-to",
        help="Also copy the .label files into DIR/sequences/<name>/predictions/ (SemanticKITTI's layout: "
        "DIR = the dataset folder holding sequences/ writes each sequence's own predictions/; each folder "
        "written fresh and renamed into place). Refused: a dataset's labels/, velodyne/, image_2/, a run "
        "folder; a folder that already holds files unless --overwrite.",
    ),
    zip_path: str | None = typer.Option(
        None,
        "--zip",
        help="Also write a stand-alone zip: .label files in the SemanticKITTI layout, label-map.yaml "
        "(semantic-kitti-api style), summary.yaml. An existing file is refused unless --overwrite.",
    ),
    with_conf: bool = typer.Option(False, "--with-conf", help="--export-to / --zip include the .conf files."),
    overwrite: bool = typer.Option(
        False,
        "--overwrite",
        help="Let --export-to / --zip replace existing files (.label/.conf only); never done without it.",
    ),
    estimate_poses: bool = typer.Option(
        False,
        "--estimate-poses",
        help="When a sequence has no poses.txt, estimate poses with KISS-ICP first, into "
        "OUT/sequences/<name>/poses/ (the dataset is not written; reused by later runs in OUT while the "
        "scans are unchanged).",
    ),
    ray: str | None = typer.Option(None, "--ray", metavar="auto|ADDRESS", help=_RAY_HELP),
    ray_cpus: int | None = typer.Option(None, "--ray-cpus", min=1, help=_RAY_CPUS_HELP),
    frame_threads: int = typer.Option(
        Runtime.frame_threads,
        "--frame-threads",
        help="Frames the projection, point-label and export stages compute at a time (threads; the same "
        "files for any value, 1 = one after another).",
    ),
    init_3dcn: str | None = typer.Option(
        None,
        "--3dcn-init",
        metavar="CKPT",
        help="Start every 3D-CN round from this network (a checkpoint a run wrote, RUN/3dcn/3dcn_iter1.pt; "
        "same classes and backbone) and fine-tune it for one epoch at consistency.finetune_lr, instead of "
        "training from random weights for consistency.min_steps. Implies --3dcn.",
    ),
    seed: int | None = typer.Option(
        None,
        "--seed",
        min=0,
        help="Seed of the 2D labeler's random draws (pipeline.<labeler section>.seed; the simulated "
        "labelers have one, default: the project's, 0). Another seed gives other 2D labels.",
    ),
) -> None:
    """Label sequences: 2D labels → projection → voxel fusion → smoothing (→ 3D-CN) → per-point labels,
    then evaluate against ground truth when it exists and export SemanticKITTI .label files.

    A run is a list of sequences (often one), each named after its folder: OUT/sequences/<name>/ per
    sequence, the 3D-CN trains one network on all of them, result tables per sequence and overall,
    exports in the sequences/<name>/predictions/ layout."""
    # The pipeline imports torch: loaded by the command that runs it, not by `leap --help`.
    from leap_core.export import check_export_targets, export_targets
    from leap_core.pipeline import run_pipeline, run_result_tables
    from leap_core.pipeline.run import open_run_folder

    root = Path(out)
    with _run_errors(out):
        specs = _sequence_specs(datasets, frames)
        sch, cfg, named = _run_choice(
            schema, project_file, labeler, consistency, cn_iterations, labeler_preset, init_3dcn=init_3dcn
        )
        runtime = _runtime(
            models,
            cache,
            device,
            allow_download,
            ray,
            ray_cpus,
            frame_threads=frame_threads,
            init_3dcn=init_3dcn,
        )
        names = [s.name for s in specs]
        # Refuse a target before a long run, not after it.
        if export_to is not None:
            try:
                folders = export_targets(_cli_path(export_to, "--export-to"), names, with_conf=with_conf)
                check_export_targets(folders, overwrite=overwrite)
            except LeapError as exc:
                more = "; add --overwrite to replace them" if "already holds" in str(exc) else ""
                raise LeapError(f"--export-to: {exc}{more}") from None
        zip_file = _zip_target(zip_path, overwrite)
        # Every refusal the pre-flight can make comes before the run folder exists.
        chosen, notes = _pick_labeler(specs, cfg, runtime, named=named, estimate_poses=estimate_poses)
        cfg = _with_labeler(cfg, chosen, seed)
        with _run_folder_lock(root):
            layout = open_run_folder(root, specs)
            if estimate_poses:
                for spec in specs:
                    _estimate_run_poses(spec.dataset, layout.sequence(spec.name).poses)
            shown = f"; sequences {', '.join(names)}" if len(specs) > 1 else ""
            typer.echo(f"2D labels: {LABELERS[cfg.labeler].title}{''.join(notes)}{shown}")
            with SequenceBars(root, names, concurrent=ray is not None and len(specs) > 1) as bars:
                result = run_pipeline(specs, sch, cfg, root, progress=bars, runtime=runtime)

    for name, res in result.sequences.items():
        timing = ", ".join(
            f"{s} {r.seconds:.1f}s" if r.ran else f"{s} {'cached' if r.status == 'done' else r.status}"
            for s, r in res.stages.items()
        )
        typer.echo(f"stages: {timing}" if len(specs) == 1 else f"sequence {name}: {timing}")
    if cfg.consistency.enabled:
        typer.echo(f"3D-CN rounds (one network per round, all sequences): {result.joint_seconds:.1f}s")
    tables = run_result_tables(root)
    typer.echo("")
    typer.echo(tables if tables else "no ground-truth labels: nothing to evaluate")
    try:
        _write_exports(result, specs, sch, cfg, export_to, zip_file, with_conf=with_conf, overwrite=overwrite)
    except LeapError as exc:
        raise fail(str(exc)) from None


class SequenceBars:
    """:class:`StageBars` for a run (``progress(sequence, stage, done, total)``): one set of bars per
    sequence and one for the 3D-CN's rounds, with a header line when the sequence changes in a run of
    several. A stage that reports complete again in the run's second pass (after the 3D-CN's rounds) is
    not printed twice, nor a sequence's ``3dcn`` stage once the rounds were shown (it only links their
    grids). With ``concurrent`` (sequences running at once on Ray, their reports interleaved) no header:
    each bar starts with its sequence's name and a sequence's bars stay open while another reports."""

    def __init__(self, root: Path, names: list[str], concurrent: bool = False) -> None:
        self.root = root
        self.headers = len(names) > 1 and not concurrent
        self.concurrent = concurrent
        self.bars: dict[str, StageBars] = {}
        self.name: str | None = None
        self.complete: set[tuple[str, str]] = set()
        self._redirect: Any = None

    def __call__(self, name: str, stage: str, done: int, total: int) -> None:
        from tqdm import tqdm

        from leap_core.pipeline import JOINT
        from leap_core.run_layout import RunLayout

        key = (name, stage)
        if key in self.complete or (stage == "3dcn" and (JOINT, stage) in self.complete):
            return
        if name != self.name:
            if self.name is not None and not self.concurrent:
                self.bars[self.name].close()
            self.name = name
            if name not in self.bars:
                folder = None if name == JOINT else RunLayout(self.root).sequence(name).folder
                self.bars[name] = StageBars(folder, f"{name} " if self.concurrent else "")
            if self.headers:
                tqdm.write(
                    "== 3D-CN rounds (all sequences)" if name == JOINT else f"== sequence {name}",
                    file=sys.stderr,
                )
        self.bars[name](stage, done, total)
        if total > 0 and done >= total:
            self.complete.add(key)

    def __enter__(self) -> SequenceBars:
        from tqdm.contrib.logging import logging_redirect_tqdm

        self._redirect = logging_redirect_tqdm()
        self._redirect.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        for bars in self.bars.values():
            bars.close()
        if self._redirect is not None:
            self._redirect.__exit__(None, None, None)
            self._redirect = None


def _sequence_specs(datasets: list[str], frames: str | None) -> list[SequenceSpec]:
    """The sequences of ``leap run A [B ...]``, each named after its folder; one-line errors for a folder
    that is not a sequence, a name that cannot be a folder, two sequences of one name."""
    from leap_core.pipeline.run import SequenceSpec, check_specs

    specs = []
    for d in datasets:
        try:
            seq = KittiSequence(d)
        except LeapError as exc:
            raise LeapError(f"{d}: not a sequence folder ({exc})") from None
        try:
            specs.append(SequenceSpec.of(seq.root, None if frames is None else _frame_range(frames, d)))
        except ConfigError as exc:
            raise LeapError(f"{d}: the folder name cannot name a sequence: {exc.problem}") from None
    try:
        check_specs(specs)
    except ConfigError as exc:
        raise LeapError(exc.problem) from None
    return specs


@contextlib.contextmanager
def _poses_bar(scans: int) -> Iterator[ProgressFn]:
    """A progress bar over pose estimation's two passes (odometry, then the pose graph) of ``scans``
    scans; yields the ``progress(done, total)`` callback that moves it."""
    from tqdm import tqdm

    with tqdm(total=2 * scans, desc="poses (2 passes)", unit="scan", dynamic_ncols=True) as bar:

        def tick(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        yield tick


def _estimate_run_poses(dataset: Path, target: Path) -> None:
    """``leap run --estimate-poses``: KISS-ICP poses into ``target`` (the sequence's ``poses/poses.txt``
    in the run folder) when the dataset has none (reused when it already holds an estimate of the same
    scans)."""

    from leap_core.odometry import estimate_into

    seq = KittiSequence(dataset)
    if seq.has_poses:
        typer.echo(f"poses: {seq.poses_path} (--estimate-poses not needed)")
        return
    with _poses_bar(len(seq)) as tick:
        note, reused = estimate_into(seq, target, progress=tick)
    how = "reused" if reused else f"estimated in {note['seconds']:.1f} s"
    typer.echo(
        f"poses: {how} with {note['method']} (KISS-ICP {note['version']}) for {note['frames']} scans "
        f"-> {target}"
    )


@cli.command("poses")
def poses_cmd(
    dataset: str = typer.Argument(..., help="Sequence folder in KITTI layout (.../sequences/NN)."),
    *,
    out: str | None = typer.Option(
        None, "--out", help="poses.txt to write (default: DATASET/poses.txt); the note goes beside it."
    ),
    force: bool = typer.Option(False, "--force", help="Replace an existing poses file."),
    truth: str | None = typer.Option(
        None,
        "--truth",
        help="A poses.txt of true poses to measure the estimate against (default: the dataset's own "
        "measured poses.txt when --out writes elsewhere).",
    ),
    refine: bool = typer.Option(
        True,
        "--refine/--no-refine",
        help="Refine KISS-ICP's poses with the pose graph (--no-refine: faster).",
    ),
) -> None:
    """Estimate the sequence's poses with KISS-ICP LiDAR odometry refined by a pose graph over
    neighbouring-scan registrations, and write them as a KITTI poses.txt (left-camera frame, first pose =
    identity) plus poses_estimated.json saying how they were made and how well they fit."""
    import time

    from leap_core.odometry import OdometryConfig, estimate_sequence_poses, write_estimated_poses
    from leap_core.trajectory import path_distances

    try:
        seq = KittiSequence(dataset, poses_path=out) if out is not None else KittiSequence(dataset)
        target = seq.poses_path
        # Refused before the work, not after it.
        if target.exists() and not force:
            raise LeapError(f"{target}: already exists; add --force to replace it")
        reference = _truth_poses(seq.root, target, truth)
        config = OdometryConfig() if refine else OdometryConfig(refine=None)
        start = time.perf_counter()
        with _poses_bar(len(seq)) as tick:
            est = estimate_sequence_poses(seq, config, progress=tick)
        if reference is not None:
            est = est.compared_with(reference[1], str(reference[0]))
        note = write_estimated_poses(target, est, force=force)
    except KeyboardInterrupt:
        raise fail("interrupted; nothing was written") from None
    except LeapError as exc:
        raise fail(str(exc)) from None
    seconds = time.perf_counter() - start
    how = "KISS-ICP + pose graph" if refine else "KISS-ICP"
    typer.echo(
        f"wrote {target} and {note.name}: {len(seq)} poses, {path_distances(est.lidar)[-1]:.1f} m driven, "
        f"{how} in {seconds:.1f} s ({1000 * est.seconds / len(seq):.0f} ms/scan)"
    )
    for line in pose_quality_lines(est.note()["quality"]):
        typer.echo(line)


def _truth_poses(root: Path, target: Path, truth: str | None) -> tuple[Path, npt.NDArray[np.float64]] | None:
    """The true LiDAR poses ``leap poses`` measures its estimate against, and their file: ``truth`` when
    given, else the dataset's own poses.txt when it holds readable measured poses (no estimate note) and is
    not the file being written; None otherwise."""
    if truth is not None:
        ref = KittiSequence(root, poses_path=truth)
        if not ref.has_poses:
            raise LeapError(f"{ref.poses_path}: --truth names no poses file")
        return ref.poses_path, ref.poses
    try:
        own = KittiSequence(root)
    except DatasetError:
        return None  # the dataset's own poses.txt cannot be read: nothing to measure against, not an error
    if own.pose_source != "file" or own.poses_path.resolve() == target.resolve():
        return None
    return own.poses_path, own.poses


def pose_quality_lines(quality: dict[str, Any]) -> list[str]:
    """The lines ``leap poses`` prints about an estimate's ``quality`` (the note's): the residual and,
    with true poses, drift, rotation error and the first step."""

    def cm(v: float | None) -> str:
        return "n/a" if v is None else f"{100 * v:.2f} cm"

    lines = [
        f"registration residual: median {cm(quality.get('residual_median_m'))} between neighbouring scans "
        f"(KISS-ICP alone: {cm(quality.get('odometry_residual_median_m'))})"
    ]
    t = quality.get("truth")
    if t is not None:
        lengths = t["segment_lengths_m"]
        drift = "n/a (the drive is too short)" if t["drift_pct"] is None else f"{t['drift_pct']:.2f} %"
        rot = "n/a" if t["rotation_deg_per_100m"] is None else f"{t['rotation_deg_per_100m']:.2f} deg/100 m"
        ratio = t["first_step_ratio"]
        first = "n/a (a true step under 0.1 m)" if ratio is None else f"{ratio:.3f}"
        lines.append(
            f"against {t['poses']}: translational drift {drift} (KITTI's definition, segments "
            f"{lengths[0]:.0f}-{lengths[-1]:.0f} m), rotation {rot}, ATE {cm(t['ate_m'])}, "
            f"first step / second step {first} (1 = as right as the second)"
        )
    return lines


@cli.command("train-3dcn")
def train_3dcn_cmd(
    datasets: list[str] = typer.Argument(..., help="Labeled sequence folders (.../sequences/NN) to train."),
    *,
    out: str = typer.Option(
        ..., "--out", metavar="CKPT", help="Checkpoint to write (for leap run --3dcn-init)."
    ),
    schema: str | None = typer.Option(
        None,
        "--schema",
        help="Schema/project YAML file, or a built-in name in projects/ (default semantickitti).",
    ),
    project_file: str | None = typer.Option(
        None,
        "--project-file",
        help="Project YAML of the runs that will start from the network: its classes "
        "and its 'pipeline: consistency:' settings (backbone, schedule).",
    ),
    steps: int | None = typer.Option(
        None,
        "--steps",
        min=1,
        help="Optimisation steps, at least one epoch (default: consistency.min_steps).",
    ),
    seed: int | None = typer.Option(None, "--seed", help="Training seed (default: consistency.seed)."),
    force: bool = typer.Option(False, "--force", help="Replace an existing checkpoint file."),
) -> None:
    """Train the 3D-CN's network on the ground-truth labels of labeled sequences (another dataset or domain,
    e.g. `leap synth --domain street-32`), to start the 3D-CN of unlabeled sequences from it with
    `leap run --3dcn-init CKPT`, as the paper fine-tunes a network trained before. The classes and the
    backbone are the project's (give the project file the runs will use)."""
    import dataclasses
    import time

    from tqdm import tqdm

    from leap_core.consistency.pretrain import ground_truth_scans, train_on_ground_truth
    from leap_core.consistency.train import save_checkpoint

    target = Path(out)
    try:
        # Refused before the work, not after it.
        if target.exists() and not force:
            raise LeapError(f"{target}: already exists; add --force to replace it")
        if target.exists() and not target.is_file():
            raise LeapError(f"{target}: not a file")
        sch, pcfg = _run_config(schema, project_file, None, None)
        cfg = pcfg.consistency
        cfg = dataclasses.replace(
            cfg, min_steps=cfg.min_steps if steps is None else steps, seed=cfg.seed if seed is None else seed
        )
        seqs = [KittiSequence(d) for d in datasets]
        data = ground_truth_scans(seqs, sch)
        start = time.perf_counter()
        with tqdm(desc="train-3dcn", unit="step", dynamic_ncols=True) as bar:

            def tick(done: int, total: int) -> None:
                bar.total = total
                bar.update(done - bar.n)

            model, stats = train_on_ground_truth(data, sch, cfg, progress=tick)
        save_checkpoint(
            target,
            model,
            cfg,
            meta={
                "kind": "ground-truth",
                "sequences": [str(_cli_path(s.root, "sequence")) for s in seqs],
                "scans": len(data.scans),
                "class_names": sch.names,
                "class_counts": data.class_counts.tolist(),
                "steps": stats.steps,
                "losses": stats.losses,
                "seconds": stats.seconds,
            },
        )
    except KeyboardInterrupt:
        raise fail("interrupted; nothing was written") from None
    except LeapError as exc:
        raise fail(str(exc)) from None
    missing = [n for n, c in zip(sch.names, data.class_counts, strict=True) if c == 0]
    tail = stats.losses[-50:]
    typer.echo(
        f"wrote {target}: {len(data.scans)} scans of {len(seqs)} sequence(s), {stats.steps} steps in "
        f"{time.perf_counter() - start:.1f} s, mean loss of the last {len(tail)} steps "
        f"{sum(tail) / max(len(tail), 1):.3f}"
        + (f"; no ground truth for {', '.join(missing)}" if missing else "")
    )


# ------------------------------------------------------------------------------- a LiDAR-only model
def _model_config(  # noqa: PLR0913  # one value per training option
    backbone: Any,
    *,
    steps: int | None,
    seed: int | None,
    points_per_scan: int | None,
    val_block: int | None,
    val_every: int | None,
    checkpoint_every: int | None,
    device: str,
    threads: int,
) -> LidarModelConfig:
    """The training settings from ``leap train``'s options (one-line error for a value out of range)."""
    from leap_core.lidar_model.config import LidarModelConfig

    given: dict[str, Any] = {
        "steps": steps,
        "seed": seed,
        "points_per_scan": points_per_scan,
        "val_block": val_block,
        "val_every": val_every,
        "checkpoint_every": checkpoint_every,
    }
    try:
        return LidarModelConfig(
            **{k: v for k, v in given.items() if v is not None},
            device=device,  # type: ignore[arg-type]  # any string: the config refuses a bad one
            num_threads=threads,
            backbone=backbone,
        )
    except ConfigError as exc:
        raise LeapError(f"--{exc.field[0].replace('_', '-')}: {exc.problem}") from None


@cli.command("train")
def train_cmd(  # noqa: PLR0913  # typer: one parameter per command-line option
    sources: list[str] = typer.Argument(
        ...,
        help="What to train on: run folders (every sequence's final labels, corrections included), a run's "
        "sequence folder (RUN/sequences/NAME), or dataset sequences with ground truth (labels/).",
    ),
    *,
    out: str = typer.Option(..., "--out", metavar="MODEL.pt", help="The model file to write."),
    schema: str | None = typer.Option(
        None,
        "--schema",
        help="Schema/project YAML file, or a built-in name in projects/ (default semantickitti).",
    ),
    project_file: str | None = typer.Option(
        None,
        "--project-file",
        help="Project YAML: its classes and its 'pipeline: consistency: backbone:' sizes.",
    ),
    val: list[str] = typer.Option(
        [],
        "--val",
        help="Sequences held apart for validation (same kinds as SOURCES); turns the block split off.",
    ),
    init: str | None = typer.Option(
        None, "--init", metavar="MODEL.pt", help="Start from this model's weights."
    ),
    steps: int | None = typer.Option(None, "--steps", help="Optimisation steps (default 1000)."),
    seed: int | None = typer.Option(None, "--seed", help="Training seed (default 0)."),
    points_per_scan: int | None = typer.Option(None, "--points-per-scan", help="Points per scan per step."),
    val_block: int | None = typer.Option(
        None, "--val-block", help="Frames per validation block (default 10; 0: no block split)."
    ),
    val_every: int | None = typer.Option(
        None, "--val-every", help="Every N-th block is held apart for validation (default 5)."
    ),
    checkpoint_every: int | None = typer.Option(
        None, "--checkpoint-every", help="Steps between resumable states (MODEL.state.pt)."
    ),
    device: str = typer.Option("auto", "--device", help="auto (CUDA when available), cpu or cuda."),
    threads: int = typer.Option(0, "--threads", min=0, help="Torch threads (0: torch's default)."),
    restart: bool = typer.Option(
        False, "--restart", help="Start over instead of resuming an interrupted training."
    ),
    force: bool = typer.Option(False, "--force", help="Replace an existing model file."),
) -> None:
    """Train a LiDAR-only segmentation model (the project's 3D backbone) on the final labels of runs or on
    ground truth, with a held-apart validation split and a model card (MODEL.card.json). An interrupted
    training resumes when the same command runs again."""
    from tqdm import tqdm

    from leap_core.lidar_model.data import labeled_sequences, split_scans
    from leap_core.lidar_model.model import LidarModel, load_model, state_path
    from leap_core.lidar_model.train import train_lidar_model

    target = Path(out)
    try:
        if target.exists() and not force:
            raise LeapError(f"{target}: already exists; add --force to replace it")
        if target.exists() and not target.is_file():
            raise LeapError(f"{target}: not a file")
        sch, pcfg = _run_config(schema, project_file, None, None)
        start: LidarModel | None = None
        backbone = pcfg.consistency.backbone
        if init is not None:
            start = load_model(_cli_path(init, "--init"))
            backbone = start.config.backbone
        cfg = _model_config(
            backbone,
            steps=steps,
            seed=seed,
            points_per_scan=points_per_scan,
            val_block=val_block,
            val_every=val_every,
            checkpoint_every=checkpoint_every,
            device=device,
            threads=threads,
        )
        if val:
            cfg = dataclasses.replace(cfg, val_block=0)
        train, held = split_scans(
            labeled_sequences(sources), labeled_sequences(val), cfg.val_block, cfg.val_every
        )
        typer.echo(f"{len(train.scans)} training scans, {len(held.scans)} held apart for validation")
        with tqdm(desc="train", unit="step", dynamic_ncols=True) as bar:

            def tick(done: int, total: int) -> None:
                bar.total = total
                bar.update(done - bar.n)

            result = train_lidar_model(
                target, train, held, sch, cfg, init=start, init_path=init, progress=tick, restart=restart
            )
    except KeyboardInterrupt:
        resume = state_path(target)
        where = f"from {resume}" if resume.is_file() else "(no state saved yet)"
        raise fail(f"interrupted; run the same command again to resume {where}") from None
    except LeapError as exc:
        raise fail(str(exc)) from None
    card = result.card
    v = card["validation"]
    score = (
        "no validation scans" if v is None or v["miou"] is None else f"validation mIoU {100 * v['miou']:.1f}"
    )
    tail = result.losses[-50:]
    typer.echo(
        f"wrote {target} and {target.with_suffix('.card.json').name}: {cfg.steps} steps"
        + (f" (resumed at {result.resumed_from})" if result.resumed_from else "")
        + f", {result.points_seen / max(result.seconds, 1e-9):,.0f} points/s, mean loss of the last "
        f"{len(tail)} steps {sum(tail) / max(len(tail), 1):.3f}; {score}"
    )


@cli.command("predict")
def predict_cmd(  # noqa: PLR0913  # typer: one parameter per command-line option
    model_file: str = typer.Argument(..., metavar="MODEL.pt", help="A model `leap train` wrote."),
    datasets: list[str] = typer.Argument(..., help="Sequence folders (.../sequences/NN) to label."),
    *,
    out: str = typer.Option(..., "--out", help="Run folder to write (created)."),
    frames: str | None = typer.Option(
        None, "--frames", help="Frame numbers A:B (B exclusive) of each sequence."
    ),
    views: int = typer.Option(1, "--views", min=1, max=32, help="Test-time views averaged per scan."),
    device: str = typer.Option("auto", "--device", help="auto (CUDA when available), cpu or cuda."),
    threads: int = typer.Option(0, "--threads", min=0, help="Torch threads (0: torch's default)."),
    export_to: str | None = typer.Option(
        None, "--export-to", help="Also copy the .label files to DIR/sequences/<name>/predictions/."
    ),
    zip_path: str | None = typer.Option(
        None, "--zip", help="Also write the export as a zip with its label map."
    ),
    with_conf: bool = typer.Option(
        False, "--with-conf", help="Include the .conf files in --export-to/--zip."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing export."),
) -> None:
    """Label sequences with a trained model: LiDAR only (no camera, images or poses needed), frame by frame,
    into a run folder (points/ and export/ .label + .conf per sequence, as `leap run` writes); scored
    where the sequence has ground truth."""
    from tqdm import tqdm

    from leap_core.export import (
        LABEL_MAP_FILE,
        export_targets,
        label_map,
        label_map_yaml,
        run_export,
        write_export_zip,
        write_run_export,
    )
    from leap_core.lidar_model.model import load_model
    from leap_core.lidar_model.predict import predict_run
    from leap_core.metrics import format_table

    try:
        zip_file = _zip_target(zip_path, overwrite)
        model = load_model(_cli_path(model_file, "MODEL.pt"))
        specs = _sequence_specs(datasets, frames)
        bars: dict[str, tqdm[Any]] = {}

        def tick(name: str, done: int, total: int) -> None:
            bar = bars.get(name)
            if bar is None:
                bar = bars[name] = tqdm(total=total, desc=f"{name} predict", unit="scan", dynamic_ncols=True)
            bar.update(done - bar.n)

        try:
            results = predict_run(
                model,
                model_file,
                [(s.name, s.dataset, s.frames) for s in specs],
                _cli_path(out, "--out"),
                views=views,
                device=device,
                num_threads=threads,
                progress=tick,
            )
        finally:
            for bar in bars.values():
                bar.close()
        for r in results:
            typer.echo(
                f"sequence {r.name}: {r.scans} scans, {r.points} points labeled, "
                f"{r.scans / max(r.seconds, 1e-9):.2f} scans/s"
            )
            if r.metrics is not None:
                typer.echo(format_table({"model": r.metrics}, model.schema.names))
        exported = run_export(Path(out))
        if export_to is not None:
            target = _cli_path(export_to, "--export-to")
            folders = export_targets(target, [s.name for s in exported], with_conf=with_conf)
            done = write_run_export(folders, exported, with_conf=with_conf, overwrite=overwrite)
            typer.echo(f"wrote {sum(done.files.values())} files to {target}/sequences/*/predictions/")
        if zip_file is not None:
            counts: dict[int, int] = {}
            for r in results:
                for raw, n in r.raw_counts.items():
                    counts[raw] = counts.get(raw, 0) + n
            lmap = label_map(
                model.schema, counts, name=model.schema.name, sequences=[s.name for s in exported]
            )
            extra = {
                LABEL_MAP_FILE: label_map_yaml(lmap),
                "model-card.json": json.dumps(model.card, indent=2),
            }
            n = write_export_zip(zip_file, exported, extra, include_confidence=with_conf, overwrite=overwrite)
            typer.echo(f"wrote {zip_file} ({n} files, {LABEL_MAP_FILE}, model-card.json)")
    except KeyboardInterrupt:
        raise fail(f"interrupted; the scans labeled so far are in {out}") from None
    except LeapError as exc:
        raise fail(str(exc)) from None


@cli.command("export-model")
def export_model_cmd(
    model_file: str = typer.Argument(..., metavar="MODEL.pt", help="A model `leap train` wrote."),
    *,
    out: str = typer.Option(..., "--out", metavar="FILE.pt", help="The TorchScript file to write."),
    force: bool = typer.Option(False, "--force", help="Replace an existing file."),
) -> None:
    """Export a trained model as TorchScript (torch.jit.load, no LeAP needed to run it; inputs in
    docs/METHOD.md "A LiDAR-only model"). ONNX is not offered: the backbone's sparse cell averaging has no
    ONNX operator."""
    from leap_core.lidar_model.export import export_torchscript
    from leap_core.lidar_model.model import load_model

    target = Path(out)
    try:
        if target.exists() and not force:
            raise LeapError(f"{target}: already exists; add --force to replace it")
        model = load_model(_cli_path(model_file, "MODEL.pt"))
        export_torchscript(model.network, target)
    except LeapError as exc:
        raise fail(str(exc)) from None
    typer.echo(f"wrote {target} (TorchScript, {model.schema.num_classes} classes)")


def _zip_target(zip_path: str | None, overwrite: bool) -> Path | None:
    """Check ``--zip`` (resolved) before the run; the write checks again."""
    from leap_core.export import export_target_problem

    if zip_path is None:
        return None
    zfile = _cli_path(zip_path, "--zip")
    problem = export_target_problem(zfile.parent)
    if problem is not None:
        raise LeapError(f"--zip: {problem}")
    if zfile.exists() and not overwrite:
        raise LeapError(f"--zip: {zfile} already exists; add --overwrite to replace it")
    return zfile


def _write_exports(  # the run and the export options
    result: RunResult,
    specs: list[SequenceSpec],
    sch: Schema,
    cfg: PipelineConfig,
    export_to: str | None,
    zip_file: Path | None,
    *,
    with_conf: bool,
    overwrite: bool,
) -> None:
    """Print each sequence's export folder and unlabeled counts, then write ``--export-to`` / ``--zip``."""
    import datetime

    from leap_core import __version__
    from leap_core.config import config_to_dict
    from leap_core.export import (
        LABEL_MAP_FILE,
        SUMMARY_FILE,
        export_targets,
        label_map,
        label_map_yaml,
        run_export,
        summary_yaml,
        write_export_zip,
        write_run_export,
    )
    from leap_core.pipeline.coverage import cached_export_coverage, coverage_counts, summed_coverage
    from leap_core.pipeline.provenance import provenance_lines, run_provenance

    covs = []
    for spec in specs:
        res = result.sequences[spec.name]
        if res.export_dir is None:
            return
        n = len(list(res.export_dir.glob("*.label")))
        # Counted once per export, then read from the run folder (a cached rerun reads no scan).
        cov = cached_export_coverage(res.folder, spec.dataset, spec.frames, cfg.fusion.voxel_size)
        covs.append(cov)
        head = "" if len(specs) == 1 else f"sequence {spec.name}: "
        typer.echo(
            f"\n{head}{n} .label files (+ .conf confidences) in {res.export_dir}\n"
            f"{cov.labeled} of {cov.points} points labeled; {cov.unlabeled} unlabeled: "
            f"{cov.outside_view} outside every camera view, {cov.no_mask} in view but no mask"
        )
    exported = run_export(result.root)
    prov = run_provenance(result.root, sch, cfg, [(s.name, s.dataset) for s in exported])
    typer.echo("\nprovenance\n" + "\n".join(f"  {line}" for line in provenance_lines(prov)))
    if export_to is not None:
        target = _cli_path(export_to, "--export-to")
        folders = export_targets(target, [s.name for s in exported], with_conf=with_conf)
        done = write_run_export(folders, exported, with_conf=with_conf, overwrite=overwrite)
        note = f" (replaced {done.replaced})" if done.replaced else ""
        typer.echo(
            f"wrote {sum(done.files.values())} files to {target}/sequences/{{{','.join(done.files)}}}/"
            f"predictions/{note}"
        )
    if zip_file is not None:
        cov = summed_coverage(covs)
        summary = summary_yaml(
            run={"folder": str(result.root)},
            sequences=exported,
            schema=sch,
            pipeline=config_to_dict(cfg),
            counts=coverage_counts(cov),
            with_confidence=with_conf,
            version=__version__,
            written_at=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            provenance=prov,
        )
        lmap = label_map(sch, cov.raw_counts, name=sch.name, sequences=[s.name for s in exported])
        extra = {LABEL_MAP_FILE: label_map_yaml(lmap), SUMMARY_FILE: summary}
        n = write_export_zip(zip_file, exported, extra, include_confidence=with_conf, overwrite=overwrite)
        typer.echo(
            f"wrote {zip_file} ({n} files in sequences/<name>/predictions/, {LABEL_MAP_FILE}, {SUMMARY_FILE})"
        )


def _run_config(
    schema: str | None,
    project_file: str | None,
    labeler: str | None,
    consistency: bool | None,
    cn_iterations: int | None = None,
    labeler_preset: str | None = None,
    *,
    init_3dcn: str | None = None,
) -> tuple[Schema, PipelineConfig]:
    """``leap run``'s classes and config (:func:`_run_choice` without whether the labeler was named)."""
    sch, cfg, _ = _run_choice(
        schema, project_file, labeler, consistency, cn_iterations, labeler_preset, init_3dcn=init_3dcn
    )
    return sch, cfg


def _run_choice(
    schema: str | None,
    project_file: str | None,
    labeler: str | None,
    consistency: bool | None,
    cn_iterations: int | None = None,
    labeler_preset: str | None = None,
    *,
    init_3dcn: str | None = None,
) -> tuple[Schema, PipelineConfig, bool]:
    """``leap run``'s classes and config: --schema's file gives the classes (and a base config),
    --project-file's pipeline applies on top, then --labeler, --labeler-preset (a preset of the chosen
    labeler's section), --3dcn and --3dcn-iterations or --3dcn-init (which turn the 3D-CN on; with
    --no-3dcn they are a contradiction, refused).

    Returns:
        (classes, config, named): ``named`` is True when the labeler was named (--labeler, or a
        ``labeler:`` in either file's ``pipeline:`` section); otherwise the run picks it
        (:func:`_pick_labeler`), as ``leap check`` does.
    """
    if init_3dcn is not None:
        if consistency is False:
            raise LeapError("--3dcn-init fine-tunes the 3D-CN: drop --no-3dcn or --3dcn-init")
        consistency = True
    cfg = None
    sch = None
    # A --labeler-preset is a setting of the configured labeler: that labeler is meant.
    named = labeler is not None or labeler_preset is not None
    if schema is not None or project_file is None:
        base = _preset("--schema", schema or "semantickitti")
        sch, cfg, named = base.schema, base.pipeline, named or base.names_labeler
    if project_file is not None:
        project = _preset("--project-file", project_file, cfg)
        sch, cfg, named = sch or project.schema, project.pipeline, named or project.names_labeler
    assert sch is not None and cfg is not None
    flags: dict[str, Any] = {}
    if labeler is not None:
        flags["labeler"] = labeler
    chosen = LABELERS.get(labeler or cfg.labeler)
    if labeler_preset is not None and chosen is not None:
        # An unknown labeler name is refused by the config (its usual one-line error) before this applies.
        flags[chosen.section] = {"preset": labeler_preset}
    if consistency is not None:
        flags["consistency"] = {"enabled": consistency}
    if cn_iterations is not None:
        if consistency is False:
            raise LeapError("--3dcn-iterations runs the 3D-CN: drop --no-3dcn or --3dcn-iterations")
        if cn_iterations not in (1, 2):
            raise LeapError(f"--3dcn-iterations: must be 1 or 2, got {cn_iterations}")
        flags["consistency"] = {"enabled": True, "iterations": cn_iterations}
    return sch, config_from_dict(flags, cfg), named


def _with_labeler(cfg: PipelineConfig, name: str, seed: int | None) -> PipelineConfig:
    """``cfg`` running the labeler ``name``, with ``--seed`` in that labeler's section.

    Raises:
        LeapError: ``--seed`` for a labeler whose settings have no seed (it draws nothing at random).
    """
    flags: dict[str, Any] = {"labeler": name}
    if seed is not None:
        spec = LABELERS[name]
        if "seed" not in {f.name for f in dataclasses.fields(spec.config_type)}:
            seeded = ", ".join(
                n
                for n, sp in LABELERS.items()
                if "seed" in {f.name for f in dataclasses.fields(sp.config_type)}
            )
            raise LeapError(
                f"--seed: the {name} labeler draws nothing at random, so it has no seed; drop --seed "
                f"(labelers with one: {seeded})"
            )
        flags[spec.section] = {"seed": seed}
    return config_from_dict(flags, cfg)


def _pick_labeler(
    specs: list[SequenceSpec],
    cfg: PipelineConfig,
    runtime: Runtime,
    *,
    named: bool,
    estimate_poses: bool,
) -> tuple[str, list[str]]:
    """``leap run``'s pre-flight: the labeler the run uses (the one rule ``leap check`` follows:
    :func:`~leap_core.pipeline.preflight.pick_labeler`), checked against every sequence before the run
    folder is touched.

    Returns:
        (labeler, notes): the notes are the lines to print (how the labeler was picked).

    Raises:
        LeapError: a sequence the pipeline cannot run on at all (its blockers, each with the fix), or one
            that lacks the labeler's input entirely (naming the --labeler that works, or what to add).
    """
    from app.advice import advice
    from leap_core.pipeline.preflight import check_dataset, describe, pick_labeler, reason_text

    reports = [
        check_dataset(
            s.dataset, config=cfg, runtime=runtime, estimate_poses=estimate_poses, labeler_named=named
        )
        for s in specs
    ]
    for report in reports:
        blockers = [f for f in report.findings if f.severity == "blocker"]
        if blockers:
            fixes = [
                f"{describe(f)}" + (f" (fix: {fix})" if (fix := advice(f, "cli", report)) else "")
                for f in blockers
            ]
            raise LeapError("; ".join(fixes))
    per_sequence = [r.labelers for r in reports]
    name = pick_labeler(per_sequence, cfg.labeler if named else None) or cfg.labeler
    notes = []
    if not named and name != cfg.labeler:
        where = "this folder" if len(specs) == 1 else "every sequence"
        notes.append(f", picked as the first labeler that can run on {where} (--labeler picks another)")
    # A labeler whose input a whole sequence lacks cannot label it; a partial input (some frames without
    # an image) is left to the run, since --frames may keep to the frames that have one.
    whole = {"images_missing", "gt2d_missing"}
    for report in reports:
        lab = next(lab for lab in report.labelers if lab.name == name)
        missing = [r for r in lab.reasons if r in whole]
        if not missing:
            continue
        others = pick_labeler([[lab for lab in labs if lab.name != name] for labs in per_sequence])
        why = ", ".join(reason_text(r) for r in missing)
        if others is not None:
            fix = f"use --labeler {others}"
        else:
            finding = report.finding(missing[0])
            fix = advice(finding, "cli", report) if finding is not None else ""
        raise LeapError(f"{report.root}: the {name} labeler cannot run ({why}); {fix or 'see `leap check`'}")
    return name, notes


def _frame_range(frames: str, dataset: str) -> range:
    """``--frames A:B``: frame numbers, B exclusive (``A`` alone: one frame; ``A:``: to the last scan)."""
    a, sep, b = frames.partition(":")
    try:
        start = int(a) if a.strip() else 0
        stop = int(b) if sep and b.strip() else (start + 1 if not sep else None)
    except ValueError:
        raise LeapError(f"--frames {frames!r}: expected A:B with integers (B exclusive)") from None
    if stop is None:
        stop = KittiSequence(dataset).frame_numbers[-1] + 1
    return range(start, stop)


@cli.command("serve")
def serve_cmd(  # noqa: PLR0913  # typer: one parameter per command-line option
    *,
    host: str | None = typer.Option(
        None, "--host", help="Address to bind (default 127.0.0.1; any other address needs --token)."
    ),
    port: int | None = typer.Option(None, "--port", help="Port (default 8000)."),
    data_root: list[str] | None = typer.Option(
        None, "--data-root", help="Folder datasets are read from and exported to (repeatable; default: data)."
    ),
    work_dir: str | None = typer.Option(
        None, "--work-dir", help="Runs, caches and the database (default ./data/studio)."
    ),
    token: str | None = typer.Option(
        None,
        "--token",
        help="Access token every request must carry (or LEAP_ACCESS_TOKEN); at least 16 characters, "
        "8 different ones, about 64 bits of entropy.",
    ),
    new_token: bool = typer.Option(
        False, "--new-token", help="Generate a random access token, print it once and require it."
    ),
    models: str | None = typer.Option(None, "--models", help="Folder with Grounding DINO / SAM weights."),
    allow_download: bool = typer.Option(
        False, "--allow-download", help=_DOWNLOAD_HELP + " (or LEAP_ALLOW_DOWNLOAD=true)"
    ),
    no_demo: bool = typer.Option(False, "--no-demo", help="Do not seed the demo project on first start."),
) -> None:
    """Start LeAP Studio: the web UI, the REST API (/api/docs) and the 3D viewer, on 127.0.0.1:8000."""
    import secrets

    from app.main import serve

    if new_token:
        if token is not None:
            raise fail("--token and --new-token exclude each other")
        token = secrets.token_urlsafe(32)  # 256 random bits
        typer.echo(f"access token (give it to the people who may use this server): {token}")
    settings = _app_settings(
        host=host,
        port=port,
        data_root=data_root,
        work_dir=work_dir,
        token=token,
        models=models,
        allow_download=True if allow_download else None,
        seed_demo=False if no_demo else None,
    )
    serve(settings)


@cli.command("demo")
def demo_cmd(
    *,
    port: int | None = typer.Option(None, "--port", help="Port (default 8000)."),
    work_dir: str | None = typer.Option(
        None, "--work-dir", help="Runs, caches and the database (default ./data/studio)."
    ),
    data_root: list[str] | None = typer.Option(None, "--data-root", help="Data root(s) (default ./data)."),
    no_serve: bool = typer.Option(False, "--no-serve", help="Stop after the demo run instead of serving."),
) -> None:
    """Generate the demo street sequence (once), label it with the simulated labeler and serve the app:
    the browser then shows the demo project with a finished run and its metrics."""
    from app import crud
    from app.core.db import init_db, open_db
    from app.demo import ensure_demo_sequence, seed_demo_project
    from app.jobs.folders import migrate_run_folders
    from app.main import serve
    from leap_core.pipeline import run_result_tables

    settings = _app_settings(port=port, data_root=data_root, work_dir=work_dir)
    generating = StageBars()
    lock = _lock_work_dir(settings)

    try:
        ensure_demo_sequence(settings.demo_dataset, dict(settings.demo_synth), progress=generating)
    except LeapError as exc:
        raise fail(str(exc)) from None
    generating.close()
    init_db(settings.database)
    migrate_run_folders(settings.database)
    seed_demo_project(settings)
    with open_db(settings.database) as db:
        project = crud.find_demo_project(db)
        if project is None:
            raise fail(f"the demo project was deleted from {settings.database}; use another --work-dir")
        finished = crud.last_finished_run(db, project.id)
        active = crud.active_run(db, project.id)
    if finished is None:
        finished = _label_demo(settings, project.id, active)
    tables = run_result_tables(finished.run_dir)
    if tables:
        typer.echo(tables)
    if no_serve:
        return
    serve(settings, lock=lock)


def _label_demo(settings: Settings, project_id: int, active: RunRow | None) -> RunRow:
    """``leap demo``'s first run of the demo project, in this process with progress bars (``active``: a
    run a killed ``leap demo`` left running is resumed); returns the finished run."""
    from app import crud
    from app.core.db import open_db
    from app.demo import DEMO_PROJECT_NAME
    from app.jobs.manager import JobManager
    from app.jobs.stages import split_stage
    from app.jobs.worker import RunDirBusy, run_dir_lock

    manager = JobManager(settings)
    if active is not None:
        # Left "running" by a killed `leap demo`, unless a live process holds its folder's lock.
        try:
            with run_dir_lock(active.run_dir):
                pass
        except RunDirBusy:
            raise fail(f"demo run {active.id} is in use (is a server running?)") from None
        with open_db(settings.database) as db:
            crud.update_run(db, active.id, status="interrupted")
    with open_db(settings.database) as db:
        resumable = [r for r in crud.list_runs(db, project_id) if r.status in ("interrupted", "cancelled")]
    run = manager.resume_run(resumable[0].id) if resumable else manager.start_run(project_id)
    typer.echo(f"labeling the demo sequence (run #{run.number} of project {DEMO_PROJECT_NAME!r})")
    with SequenceBars(run.run_dir, run.params.names) as bars:

        def report(name: str, done: int, total: int) -> None:
            sequence, stage = split_stage(name)
            bars(sequence or run.params.names[0], stage, done, total)

        status = manager.run_now(run.id, on_progress=report)
    with open_db(settings.database) as db:
        finished = crud.require_run(db, run.id)
    if status != "done":
        raise fail(f"the demo run {status}: {finished.error}")
    return finished


def _lock_work_dir(settings: Settings) -> ServerLock:
    """The work folder's and the database's lock, held from before the database is opened until the process
    ends (one process per work folder and per database; a one-line error when another holds either)."""
    from app.core.instance import ServerLock, StartupRefused

    lock = ServerLock(settings.work_dir, settings.database)
    try:
        lock.acquire(f"leap demo, port {settings.port}")
    except StartupRefused as exc:
        raise fail(str(exc)) from None
    return lock


class _GivenSettings(TypedDict, total=False):
    """The :class:`Settings` fields a command line sets; the others come from the environment."""

    host: str
    port: int
    data_roots: list[Path]
    work_dir: Path
    access_token: SecretStr
    models_dir: Path
    allow_download: bool
    seed_demo: bool


def _app_settings(
    *,
    host: str | None = None,
    port: int | None = None,
    data_root: list[str] | None = None,
    work_dir: str | None = None,
    token: str | None = None,
    models: str | None = None,
    allow_download: bool | None = None,
    seed_demo: bool | None = None,
) -> Settings:
    """App settings from the environment with the command-line values given (not None) on top (one-line
    error when invalid)."""
    from pydantic import SecretStr, ValidationError

    from app.core.config import Settings

    given: _GivenSettings = {}
    if host is not None:
        given["host"] = host
    if port is not None:
        given["port"] = port
    if data_root:
        given["data_roots"] = [Path(p) for p in data_root]
    if work_dir is not None:
        given["work_dir"] = Path(work_dir)
    if token is not None:
        given["access_token"] = SecretStr(token)
    if models is not None:
        given["models_dir"] = Path(models)
    if allow_download is not None:
        given["allow_download"] = allow_download
    if seed_demo is not None:
        given["seed_demo"] = seed_demo
    try:
        return Settings(**given)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "settings"
        raise fail(f"{where}: {err['msg']}") from None


@cli.command("synth")
def synth(
    out: str = typer.Argument(..., help="Dataset root to write (the sequence goes to OUT/sequences/NN)."),
    *,
    frames: int = typer.Option(60, "--frames", min=1, help="Number of frames (10 Hz street, 5 Hz agri-uav)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the scene, the route and all sensor noise."),
    sequence: str = typer.Option("00", "--sequence", help="Sequence folder name."),
    force: bool = typer.Option(False, "--force", help="Replace an existing non-empty sequence folder."),
    workers: int = typer.Option(0, "--workers", min=0, help="Worker processes (0 = up to 2, by core count)."),
    domain: str = typer.Option(
        "street",
        "--domain",
        help="; ".join(f"{k}: {v}" for k, v in SYNTH_DOMAINS.items()) + ".",
        autocompletion=lambda: list(SYNTH_DOMAINS),
    ),
    cameras: int = typer.Option(
        1,
        "--cameras",
        help="Cameras of the street rig: 1 (front), 2 (front, rear) or 4 (front, rear, left, right).",
    ),
) -> None:
    """Generate a demo sequence in the KITTI / SemanticKITTI layout: a procedural street (default), with
    --domain street-32 another town seen by a 32-beam LiDAR, or with --domain agri-uav a drone survey of a
    farm; --cameras 4 gives the street a surround rig."""
    import time

    from tqdm import tqdm

    from leap_core.synth import default_workers, generate_sequence
    from leap_core.synth.domains import domain_config

    if domain not in SYNTH_DOMAINS:
        raise fail(f"--domain: unknown domain {domain!r} ({', '.join(SYNTH_DOMAINS)})")

    start = time.perf_counter()
    bars: list[tqdm[Any]] = []  # opened at the first progress call, so a refusal prints only the error

    def progress(done: int, total: int) -> None:
        if not bars:
            bars.append(tqdm(total=total, unit="frame", desc="synth"))
        bars[0].update(done - bars[0].n)

    try:
        config = domain_config(domain, frames, seed, cameras)
    except ValueError as exc:
        raise fail(f"--cameras: {exc}") from None
    try:
        stats = generate_sequence(
            out,
            config,
            sequence,
            force=force,
            workers=workers or default_workers(),
            progress=progress,
        )
    except LeapError as exc:
        raise fail(str(exc)) from None
    finally:
        for bar in bars:
            bar.close()
    typer.echo(
        f"wrote {stats.path} in {time.perf_counter() - start:.1f} s: {frames} frames, "
        f"{stats.points.mean():.0f} points/scan, {100 * stats.in_image_share:.1f}% in "
        + ("the image" if cameras == 1 else f"some camera's image ({cameras} cameras)")
    )


def main() -> None:
    cli()


if __name__ == "__main__":
    main()
