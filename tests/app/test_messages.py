"""The server ↔ worker messages: every type round-trips through its JSON line, bad lines are refused with a
message that says why, and neither side's reader dies on one."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import subprocess
import sys
import threading
import typing
from pathlib import Path

import appfixtures
import pytest

from app import crud
from app.core.config import Settings
from app.core.db import init_db, open_db
from app.jobs import messages, worker
from app.jobs.manager import JobManager, _Live
from app.jobs.messages import (
    CancelRun,
    LogLine,
    Message,
    MessageError,
    RunOutcome,
    RunSpec,
    StageProgress,
    decode,
    decode_from_worker,
    decode_to_worker,
)
from app.jobs.progress import ProgressTracker
from app.rows import RunParams, RunSequence

settings, data_root = appfixtures.settings, appfixtures.data_root

EXAMPLES: list[Message] = [
    RunSpec(
        run_id=7,
        run_dir=Path("/work/runs/p1/r7"),
        sequences=[("00", Path("/data/sequences/00"), (2, 9)), ("«ü»", Path("/data/b"), None)],
        demo=True,
        demo_synth={"frames": 4, "lidar": {"beams": 32}},
        schema={"classes": [{"name": "car", "color": [1, 2, 3], "prompts": ["car", "van"]}]},
        pipeline={"fusion": {"voxel_size": 0.25}, "labeler": "simulated"},
        models_dir=Path("/models"),
        cache_dir=Path("/work/cache/p1"),
        progress_interval_s=0.05,
    ),
    RunSpec(
        run_id=1,
        run_dir=Path("r"),
        sequences=[("00", Path("d"), None)],
        demo=False,
        demo_synth={},
        schema={},
        pipeline={},
        models_dir=None,
        cache_dir=None,
        progress_interval_s=1.0,
    ),
    CancelRun(),
    StageProgress("labels2d", 3, 10),
    LogLine(logging.WARNING, "leap_core.labelers.grounded_sam", "tiny RANDOM-weight test model «ü»"),
    RunOutcome("done"),
    RunOutcome("failed", "labels2d: no images"),
]


def test_every_message_type_has_resolvable_annotations_and_an_example() -> None:
    types = messages.message_types()
    assert set(types) == {"run", "cancel", "stage", "log", "result"}
    for tag, cls in types.items():
        assert cls.type == tag and dataclasses.is_dataclass(cls)
        assert cls.__dataclass_params__.frozen  # type: ignore[attr-defined]  # set by @dataclass, untyped
        hints = typing.get_type_hints(cls)  # raises for an annotation that does not resolve
        assert {f.name for f in dataclasses.fields(cls)} <= set(hints)
    assert {type(m) for m in EXAMPLES} == set(types.values())


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_every_message_round_trips_through_one_json_line(message: Message) -> None:
    line = message.to_line()
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    assert json.loads(line)["type"] == message.type
    back = decode(line)
    assert back == message and type(back) is type(message)
    assert decode(line.decode()) == message  # str lines too
    for f in dataclasses.fields(message):  # the annotated types come back, not their JSON forms
        assert type(getattr(back, f.name)) is type(getattr(message, f.name))


def test_each_side_accepts_only_the_other_sides_messages() -> None:
    assert decode_to_worker(CancelRun().to_line()) == CancelRun()
    assert decode_from_worker(StageProgress("fuse", 1, 1).to_line()) == StageProgress("fuse", 1, 1)
    with pytest.raises(MessageError, match="worker does not send 'cancel'"):
        decode_from_worker(CancelRun().to_line())
    with pytest.raises(MessageError, match="server does not send 'result'"):
        decode_to_worker(RunOutcome("done").to_line())


@pytest.mark.parametrize(
    ("line", "error"),
    [
        (b'["stage", "fuse", 1, 2]\n', "expected a JSON object"),
        (b"cancel\n", "not a JSON line"),
        (b'{"type": "stage", "stage": "fuse", "done": 1', "not a JSON line"),
        (b'{"stage": "fuse"}', "unknown message type None"),
        (b'{"type": "progress"}', "unknown message type 'progress'"),
        (b'{"type": "stage", "stage": "fuse", "done": 1}', "stage: missing field 'total'"),
        (b'{"type": "stage", "stage": "fuse", "done": 1, "total": 2, "eta": 3}', "stage: unknown field"),
        (b'{"type": "stage", "stage": "fuse", "done": "1", "total": 2}', "stage.done: expected an integer"),
        (b'{"type": "stage", "stage": "fuse", "done": true, "total": 2}', "stage.done: expected an integer"),
        (b'{"type": "stage", "stage": 5, "done": 1, "total": 2}', "stage.stage: expected a string"),
        (b'{"type": "result", "status": "finished"}', "result.status: expected one of 'done'"),
        (b'{"type": "result", "status": "done", "error": 3}', "result.error: expected a string"),
        (b'{"type": "log", "level": 30.5, "logger": "x", "message": "m"}', "log.level: expected an integer"),
    ],
)
def test_a_malformed_line_raises_a_message_error_that_says_why(line: bytes, error: str) -> None:
    with pytest.raises(MessageError, match=re.escape(error)):
        decode(line)


def test_a_malformed_run_spec_names_the_field() -> None:
    doc = json.loads(EXAMPLES[0].to_line())
    doc["sequences"][0][2] = [1, "x"]
    with pytest.raises(MessageError, match=r"run\.sequences\[0\]\[2\]\[1\]: expected an integer"):
        decode(json.dumps(doc))
    doc["sequences"][0][2] = [1]
    with pytest.raises(MessageError, match=r"run\.sequences\[0\]\[2\]: expected a list of 2 values"):
        decode(json.dumps(doc))
    doc["sequences"][0] = ["00", "/d"]
    with pytest.raises(MessageError, match=r"run\.sequences\[0\]: expected a list of 3 values"):
        decode(json.dumps(doc))
    doc["sequences"] = {"00": "/d"}
    with pytest.raises(MessageError, match=r"run\.sequences: expected a list"):
        decode(json.dumps(doc))
    doc["sequences"] = [["00", "/d", None]]
    doc["demo_synth"] = ["frames", 4]
    with pytest.raises(MessageError, match=r"run\.demo_synth: expected an object"):
        decode(json.dumps(doc))
    del doc["demo_synth"]
    with pytest.raises(MessageError, match="run: missing field 'demo_synth'"):
        decode(json.dumps(doc))


def test_the_relay_survives_malformed_lines_and_logs_worker_warnings(
    settings: Settings, caplog: pytest.LogCaptureFixture
) -> None:
    """Garbage from the worker is logged and skipped; progress and the outcome after it still arrive."""
    init_db(settings.database)
    with open_db(settings.database) as db:
        project = crud.create_project(
            db, name="p", dataset_kind="folder", sequences=[("d", "/d")], schema={"classes": []}, pipeline={}
        )
        params = RunParams(
            sequences=(RunSequence("d", Path("/d")),), dataset_kind="folder", schema={}, pipeline={}
        )
        run = crud.create_run(db, project_id=project.id, params=params, runs_dir=settings.runs_dir)
    manager = JobManager(settings)
    label = f"run #{run.number} of project {project.id} (id {run.id})"
    live = _Live(tracker=ProgressTracker.create(run.id, project.id, ["labels2d", "fuse"]), label=label)
    read_fd, write_fd = os.pipe()
    lines = [
        b"not json at all\n",
        b'["stage", "labels2d", 1, 2]\n',  # the old list format
        b'{"type": "stage", "stage": "labels2d", "done": "x", "total": 2}\n',
        StageProgress("labels2d", 2, 2).to_line(),
        LogLine(logging.WARNING, "leap_core.labelers", "random weights").to_line(),
        b'{"type": "cancel"}\n',  # well-formed, but never sent by a worker
        StageProgress("fuse", 1, 3).to_line(),
        RunOutcome("failed", "bad data").to_line(),
    ]
    # Written from a thread in small pieces, so lines also arrive split across reads.
    data = b"".join(lines)

    def write() -> None:
        for i in range(0, len(data), 7):
            os.write(write_fd, data[i : i + 7])
        os.close(write_fd)

    writer = threading.Thread(target=write)
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    with caplog.at_level(logging.INFO, logger="leap.jobs"):
        writer.start()
        outcome = manager._relay(run.id, live, read_fd, process)
        writer.join()
    os.close(read_fd)
    process.wait()
    assert outcome == RunOutcome("failed", "bad data")
    stages = {s["name"]: s for s in live.tracker.snapshot()["stages"]}
    assert stages["labels2d"]["status"] == "done" and stages["labels2d"]["done"] == 2
    assert stages["fuse"]["status"] == "running" and stages["fuse"]["done"] == 1
    unreadable = [r.getMessage() for r in caplog.records if "unreadable worker message" in r.getMessage()]
    assert len(unreadable) == 4
    assert "not a JSON line" in unreadable[0] and "expected a JSON object" in unreadable[1]
    assert "stage.done: expected an integer" in unreadable[2] and "does not send 'cancel'" in unreadable[3]
    forwarded = [r for r in caplog.records if "random weights" in r.getMessage()]
    assert len(forwarded) == 1 and forwarded[0].levelno == logging.WARNING
    assert forwarded[0].getMessage() == f"{label}: leap_core.labelers: random weights"
    # Warnings also become part of the run the UI shows (and of its stored record).
    assert live.tracker.snapshot()["warnings"] == ["random weights"]
    assert live.tracker.stages_record()["warnings"] == ["random weights"]


def test_the_worker_forwards_pipeline_warnings_only() -> None:
    sent: list[object] = []
    handler = worker._ForwardLogs(sent.append)
    library = logging.getLogger("leap_core")
    library.addHandler(handler)
    try:
        logging.getLogger("leap_core.labelers.grounded_sam").warning("%s holds random weights", "models/x")
        logging.getLogger("leap_core.fusion").info("not forwarded")
        logging.getLogger("leap.other").warning("not the pipeline's")
    finally:
        library.removeHandler(handler)
    expected = LogLine(logging.WARNING, "leap_core.labelers.grounded_sam", "models/x holds random weights")
    assert sent == [expected]


@pytest.mark.slow
def test_a_worker_given_a_malformed_spec_reports_a_failed_outcome(tmp_path: Path) -> None:
    """The worker process answers a bad first line with a readable failure instead of dying silently."""
    read_fd, write_fd = os.pipe()
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    process = subprocess.Popen(
        [sys.executable, "-m", "app.jobs.worker", str(write_fd), str(os.getpid())],
        stdin=subprocess.PIPE,
        pass_fds=(write_fd,),
        env=env,
        cwd=tmp_path,
    )
    os.close(write_fd)
    assert process.stdin is not None
    process.stdin.write(b'{"type": "run", "run_id": 1}\n')
    process.stdin.flush()
    with os.fdopen(read_fd, "rb") as pipe:
        out = pipe.read()
    assert process.wait(30) == 0  # stdin still open: its end would make the worker exit(3) at once
    process.stdin.close()
    (line,) = out.splitlines()
    outcome = decode_from_worker(line)
    assert isinstance(outcome, RunOutcome) and outcome.status == "failed"
    assert outcome.error is not None and "MessageError: run: missing field 'run_dir'" in outcome.error
