"""Synthetic aerial scenes that look like nadir orthophotos, with a surface model.

Three kinds stand in for real imagery so the whole toolkit runs offline:

* ``residential`` (the paper's scene A): a street grid with kerbs, sidewalks
  and lane markings, blocks of houses with gable, hip and flat roofs, gardens,
  driveways, pools, trees, parked cars, a few apartment blocks and towers.
* ``campus`` (scene B): large flat-roofed buildings with rooftop units, lawn
  quads crossed by paths, parking lots with stall lines and cars, sports
  fields with a running track, tree-lined roads and a few towers.
* ``wild``: forest, agricultural fields with row textures, a meandering river
  with banks, dirt tracks, hedgerows, scattered trees and maybe a farmstead.

Frames and units: the image is north-up, row 0 is the north edge and column 0
the west edge. Layout code works in scene metres, ``x`` east from the west
edge and ``y`` south from the north edge, so pixel ``(row, col)`` covers
``x in [col, col + 1) * gsd_m`` and ``y in [row, row + 1) * gsd_m``.

How an image is made: polygons, lines and discs are drawn with OpenCV into an
albedo image (``uint8`` RGB), a material map (one label per pixel, used to
pick texture strengths) and the height map. Trees are stamped as lumpy dome or
cone sprites. The finish pass then shades sloped surfaces (roof halves, tree
crowns) with a Lambertian term, casts shadows from the height map in one sun
direction, and adds low-frequency brightness and colour drift, material
textures and fine grain, so no two places look the same.

Everything random comes from one ``numpy.random.Generator`` seeded by
``(seed, kind)``, so a scene is a pure function of
``(kind, size_m, gsd_m, seed)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from geonav.errors import ConfigError

__all__ = ["KINDS", "SynthImage", "synthesize"]

KINDS: tuple[str, ...] = ("residential", "campus", "wild")
"""Kinds of synthetic scene :func:`synthesize` can make."""

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


@dataclass(frozen=True)
class SynthImage:
    """A synthetic nadir orthophoto and its surface model.

    Attributes:
        rgb: (H, W, 3) uint8 image; row 0 is the north edge, column 0 the west edge.
        height_m: (H, W) float32 surface height above the ground, metres (0 on
            bare ground, roofs, tree crowns and cars above it).
        gsd_m: Ground sample distance, metres per pixel.
        kind: One of :data:`KINDS`.
        seed: The seed the scene was made from.
    """

    rgb: np.ndarray
    height_m: np.ndarray
    gsd_m: float
    kind: str
    seed: int


def synthesize(
    kind: str,
    size_m: float = 1200.0,
    gsd_m: float = 0.25,
    seed: int = 0,
    progress: Callable[[float], None] | None = None,
) -> SynthImage:
    """Make a synthetic aerial scene.

    Args:
        kind: One of :data:`KINDS`.
        size_m: Side of the square scene, metres (at least 100).
        gsd_m: Ground sample distance, metres per pixel, in (0.02, 5].
        seed: Non-negative seed; the output is a pure function of
            ``(kind, size_m, gsd_m, seed)``.
        progress: Called with the finished fraction (0..1) as work advances.

    Returns:
        The image, its height map and the parameters it was made with.

    Raises:
        ConfigError: Unknown kind, size below 100 m, GSD outside (0.02, 5],
            an image side above :data:`MAX_SIDE_PX` or a negative seed.
    """
    if kind not in KINDS:
        raise ConfigError(f"unknown synthetic scene kind {kind!r}; known kinds: {', '.join(KINDS)}")
    if not (math.isfinite(size_m) and size_m >= MIN_SIZE_M):
        raise ConfigError(f"size_m={size_m!r} is too small; use at least {MIN_SIZE_M:g} m")
    if not (math.isfinite(gsd_m) and MIN_GSD_M < gsd_m <= MAX_GSD_M):
        raise ConfigError(
            f"gsd_m={gsd_m!r} is outside ({MIN_GSD_M:g}, {MAX_GSD_M:g}] metres per pixel"
        )
    side_px = int(round(size_m / gsd_m))
    if side_px > MAX_SIDE_PX:
        raise ConfigError(
            f"size_m={size_m:g} at gsd_m={gsd_m:g} gives {side_px} px per side, above "
            f"{MAX_SIDE_PX}; use a coarser gsd_m or a smaller scene"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed={seed!r} must be a non-negative integer")

    report = progress if progress is not None else (lambda fraction: None)
    report(0.0)
    rng = np.random.default_rng([int(seed), _KIND_SALT[kind]])
    canvas = _Canvas(side_px, gsd_m, rng)
    layouts: dict[str, Callable[[_Canvas, np.random.Generator], None]] = {
        "residential": _residential,
        "campus": _campus,
        "wild": _wild,
    }
    layouts[kind](canvas, rng)
    report(0.6)
    rgb = _finish(canvas, rng, report)
    report(1.0)
    return SynthImage(
        rgb=rgb, height_m=canvas.height, gsd_m=float(gsd_m), kind=kind, seed=int(seed)
    )


# --------------------------------------------------------------------------
# Canvas and drawing primitives (all inputs in scene metres)
# --------------------------------------------------------------------------


class _Canvas:
    """Albedo, material, height and pattern layers plus metre-based drawing."""

    def __init__(self, side_px: int, gsd_m: float, rng: np.random.Generator) -> None:
        self.n = side_px
        self.gsd_m = gsd_m
        self.size_m = side_px * gsd_m
        self.rgb = np.zeros((side_px, side_px, 3), np.uint8)
        self.mat = np.zeros((side_px, side_px), np.uint8)
        self.height = np.zeros((side_px, side_px), np.float32)
        # Relative brightness patterns (crop rows, mowing stripes), 0 = none.
        self.pattern = np.zeros((side_px, side_px), np.float32)
        self._sprites = _SpriteBank(np.random.default_rng(rng.integers(2**63)))

    # -- coordinates -------------------------------------------------------
    def _fixed(self, pts_m: np.ndarray) -> np.ndarray:
        """Metres (N, 2) -> fixed-point pixel coordinates (N, 1, 2) int32."""
        px = np.asarray(pts_m, np.float64) / self.gsd_m - 0.5
        return np.round(px * _ONE).astype(np.int32).reshape(-1, 1, 2)

    def px(self, metres: float) -> float:
        """Length in metres -> pixels."""
        return metres / self.gsd_m

    def inside(self, x: float, y: float, margin_m: float = 0.0) -> bool:
        """Whether a point lies inside the scene grown by ``margin_m``."""
        return -margin_m <= x <= self.size_m + margin_m and -margin_m <= y <= self.size_m + margin_m

    def mat_at(self, x: float, y: float) -> int:
        """Material under a point (GROUND outside the scene)."""
        col, row = int(x / self.gsd_m), int(y / self.gsd_m)
        if 0 <= row < self.n and 0 <= col < self.n:
            return int(self.mat[row, col])
        return Mat.GROUND

    # -- filled shapes -----------------------------------------------------
    def fill(
        self, polys: Sequence[np.ndarray], colour: Colour, mat: int, height_m: float | None = None
    ) -> None:
        """Fill polygons (each (N, 2) metres) with a colour and material."""
        pts = [self._fixed(p) for p in polys]
        cv2.fillPoly(self.rgb, pts, colour, cv2.LINE_AA, _SHIFT)
        cv2.fillPoly(self.mat, pts, int(mat), cv2.LINE_8, _SHIFT)
        if height_m is not None:
            cv2.fillPoly(self.height, pts, float(height_m), cv2.LINE_8, _SHIFT)

    def fill_all(self, colour: Colour, mat: int) -> None:
        """Cover the whole scene."""
        self.rgb[:] = np.array(colour, np.uint8)
        self.mat.fill(mat)

    def line(
        self, pts_m: np.ndarray, width_m: float, colour: Colour, mat: int, closed: bool = False
    ) -> None:
        """Draw a polyline of a given width (at least one pixel)."""
        thickness = max(1, int(round(self.px(width_m))))
        pts = [self._fixed(pts_m)]
        cv2.polylines(self.rgb, pts, closed, colour, thickness, cv2.LINE_AA, _SHIFT)
        cv2.polylines(self.mat, pts, closed, int(mat), thickness, cv2.LINE_8, _SHIFT)

    def disc(
        self,
        x: float,
        y: float,
        r_m: float,
        colour: Colour,
        mat: int,
        height_m: float | None = None,
    ) -> None:
        """Fill a disc."""
        centre = tuple(int(v) for v in self._fixed(np.array([[x, y]]))[0, 0])
        radius = max(1, int(round(self.px(r_m) * _ONE)))
        cv2.circle(self.rgb, centre, radius, colour, -1, cv2.LINE_AA, _SHIFT)
        cv2.circle(self.mat, centre, radius, int(mat), -1, cv2.LINE_8, _SHIFT)
        if height_m is not None:
            cv2.circle(self.height, centre, radius, float(height_m), -1, cv2.LINE_8, _SHIFT)

    def _window(self, poly_m: np.ndarray) -> tuple[int, int, int, int] | None:
        """Pixel bounding box (r0, r1, c0, c1) of a polygon, clipped; None if empty."""
        lo = np.floor(poly_m.min(axis=0) / self.gsd_m).astype(int) - 1
        hi = np.ceil(poly_m.max(axis=0) / self.gsd_m).astype(int) + 2
        c0, r0 = max(lo[0], 0), max(lo[1], 0)
        c1, r1 = min(hi[0], self.n), min(hi[1], self.n)
        if c0 >= c1 or r0 >= r1:
            return None
        return r0, r1, c0, c1

    def stripes(
        self,
        poly_m: np.ndarray,
        angle_rad: float,
        period_m: float,
        amplitude: float,
        duty: float = 0.5,
    ) -> None:
        """Add a square-wave brightness pattern (crop rows, mowing) inside a polygon."""
        win = self._window(poly_m)
        if win is None or period_m <= 0 or amplitude == 0:
            return
        r0, r1, c0, c1 = win
        mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
        local = np.asarray(poly_m) - np.array([c0, r0]) * self.gsd_m
        cv2.fillPoly(mask, [self._fixed(local)], 1, cv2.LINE_8, _SHIFT)
        ys = (np.arange(r0, r1, dtype=np.float32) + 0.5) * self.gsd_m
        xs = (np.arange(c0, c1, dtype=np.float32) + 0.5) * self.gsd_m
        t = xs[None, :] * math.cos(angle_rad) + ys[:, None] * math.sin(angle_rad)
        phase = np.mod(t / period_m, 1.0)
        if period_m < 4 * self.gsd_m:
            # Rows finer than the pixel grid can show: a soft sinusoid, not aliased squares.
            wave = np.sin(2 * np.pi * phase) * (amplitude * 0.7)
        else:
            wave = np.where(phase < duty, amplitude, -amplitude).astype(np.float32)
        region = self.pattern[r0:r1, c0:c1]
        sel = mask.astype(bool)
        region[sel] = wave[sel]

    # -- raised objects ----------------------------------------------------
    def roof(
        self,
        cx: float,
        cy: float,
        half_len: float,
        half_wid: float,
        angle: float,
        eave_m: float,
        rise_m: float,
        shape: str,
        colour: Colour,
        mat: int = Mat.ROOF,
        edge: float = 0.82,
    ) -> None:
        """Raise a rectangular building of a given roof shape.

        The roof's ridge runs along ``angle`` (radians from east, towards
        south); ``half_len`` is along the ridge and ``half_wid`` across it.
        Shapes: ``gable`` (ridge along the length), ``hip`` (sloped on all four
        sides), ``flat`` (with a parapet line). The height map gets
        ``eave_m + rise_m * profile``; the finish pass shades the slopes.
        """
        ca, sa = math.cos(angle), math.sin(angle)
        ex = abs(half_len * ca) + abs(half_wid * sa)
        ey = abs(half_len * sa) + abs(half_wid * ca)
        box = np.array([[cx - ex, cy - ey], [cx + ex, cy + ey]])
        win = self._window(box)
        if win is None:
            return
        r0, r1, c0, c1 = win
        g = self.gsd_m
        xs = ((np.arange(c0, c1, dtype=np.float32) + 0.5) * g - cx)[None, :]
        ys = ((np.arange(r0, r1, dtype=np.float32) + 0.5) * g - cy)[:, None]
        u = xs * ca + ys * sa
        v = ys * ca - xs * sa
        du = half_len - np.abs(u)
        dv = half_wid - np.abs(v)
        inside = (du >= 0) & (dv >= 0)
        if not inside.any():
            return
        if shape == "gable":
            profile = dv / half_wid
        elif shape == "hip":
            profile = np.minimum(dv, du) / half_wid
        else:
            profile = np.zeros_like(dv)
        h = eave_m + rise_m * np.clip(profile, 0.0, 1.0)
        sub_h = self.height[r0:r1, c0:c1]
        win_mask = inside & (h > sub_h)
        sub_h[win_mask] = h[win_mask]
        rim = np.minimum(du, dv) < max(0.3, 0.6 * g)
        col = np.empty(h.shape + (3,), np.uint8)
        col[:] = colour
        col[rim] = (np.array(colour) * edge).astype(np.uint8)
        if shape == "flat":
            # Membrane seams across the roof.
            seam = (np.mod(u, 1.8) < max(0.12, g)) & ~rim
            col[seam] = (np.array(colour) * 0.94).astype(np.uint8)
        elif shape == "gable":
            ridge = (dv > half_wid - max(0.15, 0.5 * g)) & ~rim
            col[ridge] = (np.array(colour) * 0.9).astype(np.uint8)
        self.rgb[r0:r1, c0:c1][win_mask] = col[win_mask]
        self.mat[r0:r1, c0:c1][win_mask] = mat
        self.pattern[r0:r1, c0:c1][win_mask] = 0.0

    def tree(
        self,
        x: float,
        y: float,
        radius_m: float,
        height_m: float,
        colour: Colour,
        cone: bool = False,
    ) -> None:
        """Stamp a tree crown (lumpy dome, or cone for conifers) where it is the top surface."""
        r_px = self.px(radius_m)
        sprite = self._sprites.get(r_px, cone)
        k = sprite.shape[0] // 2
        col, row = int(x / self.gsd_m), int(y / self.gsd_m)
        r0, r1, c0, c1 = row - k, row + k + 1, col - k, col + k + 1
        sr0, sc0 = max(0, -r0), max(0, -c0)
        r0c, c0c, r1c, c1c = max(r0, 0), max(c0, 0), min(r1, self.n), min(c1, self.n)
        if r0c >= r1c or c0c >= c1c:
            return
        sp = sprite[sr0 : sr0 + r1c - r0c, sc0 : sc0 + c1c - c0c]
        crown = height_m * (0.55 + 0.45 * sp)
        sub_h = self.height[r0c:r1c, c0c:c1c]
        win = (sp > 0) & (crown > sub_h)
        sub_h[win] = crown[win]
        self.rgb[r0c:r1c, c0c:c1c][win] = colour
        self.mat[r0c:r1c, c0c:c1c][win] = Mat.TREE
        self.pattern[r0c:r1c, c0c:c1c][win] = 0.0


class _SpriteBank:
    """Cache of crown sprites: (2k+1)^2 float32 in [0, 1], 0 outside the crown."""

    VARIANTS = 6

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._cache: dict[tuple[int, bool], list[np.ndarray]] = {}
        self._turn = 0

    def get(self, r_px: float, cone: bool) -> np.ndarray:
        """A sprite of about ``r_px`` radius; variants rotate deterministically."""
        key = (max(1, int(round(r_px * 2))), cone)  # half-pixel radius bins
        if key not in self._cache:
            self._cache[key] = [self._make(key[0] / 2, cone) for _ in range(self.VARIANTS)]
        self._turn += 1
        return self._cache[key][self._turn % self.VARIANTS]

    def _make(self, r: float, cone: bool) -> np.ndarray:
        rng = self._rng
        k = int(math.ceil(r * 1.15)) + 1
        yy, xx = np.mgrid[-k : k + 1, -k : k + 1].astype(np.float32)
        theta = np.arctan2(yy, xx)
        edge = np.ones_like(theta)
        for harmonic in (2, 3, 5, 7):
            edge += rng.normal(0, 0.05) * np.cos(harmonic * theta + rng.uniform(0, 2 * np.pi))
        rho = np.hypot(xx, yy) / (max(r, 0.7) * edge)
        if cone:
            prof = np.clip(1.0 - rho, 0.0, None)
        else:
            prof = np.sqrt(np.clip(1.0 - rho * rho, 0.0, None))
        if r >= 3:
            # Lumps: several sub-crowns give the crown its clumpy texture.
            lumps = rng.standard_normal(xx.shape).astype(np.float32)
            lumps = cv2.GaussianBlur(lumps, (0, 0), max(0.8, r / 5))
            lumps /= lumps.std() + 1e-6
            prof = prof * (1.0 + 0.12 * lumps)
        prof = np.where(rho < 1.0, np.clip(prof, 0.02, 1.0), 0.0)
        return prof.astype(np.float32)


@dataclass(frozen=True)
class _Frame:
    """A frame rotated by ``theta`` (radians, east towards south) about (ox, oy) metres."""

    ox: float
    oy: float
    theta: float

    def pt(self, u: float, v: float) -> tuple[float, float]:
        """Local (u, v) metres -> scene (x, y) metres."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return self.ox + u * c - v * s, self.oy + u * s + v * c

    def pts(self, uv: np.ndarray) -> np.ndarray:
        """Local points (N, 2) -> scene points (N, 2)."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        uv = np.asarray(uv, np.float64)
        return np.stack(
            [self.ox + uv[:, 0] * c - uv[:, 1] * s, self.oy + uv[:, 0] * s + uv[:, 1] * c], axis=1
        )

    def rect(self, u0: float, v0: float, u1: float, v1: float) -> np.ndarray:
        """Axis-aligned local rectangle -> scene polygon (4, 2)."""
        return self.pts(np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]]))


def _rot_rect(cx: float, cy: float, length: float, width: float, angle: float) -> np.ndarray:
    """Rectangle centred at (cx, cy), ``length`` along ``angle`` -> polygon (4, 2)."""
    c, s = math.cos(angle), math.sin(angle)
    hl, hw = length / 2, width / 2
    local = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])
    return np.stack(
        [cx + local[:, 0] * c - local[:, 1] * s, cy + local[:, 0] * s + local[:, 1] * c], axis=1
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


def _tower_count(rng: np.random.Generator, size_m: float) -> int:
    """Number of towers (42 m and up) for a scene: 3-8 per km², at least one."""
    area_km2 = (size_m / 1000.0) ** 2
    return max(1, int(math.ceil(rng.uniform(*TOWER_DENSITY_PER_KM2) * area_km2)))


def _tower_heights(rng: np.random.Generator, count: int) -> list[float]:
    """Tower heights: 42-70 m; with three or more, half the time one landmark above 75 m."""
    heights = [float(rng.uniform(*TOWER_HEIGHT_M)) for _ in range(count)]
    if count >= 3 and rng.random() < 0.5:
        heights[0] = float(rng.uniform(*LANDMARK_HEIGHT_M))
    return heights


# --------------------------------------------------------------------------
# Shared elements
# --------------------------------------------------------------------------


def _car(c: _Canvas, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    """A car seen from above: body, windscreen, rear window, 1.5 m high."""
    colours = [col for col, _ in _CARS]
    weights = np.array([w for _, w in _CARS])
    body = _vary(rng, colours[int(rng.choice(len(colours), p=weights / weights.sum()))], 0.05, 0.02)
    length = rng.uniform(4.1, 4.9) if rng.random() > 0.08 else rng.uniform(5.5, 6.5)
    width = rng.uniform(1.75, 1.95)
    hl, hw = length / 2, width / 2
    outline = np.array(
        [
            [-hl + 0.3, -hw],
            [hl - 0.45, -hw],
            [hl, -hw + 0.35],
            [hl, hw - 0.35],
            [hl - 0.45, hw],
            [-hl + 0.3, hw],
            [-hl, hw - 0.3],
            [-hl, -hw + 0.3],
        ]
    )
    ca, sa = math.cos(angle), math.sin(angle)

    def place(local: np.ndarray) -> np.ndarray:
        return np.stack(
            [x + local[:, 0] * ca - local[:, 1] * sa, y + local[:, 0] * sa + local[:, 1] * ca],
            axis=1,
        )

    c.fill([place(outline)], body, Mat.CAR, CAR_HEIGHT_M)
    glass = (34, 38, 44)
    front = np.array(
        [
            [hl - 1.75, -hw * 0.82],
            [hl - 1.05, -hw * 0.88],
            [hl - 1.05, hw * 0.88],
            [hl - 1.75, hw * 0.82],
        ]
    )
    rear = np.array(
        [
            [-hl + 0.55, -hw * 0.8],
            [-hl + 1.0, -hw * 0.82],
            [-hl + 1.0, hw * 0.82],
            [-hl + 0.55, hw * 0.8],
        ]
    )
    c.fill([place(front), place(rear)], glass, Mat.CAR)


def _bush(c: _Canvas, rng: np.random.Generator, x: float, y: float) -> None:
    """A shrub: a small low crown."""
    c.tree(x, y, rng.uniform(0.6, 1.4), rng.uniform(1.0, 2.5), _vary(rng, _pick(rng, _TREES), 0.1))


def _street_tree(
    c: _Canvas, rng: np.random.Generator, x: float, y: float, scale: float = 1.0
) -> None:
    """A deciduous tree with a height in the residential/campus range."""
    height = float(np.clip(rng.normal(11.0, 3.5) * scale, *TREE_HEIGHT_M))
    radius = float(np.clip(height * rng.uniform(0.22, 0.36), 1.8, 7.0))
    c.tree(x, y, radius, height, _vary(rng, _pick(rng, _TREES), 0.1, 0.05))


def _parking_lot(
    c: _Canvas, rng: np.random.Generator, fr: _Frame, u0: float, v0: float, u1: float, v1: float
) -> None:
    """An asphalt lot with double-loaded stall rows along u, stall lines and cars."""
    c.fill(
        [fr.rect(u0, v0, u1, v1)],
        _vary(rng, _pick(rng, (_ASPHALT, _ASPHALT_OLD)), 0.05),
        Mat.ASPHALT,
    )
    line_col = _vary(rng, (214, 212, 200) if rng.random() < 0.8 else (206, 176, 70), 0.03)
    stall_w, stall_d, aisle = 2.6, 5.2, 7.0
    occupancy = rng.uniform(0.35, 0.9)
    v = v0 + aisle
    while v + 2 * stall_d <= v1 - aisle * 0.5:
        for side, vv in ((1, v), (-1, v + 2 * stall_d)):
            n_stalls = int((u1 - u0 - 4.0) // stall_w)
            start = u0 + 2.0 + (u1 - u0 - 4.0 - n_stalls * stall_w) / 2
            for i in range(n_stalls + 1):
                uu = start + i * stall_w
                c.line(
                    fr.pts(np.array([[uu, vv], [uu, vv + side * stall_d]])),
                    0.12,
                    line_col,
                    Mat.PAINT,
                )
            for i in range(n_stalls):
                if rng.random() < occupancy:
                    uu = start + (i + 0.5) * stall_w + rng.normal(0, 0.12)
                    vc = vv + side * (stall_d / 2 + rng.normal(0, 0.15))
                    x, y = fr.pt(uu, vc)
                    facing = fr.theta + math.pi / 2 + (math.pi if rng.random() < 0.5 else 0.0)
                    _car(c, rng, x, y, facing + rng.normal(0, 0.04))
        c.line(
            fr.pts(np.array([[u0 + 2, v + stall_d], [u1 - 2, v + stall_d]])),
            0.12,
            line_col,
            Mat.PAINT,
        )
        v += 2 * stall_d + aisle


def _flat_building(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    u0: float,
    v0: float,
    u1: float,
    v1: float,
    height_m: float,
    colour: Colour | None = None,
) -> None:
    """A flat-roofed building on a local rectangle, with rooftop units and skylights."""
    colour = colour or _vary(rng, _pick(rng, _FLAT_ROOFS), 0.05, 0.01)
    cx, cy = fr.pt((u0 + u1) / 2, (v0 + v1) / 2)
    half_len, half_wid = (u1 - u0) / 2, (v1 - v0) / 2
    c.roof(
        cx,
        cy,
        half_len,
        half_wid,
        fr.theta,
        height_m,
        0.0,
        "flat",
        colour,
        Mat.FLAT_ROOF,
        edge=0.78,
    )
    unit_col = _vary(rng, (150, 152, 154), 0.12)
    n_units = int(rng.integers(1, 3 + int(half_len * half_wid / 150)))
    for _ in range(min(n_units, 14)):
        lu, lv = rng.uniform(1.5, 5.0), rng.uniform(1.2, 4.0)
        if lu + 1.5 >= half_len or lv + 1.5 >= half_wid:
            continue
        uu = rng.uniform(u0 + lu + 1, u1 - lu - 1)
        vv = rng.uniform(v0 + lv + 1, v1 - lv - 1)
        x, y = fr.pt(uu, vv)
        c.roof(
            x,
            y,
            lu / 2 * 1.6,
            lv / 2 * 1.6,
            fr.theta,
            height_m + rng.uniform(1.2, 3.5),
            0.0,
            "flat",
            unit_col,
            Mat.FLAT_ROOF,
            0.7,
        )
    if rng.random() < 0.4 and half_len > 12 and half_wid > 8:
        sky = _vary(rng, (70, 84, 96), 0.08)
        n_sky = int(rng.integers(2, 6))
        vv = rng.uniform(v0 + 4, v1 - 4)
        for i in range(n_sky):
            uu = u0 + (i + 1) * (u1 - u0) / (n_sky + 1)
            c.fill([fr.rect(uu - 1.5, vv - 1.0, uu + 1.5, vv + 1.0)], sky, Mat.FLAT_ROOF)


# --------------------------------------------------------------------------
# Residential (scene A)
# --------------------------------------------------------------------------

_LOCAL_ROAD_M = 8.0
_ARTERIAL_ROAD_M = 13.0
_VERGE_M = 1.8
_SIDEWALK_M = 1.6


@dataclass
class _Street:
    """One straight street of the grid: its position across and asphalt width."""

    pos: float
    width: float
    arterial: bool

    @property
    def half_corridor(self) -> float:
        """Half-width of asphalt, verges and sidewalks together."""
        return self.width / 2 + _VERGE_M + _SIDEWALK_M


def _street_lines(
    rng: np.random.Generator, lo: float, hi: float, block: tuple[float, float]
) -> list[_Street]:
    """Parallel streets from ``lo`` to ``hi`` separated by blocks of random length."""
    streets = []
    pos = lo
    count = 0
    every = int(rng.integers(4, 7))
    first = int(rng.integers(every))
    while pos < hi:
        arterial = count % every == first
        width = _ARTERIAL_ROAD_M if arterial else _LOCAL_ROAD_M * rng.uniform(0.9, 1.15)
        streets.append(_Street(pos, width, arterial))
        pos += rng.uniform(*block) + 2 * (width / 2 + _VERGE_M + _SIDEWALK_M)
        count += 1
    return streets


def _draw_streets(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    along_u: list[_Street],
    along_v: list[_Street],
    ext: float,
) -> None:
    """Grid corridors (sidewalks, verges, kerbs, asphalt), then markings, cars and trees."""
    layers = (
        (lambda s: s.half_corridor, _CONCRETE, Mat.CONCRETE),
        (lambda s: s.width / 2 + _VERGE_M, _VERGE, Mat.GRASS),
        (lambda s: s.width / 2 + 0.3, _KERB, Mat.CONCRETE),
    )
    asphalt = {
        id(s): _vary(rng, _pick(rng, (_ASPHALT, _ASPHALT, _ASPHALT_OLD)), 0.04)
        for s in along_u + along_v
    }
    for half_width, colour, mat in (*layers, (lambda s: s.width / 2, None, Mat.ASPHALT)):
        for s in along_u:  # streets at constant v, running along u
            hw = half_width(s)
            c.fill([fr.rect(-ext, s.pos - hw, ext, s.pos + hw)], colour or asphalt[id(s)], mat)
        for s in along_v:  # streets at constant u, running along v
            hw = half_width(s)
            c.fill([fr.rect(s.pos - hw, -ext, s.pos + hw, ext)], colour or asphalt[id(s)], mat)

    for streets, crossings, swap in ((along_u, along_v, False), (along_v, along_u, True)):
        for s in streets:
            for a, b in zip(crossings[:-1], crossings[1:], strict=False):
                lo, hi = a.pos + a.half_corridor, b.pos - b.half_corridor
                _street_segment(c, rng, fr, s, lo, hi, a, b, swap)


def _street_segment(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    s: _Street,
    lo: float,
    hi: float,
    a: _Street,
    b: _Street,
    swap: bool,
) -> None:
    """Markings, crosswalks, parked cars and verge trees of one street between two crossings."""

    def uv(t: float, off: float) -> tuple[float, float]:
        return (s.pos + off, t) if swap else (t, s.pos + off)

    def seg(t0: float, t1: float, off: float) -> np.ndarray:
        return fr.pts(np.array([uv(t0, off), uv(t1, off)]))

    centre = (s.pos, (lo + hi) / 2) if swap else ((lo + hi) / 2, s.pos)
    x, y = fr.pt(*centre)
    if not c.inside(x, y, hi - lo):
        return
    white, yellow = (218, 216, 206), (212, 180, 74)
    road_angle = fr.theta + (math.pi / 2 if swap else 0.0)
    if s.arterial:
        for off in (-0.15, 0.15):
            c.line(seg(lo + 1.0, hi - 1.0, off), 0.12, yellow, Mat.PAINT)
        t = lo + 3.0
        while t + 3.0 < hi - 3.0:
            for off in (-s.width / 4, s.width / 4):
                c.line(seg(t, t + 3.0, off), 0.12, white, Mat.PAINT)
            t += 9.0
        for end, sign in ((lo - _VERGE_M - _SIDEWALK_M, 1), (hi + _VERGE_M + _SIDEWALK_M, -1)):
            # Zebra crossing just outside the intersection.
            for k in range(int(s.width / 1.1)):
                off = -s.width / 2 + 0.5 + k * 1.1
                t0 = end + sign * 0.6
                c.line(seg(t0, t0 + sign * 3.0, off), 0.5, white, Mat.PAINT)
    else:
        for end, sign, crossing in ((lo, 1, a), (hi, -1, b)):
            if crossing.arterial:
                c.line(
                    fr.pts(
                        np.array(
                            [uv(end + sign * 0.5, 0.2), uv(end + sign * 0.5, s.width / 2 - 0.3)]
                        )
                    ),
                    0.4,
                    white,
                    Mat.PAINT,
                )
    # Parked cars along the kerbs.
    p_car = 0.05 if s.arterial else rng.uniform(0.05, 0.22)
    for side in (-1, 1):
        t = lo + 4.0
        while t < hi - 4.0:
            if rng.random() < p_car:
                px_, py_ = fr.pt(*uv(t, side * (s.width / 2 - 1.3)))
                _car(
                    c,
                    rng,
                    px_,
                    py_,
                    road_angle + (0 if side > 0 else math.pi) + rng.normal(0, 0.02),
                )
            t += rng.uniform(6.0, 7.5)
    # Verge trees.
    if rng.random() < 0.55:
        spacing = rng.uniform(9.0, 15.0)
        for side in (-1, 1):
            t = lo + rng.uniform(2.0, spacing)
            while t < hi - 2.0:
                if rng.random() < 0.8:
                    tx, ty = fr.pt(*uv(t, side * (s.width / 2 + _VERGE_M / 2)))
                    _street_tree(c, rng, tx, ty, 0.9)
                t += spacing


def _residential(c: _Canvas, rng: np.random.Generator) -> None:
    """Scene A: street grid, house blocks, apartment blocks and towers."""
    size = c.size_m
    c.fill_all(_LAWNS[0], Mat.GRASS)
    fr = _Frame(
        size / 2 + rng.uniform(-20, 20), size / 2 + rng.uniform(-20, 20), rng.uniform(-0.4, 0.4)
    )
    ext = size * 0.75 + 60.0
    along_v = _street_lines(rng, -ext + rng.uniform(0, 60), ext, (110.0, 190.0))  # constant u
    along_u = _street_lines(rng, -ext + rng.uniform(0, 40), ext, (58.0, 80.0))  # constant v

    blocks = []
    for a, b in zip(along_v[:-1], along_v[1:], strict=False):
        for p, q in zip(along_u[:-1], along_u[1:], strict=False):
            u0, u1 = a.pos + a.half_corridor, b.pos - b.half_corridor
            v0, v1 = p.pos + p.half_corridor, q.pos - q.half_corridor
            x, y = fr.pt((u0 + u1) / 2, (v0 + v1) / 2)
            if c.inside(x, y, 0.6 * max(u1 - u0, v1 - v0)):
                dist = max(abs(x - size / 2), abs(y - size / 2))
                blocks.append((dist, u0, v0, u1, v1))
    blocks.sort(key=lambda b: b[0])
    inner = [b for b in blocks if b[0] < size / 2 - 20] or blocks[:1]
    heights = _tower_heights(rng, _tower_count(rng, size))
    tall_idx = rng.permutation(len(inner))[: max(1, (len(heights) + 1) // 2)]
    tall_blocks = [inner[i] for i in tall_idx]
    tall_set = {id(b) for b in tall_blocks}
    per_block = np.array_split(np.array(heights), len(tall_blocks))

    for blk in blocks:
        _, u0, v0, u1, v1 = blk
        if id(blk) in tall_set:
            k = [id(b) for b in tall_blocks].index(id(blk))
            _tower_block(c, rng, fr, u0, v0, u1, v1, [float(h) for h in per_block[k]])
            continue
        r = rng.random()
        if r < 0.05:
            _park(c, rng, fr, u0, v0, u1, v1)
        elif r < 0.12:
            _midrise_block(c, rng, fr, u0, v0, u1, v1)
        else:
            _house_block(c, rng, fr, u0, v0, u1, v1)
    _draw_streets(c, rng, fr, along_u, along_v, ext)


def _house_block(
    c: _Canvas, rng: np.random.Generator, fr: _Frame, u0: float, v0: float, u1: float, v1: float
) -> None:
    """Two rows of parcels back to back, fronting the streets at v0 and v1."""
    vm = (v0 + v1) / 2 + rng.normal(0, 2.0)
    for v_front, v_back in ((v0, vm), (v1, vm)):
        u = u0
        while u < u1 - 8.0:
            width = rng.uniform(15.0, 24.0)
            if u1 - (u + width) < 12.0:
                width = u1 - u
            _house_parcel(c, rng, fr, u, u + width, v_front, v_back)
            u += width


def _house_parcel(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    a0: float,
    a1: float,
    v_front: float,
    v_back: float,
) -> None:
    """One garden with a house, garage, driveway, maybe a pool, trees, shrubs and cars."""
    sgn = 1.0 if v_back > v_front else -1.0
    depth = abs(v_back - v_front)

    def P(a: float, d: float) -> tuple[float, float]:
        return fr.pt(a, v_front + sgn * d)

    def R(a0_: float, d0: float, a1_: float, d1: float) -> np.ndarray:
        return fr.rect(a0_, v_front + sgn * d0, a1_, v_front + sgn * d1)

    cx, cy = P((a0 + a1) / 2, depth / 2)
    if not c.inside(cx, cy, 30.0):
        return
    lawn = _vary(rng, _LAWNS[int(rng.choice(len(_LAWNS), p=_LAWN_WEIGHTS))], 0.04, 0.03)
    c.fill([R(a0, 0, a1, depth)], lawn, Mat.GRASS)
    if rng.random() < 0.5:
        c.stripes(
            R(a0, 0, a1, depth),
            fr.theta + rng.choice([0, math.pi / 2]),
            rng.uniform(1.2, 2.0),
            0.025,
        )
    if rng.random() < 0.5:
        fence = _vary(rng, (120, 104, 84) if rng.random() < 0.6 else (150, 150, 146), 0.06)
        pts = fr.pts(
            np.array([[a0, v_front + sgn * 6], [a0, v_back], [a1, v_back], [a1, v_front + sgn * 6]])
        )
        c.line(pts, 0.15, fence, Mat.CONCRETE)

    frontage = a1 - a0
    house_w = min(frontage - 2 * rng.uniform(1.8, 3.0), rng.uniform(9.0, 16.0))
    house_d = min(depth - 12.0, rng.uniform(8.0, 13.0))
    if house_w < 6.0 or house_d < 6.0:
        return
    setback = rng.uniform(5.0, min(9.0, depth - house_d - 5.0))
    garage = rng.random() < 0.55 and frontage - house_w > 9.5
    ac = (
        (a0 + a1) / 2
        + rng.uniform(-1.0, 1.0)
        + (-3.2 if garage else 0.0) * (1 if rng.random() < 0.5 else -1)
    )
    ac = float(np.clip(ac, a0 + house_w / 2 + 1.0, a1 - house_w / 2 - 1.0))
    dc = setback + house_d / 2
    roof_col = _vary(rng, _pick(rng, _PITCHED_ROOFS), 0.06, 0.03)
    shape = str(rng.choice(["gable", "hip", "flat"], p=[0.48, 0.38, 0.14]))
    ridge_along = rng.random() < 0.6
    hx, hy = P(ac, dc)
    half_l, half_w = (house_w / 2, house_d / 2) if ridge_along else (house_d / 2, house_w / 2)
    angle = fr.theta + (0.0 if ridge_along else math.pi / 2)
    if shape == "flat":
        eave, rise = rng.uniform(5.0, 7.5), 0.0
        roof_col = _vary(rng, _pick(rng, _FLAT_ROOFS), 0.06)
    else:
        eave = rng.choice([rng.uniform(3.0, 3.6), rng.uniform(5.4, 6.6)])
        rise = float(np.clip(half_w * rng.uniform(0.45, 0.9), 5.0 - eave, 12.0 - eave))
    c.roof(
        hx,
        hy,
        half_l,
        half_w,
        angle,
        eave,
        rise,
        shape,
        roof_col,
        Mat.FLAT_ROOF if shape == "flat" else Mat.ROOF,
    )
    if rng.random() < 0.3 and shape != "flat":
        # A wing at the back gives an L or T plan.
        wing_w = rng.uniform(4.5, min(8.0, house_w - 1))
        wing_d = rng.uniform(4.0, 7.0)
        wa = ac + rng.uniform(-1, 1) * (house_w - wing_w) / 2
        wx, wy = P(wa, dc + house_d / 2 + wing_d / 2 - 0.5)
        c.roof(
            wx,
            wy,
            wing_d / 2 + 0.5,
            wing_w / 2,
            fr.theta + math.pi / 2,
            eave,
            rise * 0.8,
            shape,
            roof_col,
        )

    ga = ac
    if garage:
        side = 1.0 if ac < (a0 + a1) / 2 else -1.0
        ga = ac + side * (house_w / 2 + 3.2)
        gx, gy = P(ga, setback + 3.3)
        c.roof(
            gx,
            gy,
            3.2,
            3.3,
            fr.theta + math.pi / 2,
            2.8,
            1.4 if shape != "flat" else 0.0,
            shape if shape != "gable" else "gable",
            roof_col,
            Mat.FLAT_ROOF if shape == "flat" else Mat.ROOF,
        )
    else:
        side = 1.0 if rng.random() < 0.5 else -1.0
        ga = float(np.clip(ac + side * (house_w / 2 + 2.0), a0 + 1.8, a1 - 1.8))
    drive_col = _vary(
        rng, _pick(rng, ((168, 162, 150), (150, 146, 140), (96, 96, 98), (150, 120, 104))), 0.05
    )
    dw = rng.uniform(2.8, 4.6) if garage else 3.0
    c.fill(
        [R(ga - dw / 2, -(_VERGE_M + _SIDEWALK_M), ga + dw / 2, setback + (0 if garage else 6.0))],
        drive_col,
        Mat.CONCRETE,
    )
    if rng.random() < 0.55:
        cx_, cy_ = P(ga + rng.normal(0, 0.3), setback * rng.uniform(0.35, 0.6))
        _car(
            c,
            rng,
            cx_,
            cy_,
            fr.theta
            + math.pi / 2 * sgn
            + (math.pi if rng.random() < 0.3 else 0)
            + rng.normal(0, 0.05),
        )

    back0 = setback + house_d + 1.0
    back_depth = depth - back0
    if back_depth > 7.0 and rng.random() < 0.4:
        patio = _vary(rng, _pick(rng, ((170, 160, 146), (128, 98, 72), (150, 140, 126))), 0.06)
        pw, pd = rng.uniform(3.0, 6.0), rng.uniform(2.5, 4.0)
        pa = ac + rng.uniform(-2, 2)
        c.fill([R(pa - pw / 2, back0 - 1.0, pa + pw / 2, back0 - 1.0 + pd)], patio, Mat.PAVER)
    if back_depth > 11.0 and rng.random() < 0.16:
        pl, pw = rng.uniform(6.0, 10.0), rng.uniform(3.5, 5.0)
        pa = float(np.clip(ac + rng.uniform(-3, 3), a0 + pl / 2 + 1.5, a1 - pl / 2 - 1.5))
        pdc = back0 + 4.0 + pw / 2
        c.fill(
            [R(pa - pl / 2 - 0.7, pdc - pw / 2 - 0.7, pa + pl / 2 + 0.7, pdc + pw / 2 + 0.7)],
            (186, 182, 172),
            Mat.CONCRETE,
        )
        c.fill(
            [R(pa - pl / 2, pdc - pw / 2, pa + pl / 2, pdc + pw / 2)],
            _vary(rng, _POOL, 0.05),
            Mat.POOL,
        )
    elif back_depth > 8.0 and rng.random() < 0.25:
        sw, sd = rng.uniform(2.0, 3.5), rng.uniform(2.0, 3.0)
        sa_ = rng.uniform(a0 + sw, a1 - sw)
        sx, sy = P(sa_, depth - sd / 2 - 1.0)
        c.roof(
            sx,
            sy,
            sw / 2,
            sd / 2,
            fr.theta,
            2.2,
            0.4,
            "gable",
            _vary(rng, _pick(rng, _PITCHED_ROOFS), 0.08),
        )
    if rng.random() < 0.25 and back_depth > 6.0:
        bed = _vary(rng, (96, 80, 62), 0.08)
        ba = rng.uniform(a0 + 2, a1 - 4)
        c.fill([R(ba, depth - 3.0, ba + rng.uniform(2, 5), depth - 1.0)], bed, Mat.SOIL)

    for _ in range(int(rng.poisson(2.5))):
        along = rng.choice([-1.0, 1.0]) * rng.uniform(house_w / 2 + 0.8, house_w / 2 + 1.5)
        bx, by = (
            P(ac + rng.uniform(-house_w / 2, house_w / 2), setback - rng.uniform(0.8, 1.5))
            if rng.random() < 0.6
            else P(ac + along, dc + rng.uniform(-house_d / 2, house_d / 2))
        )
        _bush(c, rng, bx, by)
    for _ in range(int(rng.poisson(1.7))):
        if rng.random() < 0.6 and back_depth > 4.0:
            d = rng.uniform(back0 + 1.0, depth - 1.0)
        else:
            d = rng.uniform(1.5, max(1.6, setback - 1.0))
        tx, ty = P(rng.uniform(a0 + 1.0, a1 - 1.0), d)
        _street_tree(c, rng, tx, ty)


def _midrise_block(
    c: _Canvas, rng: np.random.Generator, fr: _Frame, u0: float, v0: float, u1: float, v1: float
) -> None:
    """Three- to six-storey apartment slabs (12-20 m) with parking and lawns."""
    c.fill([fr.rect(u0, v0, u1, v1)], _vary(rng, _pick(rng, _LAWNS[:3]), 0.05), Mat.GRASS)
    n = 2 if u1 - u0 > 110 else 1
    width = (u1 - u0) / n
    depth = v1 - v0
    for i in range(n):
        a0 = u0 + i * width
        slab_l = min(width - 14.0, rng.uniform(40.0, 70.0))
        slab_d = rng.uniform(12.0, 16.0)
        ac = a0 + width / 2
        vc = v0 + rng.uniform(8.0, 12.0) + slab_d / 2
        x, y = fr.pt(ac, vc)
        h = rng.uniform(12.0, 20.0)
        if rng.random() < 0.5:
            _flat_building(
                c, rng, fr, ac - slab_l / 2, vc - slab_d / 2, ac + slab_l / 2, vc + slab_d / 2, h
            )
        else:
            c.roof(
                x,
                y,
                slab_l / 2,
                slab_d / 2,
                fr.theta,
                h - 3.5,
                3.5,
                "hip",
                _vary(rng, _pick(rng, _PITCHED_ROOFS), 0.05),
            )
        p0 = vc + slab_d / 2 + 4.0
        if v1 - 4.0 - p0 > 20.0:
            _parking_lot(c, rng, fr, a0 + 5.0, p0, a0 + width - 5.0, v1 - 4.0)
    for _ in range(int(rng.poisson(6))):
        x, y = fr.pt(rng.uniform(u0 + 2, u1 - 2), rng.uniform(v0 + 2, v0 + min(8.0, depth / 3)))
        _street_tree(c, rng, x, y)


def _tower_block(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    u0: float,
    v0: float,
    u1: float,
    v1: float,
    heights: list[float],
) -> None:
    """Apartment towers (42 m and up) on a plaza with parking and lawn."""
    c.fill([fr.rect(u0, v0, u1, v1)], _vary(rng, _pick(rng, _LAWNS[:3]), 0.05), Mat.GRASS)
    n = len(heights)
    width = (u1 - u0) / n
    for i, h in enumerate(heights):
        a0 = u0 + i * width
        side_l = min(width - 16.0, rng.uniform(22.0, 36.0))
        side_d = min(v1 - v0 - 30.0, rng.uniform(18.0, 30.0))
        if side_l < 12 or side_d < 12:
            side_l = side_d = max(12.0, min(width, v1 - v0) - 8.0)
        ac = a0 + width / 2
        vc = v0 + 6.0 + side_d / 2
        c.fill(
            [
                fr.rect(
                    ac - side_l / 2 - 5,
                    vc - side_d / 2 - 5,
                    ac + side_l / 2 + 5,
                    vc + side_d / 2 + 5,
                )
            ],
            _vary(rng, (184, 178, 166), 0.05),
            Mat.PAVER,
        )
        _flat_building(
            c, rng, fr, ac - side_l / 2, vc - side_d / 2, ac + side_l / 2, vc + side_d / 2, h
        )
        p0 = vc + side_d / 2 + 8.0
        if v1 - 3.0 - p0 > 18.0:
            _parking_lot(c, rng, fr, a0 + 4.0, p0, a0 + width - 4.0, v1 - 3.0)
    for _ in range(int(rng.poisson(8))):
        x, y = fr.pt(rng.uniform(u0 + 2, u1 - 2), rng.choice([v0 + 2.5, v1 - 2.0]))
        _street_tree(c, rng, x, y)


def _park(
    c: _Canvas, rng: np.random.Generator, fr: _Frame, u0: float, v0: float, u1: float, v1: float
) -> None:
    """A neighbourhood park: lawn, a looping path, a playground and many trees."""
    c.fill([fr.rect(u0, v0, u1, v1)], _vary(rng, _LAWNS[1], 0.05), Mat.GRASS)
    c.stripes(fr.rect(u0, v0, u1, v1), fr.theta, rng.uniform(4.0, 6.0), 0.035)
    path_col = _vary(rng, (186, 176, 156), 0.05)
    pts = []
    for k in range(9):
        t = 2 * math.pi * k / 8
        pts.append(
            (
                (u0 + u1) / 2 + math.cos(t) * (u1 - u0) * 0.36,
                (v0 + v1) / 2 + math.sin(t) * (v1 - v0) * 0.34,
            )
        )
    c.line(fr.pts(np.array(pts)), 2.5, path_col, Mat.PAVER, closed=True)
    c.line(fr.pts(np.array([[u0, (v0 + v1) / 2], [u1, (v0 + v1) / 2]])), 2.5, path_col, Mat.PAVER)
    pu, pv = rng.uniform(u0 + 15, u1 - 25), (v0 + v1) / 2 + 5.0
    c.fill([fr.rect(pu, pv, pu + 14, pv + 10)], (170, 120, 90), Mat.TRACK)
    for _ in range(int(rng.poisson((u1 - u0) * (v1 - v0) / 220))):
        x, y = fr.pt(rng.uniform(u0 + 2, u1 - 2), rng.uniform(v0 + 2, v1 - 2))
        _street_tree(c, rng, x, y, 1.1)


# --------------------------------------------------------------------------
# Campus (scene B)
# --------------------------------------------------------------------------


def _bsp(
    rng: np.random.Generator,
    rect: tuple[float, float, float, float],
    max_side: float,
    gap: Callable[[int], float],
    depth: int = 0,
) -> tuple[
    list[tuple[float, float, float, float]], list[tuple[tuple[float, float, float, float], int]]
]:
    """Split a rectangle recursively until both sides are below ``max_side``.

    Returns the leaves and the corridors between them, each with its depth
    (``gap(depth)`` is a corridor's width).
    """
    u0, v0, u1, v1 = rect
    du, dv = u1 - u0, v1 - v0
    if max(du, dv) <= max_side:
        return [rect], []
    w = gap(depth)
    t = rng.uniform(0.35, 0.65)
    if du >= dv:
        m = u0 + t * du
        a, b = (u0, v0, m - w / 2, v1), (m + w / 2, v0, u1, v1)
        corridor = (m - w / 2, v0, m + w / 2, v1)
    else:
        m = v0 + t * dv
        a, b = (u0, v0, u1, m - w / 2), (u0, m + w / 2, u1, v1)
        corridor = (u0, m - w / 2, u1, m + w / 2)
    la, ca = _bsp(rng, a, max_side, gap, depth + 1)
    lb, cb = _bsp(rng, b, max_side, gap, depth + 1)
    return la + lb, [(corridor, depth)] + ca + cb


def _campus(c: _Canvas, rng: np.random.Generator) -> None:
    """Scene B: superblocks of buildings, quads, parking and sports, with roads between."""
    size = c.size_m
    c.fill_all(_vary(rng, (100, 124, 62), 0.03), Mat.GRASS)
    fr = _Frame(size / 2, size / 2, rng.uniform(-0.3, 0.3))
    ext = size * 0.72 + 40
    road_w = 8.0
    side_w = 2.5
    leaves, corridors = _bsp(
        rng, (-ext, -ext, ext, ext), 240.0, lambda d: road_w + 2 * side_w + 4.0
    )

    def centre_xy(rect: tuple[float, float, float, float]) -> tuple[float, float]:
        return fr.pt((rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2)

    visible = [
        lf for lf in leaves if c.inside(*centre_xy(lf), 0.5 * max(lf[2] - lf[0], lf[3] - lf[1]))
    ]
    inner = [lf for lf in visible if c.inside(*centre_xy(lf), -30.0)] or visible[:1]
    uses = {
        id(lf): str(
            rng.choice(
                ["buildings", "quad", "parking", "sports", "green"], p=[0.46, 0.14, 0.18, 0.12, 0.1]
            )
        )
        for lf in visible
    }
    order = list(rng.permutation(len(inner)))
    big = [
        inner[i] for i in order if min(inner[i][2] - inner[i][0], inner[i][3] - inner[i][1]) > 95
    ]
    if big:
        uses[id(big[0])] = "sports"
    if len(inner) > 2:
        uses[id(inner[order[-1]])] = "parking"
    towers = _tower_heights(rng, _tower_count(rng, size))
    hosts = [inner[i] for i in order if uses[id(inner[i])] not in ("sports", "parking")] or [
        inner[order[0]]
    ]
    tower_of: dict[int, list[float]] = {}
    for k, h in enumerate(towers):
        host = hosts[k % len(hosts)]
        uses[id(host)] = (
            "buildings" if uses[id(host)] not in ("buildings", "quad") else uses[id(host)]
        )
        tower_of.setdefault(id(host), []).append(h)

    # Roads: sidewalks, then asphalt, then centre lines.
    corr = [(rect, depth) for rect, depth in corridors]
    for width, colour, mat in (
        (road_w + 2 * side_w, _CONCRETE, Mat.CONCRETE),
        (road_w, None, Mat.ASPHALT),
    ):
        for (u0, v0, u1, v1), _ in corr:
            cu, cv = (u0 + u1) / 2, (v0 + v1) / 2
            col = colour or _vary(rng, _ASPHALT, 0.03)
            if u1 - u0 < v1 - v0:
                c.fill(
                    [fr.rect(cu - width / 2, v0 - side_w - 2, cu + width / 2, v1 + side_w + 2)],
                    col,
                    mat,
                )
            else:
                c.fill(
                    [fr.rect(u0 - side_w - 2, cv - width / 2, u1 + side_w + 2, cv + width / 2)],
                    col,
                    mat,
                )

    for leaf in visible:
        use = uses[id(leaf)]
        u0, v0, u1, v1 = leaf
        if use == "buildings":
            _campus_buildings(c, rng, fr, leaf, tower_of.get(id(leaf), []))
        elif use == "quad":
            _campus_quad(c, rng, fr, leaf, tower_of.get(id(leaf), []))
        elif use == "parking":
            _parking_lot(c, rng, fr, u0 + 4, v0 + 4, u1 - 4, v1 - 4)
            for uu in np.arange(u0 + 8, u1 - 4, rng.uniform(10, 14)):
                for vv in (v0 + 2.0, v1 - 2.0):
                    _street_tree(c, rng, *fr.pt(float(uu), vv))
        elif use == "sports":
            _sports(c, rng, fr, leaf)
        else:
            _woodland(c, rng, fr, leaf)

    yellow = (210, 178, 72)
    for (u0, v0, u1, v1), _ in corr:
        cu, cv = (u0 + u1) / 2, (v0 + v1) / 2
        along_v = u1 - u0 < v1 - v0
        t0, t1 = (v0, v1) if along_v else (u0, u1)
        t = t0 + 2.0
        while t < t1 - 5.0:
            seg = (
                np.array([[cu, t], [cu, t + 3.0]])
                if along_v
                else np.array([[t, cv], [t + 3.0, cv]])
            )
            c.line(fr.pts(seg), 0.13, yellow, Mat.PAINT)
            t += 8.0
        spacing = rng.uniform(9.0, 13.0)
        t = t0 + spacing / 2
        while t < t1:
            for off in (-(road_w / 2 + side_w + 1.2), road_w / 2 + side_w + 1.2):
                uv = (cu + off, t) if along_v else (t, cv + off)
                if rng.random() < 0.75:
                    _street_tree(c, rng, *fr.pt(*uv))
            t += spacing
        p_car = rng.uniform(0.0, 0.08)
        t = t0 + 3.0
        while t < t1 - 3.0:
            if rng.random() < p_car:
                lane = road_w / 4 * (1 if rng.random() < 0.5 else -1)
                uv = (cu + lane, t) if along_v else (t, cv + lane)
                ang = fr.theta + (math.pi / 2 if along_v else 0.0) + (0.0 if lane > 0 else math.pi)
                _car(c, rng, *fr.pt(*uv), ang)
            t += 7.0


def _campus_building_shape(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    part: tuple[float, float, float, float],
    height: float,
) -> None:
    """One large flat-roofed building in a plot: a block, an L, a courtyard ring or a T."""
    u0, v0, u1, v1 = part
    du, dv = u1 - u0, v1 - v0
    colour = _vary(rng, _pick(rng, _FLAT_ROOFS), 0.05, 0.01)
    shape = str(rng.choice(["block", "L", "ring", "T"], p=[0.4, 0.25, 0.2, 0.15]))
    wing = rng.uniform(14.0, 22.0)
    if shape == "ring" and min(du, dv) > 55:
        for r in (
            (u0, v0, u1, v0 + wing),
            (u0, v1 - wing, u1, v1),
            (u0, v0, u0 + wing, v1),
            (u1 - wing, v0, u1, v1),
        ):
            _flat_building(c, rng, fr, *r, height, colour)
    elif shape == "L" and min(du, dv) > 35:
        _flat_building(c, rng, fr, u0, v0, u1, v0 + wing, height, colour)
        _flat_building(c, rng, fr, u0, v0, u0 + wing, v1, height, colour)
    elif shape == "T" and min(du, dv) > 35:
        _flat_building(c, rng, fr, u0, v0, u1, v0 + wing, height, colour)
        mu = (u0 + u1) / 2
        _flat_building(
            c, rng, fr, mu - wing / 2, v0, mu + wing / 2, v1, height * rng.uniform(0.7, 1.0), colour
        )
    else:
        _flat_building(c, rng, fr, u0, v0, u1, v1, height, colour)


def _campus_buildings(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    leaf: tuple[float, float, float, float],
    towers: list[float],
) -> None:
    """A superblock of one to four academic buildings on lawn, with plazas, paths and trees."""
    u0, v0, u1, v1 = leaf
    parts, _ = _bsp(
        rng, (u0 + 6, v0 + 6, u1 - 6, v1 - 6), rng.uniform(70, 130), lambda d: rng.uniform(10, 24)
    )
    plaza = _vary(rng, (188, 180, 164), 0.04)
    path_col = _vary(rng, (176, 170, 160), 0.04)
    tower_list = list(towers)
    plots = []
    for part in parts:
        p0, q0, p1, q1 = part
        if min(p1 - p0, q1 - q0) < 22:
            continue
        mu, mv = rng.uniform(3, 9), rng.uniform(3, 9)
        fp = (p0 + mu, q0 + mv, p1 - mu * rng.uniform(0.6, 1.4), q1 - mv * rng.uniform(0.6, 1.4))
        tower = tower_list.pop() if tower_list else None
        if tower is not None:
            # A tower stands at the entrance side of its plot.
            side_u = min(fp[2] - fp[0], rng.uniform(26, 40))
            side_v = min(fp[3] - fp[1], rng.uniform(24, 36))
            cu = (fp[0] + fp[2]) / 2
            fp = (cu - side_u / 2, fp[1], cu + side_u / 2, fp[1] + side_v)
        plots.append((part, fp, tower))
        # Paved apron on the entrance side and a path out to the road.
        c.fill(
            [fr.rect(fp[0] - 3, fp[1] - rng.uniform(5, 9), fp[2] + 3, fp[1] + 2)], plaza, Mat.PAVER
        )
        mid = (fp[0] + fp[2]) / 2 + rng.uniform(-0.3, 0.3) * (fp[2] - fp[0])
        c.line(fr.pts(np.array([(mid, fp[1]), (mid, v0 - 1)])), 3.0, path_col, Mat.PAVER)
    for part, fp, tower in plots:
        p0, q0, p1, q1 = part
        if tower is not None:
            _flat_building(c, rng, fr, *fp, tower)
        else:
            _campus_building_shape(c, rng, fr, fp, rng.uniform(*CAMPUS_BUILDING_HEIGHT_M))
        for _ in range(int(rng.poisson(4 + (p1 - p0) * (q1 - q0) / 900))):
            edge = rng.integers(4)
            uu = rng.uniform(p0, p1) if edge < 2 else (p0 + 1.5 if edge == 2 else p1 - 1.5)
            vv = rng.uniform(q0, q1) if edge >= 2 else (q0 + 1.5 if edge == 0 else q1 - 1.5)
            _street_tree(c, rng, *fr.pt(uu, vv))
    for h in tower_list:  # towers that found no plot of their own
        cu, cv = (u0 + u1) / 2 + rng.uniform(-10, 10), (v0 + v1) / 2 + rng.uniform(-10, 10)
        _flat_building(c, rng, fr, cu - 14, cv - 12, cu + 14, cv + 12, h)


def _campus_quad(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    leaf: tuple[float, float, float, float],
    towers: list[float],
) -> None:
    """A lawn quad crossed by diagonal paths lined with trees, ringed by buildings."""
    u0, v0, u1, v1 = leaf
    depth = rng.uniform(14, 22)
    q0, q1 = v0 + 10 + depth, v1 - 10 - depth
    lawn = (u0 + 10, q0, u1 - 10, q1)
    paths: list[tuple[tuple[float, float], tuple[float, float]]] = []
    pw = rng.uniform(3.0, 5.0)
    if q1 - q0 >= 20:
        c.fill([fr.rect(*lawn)], _vary(rng, (92, 124, 60), 0.04), Mat.GRASS)
        c.stripes(
            fr.rect(*lawn), fr.theta + math.pi / 2 * int(rng.integers(2)), rng.uniform(5, 8), 0.035
        )
        path_col = _vary(rng, (190, 182, 168), 0.04)
        cu, cv = (lawn[0] + lawn[2]) / 2, (lawn[1] + lawn[3]) / 2
        paths = [
            ((lawn[0], lawn[1]), (lawn[2], lawn[3])),
            ((lawn[0], lawn[3]), (lawn[2], lawn[1])),
            ((cu, lawn[1] - 8), (cu, lawn[3] + 8)),
        ]
        if rng.random() < 0.5:
            paths.append(((lawn[0], cv), (lawn[2], cv)))
        for a, b in paths:
            c.line(fr.pts(np.array([a, b])), pw, path_col, Mat.PAVER)
        c.disc(*fr.pt(cu, cv), rng.uniform(8, 12), path_col, Mat.PAVER)
        if rng.random() < 0.5:
            c.disc(*fr.pt(cu, cv), rng.uniform(3, 5), _vary(rng, (70, 120, 130), 0.05), Mat.POOL)
    ring = [(u0 + 4, v0 + 4, u1 - 4, v0 + 4 + depth), (u0 + 4, v1 - 4 - depth, u1 - 4, v1 - 4)]
    if rng.random() < 0.5:
        ring.append((u0 + 4, v0 + 10 + depth, u0 + 4 + depth, v1 - 10 - depth))
    for k, r in enumerate(ring):
        if r[2] - r[0] < 15 or r[3] - r[1] < 10:
            continue
        if k < len(towers):
            mu = (r[0] + r[2]) / 2
            _flat_building(c, rng, fr, mu - 15, r[1], mu + 15, r[1] + max(depth, 24), towers[k])
            for rr in ((r[0], r[1], mu - 20, r[3]), (mu + 20, r[1], r[2], r[3])):
                if rr[2] - rr[0] > 15:
                    _flat_building(c, rng, fr, *rr, rng.uniform(*CAMPUS_BUILDING_HEIGHT_M))
        else:
            # A long range split into two or three buildings of different heights.
            edges = [r[0], r[2]]
            if r[2] - r[0] > 40:
                cuts = rng.uniform(r[0] + 15, r[2] - 15, int(rng.integers(0, 3)))
                edges = [r[0], *sorted(cuts.tolist()), r[2]]
            for e0, e1 in zip(edges[:-1], edges[1:], strict=False):
                if e1 - e0 > 12:
                    _flat_building(
                        c,
                        rng,
                        fr,
                        e0 + 1.5,
                        r[1],
                        e1 - 1.5,
                        r[3],
                        rng.uniform(*CAMPUS_BUILDING_HEIGHT_M),
                    )
    spacing = rng.uniform(9, 13)
    for a, b in paths:
        a_, b_ = np.array(a), np.array(b)
        length = float(np.linalg.norm(b_ - a_))
        d = (b_ - a_) / max(length, 1e-6)
        nrm = np.array([-d[1], d[0]])
        for t in np.arange(spacing, length - spacing / 2, spacing):
            if abs(t - length / 2) < 14:
                continue
            for sgn in (-1, 1):
                p = a_ + d * t + nrm * sgn * (pw / 2 + 3.0)
                _street_tree(c, rng, *fr.pt(float(p[0]), float(p[1])))


def _stadium(cu: float, cv: float, straight: float, radius: float, n: int = 40) -> np.ndarray:
    """Outline of a running-track shape (straights along u) in local metres, (2n, 2)."""
    t = np.linspace(-math.pi / 2, math.pi / 2, n)
    right = np.stack([cu + straight / 2 + radius * np.cos(t), cv + radius * np.sin(t)], axis=1)
    left = np.stack([cu - straight / 2 - radius * np.cos(t), cv - radius * np.sin(t)], axis=1)
    return np.concatenate([right, left])


def _pitch_lines(c: _Canvas, fr: _Frame, cu: float, cv: float, length: float, width: float) -> None:
    """Football pitch markings (touchlines, halfway line, centre circle, boxes)."""
    white = (222, 224, 218)
    hl, hw = length / 2, width / 2
    lw = 0.12
    c.line(
        fr.pts(
            np.array(
                [[cu - hl, cv - hw], [cu + hl, cv - hw], [cu + hl, cv + hw], [cu - hl, cv + hw]]
            )
        ),
        lw,
        white,
        Mat.PAINT,
        closed=True,
    )
    c.line(fr.pts(np.array([[cu, cv - hw], [cu, cv + hw]])), lw, white, Mat.PAINT)
    t = np.linspace(0, 2 * math.pi, 48)
    c.line(
        fr.pts(np.stack([cu + 9.15 * np.cos(t), cv + 9.15 * np.sin(t)], axis=1)),
        lw,
        white,
        Mat.PAINT,
        closed=True,
    )
    for sgn in (-1, 1):
        for depth, half in ((16.5, 20.15), (5.5, 9.16)):
            x0, x1 = cu + sgn * hl, cu + sgn * (hl - depth)
            c.line(
                fr.pts(
                    np.array([[x0, cv - half], [x1, cv - half], [x1, cv + half], [x0, cv + half]])
                ),
                lw,
                white,
                Mat.PAINT,
            )


def _sports(
    c: _Canvas, rng: np.random.Generator, fr: _Frame, leaf: tuple[float, float, float, float]
) -> None:
    """Sports grounds: a 400 m track around a pitch if it fits, else pitches, plus tennis courts."""
    u0, v0, u1, v1 = leaf
    c.fill([fr.rect(u0 + 2, v0 + 2, u1 - 2, v1 - 2)], _vary(rng, (112, 128, 70), 0.04), Mat.GRASS)
    du, dv = u1 - u0, v1 - v0
    along_u = du >= dv
    sub = _Frame(*fr.pt((u0 + u1) / 2, (v0 + v1) / 2), fr.theta + (0.0 if along_u else math.pi / 2))
    long_, short = max(du, dv), min(du, dv)
    used = 0.0
    if long_ >= 190 and short >= 102:
        straight, r_in = 84.39, 36.5
        off = -(long_ - 185) / 2 + rng.uniform(0, max(0.0, long_ - 190) * 0.3)
        track_col = _vary(rng, (172, 86, 66), 0.05)
        c.fill([sub.pts(_stadium(off, 0, straight, r_in + 9.8))], (200, 196, 186), Mat.CONCRETE)
        c.fill([sub.pts(_stadium(off, 0, straight, r_in + 9.76))], track_col, Mat.TRACK)
        for lane in range(9):
            c.line(
                sub.pts(_stadium(off, 0, straight, r_in + lane * 1.22)),
                0.08,
                (226, 222, 214),
                Mat.PAINT,
                closed=True,
            )
        field = _vary(rng, (84, 128, 58), 0.04)
        c.fill([sub.pts(_stadium(off, 0, straight, r_in - 0.2))], field, Mat.GRASS)
        c.stripes(sub.rect(off - 52, -34, off + 52, 34), sub.theta, 10.0, 0.07)
        _pitch_lines(c, sub, off, 0, 100.0, 64.0)
        c.fill(
            [sub.rect(off - 40, -r_in - 22, off + 40, -r_in - 12)],
            (150, 150, 152),
            Mat.CONCRETE,
            6.0,
        )
        used = off + straight / 2 + r_in + 12
    else:
        n_pitch = max(1, int((long_ - 10) // 115))
        length = min(105.0, long_ - 14)
        width = min(68.0, short - 14)
        if length > 50 and width > 30:
            for k in range(n_pitch):
                cu = -long_ / 2 + 7 + length / 2 + k * (length + 10)
                field = _vary(rng, (86, 130, 60), 0.04)
                c.fill(
                    [
                        sub.rect(
                            cu - length / 2 - 3, -width / 2 - 3, cu + length / 2 + 3, width / 2 + 3
                        )
                    ],
                    field,
                    Mat.GRASS,
                )
                c.stripes(
                    sub.rect(cu - length / 2, -width / 2, cu + length / 2, width / 2),
                    sub.theta,
                    9.0,
                    0.07,
                )
                _pitch_lines(c, sub, cu, 0, length, width)
            used = -long_ / 2 + 7 + n_pitch * (length + 10)
        else:
            used = -long_ / 2
    # Tennis courts in the space left over.
    court_col = _vary(rng, _pick(rng, ((70, 110, 90), (60, 90, 130), (160, 90, 70))), 0.04)
    u = used + 4
    while u + 18 < long_ / 2 - 4 and short > 40:
        for row in range(int((short - 10) // 36)):
            vc = -short / 2 + 5 + 18 + row * 36
            c.fill([sub.rect(u, vc - 18, u + 18, vc + 18)], _vary(rng, court_col, 0.02), Mat.TRACK)
            cu = u + 9
            lines = np.array(
                [
                    [cu - 5.485, vc - 11.885],
                    [cu + 5.485, vc - 11.885],
                    [cu + 5.485, vc + 11.885],
                    [cu - 5.485, vc + 11.885],
                ]
            )
            c.line(sub.pts(lines), 0.08, (228, 228, 222), Mat.PAINT, closed=True)
            c.line(sub.pts(np.array([[cu - 6, vc], [cu + 6, vc]])), 0.1, (40, 40, 40), Mat.PAINT)
            c.line(
                sub.pts(np.array([[cu, vc - 6.4], [cu, vc + 6.4]])),
                0.08,
                (228, 228, 222),
                Mat.PAINT,
            )
        u += 20


def _woodland(
    c: _Canvas, rng: np.random.Generator, fr: _Frame, leaf: tuple[float, float, float, float]
) -> None:
    """A patch of campus woodland with a winding path."""
    u0, v0, u1, v1 = leaf
    c.fill([fr.rect(u0, v0, u1, v1)], _vary(rng, (82, 100, 52), 0.04), Mat.FOREST_FLOOR)
    n = int((u1 - u0) * (v1 - v0) / 45)
    for _ in range(n):
        _street_tree(c, rng, *fr.pt(rng.uniform(u0, u1), rng.uniform(v0, v1)), 1.1)


# --------------------------------------------------------------------------
# Wild land
# --------------------------------------------------------------------------


def _smooth_field(rng: np.random.Generator, side_px: int, cell_px: float) -> np.ndarray:
    """Smooth random field (side_px^2 float32, unit std) with features about ``cell_px`` across."""
    g = max(2, int(math.ceil(side_px / max(cell_px, 1.0))) + 1)
    small = rng.standard_normal((g, g)).astype(np.float32)
    big = cv2.resize(small, (side_px, side_px), interpolation=cv2.INTER_CUBIC)
    sample = big[:: max(1, side_px // 256), :: max(1, side_px // 256)]
    big -= sample.mean()
    big *= 1.0 / (sample.std() + 1e-6)
    return big


def _wild(c: _Canvas, rng: np.random.Generator) -> None:
    """Wild land: fields with rows, forest, a river with banks, tracks, hedgerows, a farmstead."""
    size = c.size_m
    c.fill_all(_vary(rng, (122, 126, 76), 0.03), Mat.GRASS)
    fr = _Frame(size / 2, size / 2, rng.uniform(-0.5, 0.5))
    ext = size * 0.75 + 40
    leaves, corridors = _bsp(rng, (-ext, -ext, ext, ext), 230.0, lambda d: rng.uniform(2.0, 6.0))
    for leaf in leaves:
        _field(c, rng, fr, leaf)

    # Forest where a low-frequency field is high (about 35 % of the land).
    forest_lo = _smooth_field(rng, max(8, c.n // 16), c.px(260.0) / 16)
    forest_lo += 0.35 * _smooth_field(rng, forest_lo.shape[0], c.px(70.0) / 16)
    thresh = float(np.quantile(forest_lo, 0.64))
    forest_small = (forest_lo > thresh).astype(np.uint8)
    forest = cv2.resize(forest_lo, (c.n, c.n), interpolation=cv2.INTER_LINEAR) > thresh
    floor = np.array(_vary(rng, (62, 70, 44), 0.05), np.uint8)
    c.rgb[forest] = floor
    c.mat[forest] = Mat.FOREST_FLOOR
    c.pattern[forest] = 0.0
    del forest

    river = _river(c, rng)
    tracks = _tracks(c, rng, fr, corridors, ext)
    if rng.random() < 0.75:
        _farmstead(c, rng, tracks)
    _forest_trees(c, rng, forest_small)
    _river_trees(c, rng, river)
    # Hedgerows along some field boundaries.
    for (u0, v0, u1, v1), _ in corridors:
        if rng.random() > 0.3:
            continue
        cu, cv = (u0 + u1) / 2, (v0 + v1) / 2
        along_v = u1 - u0 < v1 - v0
        t0, t1 = (v0, v1) if along_v else (u0, u1)
        t = t0
        while t < t1:
            x, y = fr.pt(cu, t) if along_v else fr.pt(t, cv)
            if c.inside(x, y, 10) and c.mat_at(x, y) not in (
                Mat.WATER,
                Mat.DIRT,
                Mat.GRAVEL,
                Mat.ROOF,
            ):
                _wild_tree(c, rng, x + rng.normal(0, 0.8), y + rng.normal(0, 0.8), 0.8)
            t += rng.uniform(3.0, 9.0)
    # Scattered trees in pastures and meadows.
    n_scatter = int(size * size / 4000)
    xs, ys = rng.uniform(0, size, n_scatter), rng.uniform(0, size, n_scatter)
    for x, y in zip(xs, ys, strict=False):
        if c.mat_at(x, y) == Mat.GRASS and rng.random() < 0.7:
            _wild_tree(c, rng, x, y, 1.0)


def _field(
    c: _Canvas, rng: np.random.Generator, fr: _Frame, leaf: tuple[float, float, float, float]
) -> None:
    """One agricultural field: a jittered quadrilateral with crop colour, rows and tramlines."""
    u0, v0, u1, v1 = leaf
    x, y = fr.pt((u0 + u1) / 2, (v0 + v1) / 2)
    if not c.inside(x, y, 0.75 * max(u1 - u0, v1 - v0)):
        return
    corners = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]]) + rng.uniform(-4, 4, (4, 2))
    poly = fr.pts(corners)
    colour, mat, period, amp = _CROPS[int(rng.integers(len(_CROPS)))]
    colour = _vary(rng, colour, 0.06, 0.04)
    c.fill([poly], colour, mat)
    long_along_u = (u1 - u0) >= (v1 - v0)
    angle = fr.theta + (0.0 if long_along_u else math.pi / 2) + math.pi / 2 + rng.normal(0, 0.03)
    if period > 0:
        c.stripes(
            poly, angle, period * rng.uniform(0.9, 1.1), amp, duty=0.5 if period < 4 else 0.25
        )
        # Tramlines every 12-24 m are painted by cutting a few darker rows into the pattern.
        if mat == Mat.CROP and rng.random() < 0.7:
            win = c._window(poly)
            if win is not None:
                r0, r1, c0, c1 = win
                spacing = rng.uniform(12.0, 24.0)
                mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
                local = poly - np.array([c0, r0]) * c.gsd_m
                cv2.fillPoly(mask, [c._fixed(local)], 1, cv2.LINE_8, _SHIFT)
                ys = (np.arange(r0, r1, dtype=np.float32) + 0.5) * c.gsd_m
                xs = (np.arange(c0, c1, dtype=np.float32) + 0.5) * c.gsd_m
                t = xs[None, :] * math.cos(angle) + ys[:, None] * math.sin(angle)
                ph = np.mod(t, spacing)
                lines = ((ph < 0.45) | ((ph > 1.8) & (ph < 2.25))) & mask.astype(bool)
                c.pattern[r0:r1, c0:c1][lines] = -0.2
    elif rng.random() < 0.5:
        c.stripes(poly, angle, rng.uniform(8, 14), 0.03)


def _river(c: _Canvas, rng: np.random.Generator) -> list[tuple[float, float, float]]:
    """A meandering river across the scene; returns its centreline samples (x, y, width)."""
    size = c.size_m
    step = 4.0
    horizontal = rng.random() < 0.5
    start = rng.uniform(0.25, 0.75) * size
    heading = (0.0 if horizontal else math.pi / 2) + rng.normal(0, 0.25)
    base_heading = heading
    x, y = (-40.0, start) if horizontal else (start, -40.0)
    width0 = rng.uniform(14.0, 26.0)
    amps = rng.uniform(0.25, 0.55, 3)
    waves = rng.uniform(180.0, 420.0, 3) * np.array([1.0, 0.55, 0.3])
    phases = rng.uniform(0, 2 * math.pi, 3)
    pts: list[tuple[float, float, float]] = []
    s = 0.0
    while -60 <= x <= size + 60 and -60 <= y <= size + 60 and s < 6 * size:
        heading = base_heading + float(np.sum(amps * np.sin(2 * math.pi * s / waves + phases)))
        width = width0 * (1.0 + 0.2 * math.sin(2 * math.pi * s / 230.0 + phases[0]))
        pts.append((x, y, width))
        x += step * math.cos(heading)
        y += step * math.sin(heading)
        s += step
    bank = _vary(rng, (156, 146, 118), 0.05)
    reeds = _vary(rng, (96, 110, 64), 0.05)
    water = _vary(rng, _WATER, 0.06, 0.05)
    for extra, colour, mat in (
        (14.0, reeds, Mat.GRASS),
        (5.0, bank, Mat.GRAVEL),
        (0.0, water, Mat.WATER),
    ):
        for (x0, y0, w0), (x1, y1, _) in zip(pts[:-1], pts[1:], strict=False):
            seg = np.array([[x0, y0], [x1, y1]])
            jitter = rng.uniform(-1.0, 1.0) if extra > 0 else 0.0
            c.line(seg, w0 + extra + jitter, colour, mat)
    return pts


def _river_trees(
    c: _Canvas, rng: np.random.Generator, river: list[tuple[float, float, float]]
) -> None:
    """Riparian trees along both banks."""
    for i in range(0, len(river) - 1, 2):
        x0, y0, w = river[i]
        x1, y1, _ = river[i + 1]
        d = np.array([x1 - x0, y1 - y0])
        d /= np.linalg.norm(d) + 1e-9
        n = np.array([-d[1], d[0]])
        for side in (-1, 1):
            if rng.random() < 0.45:
                off = w / 2 + rng.uniform(4.0, 12.0)
                px_, py_ = np.array([x0, y0]) + n * side * off
                if c.mat_at(px_, py_) != Mat.WATER:
                    _wild_tree(c, rng, float(px_), float(py_), 0.9)


def _tracks(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    corridors: list[tuple[tuple[float, float, float, float], int]],
    ext: float,
) -> list[tuple[float, float]]:
    """Dirt tracks along some field boundaries; returns points on them (for the farmstead)."""
    dirt = _vary(rng, (172, 152, 116), 0.05)
    strip = _vary(rng, (110, 118, 70), 0.05)
    spots: list[tuple[float, float]] = []
    chosen = [cr for cr in corridors if cr[1] <= 2 and rng.random() < 0.6] or corridors[:1]
    for (u0, v0, u1, v1), _ in chosen:
        cu, cv = (u0 + u1) / 2, (v0 + v1) / 2
        along_v = u1 - u0 < v1 - v0
        t0, t1 = (v0, v1) if along_v else (u0, u1)
        ts = np.linspace(t0, t1, max(2, int((t1 - t0) / 10)))
        wob = np.cumsum(rng.normal(0, 0.25, ts.size))
        wob -= np.linspace(0, wob[-1], ts.size)
        uv = np.stack([cu + wob, ts], axis=1) if along_v else np.stack([ts, cv + wob], axis=1)
        pts = fr.pts(uv)
        c.line(pts, 4.2, dirt, Mat.DIRT)
        c.line(pts, 0.7, strip, Mat.GRASS)
        for x, y in pts[:: max(1, len(pts) // 6)]:
            if c.inside(float(x), float(y), -40):
                spots.append((float(x), float(y)))
    return spots


def _farmstead(c: _Canvas, rng: np.random.Generator, spots: list[tuple[float, float]]) -> None:
    """A barn, a farmhouse and silos on a gravel yard beside a track."""
    if not spots:
        return
    x, y = spots[int(rng.integers(len(spots)))]
    ang = rng.uniform(0, math.pi)
    ox, oy = x + 25 * math.cos(ang + math.pi / 2), y + 25 * math.sin(ang + math.pi / 2)
    c.fill([_rot_rect(ox, oy, 60, 45, ang)], _vary(rng, (160, 150, 128), 0.05), Mat.GRAVEL)
    barn = _vary(rng, _pick(rng, ((140, 60, 48), (150, 152, 150), (96, 98, 92))), 0.05)
    c.roof(
        ox - 8 * math.cos(ang),
        oy - 8 * math.sin(ang),
        16.0,
        8.0,
        ang,
        rng.uniform(5.0, 6.5),
        rng.uniform(3.0, 4.5),
        "gable",
        barn,
    )
    hx, hy = (
        ox + 18 * math.cos(ang) + 10 * math.cos(ang + 1.57),
        oy + 18 * math.sin(ang) + 10 * math.sin(ang + 1.57),
    )
    c.roof(hx, hy, 6.0, 4.5, ang, 5.5, 3.0, "hip", _vary(rng, _pick(rng, _PITCHED_ROOFS), 0.05))
    for k in range(int(rng.integers(1, 3))):
        sx = ox + (8 + 6 * k) * math.cos(ang) - 14 * math.sin(ang)
        sy = oy + (8 + 6 * k) * math.sin(ang) + 14 * math.cos(ang)
        c.disc(sx, sy, 2.6, (176, 178, 180), Mat.FLAT_ROOF, rng.uniform(9.0, 11.5))
    for _ in range(int(rng.poisson(5))):
        _wild_tree(c, rng, ox + rng.normal(0, 30), oy + rng.normal(0, 30), 0.8)


def _wild_tree(
    c: _Canvas, rng: np.random.Generator, x: float, y: float, scale: float, conifer: bool = False
) -> None:
    """A tree of wild land (8-25 m)."""
    height = float(np.clip(rng.normal(16.0, 4.0) * scale, *WILD_TREE_HEIGHT_M))
    if conifer:
        radius = float(np.clip(height * rng.uniform(0.13, 0.2), 1.5, 4.0))
        c.tree(x, y, radius, height, _vary(rng, _pick(rng, _CONIFERS), 0.08, 0.04), cone=True)
    else:
        radius = float(np.clip(height * rng.uniform(0.18, 0.3), 2.0, 7.0))
        c.tree(x, y, radius, height, _vary(rng, _pick(rng, _TREES), 0.09, 0.05))


def _forest_trees(c: _Canvas, rng: np.random.Generator, forest_small: np.ndarray) -> None:
    """Dense, clumped canopy on a jittered grid inside the forest mask."""
    size = c.size_m
    spacing = 4.6
    grid = np.arange(spacing / 2, size, spacing)
    gx, gy = np.meshgrid(grid, grid)
    gx = gx.ravel() + rng.uniform(-1.6, 1.6, gx.size)
    gy = gy.ravel() + rng.uniform(-1.6, 1.6, gy.size)
    scale = forest_small.shape[0] / size
    col = np.clip((gx * scale).astype(int), 0, forest_small.shape[1] - 1)
    row = np.clip((gy * scale).astype(int), 0, forest_small.shape[0] - 1)
    keep = forest_small[row, col].astype(bool) & (rng.random(gx.size) < 0.93)
    conifer_lo = _smooth_field(rng, forest_small.shape[0], forest_small.shape[0] * 180.0 / size)
    conifer = conifer_lo[row, col] > 0.3
    order = rng.permutation(np.flatnonzero(keep))
    for i in order:
        x, y = float(gx[i]), float(gy[i])
        if c.mat_at(x, y) in (Mat.WATER, Mat.GRAVEL, Mat.DIRT):
            continue
        _wild_tree(c, rng, x, y, 1.0, conifer=bool(conifer[i]) and rng.random() < 0.85)


# --------------------------------------------------------------------------
# Finish: shading, shadows, texture, grain
# --------------------------------------------------------------------------


def _noise(rng: np.random.Generator, side_px: int, cell_px: float) -> np.ndarray:
    """Unit-std noise with features about ``cell_px`` pixels across (pixel noise if below 1.5)."""
    if cell_px < 1.5:
        return rng.standard_normal((side_px, side_px), dtype=np.float32)
    return _smooth_field(rng, side_px, cell_px)


def _cast_shadows(height: np.ndarray, gsd_m: float) -> np.ndarray:
    """Shadow mask (float32 0..1) cast by the height map for the scene's sun.

    ``S_j(p) = max_{0 <= k < 2^j} H(p + k d) - k c`` is built by doubling,
    ``S_{j+1}(p) = max(S_j(p), S_j(p + 2^j d) - 2^j c)``, where ``d`` is
    :data:`SUN_STEP_PX` and ``c`` the height the sun ray climbs per step. A
    pixel is in shadow where something towards the sun rises above that ray.
    """
    n = height.shape[0]
    dy, dx = SUN_STEP_PX
    climb = math.hypot(dy, dx) * gsd_m * math.tan(math.radians(SUN_ELEVATION_DEG))
    top = float(height.max())
    if top <= 0:
        return np.zeros_like(height)
    steps = top / climb
    levels = int(math.ceil(math.log2(steps + 1)))
    s = height.copy()
    for j in range(levels):
        k = 1 << j
        oy, ox = k * dy, k * dx
        if oy >= n or ox >= n:
            break
        np.maximum(
            s[: n - oy, : n - ox], s[oy:, ox:] - np.float32(k * climb), out=s[: n - oy, : n - ox]
        )
    shadow = (s > height + 0.05).astype(np.float32)
    return cv2.GaussianBlur(shadow, (0, 0), max(0.5, 0.12 / gsd_m))


def _finish(c: _Canvas, rng: np.random.Generator, report: Callable[[float], None]) -> np.ndarray:
    """Shade slopes, cast shadows and add texture; returns the (H, W, 3) uint8 photo."""
    n, g = c.n, c.gsd_m
    h = c.height
    gx: np.ndarray = cv2.Sobel(h, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / (8.0 * g))
    gy: np.ndarray = cv2.Sobel(h, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / (8.0 * g))
    norm2: np.ndarray = gx * gx
    norm2 += gy * gy
    steep = norm2 > STEEP_SLOPE**2
    gx[steep] = 0.0
    gy[steep] = 0.0
    norm2[steep] = 0.0
    del steep
    el = math.radians(SUN_ELEVATION_DEG)
    dy, dx = SUN_STEP_PX
    horiz = math.cos(el) / math.hypot(dx, dy)
    lx, ly, lz = dx * horiz, dy * horiz, math.sin(el)
    # Lambert relative to flat ground for the surface normal (-gx, -gy, 1):
    # (lz - gx lx - gy ly) / (|n| lz), then mixed with ambient light.
    gx *= -lx / lz
    gx -= gy * np.float32(ly / lz)
    gx += 1.0
    del gy
    norm2 += 1.0
    np.sqrt(norm2, out=norm2)
    gx /= norm2
    del norm2
    lum = np.clip(gx, 0.0, 1.6, out=gx)
    lum *= 1.0 - AMBIENT
    lum += AMBIENT
    report(0.65)

    shadow = _cast_shadows(h, g)
    report(0.75)

    mats = c.mat
    # Material textures: patches (~8 m), clumps (~0.9 m) and grain (a pixel).
    grain: np.ndarray = rng.standard_normal((n, n), dtype=np.float32)
    if g < 0.5:
        # Soften the grain to the camera's blur, then restore its strength.
        grain = np.multiply(cv2.GaussianBlur(grain, (0, 0), 0.6), np.float32(2.0))
    for level, field in enumerate((_noise(rng, n, c.px(8.0)), _noise(rng, n, c.px(0.9)), grain)):
        amp = _TEXTURE_LUT[level][mats]
        amp *= field
        amp += 1.0
        lum *= amp
        del amp, field
    del grain
    low = _noise(rng, n, c.px(300.0))
    low *= 0.06
    low += 0.035 * _noise(rng, n, c.px(60.0))
    low += c.pattern
    low += 1.0
    lum *= low
    del low
    report(0.9)

    out: np.ndarray = np.empty((n, n, 3), np.uint8)
    haze = (158.0, 162.0, 168.0)
    for ch in range(3):
        shade = _noise(rng, n, c.px(220.0))
        shade *= 0.015
        shade += 1.0
        shade *= lum
        shade *= 1.0 - shadow * np.float32(1.0 - SHADOW_TINT[ch])
        val = c.rgb[..., ch].astype(np.float32)
        val *= shade
        val *= 0.94  # a little atmospheric haze
        val += 0.06 * haze[ch] + 0.5
        np.clip(val, 0, 255, out=val)
        out[..., ch] = val
        del shade, val
    if g < 0.6:
        out = cv2.GaussianBlur(out, (0, 0), 0.55)
    return out
