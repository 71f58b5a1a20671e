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
    _bush,
    _car,
    _flat_building,
    _parking_lot,
    _street_tree,
    _tower_count,
    _tower_heights,
)
from geonav.tiles.synth.palette import (
    _ASPHALT,
    _ASPHALT_OLD,
    _CONCRETE,
    _FLAT_ROOFS,
    _KERB,
    _LAWN_WEIGHTS,
    _LAWNS,
    _PITCHED_ROOFS,
    _POOL,
    _VERGE,
    Colour,
    Mat,
    _pick,
    _vary,
)

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


@dataclass
class _Parcel:
    """A garden plot from ``a0`` to ``a1`` along its street, ``depth`` metres deep from the
    front (``v_front``) towards ``v_back``; ``d`` counts from the front."""

    fr: _Frame
    a0: float
    a1: float
    v_front: float
    sgn: float
    depth: float

    def P(self, a: float, d: float) -> tuple[float, float]:
        return self.fr.pt(a, self.v_front + self.sgn * d)

    def R(self, a0_: float, d0: float, a1_: float, d1: float) -> np.ndarray:
        return self.fr.rect(a0_, self.v_front + self.sgn * d0, a1_, self.v_front + self.sgn * d1)


@dataclass
class _House:
    """Where a parcel's house stands: width and depth, setback from the front, centre
    along the street (``ac``) and from the front (``dc``), and its roof."""

    w: float
    d: float
    setback: float
    garage: bool
    ac: float
    dc: float
    roof_col: Colour
    shape: str


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
    pc = _Parcel(fr, a0, a1, v_front, 1.0 if v_back > v_front else -1.0, abs(v_back - v_front))
    cx, cy = pc.P((a0 + a1) / 2, pc.depth / 2)
    if not c.inside(cx, cy, 30.0):
        return
    _garden(c, rng, pc, v_back)
    house = _house(c, rng, pc)
    if house is None:
        return
    _driveway(c, rng, pc, house)
    _backyard(c, rng, pc, house)
    _planting(c, rng, pc, house)


def _garden(c: _Canvas, rng: np.random.Generator, pc: _Parcel, v_back: float) -> None:
    """The lawn (sometimes mown in stripes) and, half the time, a fence."""
    fr, a0, a1, sgn, v_front = pc.fr, pc.a0, pc.a1, pc.sgn, pc.v_front
    lawn = _vary(rng, _LAWNS[int(rng.choice(len(_LAWNS), p=_LAWN_WEIGHTS))], 0.04, 0.03)
    c.fill([pc.R(a0, 0, a1, pc.depth)], lawn, Mat.GRASS)
    if rng.random() < 0.5:
        c.stripes(
            pc.R(a0, 0, a1, pc.depth),
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


def _house(c: _Canvas, rng: np.random.Generator, pc: _Parcel) -> _House | None:
    """The house's roof (gable, hip or flat), sometimes with a wing at the back; None
    when the plot is too small for one."""
    fr, a0, a1, depth = pc.fr, pc.a0, pc.a1, pc.depth
    frontage = a1 - a0
    house_w = min(frontage - 2 * rng.uniform(1.8, 3.0), rng.uniform(9.0, 16.0))
    house_d = min(depth - 12.0, rng.uniform(8.0, 13.0))
    if house_w < 6.0 or house_d < 6.0:
        return None
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
    hx, hy = pc.P(ac, dc)
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
        wx, wy = pc.P(wa, dc + house_d / 2 + wing_d / 2 - 0.5)
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
    return _House(house_w, house_d, setback, garage, ac, dc, roof_col, shape)


def _driveway(c: _Canvas, rng: np.random.Generator, pc: _Parcel, house: _House) -> None:
    """A garage beside the house (or none), the driveway to the street, maybe a car."""
    fr, a0, a1 = pc.fr, pc.a0, pc.a1
    ac, setback, garage, shape = house.ac, house.setback, house.garage, house.shape
    ga = ac
    if garage:
        side = 1.0 if ac < (a0 + a1) / 2 else -1.0
        ga = ac + side * (house.w / 2 + 3.2)
        gx, gy = pc.P(ga, setback + 3.3)
        c.roof(
            gx,
            gy,
            3.2,
            3.3,
            fr.theta + math.pi / 2,
            2.8,
            1.4 if shape != "flat" else 0.0,
            shape if shape != "gable" else "gable",
            house.roof_col,
            Mat.FLAT_ROOF if shape == "flat" else Mat.ROOF,
        )
    else:
        side = 1.0 if rng.random() < 0.5 else -1.0
        ga = float(np.clip(ac + side * (house.w / 2 + 2.0), a0 + 1.8, a1 - 1.8))
    drive_col = _vary(
        rng, _pick(rng, ((168, 162, 150), (150, 146, 140), (96, 96, 98), (150, 120, 104))), 0.05
    )
    dw = rng.uniform(2.8, 4.6) if garage else 3.0
    c.fill(
        [pc.R(ga - dw / 2, -(_VERGE_M + _SIDEWALK_M), ga + dw / 2,
              setback + (0 if garage else 6.0))],
        drive_col,
        Mat.CONCRETE,
    )
    if rng.random() < 0.55:
        cx_, cy_ = pc.P(ga + rng.normal(0, 0.3), setback * rng.uniform(0.35, 0.6))
        _car(
            c,
            rng,
            cx_,
            cy_,
            fr.theta
            + math.pi / 2 * pc.sgn
            + (math.pi if rng.random() < 0.3 else 0)
            + rng.normal(0, 0.05),
        )


def _backyard(c: _Canvas, rng: np.random.Generator, pc: _Parcel, house: _House) -> None:
    """Behind the house: maybe a patio, then a pool or a shed, maybe a flower bed."""
    fr, a0, a1, depth, ac = pc.fr, pc.a0, pc.a1, pc.depth, house.ac
    back0 = house.setback + house.d + 1.0
    back_depth = depth - back0
    if back_depth > 7.0 and rng.random() < 0.4:
        patio = _vary(rng, _pick(rng, ((170, 160, 146), (128, 98, 72), (150, 140, 126))), 0.06)
        pw, pd = rng.uniform(3.0, 6.0), rng.uniform(2.5, 4.0)
        pa = ac + rng.uniform(-2, 2)
        c.fill([pc.R(pa - pw / 2, back0 - 1.0, pa + pw / 2, back0 - 1.0 + pd)], patio, Mat.PAVER)
    if back_depth > 11.0 and rng.random() < 0.16:
        pl, pw = rng.uniform(6.0, 10.0), rng.uniform(3.5, 5.0)
        pa = float(np.clip(ac + rng.uniform(-3, 3), a0 + pl / 2 + 1.5, a1 - pl / 2 - 1.5))
        pdc = back0 + 4.0 + pw / 2
        c.fill(
            [pc.R(pa - pl / 2 - 0.7, pdc - pw / 2 - 0.7, pa + pl / 2 + 0.7, pdc + pw / 2 + 0.7)],
            (186, 182, 172),
            Mat.CONCRETE,
        )
        c.fill(
            [pc.R(pa - pl / 2, pdc - pw / 2, pa + pl / 2, pdc + pw / 2)],
            _vary(rng, _POOL, 0.05),
            Mat.POOL,
        )
    elif back_depth > 8.0 and rng.random() < 0.25:
        sw, sd = rng.uniform(2.0, 3.5), rng.uniform(2.0, 3.0)
        sa_ = rng.uniform(a0 + sw, a1 - sw)
        sx, sy = pc.P(sa_, depth - sd / 2 - 1.0)
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
        c.fill([pc.R(ba, depth - 3.0, ba + rng.uniform(2, 5), depth - 1.0)], bed, Mat.SOIL)


def _planting(c: _Canvas, rng: np.random.Generator, pc: _Parcel, house: _House) -> None:
    """Bushes along the house and trees in the front and back gardens."""
    a0, a1, depth = pc.a0, pc.a1, pc.depth
    ac, dc, setback, house_w, house_d = house.ac, house.dc, house.setback, house.w, house.d
    back0 = setback + house_d + 1.0
    back_depth = depth - back0
    for _ in range(int(rng.poisson(2.5))):
        along = rng.choice([-1.0, 1.0]) * rng.uniform(house_w / 2 + 0.8, house_w / 2 + 1.5)
        bx, by = (
            pc.P(ac + rng.uniform(-house_w / 2, house_w / 2), setback - rng.uniform(0.8, 1.5))
            if rng.random() < 0.6
            else pc.P(ac + along, dc + rng.uniform(-house_d / 2, house_d / 2))
        )
        _bush(c, rng, bx, by)
    for _ in range(int(rng.poisson(1.7))):
        if rng.random() < 0.6 and back_depth > 4.0:
            d = rng.uniform(back0 + 1.0, depth - 1.0)
        else:
            d = rng.uniform(1.5, max(1.6, setback - 1.0))
        tx, ty = pc.P(rng.uniform(a0 + 1.0, a1 - 1.0), d)
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
