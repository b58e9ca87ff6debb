"""Embedded demo sequence generator: a procedural street scene written in the KITTI / SemanticKITTI layout
(LiDAR scans with per-point labels, camera images with 2D ground truth, calibration, poses)."""

from __future__ import annotations

from leap_core.synth.camera import CameraConfig as CameraConfig
from leap_core.synth.generator import SynthConfig as SynthConfig
from leap_core.synth.generator import SynthStats as SynthStats
from leap_core.synth.generator import default_workers as default_workers
from leap_core.synth.generator import generate_sequence as generate_sequence
from leap_core.synth.lidar import LidarConfig as LidarConfig
from leap_core.synth.route import EgoConfig as EgoConfig
from leap_core.synth.scene import SceneConfig as SceneConfig
from leap_core.synth.scene import build_scene as build_scene

__all__ = [
    "CameraConfig",
    "EgoConfig",
    "LidarConfig",
    "SceneConfig",
    "SynthConfig",
    "SynthStats",
    "build_scene",
    "default_workers",
    "generate_sequence",
]
