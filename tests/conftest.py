"""Shared test fixtures: tiny KITTI-layout sequences built with the real writers."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from synthcache import SYNTH_CACHE_ENV

from leap_core.datasets.kitti import Calib, write_calib, write_image, write_label, write_poses, write_scan


@pytest.fixture(scope="session", autouse=True)
def shared_synth_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The folder where :func:`synthcache.synth_copy` keeps what it rendered: one per test run, shared by
    the pytest-xdist processes (their temporary folders lie side by side in the run's own)."""
    base = tmp_path_factory.getbasetemp()
    cache = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "synth-cache"
    cache.mkdir(exist_ok=True)
    before = os.environ.get(SYNTH_CACHE_ENV)
    os.environ[SYNTH_CACHE_ENV] = str(cache)
    yield cache
    if before is None:
        os.environ.pop(SYNTH_CACHE_ENV, None)
    else:
        os.environ[SYNTH_CACHE_ENV] = before


LONGEST_FILES = (
    "tests/test_demo_outputs.py",
    "tests/app/test_fuzz_api.py",
    "tests/browser/test_viewer.py",
    "tests/browser/test_viewer_review.py",
)
"""Test files of a minute or more on 2 cores (the 60-frame demo and two 3D-CN runs, the schemathesis run,
two viewer sessions in Chromium), longest first."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Long files first: :data:`LONGEST_FILES`, then every file with a slow or browser test, then the rest,
    each in collection order. pytest-xdist hands files to its processes in this order (scripts/test.sh
    turns off its own ordering by test count, which put the longest files, few tests each, last): a long
    file started last kept one process busy after the other had finished."""
    root = config.rootpath
    missing = [name for name in LONGEST_FILES if not (root / name).is_file()]
    if missing:
        raise pytest.UsageError(f"tests/conftest.py LONGEST_FILES lists files that do not exist: {missing}")
    heavy = {it.path for it in items if it.get_closest_marker("slow") or it.get_closest_marker("browser")}

    def rank(item: pytest.Item) -> int:
        name = item.path.relative_to(root).as_posix() if item.path.is_relative_to(root) else ""
        if name in LONGEST_FILES:
            return LONGEST_FILES.index(name)
        return len(LONGEST_FILES) + (0 if item.path in heavy else 1)

    items.sort(key=rank)


TINY_IMAGE_HW = (48, 64)
"""Image size of tiny sequences (KITTI's aspect ratio is wider; any size works)."""


def make_tiny_calib() -> Calib:
    """A KITTI-like calibration scaled to a 64×48 image.

    P2 = K·[I | (-0.06, 0, 0)] (colour camera 6 cm right of camera 0). Tr turns LiDAR axes (x forward,
    y left, z up) into camera axes (x right, y down, z forward) and puts the LiDAR origin at
    (0, -0.08, -0.27) in camera coordinates (8 cm above and 27 cm behind the camera).
    """
    fx, fy, cx, cy = 50.0, 50.0, 32.0, 24.0
    p2 = np.array([[fx, 0.0, cx, -fx * 0.06], [0.0, fy, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    tr = np.eye(4)
    tr[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    tr[:3, 3] = [0.0, -0.08, -0.27]
    return Calib(P2=p2, Tr=tr)


@dataclass
class TinySequence:
    """What :func:`build_tiny_sequence` wrote, for comparing against what the readers return."""

    root: Path
    frame_ids: list[str]
    points: list[np.ndarray]
    """(N, 4) float32 per frame."""
    semantic: list[np.ndarray] | None
    """(N,) raw semantic ids per frame (None without labels)."""
    instance: list[np.ndarray] | None
    """(N,) instance ids per frame (None without labels)."""
    images: list[np.ndarray] | None
    """(H, W, 3) uint8 RGB per frame (None without images)."""
    calib: Calib
    cam_poses: np.ndarray
    """(F, 4, 4) poses in the left camera frame, as written to poses.txt."""
    times: np.ndarray
    """(F,) seconds, as written to times.txt."""


def build_tiny_sequence(
    tmp_path: Path,
    n_frames: int = 3,
    n_points: int = 50,
    with_images: bool = True,
    with_labels: bool = True,
    seed: int = 0,
) -> TinySequence:
    """Write ``tmp_path/sequences/00`` in KITTI layout: points 4..20 m ahead of the LiDAR, a camera
    moving 1.5 m forward and yawing 0.05 rad per frame, labels mixing static, moving and ignored ids."""
    rng = np.random.default_rng(seed)
    root = tmp_path / "sequences" / "00"
    calib = make_tiny_calib()
    frame_ids = [f"{i:06d}" for i in range(n_frames)]
    cam_poses = np.tile(np.eye(4), (n_frames, 1, 1))
    for i in range(n_frames):
        yaw = 0.05 * i
        cam_poses[i, :3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
        cam_poses[i, :3, 3] = [0.0, 0.0, 1.5 * i]
    points, semantic, instance, images = [], [], [], []
    for fid in frame_ids:
        pts = np.column_stack(
            [
                rng.uniform(4.0, 20.0, n_points),
                rng.uniform(-6.0, 6.0, n_points),
                rng.uniform(-2.0, 1.0, n_points),
                rng.uniform(0.0, 1.0, n_points),
            ]
        ).astype(np.float32)
        write_scan(root / "velodyne" / f"{fid}.bin", pts)
        points.append(pts)
        if with_labels:
            sem = rng.choice(np.array([10, 252, 40, 60, 48, 50, 70, 0, 1, 99]), n_points)
            inst = np.where(np.isin(sem, (10, 252)), rng.integers(1, 4, n_points), 0)
            write_label(root / "labels" / f"{fid}.label", sem, inst)
            semantic.append(sem)
            instance.append(inst)
        if with_images:
            img = rng.integers(0, 256, (*TINY_IMAGE_HW, 3), dtype=np.uint8)
            write_image(root / "image_2" / f"{fid}.png", img)
            images.append(img)
    write_calib(root / "calib.txt", calib)
    write_poses(root / "poses.txt", cam_poses)
    times = np.arange(n_frames) * 0.1
    (root / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
    return TinySequence(
        root=root,
        frame_ids=frame_ids,
        points=points,
        semantic=semantic if with_labels else None,
        instance=instance if with_labels else None,
        images=images if with_images else None,
        calib=calib,
        cam_poses=cam_poses,
        times=times,
    )


@pytest.fixture
def make_tiny_sequence() -> Callable[..., TinySequence]:
    """Factory ``make_tiny_sequence(tmp_path, n_frames=3, n_points=50, with_images=True, with_labels=True)``
    writing ``tmp_path/sequences/00`` and returning a :class:`TinySequence`."""
    return build_tiny_sequence


@pytest.fixture
def tiny_calib() -> Calib:
    """The calibration of tiny sequences (see :func:`make_tiny_calib`)."""
    return make_tiny_calib()
