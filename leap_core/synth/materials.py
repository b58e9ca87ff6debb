"""Class ids, materials and their LiDAR reflectivity for the synthetic street scene.

Class ids are raw SemanticKITTI ids (the values written to ``.label`` and to the 2D ground-truth masks),
plus the demo's own ids 300..302 for objects no SemanticKITTI class names well
(``leap_core.synth.names.DEMO_EXTRA_RAW_IDS``).
A material decides how a surface is textured in the camera image and how bright it is to the LiDAR;
``Primitives.param`` carries up to four per-primitive numbers whose meaning depends on the material
(documented per member below).
"""

from __future__ import annotations

from enum import IntEnum
from typing import Final

import numpy as np


class SemanticId(IntEnum):
    """Raw SemanticKITTI ids used by the generator."""

    UNLABELED = 0
    CAR = 10
    BICYCLE = 11
    BUS = 13
    TRUCK = 18
    PERSON = 30
    ROAD = 40
    PARKING = 44
    SIDEWALK = 48
    OTHER_GROUND = 49
    BUILDING = 50
    FENCE = 51
    VEGETATION = 70
    TRUNK = 71
    TERRAIN = 72
    POLE = 80
    TRAFFIC_SIGN = 81
    MOVING_CAR = 252
    MOVING_PERSON = 254
    MOVING_BUS = 257
    TRAFFIC_CONE = 300
    """Demo extension (``DEMO_EXTRA_RAW_IDS``)."""
    BENCH = 301
    """Demo extension."""
    BOLLARD = 302
    """Demo extension."""


THING_IDS: Final = frozenset(
    {
        SemanticId.CAR,
        SemanticId.BICYCLE,
        SemanticId.TRUCK,
        SemanticId.PERSON,
        SemanticId.MOVING_CAR,
        SemanticId.MOVING_PERSON,
        SemanticId.MOVING_BUS,
        SemanticId.TRAFFIC_CONE,
        SemanticId.BENCH,
        SemanticId.BOLLARD,
    }
)
"""Classes whose objects carry an instance id (as in SemanticKITTI); everything else is stuff (instance 0).
The demo's own objects (cones, benches, bollards) are things too: one mask each, like a detector box."""

REQUIRED_IDS: Final = frozenset(
    {
        SemanticId.ROAD,
        SemanticId.SIDEWALK,
        SemanticId.PARKING,
        SemanticId.BUILDING,
        SemanticId.FENCE,
        SemanticId.VEGETATION,
        SemanticId.TRUNK,
        SemanticId.TERRAIN,
        SemanticId.POLE,
        SemanticId.TRAFFIC_SIGN,
        SemanticId.CAR,
        SemanticId.TRUCK,
        SemanticId.PERSON,
        SemanticId.BICYCLE,
        SemanticId.MOVING_CAR,
        SemanticId.MOVING_PERSON,
        SemanticId.MOVING_BUS,
        SemanticId.OTHER_GROUND,
        SemanticId.TRAFFIC_CONE,
        SemanticId.BENCH,
        SemanticId.BOLLARD,
    }
)
"""Every class a default scene must contain (the bus, gravel and the demo's own
named objects included)."""


class Material(IntEnum):
    """Surface materials. ``param`` meanings are listed per member."""

    ASPHALT = 0
    """Road. param = (street coordinate s at local x = 0, marking style, lane width, -): style 0 plain,
    1 dashed centre line + solid edge lines, 2 zebra crossing (see ``textures.road_paint``)."""
    PAVERS = 1
    """Parking lane paving (small concrete pavers in world coordinates)."""
    SLABS = 2
    """Sidewalk: concrete slabs on top, curb concrete on the sides."""
    GRASS = 3
    """Terrain / lawn."""
    LEAVES = 4
    """Tree crowns, bushes, hedges."""
    BARK = 5
    """Tree trunks."""
    FACADE = 6
    """Building walls. param = (floor height, window spacing, style, seed): style 0 plaster, 1 brick,
    2 office glass bands. The top face is a flat roof."""
    ROOF = 7
    """Pitched roof slabs (clay tiles)."""
    METAL = 8
    """Poles, lamp heads, bicycle frames."""
    SIGN = 9
    """Traffic-sign plates; the +x face is the front. param = (style, -, -, -): 0 blue info, 1 red-ringed
    prohibition, 2 yellow direction, 3 white with red border."""
    PAINT = 10
    """Car / truck cab body; +x is the front (head lamps), −x the back (tail lamps, plate).
    param = (truck, -, -, -): 1 for a truck cab (dark windscreen across the upper front, no grille)."""
    GLASS = 11
    """Car cabin: glass on the sides, paint (the primitive colour) on the roof. param = (wedge, -, -, -):
    1 for a sloped wind screen / rear window box, glass on its +z face only."""
    RUBBER = 12
    """Tyres; cylinder caps show a metal rim."""
    CLOTH = 13
    """Clothing."""
    SKIN = 14
    """Faces, hands."""
    FENCE = 15
    """Fence panels. param = (style, -, -, -): 0 wooden slats, 1 metal bars."""
    TARP = 16
    """Truck cargo box (panelled)."""
    SOIL = 17
    """Bare soil and dirt tracks (agri-uav domain). param = (furrow spacing (m, 0 = none), furrow
    direction (rad), -, -): ploughed furrows as darker stripes."""
    CROP = 18
    """Crop fields seen from above (agri-uav domain): green rows over soil on the top face.
    param = (row spacing (m), row direction (rad), canopy cover in [0, 1], -)."""


REFLECTIVITY: Final = np.array(
    [
        0.16,
        0.22,
        0.27,
        0.42,
        0.46,
        0.32,
        0.30,
        0.24,
        0.38,
        0.92,
        0.28,
        0.06,
        0.07,
        0.30,
        0.36,
        0.28,
        0.34,
        0.24,
        0.44,
    ],
    dtype=np.float32,
)
"""Base LiDAR remission (KITTI scale, 0..1) per :class:`Material` value (index = material id).
Vegetation is bright in near infrared, retro-reflective signs near 1, glass and tyres dark."""

DROPOUT: Final = np.array(
    [0.0, 0.0, 0.0, 0.01, 0.03, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01, 0.55, 0.10, 0.01, 0.01, 0.05, 0.0, 0.0, 0.02],
    dtype=np.float32,
)
"""Probability that a LiDAR return from each material is lost (specular glass, black rubber)."""

assert len(REFLECTIVITY) == len(DROPOUT) == len(Material)
