"""The synthetic scenes' drawing canvas: albedo, material, height and pattern layers
drawn in scene metres (:class:`_Canvas`), tree-crown sprites, and local frames for
rotated layouts (:class:`_Frame`, :func:`_rot_rect`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from geonav.tiles.synth.palette import _ONE, _SHIFT, Colour, Mat

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
