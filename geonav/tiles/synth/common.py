"""Shared machinery of the synthetic scenes: palettes, materials, the drawing canvas,
sprites, small objects every kind uses (cars, trees, buildings, parking), the BSP
splitter, noise fields and the finish pass (shading, shadows, texture)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
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
