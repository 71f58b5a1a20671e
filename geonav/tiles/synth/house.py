"""One house plot of the residential scene: lawn and fence, the house (gable, hip or flat
roof, maybe a wing), garage and driveway, back garden (patio, pool or shed, beds) and
planting, drawn in that order from one random stream (:func:`_house_parcel`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from geonav.tiles.synth.canvas import _Canvas, _Frame
from geonav.tiles.synth.common import _bush, _car, _street_tree
from geonav.tiles.synth.palette import (
    _FLAT_ROOFS,
    _LAWN_WEIGHTS,
    _LAWNS,
    _PITCHED_ROOFS,
    _POOL,
    _SIDEWALK_M,
    _VERGE_M,
    Colour,
    Mat,
    _pick,
    _vary,
)


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
