"""The Ray engine (``Runtime.ray_address``, :mod:`leap_core.pipeline.executor`) writes the same bytes as the
local engine: every exported ``.label`` / ``.conf``, every per-frame file and the grids, also after a run
cancelled mid-stage on Ray is resumed there; a run without Ray never imports ray. (That fusion's blocks fold
to exactly :func:`fuse`'s grid is tested in tests/test_fusion.py, with the fusion tests.)

The Ray tests share one local Ray instance of 2 CPUs (module fixture, shut down at the end)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from runhelpers import folder, label
from typer.testing import CliRunner

from leap_core.config import PipelineConfig
from leap_core.errors import Cancelled
from leap_core.pipeline import run_pipeline, stage_status
from leap_core.pipeline.executor import (
    RunJob,
    Stopped,
    StopSignal,
    frame_blocks,
    merge_records,
    run_task,
    stage_task,
    worker_context,
)
from leap_core.presets import builtin_preset
from leap_core.run_layout import RunLayout
from leap_core.runtime import Runtime
from leap_core.synth import CameraConfig, LidarConfig, SynthConfig, generate_sequence

ROOT = Path(__file__).resolve().parents[1]
SMALL = SynthConfig(
    frames=10, seed=0, lidar=LidarConfig(beams=16, azimuth_step_deg=1.0), camera=CameraConfig().scaled(0.5)
)
"""The demo street (seed 0), coarse LiDAR, half-size camera: about 400-700 observed points per frame."""
FRAMES = range(0, 8)
RAY = Runtime(ray_address="auto")


def test_frame_blocks_and_records() -> None:
    assert frame_blocks([0, 1, 2, 5, 6, 7, 8], 3) == [[0, 1, 2], [5, 6, 7], [8]]
    assert frame_blocks([], 2) == []
    parts = [
        {"frames_done": 3, "frames_computed": 3, "cache_hits": 1, "labeler": "simulated"},
        {"frames_done": 2, "frames_computed": 2, "cache_hits": 2, "labeler": "simulated"},
    ]
    rec = merge_records(parts, 8, 5)
    assert rec == {"frames_done": 8, "frames_computed": 5, "cache_hits": 3, "labeler": "simulated"}


def test_a_local_run_never_imports_ray(tmp_path: Path) -> None:
    code = (
        "import sys\n"
        "from pathlib import Path\n"
        "from leap_core.pipeline import SequenceSpec, run_pipeline\n"
        "from leap_core.presets import builtin_preset\n"
        "from leap_core.synth import CameraConfig, LidarConfig, SynthConfig, generate_sequence\n"
        f"seq = generate_sequence(Path({str(tmp_path)!r}), SynthConfig(frames=2, seed=0, "
        "lidar=LidarConfig(beams=8, azimuth_step_deg=2.0), camera=CameraConfig().scaled(0.25))).path\n"
        "p = builtin_preset('demo')\n"
        f"r = run_pipeline([SequenceSpec.of(seq)], p.schema, p.pipeline, Path({str(tmp_path / 'run')!r}))\n"
        "assert r.only().export_dir.is_dir() and r.only().folder.parent.parent == r.root\n"
        "print('ray' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip().splitlines()[-1] == "False"


def test_an_address_nobody_answers_at_is_a_one_line_error_at_once() -> None:
    """ray.init would retry such an address for minutes (the subprocess's timeout fails the test then);
    the engine tries it first. A fresh process: no Ray instance is running there."""
    code = (
        "from leap_core.errors import LeapError\n"
        "from leap_core.pipeline.executor import connect\n"
        "try:\n"
        "    connect('127.0.0.1:1', None)\n"
        "except LeapError as exc:\n"
        "    print(exc)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True, timeout=120
    )
    assert out.stdout.splitlines() == ["ray_address '127.0.0.1:1': no Ray cluster answers at 127.0.0.1:1"]


# ------------------------------------------------------------------------------------------ Ray runs
@pytest.fixture(scope="module")
def ray_instance():
    import ray  # only these tests start Ray

    # address="local": a new instance of 2 CPUs even where a cluster runs (ray.init would join it).
    # One logical GPU (this machine has none): tasks that ask for a GPU can be scheduled, and run on the CPU.
    ray.init(
        address="local",
        num_cpus=2,
        num_gpus=1,
        include_dashboard=False,
        object_store_memory=256 * 1024 * 1024,
        logging_level="ERROR",
        log_to_driver=False,
    )
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_sequence(tmp_path_factory.mktemp("demo"), SMALL).path


@pytest.fixture(scope="module")
def preset_config() -> tuple[Any, PipelineConfig]:
    p = builtin_preset("demo")
    # Small fusion chunks, so that the 8 frames fuse in several blocks (checked below).
    cfg = dataclasses.replace(p.pipeline, fusion=dataclasses.replace(p.pipeline.fusion, chunk_points=900))
    return p.schema, cfg


@pytest.fixture(scope="module")
def local_run(dataset: Path, preset_config, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The local run's sequence folder."""
    schema, cfg = preset_config
    return label(dataset, schema, cfg, tmp_path_factory.mktemp("local") / "run", frames=FRAMES).folder


OUTPUT_FOLDERS = ("labels2d", "observations", "points", "export")
OUTPUT_FILES = ("grid.npz", "grid_smooth.npz", "metrics.json")


def _outputs(run_dir: Path) -> dict[str, bytes]:
    """The outputs of a run's sequence folder ``run_dir``."""
    out = {
        f"{sub}/{p.name}": p.read_bytes() for sub in OUTPUT_FOLDERS for p in sorted((run_dir / sub).iterdir())
    }
    out.update({name: (run_dir / name).read_bytes() for name in OUTPUT_FILES})
    return out


def _same_outputs(run_dir: Path, local_run: Path) -> None:
    ray_out, local_out = _outputs(run_dir), _outputs(local_run)
    assert sorted(ray_out) == sorted(local_out)
    assert len([n for n in local_out if n.endswith(".label")]) == len(FRAMES)
    differ = [name for name in local_out if ray_out[name] != local_out[name]]
    assert differ == []


@pytest.mark.slow
def test_ray_run_writes_the_local_bytes(
    ray_instance, dataset: Path, preset_config, local_run: Path, tmp_path: Path
) -> None:
    schema, cfg = preset_config
    calls: list[tuple[str, int, int]] = []
    result = label(
        dataset,
        schema,
        cfg,
        tmp_path / "run",
        frames=FRAMES,
        runtime=RAY,
        progress=lambda *a: calls.append(a),
    )
    _same_outputs(result.folder, local_run)
    records = stage_status(result.folder)
    for stage in ("labels2d", "project", "label_points", "export"):
        assert records[stage]["ray_tasks"] >= 2, stage  # really cut into sub-ranges on Ray
        assert records[stage]["frames_computed"] == len(FRAMES)
        assert result.stages[stage].frames_computed == len(FRAMES)
    assert records["labels2d"]["labeler"] == "simulated"
    assert records["fuse"]["fusion_chunks"] >= 3
    assert ("project", len(FRAMES), len(FRAMES)) in calls
    # The partial grids are folded in chunk order (each tick is a chunk's last frame): on this small data
    # a wrong order happens not to change the float16 grid, so the order is checked here and in
    # test_fold_order_matters_and_is_kept.
    fuse_ticks = [done for stage, done, _ in calls if stage == "fuse"]
    assert fuse_ticks == sorted(fuse_ticks)
    assert len(set(fuse_ticks)) == records["fuse"]["fusion_chunks"] + 1
    assert fuse_ticks[-1] == len(FRAMES)


@pytest.mark.slow
def test_movers_kept_out_of_the_fusion_give_the_local_bytes_on_ray(
    ray_instance, dataset: Path, preset_config, tmp_path: Path
) -> None:
    """With ``tracking.exclude_moving`` the fusion's chunks count the observations left after the movers
    (``executor.fused_count``), so the tasks' partial sums are the local fusion's."""
    schema, cfg = preset_config
    cfg = dataclasses.replace(cfg, tracking=dataclasses.replace(cfg.tracking, exclude_moving=True))
    local = label(dataset, schema, cfg, tmp_path / "local", frames=FRAMES).folder
    assert stage_status(local)["motion"]["moving_points"] > 0
    on_ray = label(dataset, schema, cfg, tmp_path / "ray", frames=FRAMES, runtime=RAY).folder
    _same_outputs(on_ray, local)
    assert stage_status(on_ray)["fuse"]["fusion_chunks"] >= 3


@pytest.mark.slow
def test_cancel_on_ray_then_resume_gives_the_local_bytes(
    ray_instance,
    dataset: Path,
    preset_config,
    local_run: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    schema, cfg = preset_config
    run_dir = folder(tmp_path / "run", dataset.name)

    def no_ray_cancel(*_args: Any, **_kwargs: Any) -> None:
        raise AssertionError("ray.cancel races with a finishing task and can abort the driver (StopSignal)")

    monkeypatch.setattr(ray_instance, "cancel", no_ray_cancel)

    def cancel_mid_project(stage: str, done: int, total: int) -> None:
        if stage == "project" and 0 < done < total:
            raise Cancelled()

    with pytest.raises(Cancelled):
        label(dataset, schema, cfg, tmp_path / "run", frames=FRAMES, runtime=RAY, progress=cancel_mid_project)
    assert stage_status(run_dir)["project"]["status"] == "cancelled"
    kept = len(list((run_dir / "observations").glob("*.npz")))
    # Ray tasks already running when the cancel comes finish their frames, and on a busy machine that can
    # be every frame (the CI run of 2026-11-27: 8 of 8); their files are kept, which is what resuming uses.
    # A partial stage is resumed deterministically by test_pipeline's local cancel test.
    assert 0 < kept <= len(FRAMES)
    assert not list(run_dir.glob(".ray-stop-*"))  # every task returned, so the stop signal was cleared
    result = label(dataset, schema, cfg, tmp_path / "run", frames=FRAMES, runtime=RAY)
    assert not result.stages["labels2d"].ran
    computed = result.stages["project"].frames_computed
    assert len(FRAMES) - kept <= computed < len(FRAMES)  # resumed: the kept frames were not recomputed
    _same_outputs(run_dir, local_run)


@pytest.mark.slow
def test_a_stopped_task_computes_no_frame(dataset: Path, preset_config, tmp_path: Path) -> None:
    """The worker's side of a stop, without Ray: a task whose signal is set returns ``Stopped`` without
    calling its function; a stage task's frame loop looks at the signal before every frame."""
    schema, cfg = preset_config
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    stop = StopSignal(run_dir)
    job = RunJob(dataset, schema, cfg, run_dir, Runtime(), stop)
    record, _ = run_task(stop, stage_task, job, "labels2d", range(0, 2))
    assert record["frames_computed"] == 2

    stop.set()
    calls: list[int] = []
    assert run_task(stop, calls.append, 1) == Stopped()
    assert run_task(None, calls.append, Stopped()) == Stopped()  # an upstream task's stop is passed on
    assert calls == []
    with pytest.raises(Cancelled):  # the frame loop's own look, before its first frame
        stage_task(job, "labels2d", range(2, 4))
    assert worker_context(job, range(0, 4)).missing_frames("labels2d") == [2, 3]
    stop.clear()
    assert not stop.is_set() and not list(run_dir.glob(".ray-stop-*"))
    later = StopSignal(tmp_path / "cache-not-made-yet")  # leap labels2d's cache folder may not exist yet
    later.set()
    assert later.is_set()


@pytest.mark.slow
def test_cli_run_with_ray(ray_instance, dataset: Path, tmp_path: Path) -> None:
    from app.cli import cli

    runner = CliRunner()
    outs = {}
    for name, extra in (("local", []), ("ray", ["--ray", "auto"])):
        res = runner.invoke(
            cli,
            [
                "run",
                str(dataset),
                "--schema",
                "demo",
                "--labeler",
                "simulated",
                "--out",
                str(tmp_path / name),
                "--frames",
                "2:6",
                *extra,
            ],
        )
        assert res.exit_code == 0, res.output
        seq_dir = folder(tmp_path / name, dataset.name)
        outs[name] = {p.name: p.read_bytes() for p in sorted((seq_dir / "export").iterdir())}
    assert len(outs["ray"]) == 8
    assert outs["ray"] == outs["local"]
    state = json.loads((folder(tmp_path / "ray", dataset.name) / "stages.json").read_text())
    assert "ray_tasks" in state["project"]


@pytest.mark.slow
def test_app_setting_sends_the_worker_run_to_ray(
    ray_instance,
    dataset: Path,
    preset_config,
    local_run: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``LEAP_RAY_ADDRESS`` → ``Settings.ray_address`` → the worker's ``RunSpec`` → its ``Runtime``."""
    from app.core.config import Settings
    from app.jobs.manager import JobManager
    from app.jobs.messages import decode_to_worker
    from app.jobs.worker import execute
    from app.rows import RunParams, RunRow, RunSequence
    from leap_core.config import config_to_dict

    schema, cfg = preset_config
    monkeypatch.setenv("LEAP_RAY_ADDRESS", "auto")
    settings = Settings(work_dir=tmp_path / "work")
    assert settings.ray_address == "auto"
    params = RunParams(
        sequences=(RunSequence(dataset.name, dataset, (FRAMES.start, FRAMES.stop)),),
        dataset_kind="folder",
        schema=schema.to_dict(),
        pipeline=config_to_dict(cfg),
    )
    run = RunRow(1, 1, 1, "queued", params, tmp_path / "run", created_at="now")
    spec = decode_to_worker(JobManager(settings)._spec(run).to_line())
    assert spec.ray_address == "auto"
    outcome = execute(spec, emit=lambda _message: None, should_cancel=lambda: False)
    assert outcome.status == "done", outcome
    seq_dir = folder(tmp_path / "run", dataset.name)
    assert stage_status(seq_dir)["export"]["ray_tasks"] >= 2
    _same_outputs(seq_dir, local_run)


@pytest.mark.slow
def test_labels2d_command_on_ray_fills_the_cache_as_locally(ray_instance, tmp_path: Path) -> None:
    """``leap labels2d --ray auto`` (tiny random-weight models, CPU): the same cache files, byte for byte,
    as without Ray; tasks hold whole batches, so the model sees the same batches."""
    from conftest import build_tiny_sequence

    from app.cli import cli
    from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
    from leap_core.schema import ClassDef, Schema, save_schema

    root = build_tiny_sequence(tmp_path, n_frames=4).root
    models = make_tiny_models(tmp_path / "models", TinyModelsConfig(num_queries=12)).models_dir
    schema = Schema(
        "small",
        (ClassDef("car", (255, 0, 0), ("car",), 10), ClassDef("road", (0, 0, 255), ("road", "street"), 40)),
    )
    project = tmp_path / "small.yaml"
    save_schema(schema, project, pipeline={"grounded_sam": {"box_threshold": 0.05}})
    runner = CliRunner()
    caches = {}
    for name, extra in (("local", []), ("ray", ["--ray", "auto"])):
        cache = tmp_path / f"cache-{name}"
        res = runner.invoke(
            cli,
            [
                "labels2d",
                str(root),
                "--schema",
                str(project),
                "--models",
                str(models),
                "--cache",
                str(cache),
                "--batch-size",
                "2",
                "--device",
                "cpu",
                *extra,
            ],
        )
        assert res.exit_code == 0, res.output
        assert "done: 4 frames labeled" in res.output
        caches[name] = {p.relative_to(cache).as_posix(): p.read_bytes() for p in sorted(cache.rglob("*.npz"))}
    assert "(Ray tasks)" in res.output
    assert len(caches["ray"]) == 4
    assert caches["ray"] == caches["local"]


@pytest.mark.slow
def test_an_error_in_a_task_is_the_stage_error(
    ray_instance, dataset: Path, preset_config, tmp_path: Path
) -> None:
    """A task's LeapError reaches the caller as itself (one line naming the file), not as Ray's wrapper."""
    from leap_core.errors import DatasetError

    schema, cfg = preset_config
    copy = tmp_path / "seq"
    copy.mkdir()
    for name in ("velodyne", "image_2", "calib.txt", "poses.txt", "times.txt"):
        (copy / name).symlink_to(dataset / name)
    with pytest.raises(DatasetError) as err:
        label(copy, schema, cfg, tmp_path / "run", frames=FRAMES, runtime=RAY)
    assert type(err.value) is DatasetError
    assert "gt2d" in str(err.value) and "\n" not in str(err.value)
    assert stage_status(folder(tmp_path / "run", "seq"))["labels2d"]["status"] == "failed"


@pytest.mark.slow
def test_model_2d_labels_ask_for_a_gpu_per_task(ray_instance, tmp_path: Path) -> None:
    """grounded-sam's labels2d stage on a cluster with a (logical) GPU: each task asks for one, unless the
    runtime's device is the CPU; the soft masks are the local run's."""
    from conftest import build_tiny_sequence

    from leap_core.config import config_from_dict
    from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
    from leap_core.schema import ClassDef, Schema

    root = build_tiny_sequence(tmp_path, n_frames=3).root
    models = make_tiny_models(tmp_path / "models", TinyModelsConfig(num_queries=12)).models_dir
    schema = Schema(
        "small",
        (ClassDef("car", (255, 0, 0), ("car",), 10), ClassDef("road", (0, 0, 255), ("road", "street"), 40)),
    )
    cfg = config_from_dict({"labeler": "grounded-sam", "grounded_sam": {"box_threshold": 0.05}})
    runs = {}
    for name, runtime in (
        ("local", Runtime(models_dir=models, device="cpu")),
        ("gpu", Runtime(models_dir=models, ray_address="auto")),
        ("cpu", Runtime(models_dir=models, device="cpu", ray_address="auto")),
    ):
        seq_dir = label(root, schema, cfg, tmp_path / name, runtime=runtime, until="labels2d").folder
        runs[name] = {p.name: p.read_bytes() for p in sorted((seq_dir / "labels2d").iterdir())}
    assert stage_status(folder(tmp_path / "gpu"))["labels2d"]["ray_gpus_per_task"] == 1
    assert "ray_gpus_per_task" not in stage_status(folder(tmp_path / "cpu"))["labels2d"]
    assert len(runs["gpu"]) == 3
    assert runs["gpu"] == runs["local"] == runs["cpu"]


# ------------------------------------------------------------------------- 3D-CN inference, sequences
TINY_3DCN = {
    "enabled": True,
    "iterations": 2,
    "points_per_scan": 1024,
    "num_threads": 1,
    "min_steps": 0,
    "device": "cpu",
    "backbone": {"channels": 8, "layers": 1, "knn": 4},
}
"""A 3D-CN that trains in seconds; one torch thread, so two inference tasks share the 2 CPUs."""
CN_FILES = ("grid_3dcn1.npz", "grid_smooth_3dcn1.npz", "grid_3dcn2.npz", "grid_smooth_3dcn2.npz")


def _with_3dcn(cfg: PipelineConfig, **over: Any) -> PipelineConfig:
    from leap_core.config import config_from_dict, config_to_dict

    data = config_to_dict(cfg)
    data["consistency"] = {**TINY_3DCN, **over}
    return config_from_dict(data)


@pytest.fixture(scope="module")
def local_3dcn_run(dataset: Path, preset_config, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The local run's sequence folder (its run folder holds the 3D-CN's checkpoints)."""
    schema, cfg = preset_config
    out = tmp_path_factory.mktemp("local3dcn") / "run"
    return label(dataset, schema, _with_3dcn(cfg), out, frames=FRAMES).folder


def _joint_record(run_dir: Path) -> dict[str, Any]:
    """The 3D-CN rounds' record of the run whose sequence folder is ``run_dir``."""
    return dict(json.loads(RunLayout(run_dir.parent.parent).joint_state.read_text()))


@pytest.mark.slow
def test_3dcn_inference_runs_as_ray_tasks_with_the_local_bytes(
    ray_instance, dataset: Path, preset_config, local_3dcn_run: Path, tmp_path: Path
) -> None:
    schema, cfg = preset_config
    calls: list[tuple[str, int, int]] = []
    run_dir = label(
        dataset,
        schema,
        _with_3dcn(cfg),
        tmp_path / "run",
        frames=FRAMES,
        runtime=RAY,
        progress=lambda *a: calls.append(a),
    ).folder
    ray_out, local_out = _outputs(run_dir), _outputs(local_3dcn_run)
    for name in CN_FILES:
        ray_out[name], local_out[name] = (run_dir / name).read_bytes(), (local_3dcn_run / name).read_bytes()
    assert sorted(ray_out) == sorted(local_out)
    assert [name for name in local_out if ray_out[name] != local_out[name]] == []
    # Counted as results come back from Ray: a silent fallback to the driver's own loop leaves it out.
    # The rounds' own record, in the run's 3dcn/ (the sequence's 3dcn stage only links their grids).
    record = _joint_record(run_dir)
    assert record["ray_tasks"] >= 2 * 2  # two rounds, each cut into several tasks
    assert "ray_gpus_per_task" not in record  # consistency.device "cpu"
    assert "ray_tasks" not in stage_status(run_dir)["3dcn"] and "ray_tasks" not in _joint_record(
        local_3dcn_run
    )
    assert ("3dcn", 2000, 2000) in calls


@pytest.mark.slow
def test_3dcn_inference_asks_for_a_gpu_per_task(
    ray_instance, dataset: Path, preset_config, local_3dcn_run: Path, tmp_path: Path
) -> None:
    """consistency.device "auto" on a cluster with a (logical) GPU: each inference task asks for one (and
    computes on the CPU here, torch seeing no CUDA device): the local bytes."""
    schema, cfg = preset_config
    out = tmp_path / "run"
    run_dir = label(dataset, schema, _with_3dcn(cfg, device="auto"), out, frames=FRAMES, runtime=RAY).folder
    record = _joint_record(run_dir)
    assert record["ray_gpus_per_task"] == 1 and record["ray_tasks"] >= 2
    for name in CN_FILES:
        assert (run_dir / name).read_bytes() == (local_3dcn_run / name).read_bytes(), name


@pytest.mark.slow
def test_ray_predictions_come_back_in_frame_order(
    ray_instance, dataset: Path, preset_config, local_3dcn_run: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The predictor yields exactly the local loop's (keys, log-probabilities), frame after frame, when
    every frame is its own task (so tasks end in any order and the window of tasks in flight moves)."""
    from leap_core.consistency.remote import predict_from_checkpoint
    from leap_core.datasets.kitti import KittiSequence
    from leap_core.pipeline import executor as engine

    _, cfg = preset_config
    cfg = _with_3dcn(cfg)
    checkpoint = RunLayout(local_3dcn_run.parent.parent).cn_dir / "3dcn_iter1.pt"
    seq = KittiSequence(dataset)
    frames = seq.select(FRAMES)
    monkeypatch.setattr(engine, "INFER_TASK_FRAMES", 1)
    predictor = engine.RayExecutor("auto").predictor(cfg)
    got = list(predictor(seq, frames, checkpoint))
    expected = predict_from_checkpoint(
        seq, list(frames), checkpoint, cfg.consistency, cfg.fusion.voxel_size, 1
    )
    assert predictor.tasks == len(frames)
    assert len(got) == len(expected) == len(frames)
    for (keys, logp), (k, lp) in zip(got, expected, strict=True):
        assert keys.tobytes() == k.tobytes()
        assert logp.tobytes() == lp.tobytes()


def _seq_span(run_dir: Path, stages: tuple[str, ...]) -> tuple[float, float]:
    records = stage_status(run_dir)
    return min(records[s]["started"] for s in stages), max(records[s]["finished"] for s in stages)


@pytest.fixture(scope="module")
def streets(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two tiny ray-cast streets, ``00`` and ``01`` (as tests/test_runs.py)."""
    from test_pipeline import make_street

    base = tmp_path_factory.mktemp("streets")
    return [
        make_street(base / "x" / "sequences" / "00", n_frames=5),
        make_street(base / "y" / "sequences" / "01", n_frames=4, step=2.0),
    ]


MULTI_FILES = ("grid.npz", "grid_smooth.npz", "grid_3dcn1.npz", "grid_smooth_3dcn1.npz", "metrics.json")


def _multi_setup(streets: list[Path]) -> tuple[list[Any], Any, PipelineConfig]:
    from leap_core.config import config_from_dict
    from leap_core.pipeline import SequenceSpec
    from leap_core.schema import builtin_schema

    return (
        [SequenceSpec.of(path) for path in streets],
        builtin_schema("semantickitti"),
        config_from_dict({"consistency": {**TINY_3DCN, "iterations": 1}}),
    )


@pytest.fixture(scope="module")
def local_multi(streets: list[Path], tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, list[Any]]:
    """The two streets' run with the 3D-CN, locally, and its progress reports."""
    specs, schema, cfg = _multi_setup(streets)
    calls: list[Any] = []
    return run_pipeline(
        specs, schema, cfg, tmp_path_factory.mktemp("multi") / "local", progress=lambda *a: calls.append(a)
    ), calls


def _same_multi_outputs(root: Path, local_root: Path, names: list[str]) -> None:
    for name in names:
        lay, ref = RunLayout(root).sequence(name), RunLayout(local_root).sequence(name)
        for sub in ("labels2d", "observations", "points", "export"):
            local_files = {p.name: p.read_bytes() for p in sorted(ref.frame_folder(sub).iterdir())}
            ray_files = {p.name: p.read_bytes() for p in sorted(lay.frame_folder(sub).iterdir())}
            assert ray_files == local_files, (name, sub)
        for f in MULTI_FILES:
            assert (lay.folder / f).read_bytes() == (ref.folder / f).read_bytes(), (name, f)
    assert (root / "metrics.json").read_bytes() == (local_root / "metrics.json").read_bytes()


@pytest.mark.slow
def test_two_sequences_run_at_once_on_ray_with_the_local_bytes(
    ray_instance, streets: list[Path], local_multi, tmp_path: Path
) -> None:
    """A two-sequence project with the 3D-CN: on Ray both sequences' stages before the 3D-CN's rounds run
    at the same time (their stages.json spans overlap; locally they follow each other), the rounds'
    inference runs as tasks, and every file is the local run's."""
    specs, schema, cfg = _multi_setup(streets)
    first = ("labels2d", "project", "fuse", "smooth")
    local, local_calls = local_multi
    calls: list[Any] = []
    result = run_pipeline(
        specs, schema, cfg, tmp_path / "ray", runtime=RAY, progress=lambda *a: calls.append(a)
    )
    spans = {}
    for name, root in (("local", local.root), ("ray", result.root)):
        spans[name] = [_seq_span(RunLayout(root).sequence(s.name).folder, first) for s in specs]
    (a0, a1), (b0, b1) = spans["local"]
    assert a1 <= b0  # locally one after the other
    (a0, a1), (b0, b1) = spans["ray"]
    assert a0 < b1 and b0 < a1  # on Ray at the same time
    _same_multi_outputs(result.root, local.root, [s.name for s in specs])
    assert result.metrics == local.metrics
    joint_state = json.loads(RunLayout(result.root).joint_state.read_text())
    assert joint_state["ray_tasks"] >= 2
    # Every stage of every sequence reported its end, however the reports interleaved.
    for reports in (local_calls, calls):
        ends = {(seq, stage) for seq, stage, done, total in reports if total > 0 and done >= total}
        assert {(s.name, stage) for s in specs for stage in ("labels2d", "smooth", "export")} <= ends


@pytest.mark.slow
def test_sequences_at_once_cancel_together_and_resume(
    ray_instance, streets: list[Path], local_multi, tmp_path: Path
) -> None:
    """A cancel in one sequence stops the other at its next report; each keeps its own stages.json, and
    the rerun resumes both (kept frames not recomputed) to the local bytes."""
    specs, schema, cfg = _multi_setup(streets)
    out = tmp_path / "ray"

    def cancel_in_01(name: str, stage: str, done: int, total: int) -> None:
        if (name, stage) == ("01", "project") and 0 < done < total:
            raise Cancelled()

    with pytest.raises(Cancelled):
        run_pipeline(specs, schema, cfg, out, runtime=RAY, progress=cancel_in_01)
    layout = RunLayout(out)
    assert stage_status(layout.sequence("01").folder)["project"]["status"] == "cancelled"
    kept = len(list(layout.sequence("01").frame_folder("observations").glob("*.npz")))
    assert 0 < kept < 4
    assert not layout.joint_state.exists()  # stopped before the 3D-CN's rounds
    result = run_pipeline(specs, schema, cfg, out, runtime=RAY)
    assert result.sequences["01"].stages["project"].frames_computed == 4 - kept
    _same_multi_outputs(out, local_multi[0].root, [s.name for s in specs])


@pytest.mark.slow
def test_cli_runs_sequences_at_once_on_ray(ray_instance, streets: list[Path], tmp_path: Path) -> None:
    """``leap run A B --ray auto``: the same exports as without Ray; the bars of sequences that report in
    turn are named after their sequence instead of following a header per sequence."""
    from app.cli import cli

    runner = CliRunner()
    outs, outputs = {}, {}
    for name, extra in (("local", []), ("ray", ["--ray", "auto"])):
        res = runner.invoke(
            cli, ["run", *map(str, streets), "--labeler", "simulated", "--out", str(tmp_path / name), *extra]
        )
        assert res.exit_code == 0, res.output
        outputs[name] = res.output
        outs[name] = {
            p.relative_to(tmp_path / name).as_posix(): p.read_bytes()
            for p in sorted((tmp_path / name).glob("sequences/*/export/*"))
        }
    assert len(outs["ray"]) == 2 * (5 + 4)
    assert outs["ray"] == outs["local"]
    # The result tables' heading only (locally also the bars' headers).
    assert outputs["ray"].count("== sequence 00") == 1 < outputs["local"].count("== sequence 00")
    assert "00 labels2d" in outputs["ray"] and "01 export" in outputs["ray"]
    assert "sequence 01: " in outputs["ray"] and "points labeled" in outputs["ray"]
