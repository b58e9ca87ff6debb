"""Class ids, materials and their LiDAR reflectivity for the synthetic street scene.

Class ids are raw SemanticKITTI ids (the values written to ``.label`` and to the 2D ground-truth masks).
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
    TRUCK = 18
    PERSON = 30
    ROAD = 40
    PARKING = 44
    SIDEWALK = 48
    BUILDING = 50
    FENCE = 51
    VEGETATION = 70
    TRUNK = 71
    TERRAIN = 72
    POLE = 80
    TRAFFIC_SIGN = 81
    MOVING_CAR = 252
    MOVING_PERSON = 254


THING_IDS: Final = frozenset(
    {
        SemanticId.CAR,
        SemanticId.BICYCLE,
        SemanticId.TRUCK,
        SemanticId.PERSON,
        SemanticId.MOVING_CAR,
        SemanticId.MOVING_PERSON,
    }
)
"""Classes whose objects carry an instance id (as in SemanticKITTI); everything else is stuff (instance 0)."""

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
    }
)
"""Every class a default scene must contain (issue 2, item 4)."""


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


REFLECTIVITY: Final = np.array(
    [0.16, 0.22, 0.27, 0.42, 0.46, 0.32, 0.30, 0.24, 0.38, 0.92, 0.28, 0.06, 0.07, 0.30, 0.36, 0.28, 0.34],
    dtype=np.float32,
)
"""Base LiDAR remission (KITTI scale, 0..1) per :class:`Material` value (index = material id).
Vegetation is bright in near infrared, retro-reflective signs near 1, glass and tyres dark."""

DROPOUT: Final = np.array(
    [0.0, 0.0, 0.0, 0.01, 0.03, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01, 0.55, 0.10, 0.01, 0.01, 0.05, 0.0],
    dtype=np.float32,
)
"""Probability that a LiDAR return from each material is lost (specular glass, black rubber)."""

assert len(REFLECTIVITY) == len(DROPOUT) == len(Material)
