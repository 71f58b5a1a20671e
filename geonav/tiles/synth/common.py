"""Small objects every synthetic scene kind uses (cars, bushes, trees, parking lots,
flat-roofed buildings, tower counts and heights), the BSP splitter and woodland
patches. Palettes live in :mod:`.palette`, the canvas in :mod:`.canvas`, the finish
pass (shading, shadows, texture) in :mod:`.finish`."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from geonav.tiles.synth.canvas import _Canvas, _Frame
from geonav.tiles.synth.palette import (
    _ASPHALT,
    _ASPHALT_OLD,
    _CARS,
    _FLAT_ROOFS,
    _TREES,
    CAR_HEIGHT_M,
    LANDMARK_HEIGHT_M,
    TOWER_DENSITY_PER_KM2,
    TOWER_HEIGHT_M,
    TREE_HEIGHT_M,
    Colour,
    Mat,
    _pick,
    _vary,
)


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
