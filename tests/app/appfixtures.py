"""Fixtures for the app tests: a real app on a real SQLite file in a temp folder, and tiny datasets.

Test modules bind them by name at module level (``client = appfixtures.client``), where pytest finds them.
This folder deliberately has no ``conftest.py``: a second module named ``conftest`` would shadow
``tests/conftest.py`` for the tests that import helpers from it.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app
from leap_core.datasets.kitti import write_png16


def add_gt2d(seq_root: Path, frame_ids: list[str], hw: tuple[int, int]) -> None:
    """2D ground-truth masks (what the simulated labeler reads): road below, a car and a building above."""
    h, w = hw
    for fid in frame_ids:
        sem = np.zeros((h, w), np.uint16)
        sem[h // 2 :, :] = 40
        sem[: h // 2, : w // 2] = 10
        sem[: h // 2, w // 2 :] = 50
        inst = np.zeros((h, w), np.uint16)
        inst[: h // 2, : w // 2] = 1
        write_png16(seq_root / "gt2d" / "semantic" / f"{fid}.png", sem)
        write_png16(seq_root / "gt2d" / "instance" / f"{fid}.png", inst)


def kitti_sequences(
    data_root: Path, make_tiny_sequence: Callable[..., Any], build: Path, frames: tuple[int, ...]
) -> list[Path]:
    """``data_root/kitti/sequences/00``, ``01``, ... with ``frames[i]`` frames each (400 points, seed i),
    images, labels and 2D ground truth; built under ``build`` and moved into place."""
    out = []
    for i, n_frames in enumerate(frames):
        seq = make_tiny_sequence(build / f"build{i}", n_frames=n_frames, n_points=400, seed=i)
        add_gt2d(seq.root, seq.frame_ids, (48, 64))
        target = data_root / "kitti" / "sequences" / f"{i:02d}"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(seq.root, target)
        out.append(target)
    return out


@pytest.fixture
def data_root(tmp_path: Path) -> Path:
    root = tmp_path / "data"
    root.mkdir()
    return root


@pytest.fixture
def tiny_dataset(data_root: Path, make_tiny_sequence: Callable[..., Any]) -> Path:
    """``data/tiny/sequences/00``: 4 frames of 400 points with images, labels and 2D ground truth."""
    seq = make_tiny_sequence(data_root / "tiny", n_frames=4, n_points=400)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    return seq.root


@pytest.fixture
def settings(data_root: Path) -> Settings:
    # No pre-started worker: tests that never run the pipeline should not pay for its imports.
    return Settings(
        data_roots=[data_root],
        work_dir=data_root / "studio",
        seed_demo=False,
        progress_interval_s=0.02,
        prewarm_workers=False,
    )


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(settings), base_url="http://127.0.0.1") as c:
        yield c
