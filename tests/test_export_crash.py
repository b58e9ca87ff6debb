"""An export killed with kill -9 half-way (a real subprocess, paused at a known point, then killed) leaves
its hidden scratch folder beside the target; the next export to that target deletes it, and never a
user's own folder that merely carries such a name, a link, the scratch folder of another target or that of
an export still running."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from leap_core.export import (
    SCRATCH,
    ExportedSequence,
    export_labels,
    export_targets,
    remove_export_leftovers,
    write_run_export,
)

EXPORT_IDS = np.array([10, 40, 48], np.uint32)

CHILD = """
import os, shutil, sys
from pathlib import Path
from leap_core.export import ExportedSequence, export_targets, write_run_export

def pause():
    # Tell the test where this export stands, then wait for the kill (stdin stays open until then).
    Path(os.environ["LEAP_TEST_READY"]).write_text("paused")
    sys.stdin.read()

if os.environ["LEAP_TEST_PAUSE"] == "copying":
    copy, copied = shutil.copyfile, []
    def copyfile(src, dst, *args, **kwargs):
        out = copy(src, dst, *args, **kwargs)
        copied.append(dst)
        if len(copied) == 2:
            pause()
        return out
    shutil.copyfile = copyfile
else:
    rmtree = shutil.rmtree
    def rmtree_pausing(path, *args, **kwargs):
        if ".leap-old-" in str(path):
            pause()
        return rmtree(path, *args, **kwargs)
    shutil.rmtree = rmtree_pausing

seq = ExportedSequence("00", Path(os.environ["LEAP_TEST_EXPORT"]))
write_run_export(export_targets(Path(os.environ["LEAP_TEST_DATASET"]), ["00"]), [seq], overwrite=True)
"""
"""The export of one run sequence into a dataset, as the app and ``leap export`` write it, paused either
after two files were copied into its scratch folder or when it deletes the folder it replaced."""


def _run_export(folder: Path, seed: int, frames: int = 5) -> ExportedSequence:
    """A run sequence's export folder with ``frames`` real ``.label`` / ``.conf`` pairs."""
    rng = np.random.default_rng(seed)
    for i in range(frames):
        labels = rng.integers(-1, 3, 200).astype(np.int16)
        export_labels(
            folder / f"{i:06d}.label", folder / f"{i:06d}.conf", labels, rng.random(200), EXPORT_IDS
        )
    return ExportedSequence("00", folder)


def _kill_mid_export(
    tmp_path: Path, dataset: Path, export: ExportedSequence, pause: str, while_paused: Callable[[], None]
) -> None:
    """Run the export in a subprocess, wait until it reached ``pause``, call ``while_paused``, kill -9 it."""
    ready = tmp_path / f"ready-{pause}"
    env = {
        **os.environ,
        "LEAP_TEST_READY": str(ready),
        "LEAP_TEST_PAUSE": pause,
        "LEAP_TEST_EXPORT": str(export.export_dir),
        "LEAP_TEST_DATASET": str(dataset),
    }
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD], env=env, stdin=subprocess.PIPE, stderr=subprocess.PIPE
    )
    try:
        deadline = time.monotonic() + 120
        while not ready.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert ready.exists(), (
            f"the export never reached its pause: {proc.stderr.read() if proc.stderr else ''}"
        )
        while_paused()
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)


def _scratch(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if SCRATCH.fullmatch(p.name))


@pytest.mark.parametrize("pause", ["copying", "replacing"])
def test_the_next_export_deletes_what_an_export_killed_with_kill_9_left(tmp_path: Path, pause: str) -> None:
    dataset = tmp_path / "dataset"
    sequence = dataset / "sequences" / "00"
    (sequence / "velodyne").mkdir(parents=True)
    first, second = _run_export(tmp_path / "run1", 1), _run_export(tmp_path / "run2", 2)
    targets = export_targets(dataset, ["00"])
    predictions = sequence / "predictions"
    if pause == "replacing":  # an earlier export that the killed one replaces
        write_run_export(targets, [first])

    def another_export_cleans_up() -> None:
        # The paused export is alive and holds its scratch folder: another export's clean-up leaves it.
        (running,) = _scratch(sequence)
        assert remove_export_leftovers(predictions) == [] and _scratch(sequence) == [running]

    _kill_mid_export(tmp_path, dataset, second, pause, another_export_cleans_up)
    (left,) = _scratch(sequence)
    if pause == "copying":
        assert left.startswith(".predictions.leap-new-") and not predictions.exists()
        assert len(list((sequence / left).iterdir())) == 2  # copied before the kill
    else:
        assert left.startswith(".predictions.leap-old-")  # the replaced export, not yet deleted
        assert sorted(p.name for p in (sequence / left).iterdir()) == sorted(
            p.name for p in first.files(False)
        )
        assert sorted(p.read_bytes() for p in predictions.iterdir()) == sorted(
            p.read_bytes() for p in second.files(False)
        )

    # A user's own folders beside it: named like scratch but holding a file of their own, named otherwise,
    # a link named like scratch (and what it points to), the scratch folder of another target.
    mine = sequence / ".predictions.leap-new-0123abcd"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    (sequence / ".predictions.leap-new-keep").mkdir()
    (sequence / ".predictions.leap-new-keep" / "000000.label").write_bytes(b"mine")
    linked = tmp_path / "my-labels"
    linked.mkdir()
    (linked / "000000.label").write_bytes(b"mine")
    (sequence / ".predictions.leap-old-89abcdef").symlink_to(linked, target_is_directory=True)
    other = sequence / ".confidences.leap-new-0000ffff"
    other.mkdir()
    (other / "000000.conf").write_bytes(b"other")

    done = write_run_export(targets, [first], overwrite=True)
    assert done.files == {"00": 5}
    assert sorted(p.read_bytes() for p in predictions.iterdir()) == sorted(
        p.read_bytes() for p in first.files(False)
    )
    assert not (sequence / left).exists()
    assert _scratch(sequence) == sorted(
        [".confidences.leap-new-0000ffff", ".predictions.leap-new-0123abcd", ".predictions.leap-old-89abcdef"]
    )
    assert (mine / "notes.txt").read_text() == "mine"
    assert (sequence / ".predictions.leap-new-keep" / "000000.label").read_bytes() == b"mine"
    assert (linked / "000000.label").read_bytes() == b"mine"
    assert (other / "000000.conf").read_bytes() == b"other"
