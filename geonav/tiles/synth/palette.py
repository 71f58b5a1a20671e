"""Palettes and constants of the synthetic scenes: sizes, the sun, object heights,
materials (:class:`Mat`) with their textures, and the colours every kind draws with."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

# Salt mixed into the seed so that the kinds do not share random streams.
_KIND_SALT = {"residential": 0xA11CE, "campus": 0xB0B, "wild": 0xC0FFEE}

MIN_SIZE_M = 100.0
"""Smallest scene side, metres."""
MIN_GSD_M = 0.02
"""Ground sample distance must be strictly above this, metres per pixel."""
MAX_GSD_M = 5.0
"""Largest ground sample distance, metres per pixel."""
MAX_SIDE_PX = 20_000
"""Largest image side, pixels (memory guard: 20k x 20k RGB plus maps is ~4 GB)."""

# Sun: shadows are cast with an integer pixel step towards the sun,
# (rows, cols) = (1, 2) means the sun stands to the east-south-east.
SUN_STEP_PX = (1, 2)
SUN_ELEVATION_DEG = 50.0
SUN_AZIMUTH_DEG = math.degrees(math.atan2(SUN_STEP_PX[1], -SUN_STEP_PX[0])) % 360.0
"""Sun azimuth, degrees clockwise from north (about 117, east-south-east)."""
SHADOW_TINT = (0.44, 0.48, 0.55)
"""RGB factors in cast shadow (lit by blue skylight only)."""
AMBIENT = 0.35
"""Share of light that is ambient when shading sloped surfaces."""
STEEP_SLOPE = 3.0
"""Height gradients above this (m/m) are walls or crown edges, shaded flat."""

CAR_HEIGHT_M = 1.5
TOWER_DENSITY_PER_KM2 = (3.0, 8.0)
TOWER_HEIGHT_M = (42.0, 70.0)
LANDMARK_HEIGHT_M = (76.0, 92.0)
HOUSE_HEIGHT_M = (5.0, 12.0)
CAMPUS_BUILDING_HEIGHT_M = (10.0, 30.0)
TREE_HEIGHT_M = (6.0, 20.0)
WILD_TREE_HEIGHT_M = (8.0, 25.0)

# Fixed-point bits for sub-pixel OpenCV drawing.
_SHIFT = 3
_ONE = 1 << _SHIFT

Colour = tuple[int, int, int]


class Mat:
    """Material labels of the material map; they select texture strengths."""

    GROUND = 0
    GRASS = 1
    ASPHALT = 2
    CONCRETE = 3
    ROOF = 4
    FLAT_ROOF = 5
    TREE = 6
    WATER = 7
    CROP = 8
    SOIL = 9
    CAR = 10
    PAINT = 11
    TRACK = 12
    DIRT = 13
    FOREST_FLOOR = 14
    POOL = 15
    PAVER = 16
    GRAVEL = 17


# Per-material texture amplitudes (relative brightness): patches (~8 m),
# clumps (~1 m) and grain (one pixel).
_TEXTURE = {
    Mat.GROUND: (0.06, 0.05, 0.05),
    Mat.GRASS: (0.09, 0.08, 0.07),
    Mat.ASPHALT: (0.05, 0.04, 0.06),
    Mat.CONCRETE: (0.04, 0.03, 0.04),
    Mat.ROOF: (0.03, 0.04, 0.06),
    Mat.FLAT_ROOF: (0.04, 0.04, 0.04),
    Mat.TREE: (0.05, 0.16, 0.13),
    Mat.WATER: (0.04, 0.02, 0.015),
    Mat.CROP: (0.06, 0.05, 0.06),
    Mat.SOIL: (0.08, 0.06, 0.07),
    Mat.CAR: (0.0, 0.01, 0.02),
    Mat.PAINT: (0.02, 0.02, 0.04),
    Mat.TRACK: (0.03, 0.03, 0.05),
    Mat.DIRT: (0.08, 0.07, 0.08),
    Mat.FOREST_FLOOR: (0.08, 0.18, 0.14),
    Mat.POOL: (0.02, 0.03, 0.015),
    Mat.PAVER: (0.04, 0.05, 0.08),
    Mat.GRAVEL: (0.06, 0.06, 0.10),
}
_TEXTURE_LUT = np.zeros((3, 256), np.float32)
for _mat, _amps in _TEXTURE.items():
    _TEXTURE_LUT[:, _mat] = _amps

# Palettes (RGB as seen in sunlight).
_ASPHALT = (86, 87, 90)
_ASPHALT_OLD = (112, 110, 106)
_CONCRETE = (176, 172, 163)
_KERB = (198, 195, 188)
_LAWNS = ((92, 118, 58), (104, 126, 62), (120, 130, 72), (138, 136, 86), (84, 108, 56))
_LAWN_WEIGHTS = (0.3, 0.3, 0.18, 0.07, 0.15)
_VERGE = (104, 122, 66)
_SOIL = (126, 104, 80)
_WATER = (52, 68, 66)
_POOL = (72, 158, 178)
_PITCHED_ROOFS = (
    (148, 82, 62),  # terracotta tiles
    (76, 76, 80),  # dark asphalt shingles
    (104, 86, 72),  # brown shingles
    (146, 146, 144),  # light grey shingles
    (118, 64, 54),  # red-brown
    (86, 94, 104),  # slate
    (82, 100, 86),  # green metal
    (168, 150, 122),  # tan
    (60, 62, 66),  # near-black
)
_FLAT_ROOFS = (
    (202, 200, 194),
    (226, 225, 218),
    (170, 168, 162),
    (94, 94, 96),
    (182, 172, 152),
    (132, 130, 126),
)
_TREES = ((58, 78, 42), (70, 92, 46), (86, 102, 52), (52, 68, 44), (96, 108, 58), (74, 84, 48))
_CONIFERS = ((42, 58, 40), (48, 64, 46), (38, 52, 38))
_CARS = (
    ((225, 225, 222), 0.24),
    ((30, 31, 34), 0.16),
    ((170, 172, 176), 0.18),
    ((100, 102, 106), 0.14),
    ((150, 32, 30), 0.08),
    ((36, 60, 120), 0.09),
    ((20, 40, 70), 0.05),
    ((190, 180, 150), 0.06),
)
_CROPS = (
    # colour, material, row period (m), row amplitude
    ((188, 168, 108), Mat.CROP, 0.8, 0.10),  # ripe cereal
    ((110, 136, 62), Mat.CROP, 0.75, 0.14),  # green cereal
    ((78, 106, 50), Mat.CROP, 0.9, 0.22),  # maize rows
    ((128, 102, 76), Mat.SOIL, 1.2, 0.18),  # ploughed
    ((176, 160, 118), Mat.CROP, 6.0, 0.10),  # stubble with swaths
    ((126, 138, 78), Mat.GRASS, 0.0, 0.0),  # pasture
    ((150, 150, 82), Mat.CROP, 0.8, 0.08),  # rapeseed going over
    ((98, 124, 66), Mat.CROP, 3.0, 0.12),  # vegetables in beds
)


def _vary(
    rng: np.random.Generator, colour: Colour, rel: float = 0.08, tint: float = 0.02
) -> Colour:
    """Jitter a colour's brightness by ``rel`` and each channel by ``tint`` (relative)."""
    gain = 1.0 + rel * rng.standard_normal()
    out = np.array(colour, np.float64) * gain * (1.0 + tint * rng.standard_normal(3))
    r, g, b = np.clip(np.round(out), 0, 255).astype(int)
    return int(r), int(g), int(b)


def _pick(rng: np.random.Generator, options: Sequence[Colour]) -> Colour:
    """Uniform choice from a palette."""
    return options[int(rng.integers(len(options)))]

# Street cross-section of the residential scene, metres.
_LOCAL_ROAD_M = 8.0
_ARTERIAL_ROAD_M = 13.0
_VERGE_M = 1.8
_SIDEWALK_M = 1.6
