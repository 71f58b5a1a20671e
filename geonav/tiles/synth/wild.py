"""The ``wild`` kind: forest, fields, a meandering river, tracks and a farmstead."""

from __future__ import annotations

import math

import cv2
import numpy as np

from geonav.tiles.synth.canvas import (
    _Canvas,
    _Frame,
    _rot_rect,
)
from geonav.tiles.synth.common import (
    _bsp,
)
from geonav.tiles.synth.finish import (
    _smooth_field,
)
from geonav.tiles.synth.palette import (
    _CONIFERS,
    _CROPS,
    _PITCHED_ROOFS,
    _SHIFT,
    _TREES,
    _WATER,
    WILD_TREE_HEIGHT_M,
    Mat,
    _pick,
    _vary,
)


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
