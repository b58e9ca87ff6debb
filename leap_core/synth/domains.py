"""The domains ``leap synth --domain`` generates, by name, and the generator config of each.

- ``street``: the demo town seen from a car with a spinning 64-beam LiDAR (HDL-64E-like, 1.73 m, as on
  the KITTI car), 10 Hz.
- ``street-32``: *another* street domain, for a 3D-CN network trained on ground truth (``leap train-3dcn``)
  that the street's 3D-CN then starts from, as the paper fine-tunes a network trained on another dataset
  (docs/METHOD.md C.2). It differs from ``street`` where nuScenes differs from SemanticKITTI for a network
  that sees only XYZ: the sensor (32 beams from +10° to −30° at 1.84 m, as nuScenes' HDL-32E: half the
  rings, twice their spacing, a wider vertical field) and the town (blocks about a quarter shorter,
  narrower lanes and sidewalks, fewer tree rows and yards, two to two and a half times the trucks, cyclists
  and people). Objects, materials, camera and classes are the street's.
- ``agri-uav``: a survey drone over a farm (``leap_core.synth.agri``), 5 Hz.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from leap_core.synth.generator import SynthConfig
from leap_core.synth.lidar import LidarConfig
from leap_core.synth.scene import SceneConfig

if TYPE_CHECKING:
    from leap_core.synth.agri import AgriSynthConfig

DOMAINS: dict[str, str] = {
    "street": "a car with a spinning 64-beam LiDAR in a town (10 Hz)",
    "street-32": "another town seen by a 32-beam LiDAR (+10° to −30°, 1.84 m, like nuScenes'), as a labeled "
    "source domain for `leap train-3dcn` (10 Hz)",
    "agri-uav": "a survey drone over a farm with a pitched camera and a 70°×30° solid-state LiDAR (5 Hz; "
    "classes of projects/agri_uav.yaml)",
}
"""Domain name → one line on what it generates (the CLI's help)."""

STREET_32_LIDAR = LidarConfig(height=1.84, beams=32, upper_deg=(10.0, -9.4), lower_deg=(-10.7, -30.0))
"""The ``street-32`` sensor: 32 rings about 1.3° apart from +10° to −30° (the two blocks of
:class:`LidarConfig` laid end to end), mounted 1.84 m above the road."""

STREET_32_SCENE = SceneConfig(
    block_x=(56.0, 72.0),
    block_y=(60.0, 80.0),
    lane_width=3.2,
    sidewalk_width=2.6,
    truck_rate=0.15,
    tree_row_rate=0.45,
    yard_rate=0.3,
    bicycles_per_side=1.2,
    persons_per_side=1.0,
)
"""The ``street-32`` town (the fields it changes from :class:`SceneConfig`'s defaults)."""


def domain_config(domain: str, frames: int, seed: int, cameras: int = 1) -> SynthConfig | AgriSynthConfig:
    """The generator config of ``domain`` (a key of :data:`DOMAINS`) for ``frames`` frames from ``seed``,
    with a rig of ``cameras`` cameras (``SynthConfig.cameras``; the street domains only).

    Raises:
        ValueError: an unknown domain (the message lists the known ones), or a rig the domain lacks.
    """
    if domain == "street":
        return SynthConfig(frames=frames, seed=seed, cameras=cameras)
    if domain == "street-32":
        return SynthConfig(
            frames=frames, seed=seed, lidar=STREET_32_LIDAR, scene=STREET_32_SCENE, cameras=cameras
        )
    if cameras != 1 and domain in DOMAINS:
        raise ValueError(f"the {domain} domain has one camera (a rig of several is a street option)")
    if domain == "agri-uav":
        # Loaded when asked for: a street run never imports the farm's modules.
        from leap_core.synth.agri import AgriSynthConfig  # noqa: PLC0415

        return AgriSynthConfig(frames=frames, seed=seed)
    raise ValueError(f"unknown domain {domain!r} (known: {', '.join(DOMAINS)})")
