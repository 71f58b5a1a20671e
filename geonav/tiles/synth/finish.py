"""The finish pass of a synthetic scene: noise fields, slope shading, cast shadows from
the height map for the scene's sun, texture and grain (:func:`_finish`)."""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from geonav.tiles.synth.canvas import _Canvas
from geonav.tiles.synth.palette import (
    _TEXTURE_LUT,
    AMBIENT,
    SHADOW_TINT,
    STEEP_SLOPE,
    SUN_ELEVATION_DEG,
    SUN_STEP_PX,
)

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
