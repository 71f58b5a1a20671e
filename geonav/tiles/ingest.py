"""Ingestion: source rasters in any CRS -> a scene package on the local tmerc grid.

Every input the toolkit accepts (GeoTIFF, XYZ tile mosaics, MBTiles,
synthetic scenes) becomes one or more :class:`RasterSource` (an array with its
CRS, affine transform and validity mask) and goes through :func:`ingest`:

1. plan the scene grid (:func:`plan_grid`): origin (default: the centre of the
   sources), the local tmerc CRS there, a GSD (default: the finest the sources
   support), bounds snapped to GSD multiples, optionally cut to a lon/lat bbox;
2. reproject each source with rasterio/GDAL onto that grid, ``average`` when
   downsampling and ``bilinear`` when upsampling, carrying the mask as an
   alpha band; several sources are mosaicked, the first valid one wins;
3. resample an optional DSM of absolute heights with ``max`` when downsampling
   (so roofs survive), subtract the ground, and store height above ground;
4. write the package atomically (:meth:`geonav.scene.Scene.save`).
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geonav.errors import GeonavWarning, IngestError, NoOverlap
from geonav.geo import GROUND_ALT_RANGE_M, LonLat, scene_crs
from geonav.outputs import check_replaceable, not_a_scene_package, output_lock
from geonav.scene import Scene, clean_stale_temps, temp_dir
from geonav.tiles.raster import (
    RasterSource,
    check_budget,
    native_gsd_m,
    open_raster,
    source_bounds_lonlat,
)
from geonav.tiles.sources import open_source

__all__ = ["RasterSource", "SceneGrid", "ingest", "ingest_synthetic", "native_gsd_m",
           "open_raster", "open_source", "plan_grid", "reproject_heights", "reproject_rgb",
           "source_bounds_lonlat"]

log = logging.getLogger(__name__)

Progress = Callable[[str, float], None]
"""Progress callback: (phase name, fraction 0..1)."""

#: Highest altitude (m) of the paper's protocol; its view sets the margin a task needs.
MAX_ALT_M = 300.0
#: Lowest altitude (m); its view sets the finest GSD the imagery should have.
MIN_ALT_M = 15.0
META_TASK_SIZE_M = 150.0
GSD_TOLERANCE = 0.01
"""How far below half the native GSD ``--gsd`` may go (a projected CRS's scale factor moves
the native GSD in ground metres by up to ~0.1 % from its nominal value)."""


@dataclass(frozen=True)
class CoverageNeeds:
    """What a scene will be flown at, for ingestion's coverage warnings: a warning only
    for what the run will use (a config with 30 m tasks of 45 m is not warned about the
    paper's 15 m views or 150 m tasks at 300 m).

    Attributes:
        views: (altitude m, view side px, field of view deg) of every view the tasks use;
            the imagery should be fine enough for the lowest one.
        tasks: (task side m, altitude m of its view margin, fov deg) of every region task;
            the scene should hold the region with that view around it.
    """

    views: tuple[tuple[float, int, float], ...] = ((MIN_ALT_M, 84, 90.0),)
    tasks: tuple[tuple[float, float, float], ...] = ((META_TASK_SIZE_M, MAX_ALT_M, 90.0),)

    @classmethod
    def paper(cls) -> CoverageNeeds:
        """The paper's protocol (the default when nothing says otherwise): 84 px views
        down to 15 m, 150 m tasks with a 300 m view margin."""
        return cls()


@dataclass(frozen=True)
class SceneGrid:
    """The target grid: local tmerc at ``origin``, north-up square pixels of ``gsd_m``."""

    origin: LonLat
    gsd_m: float
    transform: Affine
    width: int
    height: int

    @property
    def crs(self):  # rasterio CRS of the local tmerc
        from rasterio.crs import CRS as RioCRS

        return RioCRS.from_wkt(scene_crs(self.origin).to_wkt())


#: Fewest pixels a source raster and a scene must have along each side.
MIN_SCENE_PX = 16

#: Coarsest GSD (m/px) a scene may have: a 300 m view of 84 px is 7 m/px already.
MAX_GSD_M = 1000.0

#: How far (m) the scene origin may lie from the imagery: the local tmerc is exact near
#: its centre, and an origin far off is almost always a lat/lon swap or a typo.
MAX_ORIGIN_OFFSET_M = 5000.0


def _unwrap(boxes: list[tuple[float, ...]]) -> tuple[float, float, float, float]:
    """Union of lon/lat boxes, east unwrapped past 180 when a box crosses the antimeridian."""
    fixed = [(w, s, e + 360.0 if e < w else e, n) for w, s, e, n in boxes]
    crossing = any(e > 180.0 for _, _, e, _ in fixed)
    if crossing:  # put every box on the 0..360 side so they compare
        fixed = [(w + 360.0 if w < 0 else w, s, e + 360.0 if e < 0 else e, n)
                 for w, s, e, n in fixed]
    return (min(b[0] for b in fixed), min(b[1] for b in fixed),
            max(b[2] for b in fixed), max(b[3] for b in fixed))


def _wrap_lon(lon: float) -> float:
    return (lon + 180.0) % 360.0 - 180.0


def plan_grid(
    sources: Sequence[RasterSource],
    *,
    gsd_m: float | None = None,
    origin: LonLat | None = None,
    bbox_lonlat: tuple[float, float, float, float] | None = None,
) -> SceneGrid:
    """Plan the scene grid covering the sources (cut to ``bbox_lonlat`` if given).

    Raises:
        IngestError: a GSD that is not a positive finite number or far finer than the
            sources, an origin more than :data:`MAX_ORIGIN_OFFSET_M` from the data, or
            a grid of under 2x2 px.
        NoOverlap: the bbox misses the data.
    """
    from rasterio.warp import transform_bounds

    if not sources:
        raise IngestError("no source rasters given")
    if gsd_m is not None and not (math.isfinite(gsd_m) and gsd_m > 0):
        raise IngestError(f"gsd must be a positive number of metres, got {gsd_m}")
    w, s, e, n = _unwrap([source_bounds_lonlat(src) for src in sources])
    for src in sources:
        rows, cols = src.data.shape[-2:]
        if min(rows, cols) < MIN_SCENE_PX:
            native = native_gsd_m(src, LonLat(_wrap_lon((w + e) / 2), (s + n) / 2, 0.0))
            raise IngestError(
                f"{src.info.get('file') or 'a source'} is {cols}x{rows} px; imagery needs at "
                f"least {MIN_SCENE_PX} px each way ({MIN_SCENE_PX * native:.3g} m at its "
                f"{native:.3g} m/px) to become a scene; a view at {MAX_ALT_M:g} m needs "
                f"{2 * MAX_ALT_M:g} m of it")
    if bbox_lonlat is not None:
        bw, bs, be, bn = bbox_lonlat
        if not (bw < be and bs < bn) or not all(map(math.isfinite, bbox_lonlat)):
            raise IngestError(f"bbox {bbox_lonlat} must be west,south,east,north with w<e, s<n")
        if e > 180.0 and bw < 0:
            bw, be = bw + 360.0, be + 360.0
        if be <= w or bw >= e or bn <= s or bs >= n:
            raise NoOverlap(f"bbox {bbox_lonlat} misses the data, which covers "
                            f"lon {_wrap_lon(w):.6f}..{_wrap_lon(e):.6f}, lat {s:.6f}..{n:.6f}")
        w, s, e, n = max(w, bw), max(s, bs), min(e, be), min(n, bn)
    if origin is None:
        origin = LonLat(_wrap_lon((w + e) / 2), (s + n) / 2, 0.0)
    natives = [native_gsd_m(src, origin) for src in sources]
    finest = min(natives)
    if gsd_m is None:
        gsd_m = float(f"{finest:.3g}")  # e.g. 0.2500003 -> 0.25
    elif gsd_m < finest / 2 * (1.0 - GSD_TOLERANCE):
        # The native GSD is in ground metres at the origin: a projected CRS's scale factor
        # makes a nominal 0.5 m UTM pixel 0.5002 m there, and --gsd 0.25 asks for 2x, not
        # more (it was refused with "use >= 0.250", the limit rounded away).
        least = math.ceil(finest / 2 * (1.0 - GSD_TOLERANCE) * 1e4) / 1e4
        raise IngestError(f"--gsd {gsd_m:g} m is more than 2x finer than the source's native "
                          f"{finest:.4g} m/px (ground metres at the scene origin); upsampling "
                          f"adds no detail: use --gsd {least:g} or more")
    probe = SceneGrid(origin, gsd_m, Affine.identity(), 1, 1)
    xmin, ymin, xmax, ymax = transform_bounds("EPSG:4326", probe.crs, _wrap_lon(w), s,
                                              _wrap_lon(e), n, densify_pts=21)
    if bbox_lonlat is None:
        # Shrink to the sources' own footprint in the scene CRS (no empty wedges from
        # the lon/lat bbox of a rotated source).
        boxes = [transform_bounds(src.crs, probe.crs, *src.bounds(), densify_pts=21)
                 for src in sources]
        xmin, ymin = min(b[0] for b in boxes), min(b[1] for b in boxes)
        xmax, ymax = max(b[2] for b in boxes), max(b[3] for b in boxes)
    if not all(map(math.isfinite, (xmin, ymin, xmax, ymax))):
        raise IngestError(f"the data cannot be projected around the origin {origin}; is the "
                          "origin lon,lat (longitude first) near the data?")
    off_x = max(xmin - 0.0, 0.0 - xmax, 0.0)
    off_y = max(ymin - 0.0, 0.0 - ymax, 0.0)
    offset = math.hypot(off_x, off_y)
    if offset > MAX_ORIGIN_OFFSET_M:
        raise IngestError(
            f"origin {origin.lon_deg:.6f},{origin.lat_deg:.6f} is {offset / 1000:.1f} km from "
            f"the data (lon {_wrap_lon(w):.5f}..{_wrap_lon(e):.5f}, lat {s:.5f}..{n:.5f}); "
            f"give an --origin within {MAX_ORIGIN_OFFSET_M / 1000:.0f} km of it, longitude "
            "first, or leave it out to use the centre"
            + ("; tile rows read in the wrong order put a scene in the other hemisphere: "
               "check --tms" if any(src.info.get("scheme") in ("xyz", "tms")
                                   for src in sources) else ""))
    x0, y0 = math.ceil(xmin / gsd_m - 1e-6) * gsd_m, math.ceil(ymin / gsd_m - 1e-6) * gsd_m
    x1, y1 = math.floor(xmax / gsd_m + 1e-6) * gsd_m, math.floor(ymax / gsd_m + 1e-6) * gsd_m
    width, height = round((x1 - x0) / gsd_m), round((y1 - y0) / gsd_m)
    if width < MIN_SCENE_PX or height < MIN_SCENE_PX:
        raise IngestError(f"the scene would be {width}x{height} px at {gsd_m} m/px; it needs "
                          f"at least {MIN_SCENE_PX} px each way ({MIN_SCENE_PX * gsd_m:.3g} m): "
                          "a larger --bbox or a finer --gsd")
    transform = Affine(gsd_m, 0.0, x0, 0.0, -gsd_m, y1)
    return SceneGrid(origin, float(gsd_m), transform, width, height)


def reproject_rgb(sources: Sequence[RasterSource], grid: SceneGrid,
                  progress: Progress | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """Mosaic the sources onto the grid: (rgb (H, W, 3) uint8, mask (H, W) bool, resampling)."""
    from rasterio.warp import Resampling, reproject

    rgb: np.ndarray | None = None
    mask = np.zeros((grid.height, grid.width), bool)
    methods = set()
    for i, src in enumerate(sources):
        native = native_gsd_m(src, grid.origin)
        resampling = Resampling.average if grid.gsd_m > native * 1.01 else Resampling.bilinear
        methods.add(resampling.name)
        out = np.zeros((4, grid.height, grid.width), np.uint8)
        warp = dict(src_transform=src.transform, src_crs=src.crs, dst_transform=grid.transform,
                    dst_crs=grid.crs, resampling=resampling, dst_alpha=4, num_threads=2,
                    init_dest_nodata=True)
        if src.mask is None or src.mask.all():
            # No source alpha to carry: GDAL still writes the footprint into the
            # destination alpha, and skips the per-pixel alpha weighting (same result,
            # about 1.3x faster).
            reproject(src.data, out, **warp)
        else:
            alpha = src.mask.astype(np.uint8) * 255
            reproject(np.concatenate([src.data, alpha[None]], axis=0), out, src_alpha=4, **warp)
        valid = out[3] >= 128
        if rgb is None:  # first source: take its pixels as they are (masked ones are 0)
            rgb, mask = out[:3], valid
            np.multiply(rgb, valid[None], out=rgb, casting="unsafe")
        else:
            fill = valid & ~mask
            np.copyto(rgb, out[:3], where=fill[None])  # far faster than rgb[:, fill] = ...
            mask |= fill
        if progress:
            progress("reproject", (i + 1) / len(sources))
    if rgb is None or not mask.any():
        raise NoOverlap("no source pixel falls on the scene grid")
    import cv2

    # band-sequential -> (H, W, 3) contiguous; cv2.merge is ~3x faster than a numpy transpose
    return cv2.merge(list(rgb)), mask, "+".join(sorted(methods))


def reproject_heights(src: RasterSource, grid: SceneGrid) -> np.ndarray:
    """A height raster on the grid in metres (NaN where unknown); ``max`` when downsampling.

    The unit factor comes from :func:`geonav.tiles.raster.open_raster` (band unit,
    vertical CRS or ``--dsm-units``); in-memory sources without one are taken as metres.
    """
    from rasterio.warp import Resampling, reproject

    native = native_gsd_m(src, grid.origin)
    resampling = Resampling.max if grid.gsd_m > native * 1.01 else Resampling.bilinear
    out = np.full((grid.height, grid.width), np.nan, np.float32)
    data = src.data[0].astype(np.float32)
    factor = float(src.info.get("height_unit_factor", 1.0))
    reproject(data * np.float32(factor), out, src_transform=src.transform, src_crs=src.crs,
              src_nodata=np.nan, dst_transform=grid.transform, dst_crs=grid.crs,
              dst_nodata=np.nan, resampling=resampling, num_threads=2)
    return out


#: A DSM more than this far (m) below the ground counts as "below the ground".
BELOW_GROUND_TOL_M = 1.0


def heights_above_ground(dsm_abs: np.ndarray, ground_alt_m: float | None,
                         dem: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Absolute surface heights -> height above ground; also returns the ground used.

    The ground is the DEM per pixel, else ``ground_alt_m``, else the 2nd
    percentile of the valid DSM (flat-ground estimate, logged). A DSM mostly below
    the given ground is refused (wrong unit or datum); a few percent below is
    warned about and clamped to 0.
    """
    valid = np.isfinite(dsm_abs)
    if not valid.any():
        raise NoOverlap("the DSM has no valid height on the scene grid; does it overlap?")
    estimated = False
    if dem is not None:
        ground = dem
        ground_ref = float(np.nanmedian(dem))
    else:
        if ground_alt_m is None:
            ground_alt_m = float(np.percentile(dsm_abs[valid], 2))
            estimated = True
            log.info("ground level estimated from the DSM: %.2f m", ground_alt_m)
        elif not math.isfinite(ground_alt_m):
            raise IngestError(f"--ground-alt must be a finite height in metres, got "
                              f"{ground_alt_m}")
        ground, ground_ref = ground_alt_m, ground_alt_m
    diff = dsm_abs - ground
    known = valid & np.isfinite(diff)
    if not known.any():
        raise NoOverlap("the DSM and the DEM share no valid pixel on the scene grid")
    below = 0.0 if estimated else float((diff[known] < -BELOW_GROUND_TOL_M).mean())
    if below > 0.5:
        raise IngestError(
            f"the DSM lies below the ground on {below:.0%} of the scene (median "
            f"{float(np.median(diff[known])):+.1f} m); check its vertical unit (--dsm-units), "
            "datum, or --ground-alt/--dem")
    if below > 0.01:
        warnings.warn(f"the DSM lies more than {BELOW_GROUND_TOL_M:g} m below the ground on "
                      f"{below:.1%} of the scene; those heights are set to 0", GeonavWarning,
                      stacklevel=4)
    height = np.where(valid, np.maximum(diff, 0.0), np.nan).astype(np.float32)
    return height, ground_ref


def check_coverage(scene: Scene, needs: CoverageNeeds | None = None) -> list[str]:
    """Warnings for imagery too coarse for the lowest view ``needs`` names, or too small for
    its largest task with its view margin (default: the paper's 15 m views and 150 m tasks
    at 300 m)."""
    needs = needs or CoverageNeeds.paper()
    messages = []
    if needs.views:
        alt, px, fov = min(needs.views, key=lambda v: 2 * v[0] * math.tan(
            math.radians(v[2]) / 2) / v[1])
        need_gsd = 2 * alt * math.tan(math.radians(fov) / 2) / px
        if scene.gsd_m > need_gsd * 1.001:
            messages.append(
                f"imagery at {scene.gsd_m:.3f} m/px is {scene.gsd_m / need_gsd:.2f}x coarser "
                f"than the {need_gsd:.3f} m/px that {px} px views at {alt:g} m need; "
                "low-altitude views will be blurred")
    if needs.tasks:
        size, alt, fov = max(needs.tasks, key=lambda t: 2 * t[1] * math.tan(
            math.radians(t[2]) / 2) + t[0])
        need_m = 2 * alt * math.tan(math.radians(fov) / 2) + size
        side = min(scene.size_m)
        if side < need_m:
            messages.append(
                f"the scene is {side:.0f} m across, {need_m - side:.0f} m short of the "
                f"{need_m:.0f} m a {size:g} m task needs with its {alt:g} m view margin")
    return messages


def _mask_coverage(mask: np.ndarray, bbox_lonlat: tuple | None,
                   rotated: bool = False) -> list[str]:
    # The grid hugs the sources, so a few percent of edge pixels can be empty after a
    # reprojection; more than that means missing tiles or a bbox reaching past the data.
    valid = float(mask.mean())
    if valid >= 0.95:
        return []
    if bbox_lonlat is not None:
        why = "the bbox reaches beyond the imagery, or tiles are missing or corrupt"
    elif rotated:
        why = "a source is rotated, so the north-up grid around it has empty corners"
    else:
        why = "missing or corrupt tiles, or gaps between sources"
    return [f"only {valid:.0%} of the scene has imagery ({why}); the rest is masked"]


def check_writable_folder(out: Path) -> None:
    """IngestError unless ``out`` can be created: fail before the work, not after it."""
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise IngestError(f"cannot write {out}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise IngestError(f"cannot write {out}: no write permission in {parent}")


def ingest(
    sources: Sequence[str | os.PathLike[str] | RasterSource],
    *,
    name: str,
    out: str | os.PathLike[str],
    dsm: str | os.PathLike[str] | RasterSource | None = None,
    dem: str | os.PathLike[str] | RasterSource | None = None,
    ground_alt_m: float | None = None,
    gsd_m: float | None = None,
    origin: LonLat | None = None,
    bbox_lonlat: tuple[float, float, float, float] | None = None,
    attribution: str = "",
    overwrite: bool = False,
    compress: str = "JPEG",
    extra_manifest: dict[str, Any] | None = None,
    progress: Progress | None = None,
    needs: CoverageNeeds | None = None,
    tms: bool = False,
    zoom: int | None = None,
    rgb_bands: Sequence[int] | None = None,
    dsm_units: str | None = None,
    memory_budget_mb: float | None = None,
) -> Scene:
    """Turn source imagery (and an optional surface model) into a scene package.

    Args:
        sources: GeoTIFF paths, XYZ tile folders, ``.mbtiles`` files or in-memory
            sources, mosaicked in order (first wins); see :func:`open_source`.
        name: scene name, e.g. "A".
        out: the package folder to write (atomically).
        dsm: a raster of absolute surface heights (buildings, trees), any CRS.
        dem: a raster of ground heights; default: ``ground_alt_m`` or an estimate.
        ground_alt_m: the ground height AMSL when there is no DEM.
        gsd_m: the scene GSD; default: the finest the sources support.
        origin: the scene origin; default: the centre of the sources (or bbox).
        bbox_lonlat: (west, south, east, north) to cut the scene to; only that
            window of each file is read.
        attribution: the licence/attribution text the user holds for the imagery;
            default: the attributions the sources carry (fetch sidecar, MBTiles metadata).
        overwrite: replace an existing scene package (never any other folder).
        compress: ortho compression, "JPEG" or "DEFLATE".
        extra_manifest: more provenance for ``scene.json`` (e.g. synthetic parameters).
        progress: callback (phase, fraction).
        needs: what the scene will be flown at, for the coverage warnings (default: the
            paper's protocol, :meth:`CoverageNeeds.paper`).
        tms: tile folders among ``sources`` are in TMS row order.
        zoom: the zoom level to read from tile folders / MBTiles (default: highest).
        rgb_bands: 1-based bands of GDAL rasters to use as R,G,B (default: colour
            interpretation, else 1,2,3).
        dsm_units: unit of the DSM/DEM values, "m", "ft" or "us-ft" (default: from
            the file, see :func:`geonav.tiles.raster.height_unit_factor`).
        memory_budget_mb: refuse reads and grids above this many MiB (default 4096).

    Returns:
        The written scene (also opened-equivalent: arrays in memory).
    """
    out = Path(out)
    check_writable_folder(out)
    if not name or "/" in name:
        raise IngestError(f"scene name {name!r} must be a non-empty name without '/'")
    if ground_alt_m is not None and not math.isfinite(ground_alt_m):
        raise IngestError(f"ground_alt_m must be a finite height in metres, got {ground_alt_m}")
    lo, hi = GROUND_ALT_RANGE_M
    for what, alt in (("--ground-alt", ground_alt_m),
                      ("the --origin altitude", None if origin is None else origin.alt_m)):
        if alt is not None and math.isfinite(alt) and not lo <= alt <= hi:
            raise IngestError(f"{what} {alt:g} m is not a ground height ({lo:g}..{hi:g} m "
                              "above mean sea level); give the ground's height at the origin")
    if gsd_m is not None and not (math.isfinite(gsd_m) and 0 < gsd_m <= MAX_GSD_M):
        raise IngestError(f"--gsd {gsd_m} m/px must be within 0..{MAX_GSD_M:g} m/px (a view "
                          f"at {MIN_ALT_M:g} m needs about 0.36 m/px)")
    if compress.upper() not in ("JPEG", "DEFLATE"):
        raise IngestError(f"compress {compress!r}: use JPEG or DEFLATE")
    if dem is not None and dsm is None:
        raise IngestError("--dem needs --dsm: the DEM is the ground the DSM heights are "
                          "measured from")
    # The lock is held from here to the rename: a second ingest into the same --out is
    # refused now, not silently replaced minutes later.
    with output_lock(out, "--out"):
        check_replaceable(out, "scene package", force=overwrite,
                          why_not=not_a_scene_package, error=IngestError)
        return _ingest(
            sources, name=name, out=out, dsm=dsm, dem=dem, ground_alt_m=ground_alt_m,
            gsd_m=gsd_m, origin=origin, bbox_lonlat=bbox_lonlat, attribution=attribution,
            overwrite=overwrite, compress=compress, extra_manifest=extra_manifest,
            progress=progress, tms=tms, zoom=zoom, rgb_bands=rgb_bands, dsm_units=dsm_units,
            memory_budget_mb=memory_budget_mb, needs=needs)


def _ingest(
    sources: Sequence[str | os.PathLike[str] | RasterSource], *, name: str, out: Path,
    dsm: Any, dem: Any, ground_alt_m: float | None, gsd_m: float | None,
    origin: LonLat | None, bbox_lonlat: tuple[float, float, float, float] | None,
    attribution: str, overwrite: bool, compress: str, extra_manifest: dict[str, Any] | None,
    progress: Progress | None, tms: bool, zoom: int | None, rgb_bands: Sequence[int] | None,
    dsm_units: str | None, memory_budget_mb: float | None, needs: CoverageNeeds | None = None,
) -> Scene:
    """The body of :func:`ingest`, under the lock of ``out``."""
    rasters = [s if isinstance(s, RasterSource) else
               open_source(s, tms=tms, zoom=zoom, bbox_lonlat=bbox_lonlat, progress=progress,
                           rgb_bands=rgb_bands, target_gsd_m=gsd_m,
                           memory_budget_mb=memory_budget_mb)
               for s in sources]
    if progress:
        progress("read", 1.0)
    grid = plan_grid(rasters, gsd_m=gsd_m, origin=origin, bbox_lonlat=bbox_lonlat)
    # rgb + mask + the 4-band warp output, and with a DSM three float32 grids
    check_budget(grid.width * grid.height * (8 + (12 if dsm is not None else 0)),
                 memory_budget_mb, f"a {grid.width}x{grid.height} px scene grid")
    rgb, mask, resampling = reproject_rgb(rasters, grid, progress)
    if not attribution:
        attribution = "; ".join(dict.fromkeys(
            str(r.info["attribution"]) for r in rasters if r.info.get("attribution")))
    heights = None
    ground_ref = origin.alt_m if origin is not None else 0.0
    dsm_info = None
    if dsm is not None:
        dsm_src = dsm if isinstance(dsm, RasterSource) else open_raster(
            dsm, bands=1, bbox_lonlat=bbox_lonlat, memory_budget_mb=memory_budget_mb,
            height_units=dsm_units)
        dsm_abs = reproject_heights(dsm_src, grid)
        if not np.isfinite(dsm_abs).any():
            raise NoOverlap(f"the DSM {dsm_src.info.get('file', '')} does not overlap the "
                            "imagery; check its CRS and extent")
        dem_grid = None
        if dem is not None:
            dem_src = dem if isinstance(dem, RasterSource) else open_raster(
                dem, bands=1, bbox_lonlat=bbox_lonlat, memory_budget_mb=memory_budget_mb,
                height_units=dsm_units)
            dem_grid = reproject_heights(dem_src, grid)
            if not np.isfinite(dem_grid).any():
                raise NoOverlap("the DEM does not overlap the imagery")
        heights, ground_ref = heights_above_ground(dsm_abs, ground_alt_m, dem_grid)
        dsm_info = {k: v for k, v in dsm_src.info.items() if k != "path"}
        if progress:
            progress("dsm", 1.0)
    scene_origin = LonLat(grid.origin.lon_deg, grid.origin.lat_deg,
                          float(ground_ref if origin is None else origin.alt_m))
    scene = Scene(name, rgb, mask, grid.gsd_m, grid.transform, scene_origin, heights)
    scene.manifest = dict(
        sources=[{k: v for k, v in s.info.items() if k != "path"} | dict(
            native_gsd_m=round(native_gsd_m(s, grid.origin), 4)) for s in rasters],
        dsm_source=dsm_info,
        ground_alt_m=ground_ref,
        resampling=resampling,
        attribution=attribution,
        mask_fraction=float(mask.mean()),
        **(extra_manifest or {}),
    )
    rotated = any(r.transform.b or r.transform.d for r in rasters)
    for message in check_coverage(scene, needs) + _mask_coverage(mask, bbox_lonlat, rotated):
        warnings.warn(f"scene {name}: {message}", GeonavWarning, stacklevel=3)
    scene.save(out, overwrite=overwrite, compress=compress)
    if progress:
        progress("write", 1.0)
    return scene


#: Default origins of the built-in synthetic scenes (lon, lat, ground alt AMSL m).
SYNTH_ORIGINS: dict[str, LonLat] = {
    "residential": LonLat(4.4777, 51.9244, 2.0),
    "campus": LonLat(-84.3963, 33.7756, 290.0),
    "wild": LonLat(8.2275, 46.8182, 540.0),
}


def ingest_synthetic(
    kind: str,
    *,
    out: str | os.PathLike[str],
    name: str | None = None,
    size_m: float = 1200.0,
    gsd_m: float = 0.25,
    seed: int = 0,
    origin: LonLat | None = None,
    overwrite: bool = False,
    keep_sources: str | os.PathLike[str] | None = None,
    progress: Progress | None = None,
    needs: CoverageNeeds | None = None,
) -> Scene:
    """Synthesise a scene, write it as real GeoTIFFs in EPSG:3857, and ingest those.

    The image and a DSM of absolute heights (ground + objects) are written the
    way web imagery arrives (Web-Mercator, north-up), then go through
    :func:`ingest` exactly like a user's files.

    Args:
        kind: "residential" (scene A), "campus" (scene B) or "wild".
        out: the package folder.
        name: scene name (default: the kind).
        size_m: side of the square scene in metres.
        gsd_m: ground sample distance in metres per pixel.
        seed: generator seed (same seed, same scene).
        origin: scene centre (default: a fixed place per kind).
        overwrite: replace an existing scene package (never any other folder).
        keep_sources: a folder to keep the two source GeoTIFFs in.
        progress: callback (phase, fraction).
        needs: what the scene will be flown at, for the coverage warnings (default: the
            paper's protocol).
    """
    check_writable_folder(Path(out))
    if not (0 < gsd_m <= MAX_GSD_M and math.isfinite(gsd_m)) or \
            not (0 < size_m and math.isfinite(size_m)):
        raise IngestError(f"--size {size_m} m and --gsd {gsd_m} m/px must be positive, the GSD "
                          f"at most {MAX_GSD_M:g} m/px")
    side_px = size_m / gsd_m
    # the synthetic image, its heights and the ingest's own grids: about 32 bytes a pixel
    check_budget(side_px * side_px * 32, None, f"a {size_m:g} m synthetic scene at {gsd_m:g} m/px")
    if side_px < MIN_SCENE_PX:
        raise IngestError(f"a {size_m:g} m scene at {gsd_m:g} m/px is {side_px:.1f} px across; "
                          f"give --size of at least {MIN_SCENE_PX * gsd_m:g} m")
    if keep_sources:  # files it would replace there must be its own earlier sources
        for path in synth_source_paths(Path(keep_sources), kind, seed):
            check_replaceable(path, "synthetic source", force=True,
                              why_not=_not_a_synth_source, error=IngestError)
    with output_lock(out, "--out"):  # held through the synthesis: minutes for a big scene
        check_replaceable(out, "scene package", force=overwrite,
                          why_not=not_a_scene_package, error=IngestError)
        return _ingest_synthetic(kind, out=out, name=name, size_m=size_m, gsd_m=gsd_m,
                                 seed=seed, origin=origin, overwrite=overwrite,
                                 keep_sources=keep_sources, progress=progress, needs=needs)


#: The TIFF Software tag of the GeoTIFFs that ``tiles synth`` writes.
SYNTH_SOFTWARE = "geonav synth"


def synth_source_paths(folder: Path, kind: str, seed: int) -> tuple[Path, Path]:
    """(ortho, DSM) GeoTIFFs of a synthetic scene in ``folder``."""
    return folder / f"{kind}-{seed}-3857.tif", folder / f"{kind}-{seed}-dsm.tif"


def _not_a_synth_source(path: Path) -> str | None:
    import rasterio
    from rasterio.errors import RasterioError

    try:
        with rasterio.open(path) as src:
            ours = src.tags().get("TIFFTAG_SOFTWARE") == SYNTH_SOFTWARE
    except RasterioError:
        ours = False
    return None if ours else "it is not a GeoTIFF that geonav tiles synth wrote"


def _ingest_synthetic(kind: str, *, out: str | os.PathLike[str], name: str | None,
                      size_m: float, gsd_m: float, seed: int, origin: LonLat | None,
                      overwrite: bool, keep_sources: str | os.PathLike[str] | None,
                      progress: Progress | None, needs: CoverageNeeds | None = None) -> Scene:
    """The body of :func:`ingest_synthetic`, under the lock of ``out``."""
    import tempfile

    import rasterio
    from pyproj import Proj, Transformer

    from geonav.tiles.synth import synthesize

    origin = origin or SYNTH_ORIGINS.get(kind, LonLat(0.0, 45.0, 0.0))
    image = synthesize(kind, size_m=size_m, gsd_m=gsd_m, seed=seed,
                       progress=(lambda f: progress("synthesise", f)) if progress else None)
    mx, my = Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True).transform(
        origin.lon_deg, origin.lat_deg)
    # Web-Mercator metres per ground metre at the origin (about 1/cos(lat)).
    scale = Proj("EPSG:3857").get_factors(origin.lon_deg, origin.lat_deg).meridional_scale
    res = gsd_m * scale
    h, w = image.rgb.shape[:2]
    transform = Affine(res, 0.0, mx - w * res / 2, 0.0, -res, my + h * res / 2)
    if keep_sources:
        folder = Path(keep_sources)
        folder.mkdir(parents=True, exist_ok=True)
    else:
        tmp_root = Path(tempfile.gettempdir())
        clean_stale_temps(tmp_root, "geonav-synth")
        folder = temp_dir(tmp_root, "geonav-synth")
    try:
        ortho_path, dsm_path = synth_source_paths(folder, kind, seed)
        common = dict(driver="GTiff", width=w, height=h, crs="EPSG:3857", transform=transform,
                      tiled=True, compress="DEFLATE")
        with rasterio.open(ortho_path, "w", count=3, dtype="uint8", **common) as dst:
            dst.write(np.moveaxis(image.rgb, 2, 0))
            dst.update_tags(TIFFTAG_SOFTWARE=SYNTH_SOFTWARE)
        with rasterio.open(dsm_path, "w", count=1, dtype="float32", nodata=float("nan"),
                           **common) as dst:
            dst.write((image.height_m + origin.alt_m).astype(np.float32), 1)
            dst.update_tags(TIFFTAG_SOFTWARE=SYNTH_SOFTWARE)
        return ingest(
            [ortho_path], name=name or kind, out=out, dsm=dsm_path, ground_alt_m=origin.alt_m,
            gsd_m=gsd_m, origin=origin, overwrite=overwrite, progress=progress, needs=needs,
            attribution="synthetic scene generated by geonav (no third-party imagery)",
            extra_manifest=dict(synthetic=dict(kind=kind, seed=seed, size_m=size_m,
                                               gsd_m=gsd_m)),
        )
    finally:
        if not keep_sources:
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
