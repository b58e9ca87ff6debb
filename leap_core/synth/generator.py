"""Write a synthetic street sequence in the KITTI odometry / SemanticKITTI layout.

``OUT/sequences/NN/`` receives ``velodyne/*.bin``, ``labels/*.label`` (semantic | instance << 16),
``image_2/*.png``, ``calib.txt`` (P2, Tr), ``poses.txt`` (camera-frame poses relative to the first
frame, as KITTI stores them), ``times.txt``, the 2D ground truth ``gt2d/{semantic,instance,name,cell}/*.png``
(uint16; ``name`` holds the fine-grained name id of every pixel, see ``leap_core.synth.names``; ``cell`` the
2 m world cell each pixel sees, ``leap_core.synth.camera.world_cells``) and
``synth_version.txt`` (:data:`SYNTH_VERSION`). Output is byte-identical for the same configuration,
whatever the number of worker processes: every frame draws its noise from its own generator seeded by
(seed, frame).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import (
    Calib,
    write_calib,
    write_poses,
)
from leap_core.datasets.rig import RIG_FILE, Camera, camera_rig_text
from leap_core.errors import DatasetError
from leap_core.io_utils import atomic_write_bytes
from leap_core.progress import ProgressFn, report
from leap_core.synth.camera import CameraConfig, SunShadows, camera_to_world, pixel_rays, render
from leap_core.synth.frame_io import in_image_mask, write_camera, write_frame
from leap_core.synth.lidar import LidarConfig, ray_grid, scan
from leap_core.synth.route import EgoConfig
from leap_core.synth.scene import Scene, SceneConfig, build_scene

if TYPE_CHECKING:
    from leap_core.synth.agri import AgriSynthConfig, AgriWorker

SYNTH_VERSION = 3
"""Version of what the generator writes for a given config; bumped whenever the same config would produce
different files (a new object kind, a new ground-truth image). A demo folder with another (or no)
``synth_version.txt`` is stale and is generated again. 2: the demo world with names; 3: the
world-cell images ``gt2d/cell``."""

VERSION_FILE = "synth_version.txt"


def synth_stamp(seq_dir: str | Path) -> str | None:
    """The text of a sequence folder's ``synth_version.txt``, stripped (None: no such file): a bare
    :data:`SYNTH_VERSION` number for the street demo, ``leap_core.synth.agri.AGRI_SYNTH_STAMP`` for
    agri-uav."""
    try:
        return (Path(seq_dir) / VERSION_FILE).read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None


def synth_version(seq_dir: str | Path) -> int | None:
    """The :data:`SYNTH_VERSION` a sequence folder was generated with (None: not written by this
    generator, or by a version before the stamp existed)."""
    try:
        return int((Path(seq_dir) / VERSION_FILE).read_text().strip())
    except (OSError, ValueError):
        return None


SURROUND_RIGS: dict[int, tuple[tuple[str, float], ...]] = {
    1: (("image_2", 0.0),),
    2: (("image_2", 0.0), ("image_rear", 180.0)),
    4: (("image_2", 0.0), ("image_rear", 180.0), ("image_left", 90.0), ("image_right", -90.0)),
}
"""The demo's rigs: per camera its folder and its yaw (degrees to the left of straight ahead)."""


@dataclass(frozen=True)
class SynthConfig:
    """Everything that determines a generated sequence (same config → identical bytes)."""

    frames: int = 60
    """Number of frames (scans + images)."""
    seed: int = 0
    """Seed of the scene layout, the route and all sensor noise."""
    hz: float = 10.0
    """Frame rate (Hz); KITTI records at 10 Hz."""
    shadows: bool = True
    """Render sun shadows in the camera images."""
    lidar: LidarConfig = field(default_factory=LidarConfig)
    """LiDAR sensor model."""
    camera: CameraConfig = field(default_factory=CameraConfig)
    """Camera intrinsics, mounting and rendering."""
    scene: SceneConfig = field(default_factory=SceneConfig)
    """Street layout and object density."""
    ego: EgoConfig = field(default_factory=EgoConfig)
    """How the ego vehicle drives."""
    cameras: int = 1
    """Cameras of the rig (:data:`SURROUND_RIGS`): 1 = the front camera alone (``image_2``); 2 adds a rear
    camera, 4 a rear, a left and a right one, each the front camera turned about the LiDAR's vertical axis
    and written with a ``cameras.yaml``."""

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"SynthConfig.frames must be >= 1, got {self.frames}")
        if self.cameras not in SURROUND_RIGS:
            raise ValueError(
                f"SynthConfig.cameras must be one of {sorted(SURROUND_RIGS)}, got {self.cameras}"
            )
        if self.hz <= 0:
            raise ValueError(f"SynthConfig.hz must be > 0, got {self.hz}")


@dataclass(frozen=True)
class SynthStats:
    """Summary of a generated sequence.

    Attributes:
        path: the sequence folder.
        points: (F,) points per scan.
        in_image: (F,) points per scan that project inside the image (depth > 0); with several cameras,
            inside some camera's image.
    """

    path: Path
    points: npt.NDArray[np.int64]
    in_image: npt.NDArray[np.int64]

    @property
    def in_image_share(self) -> float:
        return float(self.in_image.sum() / max(self.points.sum(), 1))


def lidar_mount(cfg: SynthConfig) -> npt.NDArray[np.float64]:
    """(4, 4) LiDAR → vehicle transform (sensor ``lidar.height`` above the road, axes aligned)."""
    m = np.eye(4)
    m[2, 3] = cfg.lidar.height
    return m


def calibration(cfg: SynthConfig) -> Calib:
    """The sequence's calibration (P2 and Tr as written to ``calib.txt``)."""
    return Calib(P2=cfg.camera.P2(), Tr=cfg.camera.Tr())


def yaw_about_lidar(deg: float) -> npt.NDArray[np.float64]:
    """(4, 4) rotation by ``deg`` about the LiDAR's vertical axis (z up; positive turns x towards y, left)."""
    t = np.deg2rad(deg)
    out = np.eye(4)
    out[:2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    return out


def rig_cameras(cfg: SynthConfig) -> tuple[Camera, ...]:
    """The rig of ``cfg``: the front camera (``P2``, ``Tr``) and the others as it, turned by their yaw
    about the LiDAR (``Tr_k = Tr · R_z(yaw)⁻¹``: the camera's mount turns with it, so each looks out of the
    same point of the car in its own direction)."""
    calib = calibration(cfg)
    return tuple(
        Camera(name, calib.P2, calib.Tr @ np.linalg.inv(yaw_about_lidar(yaw)), source=RIG_FILE)
        for name, yaw in SURROUND_RIGS[cfg.cameras]
    )


def lidar_poses(scene: Scene, cfg: SynthConfig) -> npt.NDArray[np.float64]:
    """(F, 4, 4) LiDAR → world pose per frame."""
    return scene.route.poses @ lidar_mount(cfg)[None]


def camera_poses_kitti(
    lidar_to_world: npt.NDArray[np.float64], tr: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """KITTI ``poses.txt`` matrices: camera i → camera 0, ``Tr · L₀⁻¹ · Lᵢ · Tr⁻¹``.

    A reader recovers the LiDAR poses relative to the first scan as ``Tr⁻¹ · P · Tr = L₀⁻¹ · Lᵢ``.
    """
    rel = np.linalg.inv(lidar_to_world[0])[None] @ lidar_to_world
    return tr[None] @ rel @ np.linalg.inv(tr)[None]


class _Worker:
    """Per-process state: the scene (rebuilt from the config, deterministic), ray grids, shadow tiles."""

    def __init__(self, cfg: SynthConfig, seq_dir: Path) -> None:
        self.cfg = cfg
        self.seq_dir = seq_dir
        self.scene = build_scene(cfg.scene, cfg.ego, cfg.frames, cfg.hz, cfg.seed)
        self.lidar_rays = ray_grid(cfg.lidar)
        self.pixel_rays = pixel_rays(cfg.camera)
        self.shadows = (
            SunShadows(self.scene.static, self.scene.sun, cfg.camera.shadow_res) if cfg.shadows else None
        )
        self.poses = lidar_poses(self.scene, cfg)
        self.calib = calibration(cfg)
        self.rig = rig_cameras(cfg)
        self.version_text = f"{SYNTH_VERSION}\n"

    def frame(self, i: int) -> tuple[int, int, int]:
        cfg, scene = self.cfg, self.scene
        prims = scene.primitives_at(i)
        rng_l, rng_c = (
            np.random.default_rng(s) for s in np.random.SeedSequence([cfg.seed, i, 0x11DA]).spawn(2)
        )
        sc = scan(prims, self.poses[i], cfg.lidar, rng_l, self.lidar_rays)
        cam = render(
            prims,
            len(scene.static),
            camera_to_world(cfg.camera, self.poses[i]),
            cfg.camera,
            sun=scene.sun,
            shadows=self.shadows,
            rng=rng_c,
            rays=self.pixel_rays,
        )
        write_frame(self.seq_dir, i, sc, cam)
        seen = in_image_mask(sc.points[:, :3], self.calib, cfg.camera.width, cfg.camera.height)
        for k, (name, yaw) in enumerate(SURROUND_RIGS[cfg.cameras][1:], start=1):
            # Each further camera draws its sensor noise from its own stream: the front camera's stays.
            rng_k = np.random.default_rng(np.random.SeedSequence([cfg.seed, i, 0x11DA, k]))
            view = render(
                prims,
                len(scene.static),
                camera_to_world(cfg.camera, self.poses[i] @ yaw_about_lidar(yaw)),
                cfg.camera,
                sun=scene.sun,
                shadows=self.shadows,
                rng=rng_k,
                rays=self.pixel_rays,
            )
            write_camera(self.seq_dir, i, view, name, f"gt2d/{name}")
            cam_k = self.rig[k]
            seen |= in_image_mask(
                sc.points[:, :3], Calib(P2=cam_k.P, Tr=cam_k.Tr), cfg.camera.width, cfg.camera.height
            )
        return i, len(sc.points), int(seen.sum())


def make_worker(cfg: SynthConfig | AgriSynthConfig, seq_dir: Path) -> _Worker | AgriWorker:
    """The per-process frame writer of ``cfg``'s domain (street or agri-uav)."""
    # Loaded when first needed: a street run never imports the farm's modules.
    from leap_core.synth.agri import AgriSynthConfig, AgriWorker  # noqa: PLC0415

    if isinstance(cfg, AgriSynthConfig):
        return AgriWorker(cfg, seq_dir)
    return _Worker(cfg, seq_dir)


_WORKER: _Worker | AgriWorker | None = None


def _init_worker(cfg: SynthConfig | AgriSynthConfig, seq_dir: Path) -> None:
    global _WORKER  # noqa: PLW0603  a pool initializer can only leave per-process state in a module global
    _WORKER = make_worker(cfg, seq_dir)


def _run_frame(i: int) -> tuple[int, int, int]:
    assert _WORKER is not None
    return _WORKER.frame(i)


def generate_sequence(
    root: str | Path,
    cfg: SynthConfig | AgriSynthConfig = SynthConfig(),
    sequence: str = "00",
    *,
    force: bool = False,
    workers: int = 1,
    progress: ProgressFn | None = None,
) -> SynthStats:
    """Generate ``root/sequences/<sequence>`` from ``cfg``.

    Args:
        root: dataset root (the folder that holds ``sequences/``).
        cfg: generator configuration: a street (:class:`SynthConfig`) or an agri-uav
            (:class:`leap_core.synth.agri.AgriSynthConfig`) sequence.
        sequence: sequence name (two digits in KITTI).
        force: replace an existing non-empty sequence folder (it is deleted first).
        workers: processes rendering frames in parallel (1 = in this process). The output does not depend
            on it.
        progress: called as ``progress(0, total)`` once the output folder is ready, then as
            ``progress(done, total)`` after each frame.

    Returns:
        Per-frame point counts.

    Raises:
        DatasetError: the sequence folder exists, is not empty and ``force`` is False.
    """
    seq_dir = Path(root) / "sequences" / sequence
    if seq_dir.exists() and any(seq_dir.iterdir()):
        if not force:
            raise DatasetError(seq_dir, "sequence folder is not empty; refusing to overwrite (use --force)")
        shutil.rmtree(seq_dir)
    for sub in ("velodyne", "labels", "image_2", "gt2d/semantic", "gt2d/instance", "gt2d/name"):
        (seq_dir / sub).mkdir(parents=True, exist_ok=True)
    report(progress, 0, cfg.frames)
    points = np.zeros(cfg.frames, np.int64)
    in_image = np.zeros(cfg.frames, np.int64)
    workers = max(1, min(int(workers), cfg.frames))
    global _WORKER  # noqa: PLW0603  forked pool children inherit the built scene through this global
    worker = make_worker(cfg, seq_dir)
    if workers == 1:
        _collect((worker.frame(i) for i in range(cfg.frames)), points, in_image, cfg.frames, progress)
    else:
        # Forked children inherit the built scene. Forking a process that runs other threads can deadlock,
        # so there (and where fork does not exist) the workers are spawned and rebuild it (deterministic).
        fork = "fork" in mp.get_all_start_methods() and threading.active_count() == 1
        ctx = mp.get_context("fork" if fork else "spawn")
        _WORKER = worker
        try:
            pool = (
                ctx.Pool(workers)
                if fork
                else ctx.Pool(workers, initializer=_init_worker, initargs=(cfg, seq_dir))
            )
            with pool:
                _collect(pool.imap(_run_frame, range(cfg.frames)), points, in_image, cfg.frames, progress)
        finally:
            _WORKER = None
    calib = worker.calib
    write_calib(seq_dir / "calib.txt", calib)
    write_poses(seq_dir / "poses.txt", camera_poses_kitti(worker.poses, calib.Tr))
    times = "".join(f"{i / cfg.hz:.6e}\n" for i in range(cfg.frames))
    atomic_write_bytes(seq_dir / "times.txt", times.encode())
    atomic_write_bytes(seq_dir / VERSION_FILE, worker.version_text.encode())
    if isinstance(cfg, SynthConfig) and cfg.cameras > 1:
        atomic_write_bytes(seq_dir / RIG_FILE, camera_rig_text(rig_cameras(cfg)).encode())
    return SynthStats(path=seq_dir, points=points, in_image=in_image)


def _collect(
    results: Iterable[tuple[int, int, int]],
    points: npt.NDArray[np.int64],
    in_image: npt.NDArray[np.int64],
    total: int,
    progress: ProgressFn | None,
) -> None:
    """Store each frame's (index, points, points in image) and report progress."""
    for done, (i, n, n_img) in enumerate(results, start=1):
        points[i] = n
        in_image[i] = n_img
        report(progress, done, total)


def default_workers() -> int:
    """Worker processes to use by default: up to two, never more than the machine's cores."""
    return max(1, min(2, os.cpu_count() or 1))
