"""Scene A, ``residential``: a street grid, house parcels, mid-rise blocks, towers, parks."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from geonav.tiles.synth.canvas import (
    _Canvas,
    _Frame,
)
from geonav.tiles.synth.common import (
    _car,
    _flat_building,
    _parking_lot,
    _street_tree,
    _tower_count,
    _tower_heights,
)
from geonav.tiles.synth.house import _house_parcel
from geonav.tiles.synth.palette import (
    _ARTERIAL_ROAD_M,
    _ASPHALT,
    _ASPHALT_OLD,
    _CONCRETE,
    _KERB,
    _LAWNS,
    _LOCAL_ROAD_M,
    _PITCHED_ROOFS,
    _SIDEWALK_M,
    _VERGE,
    _VERGE_M,
    Mat,
    _pick,
    _vary,
)


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
