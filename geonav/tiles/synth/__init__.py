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
* ``mixed``: the three side by side, in north-south bands of a third of the scene
  each (west to east: residential, campus, wild), each band cut from a whole scene
  of its kind with the same seed; for meta-training on several kinds of place in
  one task set.

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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from geonav.errors import ConfigError
from geonav.tiles.synth.campus import _campus
from geonav.tiles.synth.canvas import (
    _Canvas,
)
from geonav.tiles.synth.finish import (
    _finish,
)
from geonav.tiles.synth.palette import (
    _KIND_SALT,
    MAX_GSD_M,
    MAX_SIDE_PX,
    MIN_GSD_M,
    MIN_SIZE_M,
)
from geonav.tiles.synth.residential import _residential
from geonav.tiles.synth.wild import _wild

__all__ = ["KINDS", "SynthImage", "synthesize"]

KINDS: tuple[str, ...] = ("residential", "campus", "wild", "mixed")
"""Kinds of synthetic scene :func:`synthesize` can make."""


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
    if kind == "mixed":
        return _mixed(size_m, gsd_m, int(seed), report)
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


MIXED_BANDS: tuple[str, ...] = ("residential", "campus", "wild")
"""The kinds of a ``mixed`` scene's bands, west to east."""


def _mixed(size_m: float, gsd_m: float, seed: int, report: Callable[[float], None]
           ) -> SynthImage:
    """A ``mixed`` scene: column band ``i`` of thirds taken from the whole scene of kind
    ``MIXED_BANDS[i]`` (same size, GSD and seed), so each band is what that kind's scene
    holds there; the seams are straight cuts."""
    n = len(MIXED_BANDS)
    parts = []
    for i, kind in enumerate(MIXED_BANDS):
        parts.append(synthesize(kind, size_m, gsd_m, seed,
                                lambda f, i=i: report((i + f) / n)))
    side = parts[0].rgb.shape[1]
    cuts = np.linspace(0, side, n + 1).round().astype(int)
    rgb = np.empty_like(parts[0].rgb)
    height = np.empty_like(parts[0].height_m)
    for part, a, b in zip(parts, cuts[:-1], cuts[1:], strict=True):
        rgb[:, a:b] = part.rgb[:, a:b]
        height[:, a:b] = part.height_m[:, a:b]
    report(1.0)
    return SynthImage(rgb=rgb, height_m=height, gsd_m=float(gsd_m), kind="mixed",
                      seed=int(seed))
