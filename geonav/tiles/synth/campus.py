"""Scene B, ``campus``: flat-roofed buildings, quads, parking lots, sports fields, towers."""

from __future__ import annotations

import math

import numpy as np

from geonav.tiles.synth.canvas import (
    _Canvas,
    _Frame,
)
from geonav.tiles.synth.common import (
    _bsp,
    _car,
    _flat_building,
    _parking_lot,
    _street_tree,
    _tower_count,
    _tower_heights,
    _woodland,
)
from geonav.tiles.synth.palette import (
    _ASPHALT,
    _CONCRETE,
    _FLAT_ROOFS,
    CAMPUS_BUILDING_HEIGHT_M,
    Mat,
    _pick,
    _vary,
)

_ROAD_W = 8.0
_SIDE_W = 2.5


def _campus(c: _Canvas, rng: np.random.Generator) -> None:
    """Scene B: superblocks of buildings, quads, parking and sports, with roads between."""
    c.fill_all(_vary(rng, (100, 124, 62), 0.03), Mat.GRASS)
    fr = _Frame(c.size_m / 2, c.size_m / 2, rng.uniform(-0.3, 0.3))
    visible, corridors, uses, tower_of = _campus_layout(c, rng, fr)
    _campus_roads(c, rng, fr, corridors)
    for leaf in visible:
        _campus_leaf(c, rng, fr, leaf, uses[id(leaf)], tower_of.get(id(leaf), []))
    for rect, _ in corridors:
        _campus_road_furniture(c, rng, fr, rect)


def _campus_layout(
    c: _Canvas, rng: np.random.Generator, fr: _Frame
) -> tuple[
    list[tuple[float, float, float, float]],
    list[tuple[tuple[float, float, float, float], int]],
    dict[int, str],
    dict[int, list[float]],
]:
    """The superblocks in view, the road corridors between them, each block's use
    (keyed by ``id(block)``) and the towers each block hosts."""
    size = c.size_m
    ext = size * 0.72 + 40
    leaves, corridors = _bsp(
        rng, (-ext, -ext, ext, ext), 240.0, lambda d: _ROAD_W + 2 * _SIDE_W + 4.0
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
    return visible, corridors, uses, tower_of


def _campus_roads(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    corridors: list[tuple[tuple[float, float, float, float], int]],
) -> None:
    """Roads: sidewalks, then asphalt (centre lines come with the road furniture)."""
    road_w, side_w = _ROAD_W, _SIDE_W
    for width, colour, mat in (
        (road_w + 2 * side_w, _CONCRETE, Mat.CONCRETE),
        (road_w, None, Mat.ASPHALT),
    ):
        for (u0, v0, u1, v1), _ in corridors:
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


def _campus_leaf(
    c: _Canvas,
    rng: np.random.Generator,
    fr: _Frame,
    leaf: tuple[float, float, float, float],
    use: str,
    towers: list[float],
) -> None:
    """One superblock, drawn as its use says."""
    u0, v0, u1, v1 = leaf
    if use == "buildings":
        _campus_buildings(c, rng, fr, leaf, towers)
    elif use == "quad":
        _campus_quad(c, rng, fr, leaf, towers)
    elif use == "parking":
        _parking_lot(c, rng, fr, u0 + 4, v0 + 4, u1 - 4, v1 - 4)
        for uu in np.arange(u0 + 8, u1 - 4, rng.uniform(10, 14)):
            for vv in (v0 + 2.0, v1 - 2.0):
                _street_tree(c, rng, *fr.pt(float(uu), vv))
    elif use == "sports":
        _sports(c, rng, fr, leaf)
    else:
        _woodland(c, rng, fr, leaf)


def _campus_road_furniture(
    c: _Canvas, rng: np.random.Generator, fr: _Frame, rect: tuple[float, float, float, float]
) -> None:
    """A road's dashed yellow centre line, the trees along it and a few cars."""
    road_w, side_w = _ROAD_W, _SIDE_W
    yellow = (210, 178, 72)
    u0, v0, u1, v1 = rect
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
