"""The demo's outputs stay byte for byte what they were: the exported ``.label`` files, ``grid.npz``,
``grid_smooth.npz``, the 3D-CN's grids and ``metrics.json`` of three runs through the ``leap`` command
line, against SHA-256 digests recorded before runs had one shape (``tests/data/demo_output_digests.json``,
written by the version whose single-sequence runs kept their files at the top of the run folder):

- ``demo``: the built-in demo street (``leap synth``, 60 frames, seed 0) with the default settings, as
  ``leap demo`` labels it;
- ``small-3dcn``: 4 frames of the street with two 3D-CN rounds of a small network;
- ``two-sequences-3dcn``: that sequence and 3 frames of seed 1 in one run, the 3D-CN trained on both,
  plus the run's overall ``metrics.json``.

A refactor that changes a single byte of these files fails here, naming the file.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from leap_core.run_layout import RunLayout

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
DIGESTS = json.loads((ROOT / "tests" / "data" / "demo_output_digests.json").read_text())

SMALL_3DCN = """
pipeline:
  consistency:
    enabled: true
    iterations: 2
    device: cpu
    precision: float32
    num_threads: 1
    min_steps: 6
    points_per_scan: 2000
    backbone: {channels: 16, layers: 2}
"""
"""The pipeline section the recorded 3D-CN runs used, after the built-in SemanticKITTI classes (float32,
the only precision there was then, pinned: ``auto`` would take bfloat16 on a CPU that has it)."""


def _leap(*args: object) -> None:
    subprocess.run(
        [sys.executable, "-m", "app.cli", *map(str, args)], check=True, capture_output=True, text=True
    )


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def digests(root: Path) -> dict[str, str]:
    """What the recorded digests cover, for every sequence of the run folder ``root``."""
    layout = RunLayout(root)
    out: dict[str, str] = {}
    for name in layout.names():
        folder = layout.sequence(name).folder
        for f in ("grid.npz", "grid_smooth.npz", "metrics.json"):
            if (folder / f).is_file():
                out[f"{name}/{f}"] = _sha(folder / f)
        for f in sorted(folder.glob("grid*_3dcn*.npz")):
            out[f"{name}/{f.name}"] = _sha(f)
        for f in sorted((folder / "export").glob("*.label")):
            out[f"{name}/export/{f.name}"] = _sha(f)
    return out


def _compare(got: dict[str, str], want: dict[str, str]) -> None:
    assert sorted(got) == sorted(want), "the runs wrote other files than the recorded ones"
    changed = [k for k in want if got[k] != want[k]]
    assert not changed, f"{len(changed)} of {len(want)} files changed, e.g. {changed[:5]}"


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("demo-outputs")
    _leap("synth", root / "small", "--frames", 4, "--seed", 0)
    _leap("synth", root / "small1", "--frames", 3, "--seed", 1)
    project = root / "small-3dcn.yaml"
    project.write_text((ROOT / "projects" / "semantickitti.yaml").read_text() + SMALL_3DCN)
    return root


def test_the_demo_street_labels_as_recorded(data: Path, tmp_path: Path) -> None:
    _leap("synth", data / "demo", "--seed", 0)
    _leap(
        "run",
        data / "demo/sequences/00",
        "--schema",
        "semantickitti",
        "--labeler",
        "simulated",
        "--out",
        tmp_path,
    )
    _compare(digests(tmp_path), DIGESTS["demo"])


def test_two_3dcn_rounds_on_one_sequence_label_as_recorded(data: Path, tmp_path: Path) -> None:
    _leap("run", data / "small/sequences/00", "--project-file", data / "small-3dcn.yaml", "--out", tmp_path)
    _compare(digests(tmp_path), DIGESTS["small-3dcn"])


def test_a_3dcn_trained_on_two_sequences_labels_as_recorded(data: Path, tmp_path: Path) -> None:
    named = data / "two" / "sequences"
    named.mkdir(parents=True)
    (named / "a").symlink_to(data / "small/sequences/00")
    (named / "b").symlink_to(data / "small1/sequences/00")
    _leap("run", named / "a", named / "b", "--project-file", data / "small-3dcn.yaml", "--out", tmp_path)
    got = digests(tmp_path)
    got["overall/metrics.json"] = _sha(RunLayout(tmp_path).metrics)
    _compare(got, DIGESTS["two-sequences-3dcn"])
