"""Run folders and an app database written before every run had one shape are moved into today's.

The folders are real ones: ``tests/data/former-runs.tar.gz`` holds what that version wrote
(``tests/data/make_former_runs.py`` says how): a ``leap run`` of one sequence with a 3D-CN round (its files
at the top of the run folder), a ``leap run`` of two sequences (``multi.json``), and an app work folder
(database of schema version 7, a project of one sequence with two runs, one of two sequences, a correction
each). The archive's absolute paths are replaced by the test's folder, as if the data had moved.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import formerruns
import numpy as np
import pytest

from leap_core.errors import LeapError
from leap_core.pipeline import migrate_run_folder, result_tables, run_result_tables
from leap_core.run_layout import FORMER_MULTI_SPEC, RunLayout, former_layout

former = formerruns.former


def _files(folder: Path) -> dict[Path, bytes]:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_run_of_one_sequence_moves_into_its_sequence_folder(former: Path) -> None:
    single = former / "cli" / "single"
    before = _files(single)
    tables = result_tables(single)
    assert former_layout(single) == "single"

    assert migrate_run_folder(single, "00", former / "data/street/sequences/00")
    layout = RunLayout(single)
    seq = layout.sequence("00")
    assert former_layout(single) is None and layout.names() == ["00"]
    run_own = RunLayout.RUN_FILES - {RunLayout.METRICS}
    assert {rel.parts[0] for rel in before} & run_own == {"3dcn", ".lock"}
    for rel, data in before.items():
        # The checkpoints are the run's (its 3D-CN trains on all its sequences), and so is the lock; the
        # rest is the sequence's.
        moved = single / rel if rel.parts[0] in run_own else seq.folder / rel
        assert moved.read_bytes() == data, rel
    spec = json.loads(layout.spec.read_text())
    assert spec == {
        "sequences": [{"name": "00", "dataset": str(former / "data/street/sequences/00"), "frames": None}]
    }
    overall = json.loads(layout.metrics.read_text())
    assert overall["sequences"] == {"00": json.loads(before[Path("metrics.json")])}
    assert overall["overall"]["sequences"] == ["00"]
    assert run_result_tables(single) == tables  # a run of one sequence shows that sequence's tables
    assert not migrate_run_folder(single, "00")  # once only


def test_a_move_stopped_half_way_is_finished_by_the_next_call(former: Path) -> None:
    single = former / "cli" / "single"
    before = _files(single)
    seq = RunLayout(single).sequence("00")
    seq.folder.mkdir(parents=True)
    for name in ("labels2d", "grid.npz", "metrics.json"):  # moved before the stop
        (single / name).rename(seq.folder / name)
    assert former_layout(single) == "single"  # stages.json moves last, so the folder still says so
    assert migrate_run_folder(single, "00")
    assert _files(seq.folder)[Path("grid.npz")] == before[Path("grid.npz")]
    assert sorted(p.name for p in single.iterdir()) == [
        ".lock",
        "3dcn",
        "metrics.json",
        "run.json",
        "sequences",
    ]


def test_an_entry_in_the_way_stops_the_move_and_names_it(former: Path) -> None:
    single = former / "cli" / "single"
    seq = RunLayout(single).sequence("00")
    seq.folder.mkdir(parents=True)
    (seq.folder / "grid.npz").write_bytes(b"someone else's")
    with pytest.raises(LeapError, match=r"cannot move grid\.npz into .*sequences/00"):
        migrate_run_folder(single, "00")
    assert (seq.folder / "grid.npz").read_bytes() == b"someone else's"
    assert former_layout(single) == "single"


def test_a_run_of_several_sequences_gets_its_run_record(former: Path) -> None:
    multi = former / "cli" / "multi"
    before = _files(multi)
    assert former_layout(multi) == "multi"
    assert migrate_run_folder(multi, "ignored")
    assert not (multi / FORMER_MULTI_SPEC).exists()
    assert RunLayout(multi).names() == ["00", "01"]
    after = _files(multi)
    assert after.pop(Path("run.json")) == before.pop(Path(FORMER_MULTI_SPEC))
    assert after == before


@pytest.mark.slow
def test_leap_run_moves_an_earlier_folder_and_labels_it_the_same(former: Path) -> None:
    """Rerunning the recorded command on the earlier folder: the folder moves first, the pipeline then
    recomputes (the data moved, so every fingerprint changed) and writes the same labels and grids. The
    earlier version had no tracks stage: every point the new one leaves without an object (instance 0)
    keeps its label byte for byte; tracked points carry their track id (and class) on top."""
    single = former / "cli" / "single"
    before = _files(single)
    # The earlier version trained in float32, the only precision it had; ``auto`` would take bfloat16 on a
    # CPU that has it, and another arithmetic writes other bytes.
    project = former / "small-3dcn.yaml"
    text = project.read_text()
    project.write_text(text.replace("    device: cpu\n", "    device: cpu\n    precision: float32\n", 1))
    subprocess.run(
        [
            sys.executable,
            "-m",
            "app.cli",
            "run",
            former / "data/street/sequences/00",
            "--project-file",
            former / "small-3dcn.yaml",
            "--out",
            single,
        ],
        check=True,
        capture_output=True,
    )
    seq = RunLayout(single).sequence("00").folder
    for rel, data in before.items():
        if rel.suffix == ".label":
            old, new = np.frombuffer(data, "<u4"), np.fromfile(seq / rel, "<u4")
            untracked = new >> 16 == 0
            assert untracked.any() and (new[untracked] == old[untracked]).all(), rel
        elif rel.suffix == ".conf" or rel.name.startswith("grid"):
            assert (seq / rel).read_bytes() == data, rel
