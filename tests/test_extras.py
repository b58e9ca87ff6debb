"""Without an optional stack (pyproject.toml's extras), the command that needs it stops with one line that
names the extra to install, and the rest of ``leap`` works.

A stack is hidden in a subprocess by a ``None`` entry in ``sys.modules``: importing it then fails exactly as
when it is not installed, while everything else (our code included) is the real installed one.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from conftest import build_tiny_sequence

from leap_core.extras import NUSCENES_DEVKIT, STACKS, MissingExtra

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: pytest's own TOML reader
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
EXTRA_MODULES = [
    "ray",
    "rosbags",
    "apsw",
    "nuscenes",
    "matplotlib",
    "sklearn",
    "shapely",
    "pycocotools",
    "descartes",
    "fire",
    "cachetools",
    "parameterized",
    "psutil",
    "numba",
    "llvmlite",
]
"""Modules only the extras install (pyquaternion is not among them: kiss-icp, a core dependency, needs it)."""


def _python(hidden: list[str], code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a fresh interpreter in which the ``hidden`` modules cannot be imported."""
    prelude = f"import sys\nfor _m in {hidden!r}:\n    sys.modules[_m] = None\n"
    return subprocess.run(
        [sys.executable, "-c", prelude + code],
        check=False,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _leap(hidden: list[str], args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """``leap ARGS`` (the console script's entry point) with the ``hidden`` modules missing."""
    return _python(hidden, f"from app.cli import main\nsys.argv = ['leap', *{args!r}]\nmain()", cwd)


def _error_line(proc: subprocess.CompletedProcess[str]) -> str:
    lines = proc.stderr.strip().splitlines()
    return lines[-1] if lines else ""


def test_leap_its_server_and_the_pipeline_need_no_extra(tmp_path: Path) -> None:
    """``leap --help``, ``leap import --help``, the app (``leap serve``) and the local pipeline import
    without any extra."""
    code = (
        "import app.main, leap_core.pipeline.runner, leap_core.odometry\n"
        "from app.cli import main\n"
        "for args in (['--help'], ['import', '--help'], ['run', '--help']):\n"
        "    sys.argv = ['leap', *args]\n"
        "    try:\n"
        "        main()\n"
        "    except SystemExit as exc:\n"
        "        assert exc.code == 0, (args, exc.code)\n"
        "print('no extra needed')\n"
    )
    proc = _python(EXTRA_MODULES, code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Usage: leap" in proc.stdout and proc.stdout.rstrip().endswith("no extra needed")


def test_leap_run_with_ray_names_the_ray_extra(tmp_path: Path) -> None:
    seq = build_tiny_sequence(tmp_path).root
    proc = _leap(["ray"], ["run", str(seq), "--out", str(tmp_path / "run"), "--ray", "auto"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert _error_line(proc) == "error: Ray is not installed: pip install 'leap-studio[ray]'"


@pytest.mark.parametrize(
    ("hidden", "what"), [(["rosbags", "apsw"], "rosbags"), (["apsw"], "apsw (needed by rosbags)")]
)
def test_leap_import_rosbag_names_the_ros_extra(tmp_path: Path, hidden: list[str], what: str) -> None:
    args = ["import", "rosbag", "x.bag", "--lidar-topic", "/points", "--camera-topic", "/image"]
    proc = _leap(hidden, args, tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert _error_line(proc) == f"error: {what} is not installed: pip install 'leap-studio[ros]'"


@pytest.mark.parametrize(
    ("hidden", "what"),
    [(EXTRA_MODULES, "nuscenes-devkit"), (["matplotlib"], "matplotlib (needed by nuscenes-devkit)")],
)
def test_leap_import_nuscenes_names_the_nuscenes_extra_and_the_devkit(
    tmp_path: Path, hidden: list[str], what: str
) -> None:
    proc = _leap(hidden, ["import", "nuscenes", str(tmp_path), "--scene", "scene-0061"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert _error_line(proc) == (
        f"error: {what} is not installed: "
        "pip install 'leap-studio[nuscenes]' && pip install --no-deps 'nuscenes-devkit==1.2.0'"
    )


@pytest.mark.parametrize(
    ("script", "hidden", "what"),
    [
        ("bench_memory.py", "psutil", "psutil"),
        ("bench_scale.py", "psutil", "psutil"),
        ("bench_app_load.py", "httpx", "httpx (needed by the benchmarks)"),
    ],
)
def test_benchmarks_name_the_bench_extra(tmp_path: Path, script: str, hidden: str, what: str) -> None:
    code = (
        "import runpy\n"
        "sys.argv = ['bench', '--help']\n"
        f"runpy.run_path({str(ROOT / 'benchmarks' / script)!r}, run_name='__main__')\n"
    )
    proc = _python([hidden], code, tmp_path)
    assert proc.returncode == 1, proc.stderr
    assert _error_line(proc) == f"error: {what} is not installed: pip install 'leap-studio[bench]'"


def test_the_messages_name_the_extras_pyproject_declares() -> None:
    """Each message's extra exists in pyproject.toml, [test] pulls them all, and the devkit the nuscenes
    message names is the one scripts/install.sh installs."""
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert set(STACKS) == set(extras) - {"test"}
    assert f"leap-studio[{','.join(STACKS)}]" in extras["test"]
    assert f'pip install -q --no-deps "{NUSCENES_DEVKIT}"' in (ROOT / "scripts" / "install.sh").read_text()
    for extra in STACKS:
        assert f"pip install 'leap-studio[{extra}]'" in str(MissingExtra(extra))
