"""Embedded demo sequence generator: a procedural street scene written in the KITTI / SemanticKITTI layout
(LiDAR scans with per-point labels, camera images with 2D ground truth and per-pixel names, calibration,
poses)."""

from __future__ import annotations

from leap_core.synth.camera import CameraConfig as CameraConfig
from leap_core.synth.generator import SYNTH_VERSION as SYNTH_VERSION
from leap_core.synth.generator import SynthConfig as SynthConfig
from leap_core.synth.generator import SynthStats as SynthStats
from leap_core.synth.generator import default_workers as default_workers
from leap_core.synth.generator import generate_sequence as generate_sequence
from leap_core.synth.generator import synth_version as synth_version
from leap_core.synth.lidar import LidarConfig as LidarConfig
from leap_core.synth.route import EgoConfig as EgoConfig
from leap_core.synth.scene import SceneConfig as SceneConfig
from leap_core.synth.scene import build_scene as build_scene

__all__ = [
    "SYNTH_VERSION",
    "CameraConfig",
    "EgoConfig",
    "LidarConfig",
    "SceneConfig",
    "SynthConfig",
    "SynthStats",
    "build_scene",
    "default_workers",
    "generate_sequence",
    "synth_version",
]
