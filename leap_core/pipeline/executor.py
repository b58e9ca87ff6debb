"""Where a run's stages compute: in this process (the default) or as Ray tasks on a cluster.

:func:`make_executor` picks the engine from :attr:`leap_core.runtime.Runtime.ray_address`: None =
:class:`LocalExecutor` (each stage's function in this process; ray is never imported), else
:class:`RayExecutor`. The runner (:func:`leap_core.pipeline.runner.run_sequence`) keeps everything else:
fingerprints, ``stages.json``, clearing, resuming.

The Ray engine changes where work runs, never what it computes, so a run's files are the same bytes as a
local run's (``tests/test_ray.py``):

* **Per-frame stages** (labels2d, project, label_points, export): the frames that still lack their files
  are cut into contiguous sub-ranges; each Ray task rebuilds the run context in its worker for its
  sub-range (:func:`worker_context`: the run folder and the dataset must be on storage every node sees at
  the same path) and calls the stage's own function, which computes and atomically writes exactly those
  frames, as it does locally. The driver reports progress as tasks finish; a ``Cancelled`` from the
  progress callback stops the tasks not yet finished at their next frame (:class:`StopSignal`; finished
  frames are kept: a rerun resumes).
  2D labeling by a labeler that runs models (it reads camera images) asks for one GPU per task when
  the cluster has GPUs and the runtime's device is not ``cpu``.
* **Fusion**: float32 sums are not associative, so partial grids may not be added in any order. The
  frames are cut into the very chunks :func:`leap_core.fusion.fuse` reduces one after the other
  (:func:`~leap_core.fusion.fusion_blocks`, ``fusion.chunk_points``); tasks prepare each frame's
  observations and reduce each chunk (:func:`~leap_core.fusion.reduce_block`) in parallel, and the driver
  adds the partials in chunk order (:func:`~leap_core.fusion.fold_blocks`): the same additions in the
  same order as the local fusion, whose code and bytes are unchanged.
* **3D-CN inference**: the network is trained in the driver (one network) and saved to the run folder as
  locally; then tasks load that checkpoint (a path, never the model object), predict blocks of consecutive
  frames with the driver's torch thread count
  (:func:`leap_core.consistency.remote.predict_from_checkpoint`) and send each frame's keys and
  log-probabilities back; the driver fuses them in frame order, as the local loop would have produced
  them (:class:`RayPredictor`).
* Everything else (smoothing, 3D-CN training, evaluation) runs in the driver, as locally.

Warnings the stage code logs in a worker (``leap_core`` loggers) are sent back with the task's result and
logged again in the driver, so the CLI and the app's run log show them as for a local run.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import math
import os
import socket
import traceback
import uuid
import zipfile
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from leap_core.config import PipelineConfig
from leap_core.errors import Cancelled, DatasetError, LeapError
from leap_core.extras import MissingExtra
from leap_core.fusion import Observations, Partial, fold_blocks, fusion_blocks, log_table, reduce_block
from leap_core.io_utils import read_npz
from leap_core.labelers import LABELERS
from leap_core.pipeline.context import Ctx, StageInfo
from leap_core.pipeline.objects import read_motion
from leap_core.pipeline.stages import STAGE_TABLE, finish_fuse, observed_keys
from leap_core.run_layout import SequenceLayout
from leap_core.runtime import Runtime
from leap_core.schema import Schema

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from types import ModuleType

    from leap_core.consistency.config import ConsistencyConfig
    from leap_core.consistency.stage import Predict
    from leap_core.datasets.kitti import KittiSequence

TASKS_PER_CPU = 2
"""Per-frame stages are cut into about this many sub-ranges per cluster CPU: enough for progress and for
balancing uneven frames, few enough that each task's start (context, labeler, final grid) is paid rarely."""

INFER_TASK_FRAMES = 8
"""At most this many frames per 3D-CN inference task: a frame's predictions are ≈ 4·C bytes per point
(≈ 8 MB for a 106k-point scan at C = 20), held in the object store until the driver fuses them."""

STOP_WAIT_S = 600.0
"""After a stop (a cancel, or another task's error) the driver waits up to this long for the running tasks
to reach their next frame and return; a frame of Grounding DINO + SAM on a CPU takes about a minute."""

LOCAL_OBJECT_STORE_BYTES = 512 * 1024 * 1024
"""Object store of a local instance started for ``"auto"``: a task's results (one chunk's observations,
its partial grid) are a few tens of MB; Ray's default (30 % of the RAM) would reserve far more."""


class Executor(Protocol):
    """Runs one enabled stage of a run: its effect is the stage function's (``stage.run(ctx)``)."""

    name: str

    def run_stage(self, ctx: Ctx, stage: StageInfo) -> dict[str, Any]:
        """Compute the stage's outputs into ``ctx.layout``; returns the stage function's record fields."""
        ...

    def predictor(self, cfg: PipelineConfig) -> Predict | None:
        """Where the 3D-CN's inference runs: None = in this process (the round's own loop)."""
        ...


class LocalExecutor:
    """Every stage in this process (the default engine)."""

    name = "local"

    def run_stage(self, ctx: Ctx, stage: StageInfo) -> dict[str, Any]:
        return stage.run(ctx)

    def predictor(self, cfg: PipelineConfig) -> Predict | None:  # noqa: ARG002  the protocol's signature
        return None


def make_executor(runtime: Runtime | None) -> Executor:
    """The engine ``runtime`` asks for: :class:`LocalExecutor` without :attr:`Runtime.ray_address`, else a
    :class:`RayExecutor` connected to that cluster (raises :class:`LeapError` when it cannot connect)."""
    if runtime is None or runtime.ray_address is None:
        return LocalExecutor()
    return RayExecutor(runtime.ray_address, runtime.ray_cpus)


# ------------------------------------------------------------------------------------------ helpers
def frame_blocks(indices: Sequence[int], size: int) -> list[list[int]]:
    """Cut sorted frame indices into runs of consecutive indices of at most ``size`` each.

    Example: [0, 1, 2, 5, 6, 7, 8], size 3 → [[0, 1, 2], [5, 6, 7], [8]].
    """
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    blocks: list[list[int]] = []
    for i in indices:
        if blocks and blocks[-1][-1] == i - 1 and len(blocks[-1]) < size:
            blocks[-1].append(i)
        else:
            blocks.append([i])
    return blocks


def number_range(ctx: Ctx, indices: Sequence[int]) -> range:
    """The frame numbers spanning consecutive indices (what :meth:`KittiSequence.select` turns back into
    exactly those indices: numbers in between belong to no scan)."""
    numbers = ctx.seq.frame_numbers
    return range(numbers[indices[0]], numbers[indices[-1]] + 1)


def observed_count(path: Path) -> int:
    """Number of observed points of an ``observations/`` file, read from the array header only."""
    try:
        with zipfile.ZipFile(path) as zf, zf.open("point_idx.npy") as fh:
            version = np.lib.format.read_magic(fh)
            header = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            shape, _, _ = header(fh)
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise DatasetError(path, f"unreadable observation file ({exc})") from exc
    if len(shape) != 1:
        raise DatasetError(path, f"point_idx must be 1-D, got shape {shape}")
    return int(shape[0])


def fused_count(path: Path, moving: npt.NDArray[np.int32] | None) -> int:
    """Number of observations of an ``observations/`` file that the fusion adds: :func:`observed_count`
    less those of the ``moving`` point rows (:func:`~leap_core.pipeline.stages.fused_observation`), so the
    tasks' chunks are the local fusion's."""
    if moving is None or not moving.size:
        return observed_count(path)
    try:
        point_idx = read_npz(path, ("point_idx",))["point_idx"]
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(path, f"unreadable observation file ({exc})") from exc
    return int((~np.isin(point_idx, moving)).sum())


def merge_records(parts: Sequence[dict[str, Any]], total: int, computed: int) -> dict[str, Any]:
    """One ``stages.json`` record from the per-task records of a per-frame stage: counts (integers) add
    up, other values are the first task's; ``frames_done`` / ``frames_computed`` are the stage's."""
    out: dict[str, Any] = {}
    for part in parts:
        for key, value in part.items():
            if isinstance(value, int) and not isinstance(value, bool):
                out[key] = out.get(key, 0) + value
            else:
                out.setdefault(key, value)
    out["frames_done"] = total
    out["frames_computed"] = computed
    return out


# ------------------------------------------------------------------------------- the worker's side
class StopSignal:
    """Tells a batch of Ray tasks to stop: a file that the driver creates in a folder every worker sees
    (the run folder, the 2D cache) and that each task looks for before its next frame.

    Tasks are never cancelled through Ray: ``ray.cancel`` of a task that is just finishing races with the
    task's reply in Ray's core worker, which then aborts the whole driver process (the CLI, or the app's
    worker) with ``Check failed: it != submissible_tasks_.end()`` (ray-project/ray#54846; seen here with
    Ray 2.60 in the cancel tests). Asking the tasks to stop has no such race, and a task stops where a local
    run would: between frames, whose files are whole.
    """

    def __init__(self, folder: Path) -> None:
        self.path = Path(folder) / f".ray-stop-{uuid.uuid4().hex}"

    def set(self) -> None:
        """Ask the tasks to stop (idempotent). A folder that cannot take the file leaves the tasks to run to
        their end, which the driver then waits for (logged)."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.touch()
        except OSError as exc:
            log.warning(
                "cannot write the stop signal %s (%s): the running Ray tasks finish their frames",
                self.path,
                exc,
            )

    def is_set(self) -> bool:
        return self.path.exists()

    def clear(self) -> None:
        self.path.unlink(missing_ok=True)

    def check(self) -> None:
        """Raise :class:`~leap_core.errors.Cancelled` when the driver asked to stop (a task's frame loop)."""
        if self.is_set():
            raise Cancelled()


@dataclass(frozen=True)
class Stopped:
    """What a task returns when it stopped (or never started) because of its :class:`StopSignal`."""


@dataclass(frozen=True)
class RunJob:
    """What a worker needs to rebuild a run's context: the run's inputs, never its state."""

    dataset: Path
    schema: Schema
    config: PipelineConfig
    folder: Path
    """The sequence's folder in the run."""
    runtime: Runtime
    """The run's runtime without its Ray address (a worker computes in its own process)."""
    stop: StopSignal | None = None
    """Checked at each frame's progress report: a set signal ends the task's frame loop."""


def worker_context(job: RunJob, frames: range) -> Ctx:
    """The run context of ``job`` restricted to the frame numbers ``frames``, as a worker builds it: the
    same sequence (with the run's estimated poses when the dataset has none), no records; its progress
    reports only look at ``job.stop``, so a stopped task ends before its next frame."""
    layout = SequenceLayout(job.folder)
    seq = layout.open_sequence(job.dataset)
    stop = job.stop
    progress = None if stop is None else lambda _stage, _done, _total: stop.check()
    return Ctx(
        seq,
        job.schema,
        job.config,
        layout,
        seq.select(frames),
        job.runtime,
        progress,
        {s.name: s for s in STAGE_TABLE},
    )


class _Collect(logging.Handler):
    """Keeps the warning records logged under ``leap_core`` while a task runs."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append((record.name, record.levelno, record.getMessage()))


def _with_warnings(fn: Callable[[], Any]) -> tuple[Any, list[tuple[str, int, str]]]:
    handler = _Collect()
    logger = logging.getLogger("leap_core")
    logger.addHandler(handler)
    try:
        return fn(), handler.lines
    finally:
        logger.removeHandler(handler)


def stage_task(job: RunJob, stage: str, frames: range) -> tuple[dict[str, Any], list[tuple[str, int, str]]]:
    """A per-frame stage on a sub-range of the run's frames (a Ray task): the stage's own function on the
    worker's context, so each frame is computed and written by the code a local run uses."""

    def work() -> dict[str, Any]:
        ctx = worker_context(job, frames)
        return ctx.table[stage].run(ctx)

    result, lines = _with_warnings(work)
    return result, lines


def observations_task(job: RunJob, frames: range) -> list[Observations]:
    """Each frame's observations in voxel keys, as :func:`~leap_core.pipeline.stages.stage_fuse` feeds
    them to the fusion (a Ray task)."""
    ctx = worker_context(job, frames)
    floor = ctx.cfg.fusion.prob_floor
    return [
        Observations(keys, painted.rows, log_table(painted.table, floor))
        for painted, keys in observed_keys(ctx)
    ]


def reduce_task(num_classes: int, *parts: list[Observations]) -> Partial:
    """One fusion chunk's partial sum from its frames' observations, in frame order (a Ray task)."""
    return reduce_block((o for part in parts for o in part), num_classes)


def label_cache_task(
    dataset: Path,
    schema: Schema,
    config: PipelineConfig,
    runtime: Runtime,
    frame_ids: list[str],
    stop: StopSignal | None = None,
) -> dict[str, int]:
    """``leap labels2d``'s work on some frames (a Ray task): the model labeler ``config.labeler`` on each
    camera's image of them into the 2D cache of ``runtime.cache_dir``, its ``batch_size`` images per
    forward pass, ``stop`` checked before each batch. Returns its forward passes by model part."""
    # Imported here: the labelers' modules are only needed where this task runs.
    from leap_core.datasets.kitti import KittiSequence  # noqa: PLC0415
    from leap_core.labelers import model_labeler  # noqa: PLC0415

    seq = KittiSequence(dataset)
    labeler, batch = model_labeler(config, runtime)
    index = {fid: i for i, fid in enumerate(seq.frame_ids)}
    # Every camera's image of each frame (one for a one-camera sequence).
    frames = [v for fid in frame_ids for v in seq.frame(index[fid]).cameras() if v.has_image]
    for start in range(0, len(frames), batch):
        if stop is not None:
            stop.check()
        chunk = frames[start : start + batch]
        labeler.label_frames(chunk, schema)
        for f in chunk:
            f.__dict__.pop("image", None)  # a frame keeps its decoded image otherwise
    return labeler.forward_passes()


def predict_task(
    seq: KittiSequence,
    indices: list[int],
    checkpoint: Path,
    cfg: ConsistencyConfig,
    voxel_size: float,
    threads: int,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 3D-CN's predictions of some frames (a Ray task):
    :func:`leap_core.consistency.remote.predict_from_checkpoint`."""
    # Imported here: the 3D-CN needs torch, which only the processes that run it load.
    from leap_core.consistency.remote import predict_from_checkpoint  # noqa: PLC0415

    return predict_from_checkpoint(seq, indices, checkpoint, cfg, voxel_size, threads)


@dataclass(frozen=True)
class TaskError:
    """A :class:`LeapError` raised in a task, carried back as data. Ray would pickle the exception, and
    unpickling calls its class with its ``args``: that fails for the subclasses whose constructors take
    other arguments (``DatasetError(path, problem)``), and the driver would get Ray's wrapper instead of
    the one-line error naming the file (and the app could not tell a :class:`ModelLoadError`)."""

    module: str
    qualname: str
    args: tuple[Any, ...]
    state: dict[str, Any]
    traceback: str

    @classmethod
    def of(cls, exc: BaseException) -> TaskError:
        kind = type(exc)
        return cls(
            kind.__module__,
            kind.__qualname__,
            exc.args,
            dict(vars(exc)),
            "".join(traceback.format_exception(exc)),
        )

    def rebuild(self) -> BaseException:
        """The same exception: same class, ``args`` (its message) and attributes (``path``, ``field``)."""
        kind = getattr(importlib.import_module(self.module), self.qualname)
        exc: BaseException = kind.__new__(kind)
        exc.args = self.args
        vars(exc).update(self.state)
        return exc


def run_task(stop: StopSignal | None, fn: Callable[..., Any], *args: Any) -> Any:
    """What every Ray task runs: ``fn(*args)``, a :class:`LeapError` returned as a :class:`TaskError`
    (and a :class:`TaskError` or :class:`Stopped` among the arguments, an upstream task's, passed on instead
    of calling). :class:`Stopped` without calling when ``stop`` is set, or when ``fn`` raised
    :class:`~leap_core.errors.Cancelled` (its frame loop saw ``stop``)."""
    for arg in args:
        if isinstance(arg, (TaskError, Stopped)):
            return arg
    if stop is not None and stop.is_set():
        return Stopped()
    try:
        return fn(*args)
    except Cancelled:
        return Stopped()
    except LeapError as exc:
        return TaskError.of(exc)


# --------------------------------------------------------------------------------------- the driver
def connect(address: str, cpus: int | None) -> ModuleType:
    """Import ray and join the cluster at ``address`` (``"auto"``: the one this machine belongs to, else a
    new local instance of ``cpus`` CPUs, by default the cores this process may use), once per process: a
    process already connected (the app's worker between runs, a test's fixture) keeps its connection.
    No dashboard, Ray's own logging at ERROR and workers' output not copied here (warnings of the
    stage code come back with the results)."""
    try:
        import ray  # noqa: PLC0415  imported only by a run that asks for Ray (the local engine never does)
    except ModuleNotFoundError as exc:  # the ray extra
        raise MissingExtra("ray", exc.name) from None
    if ray.is_initialized():
        return ray
    common: dict[str, Any] = {
        "include_dashboard": False,
        "logging_level": logging.ERROR,
        "log_to_driver": False,
        "configure_logging": True,
    }
    target = _cluster_address(address)
    # ray.init retries an address nobody answers at for minutes (a cluster stopped without `ray stop`
    # leaves its address behind for "auto"), so the address is first tried with a short connect.
    if target is not None and _answers(target):
        try:
            ray.init(address=target, **common)
            return ray
        except ConnectionError as exc:
            if address != "auto":
                raise LeapError(f"ray_address {address!r}: cannot join the Ray cluster ({exc})") from None
    elif address != "auto":
        raise LeapError(f"ray_address {address!r}: no Ray cluster answers at {target or address}")
    n = cpus if cpus is not None else len(os.sched_getaffinity(0))
    log.info("no running Ray cluster found; starting a local Ray instance of %d CPUs", n)
    ray.init(address="local", num_cpus=n, object_store_memory=LOCAL_OBJECT_STORE_BYTES, **common)
    return ray


def _cluster_address(address: str) -> str | None:
    """The ``host:port`` (or ``ray://host:port``) that ``address`` names; for ``"auto"`` the cluster Ray
    finds for this machine (``ray start``'s address file, a running GCS), None when there is none."""
    if address != "auto":
        return address
    try:
        from ray._private.services import canonicalize_bootstrap_address  # noqa: PLC0415  (see below)
    except ImportError:  # a Ray without this helper: let ray.init resolve "auto" itself
        return address
    # Ray's own resolution of "auto" (private: there is no public way to ask without connecting).
    try:
        return canonicalize_bootstrap_address("auto")
    except (ConnectionError, ValueError):
        return None


def _answers(address: str, timeout_s: float = 3.0) -> bool:
    """Whether something accepts a TCP connection at ``address`` (``[ray://]host:port``); True for an
    address that is not of that form (ray.init then judges it)."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit():
        return True
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return True
    except OSError:
        return False


class RayExecutor:
    """Per-frame stages and fusion as Ray tasks (module docstring); other stages in this process."""

    name = "ray"

    def __init__(self, address: str, cpus: int | None = None) -> None:
        self.ray = connect(address, cpus)
        self._task = self.ray.remote(run_task)

    # ----------------------------------------------------------------------------------- dispatch
    def run_stage(self, ctx: Ctx, stage: StageInfo) -> dict[str, Any]:
        if stage.frame_files is not None:
            return self._per_frame(ctx, stage)
        if stage.name == "fuse":
            return self._fuse(ctx)
        return stage.run(ctx)

    def predictor(self, cfg: PipelineConfig) -> RayPredictor:
        """The 3D-CN's inference as Ray tasks (:class:`RayPredictor`)."""
        return RayPredictor(self, cfg)

    def _job(self, ctx: Ctx, stop: StopSignal) -> RunJob:
        return RunJob(
            ctx.seq.root,
            ctx.schema,
            ctx.cfg,
            ctx.layout.folder,
            # A task holds one Ray CPU: it computes its frames one at a time.
            dataclasses.replace(ctx.runtime or Runtime(), ray_address=None, frame_threads=1),
            stop,
        )

    def _cpus(self) -> int:
        return max(1, int(self.ray.cluster_resources().get("CPU", 1)))

    def _gpu_options(self, ctx: Ctx, stage: StageInfo) -> dict[str, Any]:
        # Only a labeler that runs models on camera images uses a GPU; a task that asks for one waits for
        # a free GPU, so nothing else may ask.
        runtime = ctx.runtime or Runtime()
        if (
            stage.name == "labels2d"
            and LABELERS[ctx.cfg.labeler].needs == "images"
            and runtime.device != "cpu"
            and self.ray.cluster_resources().get("GPU", 0) >= 1
        ):
            return {"num_gpus": 1}
        return {}

    def _get(self, ref: Any) -> Any:
        """``ray.get`` that raises a task's own error (a :class:`LeapError` names its file in one line)."""
        try:
            result = self.ray.get(ref)
        except self.ray.exceptions.RayTaskError as exc:
            cause = exc.cause
            if isinstance(cause, BaseException):
                raise cause from None
            raise
        if isinstance(result, TaskError):
            log.debug("task failed:\n%s", result.traceback)
            raise result.rebuild() from None
        if isinstance(result, Stopped):  # only after a stop of this batch, whose results are not read
            raise Cancelled()
        return result

    def _stop(self, refs: Sequence[Any], stop: StopSignal) -> None:
        """Ask the unfinished tasks to stop and wait (up to :data:`STOP_WAIT_S`) until they have returned,
        so none still writes into the run folder after the stage returned (never ``ray.cancel``: see
        :class:`StopSignal`)."""
        stop.set()
        running: Sequence[Any] = ()
        if refs:
            _, running = self.ray.wait(list(refs), num_returns=len(refs), timeout=STOP_WAIT_S)
        if running:  # the signal stays, so that these stop too when they reach their next frame
            log.warning(
                "%d Ray task(s) still running %.0f s after the stop; they end at their next frame",
                len(running),
                STOP_WAIT_S,
            )
        else:
            stop.clear()

    def _drain(self, pending: dict[Any, int], finished: Callable[[Any, int], None], stop: StopSignal) -> None:
        """``finished(result, weight)`` for each task of ``pending`` (ref → weight) as it ends, in the order
        they end; an error (a task's, or ``Cancelled`` from ``finished``) stops the others first."""
        try:
            while pending:
                ready, _ = self.ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    n = pending.pop(ref)
                    finished(self._get(ref), n)
        except BaseException:
            self._stop(list(pending), stop)
            raise

    # ----------------------------------------------------------------------------- per-frame stages
    def _per_frame(self, ctx: Ctx, stage: StageInfo) -> dict[str, Any]:
        todo = ctx.missing_frames(stage.name)
        if not todo:
            return stage.run(ctx)  # nothing to compute: the stage's own (cheap) record
        total = len(ctx.frames)
        options = self._gpu_options(ctx, stage)
        # Tasks that each take a GPU run one per GPU: as many sub-ranges as for the CPUs would only load
        # the models more often.
        slots = int(self.ray.cluster_resources().get("GPU", 1)) if options else self._cpus()
        size = math.ceil(len(todo) / (TASKS_PER_CPU * slots))
        stop = StopSignal(ctx.layout.folder)
        job = self._job(ctx, stop)
        task = self._task.options(**options)
        pending = {
            task.remote(stop, stage_task, job, stage.name, number_range(ctx, block)): len(block)
            for block in frame_blocks(todo, size)
        }
        done = total - len(todo)
        parts: list[dict[str, Any]] = []
        ctx.tick(stage.name, done, total)

        def finished(result: tuple[dict[str, Any], list[tuple[str, int, str]]], n: int) -> None:
            nonlocal done
            record, lines = result
            for name, level, message in lines:
                logging.getLogger(name).log(level, "%s", message)
            parts.append(record)
            done += n
            ctx.tick(stage.name, done, total)

        self._drain(pending, finished, stop)
        record = merge_records(parts, total, len(todo))
        record["ray_tasks"] = len(parts)
        if options:
            record["ray_gpus_per_task"] = options["num_gpus"]
        return record

    # ---------------------------------------------------------------------------- leap labels2d
    def label_cache(
        self,
        dataset: Path,
        schema: Schema,
        config: PipelineConfig,
        runtime: Runtime,
        frame_ids: Sequence[str],
        progress: Callable[[int], None] | None = None,
    ) -> dict[str, int]:
        """:func:`label_cache_task` over ``frame_ids`` cut into runs of whole batches, one GPU per task when
        the cluster has GPUs (and ``runtime.device`` is not ``cpu``); ``progress(frames)`` as each ends.
        Returns the forward passes of all tasks by model part.

        Raises:
            ValueError: ``runtime.cache_dir`` is not set (the cache is where the tasks write).
        """
        if runtime.cache_dir is None:
            raise ValueError("label_cache needs runtime.cache_dir: the 2D cache the tasks fill")
        stop = StopSignal(runtime.cache_dir)
        gpus = self.ray.cluster_resources().get("GPU", 0) >= 1 and runtime.device != "cpu"
        slots = int(self.ray.cluster_resources().get("GPU", 1)) if gpus else self._cpus()
        batch = LABELERS[config.labeler].config_of(config).batch_size
        per_task = math.ceil(len(frame_ids) / (TASKS_PER_CPU * slots) / batch) * batch
        task = self._task.options(num_gpus=1 if gpus else 0)
        worker_runtime = dataclasses.replace(runtime, ray_address=None, frame_threads=1)
        pending = {
            task.remote(
                stop,
                label_cache_task,
                dataset,
                schema,
                config,
                worker_runtime,
                list(frame_ids[s : s + per_task]),
                stop,
            ): len(frame_ids[s : s + per_task])
            for s in range(0, len(frame_ids), max(per_task, 1))
        }
        calls: dict[str, int] = {}

        def finished(result: dict[str, int], n: int) -> None:
            for part, count in result.items():
                calls[part] = calls.get(part, 0) + count
            if progress is not None:
                progress(n)

        self._drain(pending, finished, stop)
        return calls

    # ---------------------------------------------------------------------------------------- fusion
    def _fuse(self, ctx: Ctx) -> dict[str, Any]:
        frames = list(ctx.frames)
        total = len(frames)
        movers = read_motion(ctx)
        counts = [
            fused_count(
                ctx.layout.observation(ctx.fid(i)), None if movers is None else movers.scan(ctx.fid(i)).rows
            )
            for i in frames
        ]
        chunks = fusion_blocks(counts, ctx.cfg.fusion.chunk_points)
        size = max(1, math.ceil(total / (TASKS_PER_CPU * self._cpus())))
        stop = StopSignal(ctx.layout.folder)
        job = self._job(ctx, stop)
        c = ctx.schema.num_classes
        partials: list[tuple[Any, int]] = []
        refs: list[Any] = []
        for chunk in chunks:
            # A chunk spans consecutive frames (the empty ones between its members add nothing).
            span = frames[chunk[0] : chunk[-1] + 1]
            blocks = frame_blocks(span, size)
            parts = [
                self._task.remote(stop, observations_task, job, number_range(ctx, block)) for block in blocks
            ]
            partials.append((self._task.remote(stop, reduce_task, c, *parts), chunk[-1] + 1))
            refs += [*parts, partials[-1][0]]
        ctx.tick("fuse", 0, total)

        def in_order() -> Iterator[Partial]:
            for ref, reached in partials:
                partial = self._get(ref)
                ctx.tick("fuse", reached, total)
                yield partial

        try:
            grid = fold_blocks(in_order(), c, ctx.cfg.fusion)
        except BaseException:
            self._stop(refs, stop)
            raise
        record = finish_fuse(ctx, grid)
        record["ray_tasks"] = len(refs)
        record["fusion_chunks"] = len(chunks)
        return record


class RayPredictor:
    """``predict(seq, frames, checkpoint)`` of a 3D-CN round as Ray tasks
    (:data:`leap_core.consistency.stage.Predict`).

    ``frames`` is cut into blocks of consecutive frames (about :data:`TASKS_PER_CPU` per task slot, at
    most :data:`INFER_TASK_FRAMES` each); each task loads the checkpoint once and predicts its block
    (:func:`predict_task`) with this process's torch thread count (the local rule,
    :func:`leap_core.consistency.remote.inference_threads`), asking for that many CPUs (or one GPU where
    the cluster has GPUs and ``consistency.device`` is not ``cpu``). The frames come back in frame order,
    whatever order the tasks end in, and at most ``2 × slots`` tasks are ahead of the one being read, so
    the object store holds a bounded number of frames' predictions.
    """

    def __init__(self, executor: RayExecutor, cfg: PipelineConfig) -> None:
        self.executor = executor
        self.cfg = cfg.consistency
        self.voxel_size = cfg.fusion.voxel_size
        self.tasks = 0
        """Inference tasks whose results came back (what a run's ``3dcn`` record calls ``ray_tasks``)."""
        self.gpus = 0
        """GPUs each inference task asked for (0 or 1)."""

    def __call__(self, seq: KittiSequence, frames: range, checkpoint: Path) -> Iterator[tuple[Any, Any]]:
        from leap_core.consistency.remote import inference_threads  # noqa: PLC0415  loads torch

        ex = self.executor
        ray = ex.ray
        threads = inference_threads(self.cfg)
        resources = ray.cluster_resources()
        if self.cfg.device != "cpu" and resources.get("GPU", 0) >= 1:
            options: dict[str, Any] = {"num_gpus": 1}
            slots = int(resources["GPU"])
            self.gpus = 1
        else:
            cpus = min(threads, ex._cpus())
            options = {"num_cpus": cpus}
            slots = max(1, ex._cpus() // cpus)
        size = min(INFER_TASK_FRAMES, max(1, math.ceil(len(frames) / (TASKS_PER_CPU * slots))))
        blocks = iter(frame_blocks(list(frames), size))
        task = ex._task.options(**options)
        stop = StopSignal(Path(checkpoint).parent)
        seq_ref = ray.put(seq)
        pending: deque[Any] = deque()

        def submit() -> None:
            block = next(blocks, None)
            if block is not None:
                pending.append(
                    task.remote(
                        stop,
                        predict_task,
                        seq_ref,
                        block,
                        Path(checkpoint),
                        self.cfg,
                        self.voxel_size,
                        threads,
                    )
                )

        try:
            for _ in range(2 * slots + 1):
                submit()
            while pending:
                result = ex._get(pending.popleft())
                self.tasks += 1
                submit()
                yield from result
                del result
        except BaseException:  # an error, a Cancelled from progress, or the consumer closing the generator
            ex._stop(list(pending), stop)
            raise


__all__ = [
    "INFER_TASK_FRAMES",
    "STOP_WAIT_S",
    "TASKS_PER_CPU",
    "Executor",
    "LocalExecutor",
    "RayExecutor",
    "RayPredictor",
    "RunJob",
    "StopSignal",
    "Stopped",
    "TaskError",
    "connect",
    "frame_blocks",
    "label_cache_task",
    "make_executor",
    "merge_records",
    "number_range",
    "observed_count",
    "predict_task",
    "run_task",
    "worker_context",
]
