"""The agri-uav domain (``leap synth OUT --domain agri-uav``): a survey drone over a farm with a pitched-down
camera and a fixed-FOV solid-state LiDAR, written in the same KITTI / SemanticKITTI layout as the street
demo (``leap_core.synth.generator.generate_sequence`` writes both).

The sensor rig. Camera and LiDAR sit together under the drone, tilted down by ``rig_pitch_deg`` and looking
forward along the flight direction (as on a mapping drone whose gimbal holds an oblique view). The LiDAR's
points are written in the *LiDAR frame*: the drone body's axes at the sensor (x forward, y left, z up), that
is, the sensor head's frame rotated back by the fixed mount tilt (``leap_core.synth.solid_state``). So
``poses.txt`` holds body poses (gravity stays about z, apart from the drone's ±1° wobble) and calib.txt's
``Tr`` (LiDAR → camera) carries the tilt: the camera is not level with the LiDAR frame, as it is on a car.

Classes and ids: ``projects/agri_uav.yaml`` (tree 1, pole 2, fence 3, wire 4, person 5, building 6,
ground 7); names: ``leap_core.synth.names.AGRI_VOCABULARY``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import Calib
from leap_core.errors import ConfigError
from leap_core.synth.camera import CameraConfig, SunShadows, camera_to_world, pixel_rays, render
from leap_core.synth.farm import FarmConfig, FarmScene, build_farm
from leap_core.synth.frame_io import count_in_image, write_frame
from leap_core.synth.raycast import rotation_xyz
from leap_core.synth.solid_state import SolidStateLidarConfig, solid_state_scan
from leap_core.synth.survey import SurveyConfig

AGRI_SYNTH_STAMP = "agri-uav 2"
"""What an agri-uav sequence's ``synth_version.txt`` holds (the street demo's holds a bare number); bumped
whenever the same config would produce different files."""

AGRI_CAMERA = CameraConfig(
    width=800,
    height=600,
    fx=476.7,
    fy=476.7,
    cx=399.5,
    cy=299.5,
    p2_offset=(0.0, 0.0, 0.0),
    tr_translation=(0.0, 0.06, -0.04),
    tr_rotation_deg=(0.2, -0.3, 0.15),
    max_range=260.0,
    shadow_range=140.0,
    shadow_res=0.15,
    noise_std=1.6,
)
"""The drone camera: 800 × 600, 80° × 64° field of view (f = 476.7 px), camera 2 = camera 0. The Tr
translation and rotation are the camera's small offset and mounting error relative to the LiDAR head; the
rig's tilt is added by :func:`rig_camera`."""


@dataclass(frozen=True)
class AgriSynthConfig:
    """Everything that determines a generated agri-uav sequence (same config → identical bytes)."""

    frames: int = 40
    """Number of frames (scans + images)."""
    seed: int = 0
    """Seed of the farm layout, the flight and all sensor noise."""
    hz: float = 5.0
    """Frame rate (Hz): 1.2 m of flight per frame at the default 6 m/s."""
    shadows: bool = True
    """Render sun shadows in the camera images."""
    rig_pitch_deg: float = 45.0
    """Downward tilt of the camera and LiDAR from the drone's forward axis (degrees)."""
    lidar: SolidStateLidarConfig = field(default_factory=SolidStateLidarConfig)
    """Solid-state LiDAR model."""
    camera: CameraConfig = AGRI_CAMERA
    """Camera intrinsics and its mounting relative to the LiDAR head (the rig tilt is added on top)."""
    farm: FarmConfig = field(default_factory=FarmConfig)
    """Farm layout and object density."""
    survey: SurveyConfig = field(default_factory=SurveyConfig)
    """How the drone flies."""

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ConfigError(f"must be >= 1, got {self.frames}", field=("frames",))
        if self.hz <= 0:
            raise ConfigError(f"must be > 0, got {self.hz}", field=("hz",))
        if not 0 <= self.rig_pitch_deg <= 90:
            raise ConfigError(
                f"must be in [0, 90] degrees, got {self.rig_pitch_deg}", field=("rig_pitch_deg",)
            )


def head_to_lidar(cfg: AgriSynthConfig) -> npt.NDArray[np.float64]:
    """(4, 4) sensor head → LiDAR frame: the head is pitched down by ``rig_pitch_deg`` about the body's y
    axis, so its boresight is ``(cos p, 0, −sin p)`` in the LiDAR frame."""
    m = np.eye(4)
    m[:3, :3] = rotation_xyz(0.0, np.deg2rad(cfg.rig_pitch_deg), 0.0)
    return m


def rig_camera(cfg: AgriSynthConfig) -> CameraConfig:
    """The camera with the rig tilt in its Tr: a pitch of −rig_pitch about the LiDAR's y axis, so
    ``Tr⁻¹ · e_z`` (the optical axis in the LiDAR frame) is the head's boresight."""
    r, p, y = cfg.camera.tr_rotation_deg
    return replace(cfg.camera, tr_rotation_deg=(r, p - cfg.rig_pitch_deg, y))


def agri_calibration(cfg: AgriSynthConfig) -> Calib:
    """The sequence's calibration (P2 and Tr as written to ``calib.txt``)."""
    cam = rig_camera(cfg)
    return Calib(P2=cam.P2(), Tr=cam.Tr())


class AgriWorker:
    """Per-process state of the agri-uav generator: the farm (rebuilt from the config, deterministic), the
    camera rays and the shadow tiles. Writes the same files per frame as the street generator."""

    def __init__(self, cfg: AgriSynthConfig, seq_dir: Path) -> None:
        self.cfg = cfg
        self.seq_dir = seq_dir
        self.scene: FarmScene = build_farm(cfg.farm, cfg.survey, cfg.frames, cfg.hz, cfg.seed)
        self.camera = rig_camera(cfg)
        self.pixel_rays = pixel_rays(self.camera)
        self.shadows = (
            SunShadows(self.scene.static, self.scene.sun, self.camera.shadow_res) if cfg.shadows else None
        )
        self.poses = self.scene.poses
        """(F, 4, 4) LiDAR → world: the LiDAR frame is the body frame at the sensor."""
        self.calib = agri_calibration(cfg)
        self.head = head_to_lidar(cfg)
        self.version_text = f"{AGRI_SYNTH_STAMP}\n"

    def frame(self, i: int) -> tuple[int, int, int]:
        cfg, scene = self.cfg, self.scene
        prims = scene.primitives_at(i)
        rng_l, rng_c = (
            np.random.default_rng(s) for s in np.random.SeedSequence([cfg.seed, i, 0xA61D]).spawn(2)
        )
        sc = solid_state_scan(prims, self.poses[i] @ self.head, self.head, cfg.lidar, i, rng_l)
        cam = render(
            prims,
            len(scene.static),
            camera_to_world(self.camera, self.poses[i]),
            self.camera,
            sun=scene.sun,
            shadows=self.shadows,
            rng=rng_c,
            rays=self.pixel_rays,
        )
        write_frame(self.seq_dir, i, sc, cam)
        cam_w, cam_h = self.camera.width, self.camera.height
        return i, len(sc.points), count_in_image(sc.points[:, :3], self.calib, cam_w, cam_h)
