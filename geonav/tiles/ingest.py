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

This module owns the driver (:func:`ingest`, :func:`ingest_synthetic`: reading the
sources, the output checks, the coverage warnings, the write); the grid and the
reprojection (steps 1-3) live in :mod:`geonav.tiles.grid`, the coverage needs and
warnings in :mod:`geonav.tiles.coverage`, and are re-exported here.
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geonav.errors import GeonavWarning, IngestError, NoOverlap
from geonav.geo import GROUND_ALT_RANGE_M, LonLat
from geonav.outputs import check_replaceable, not_a_scene_package, output_lock
from geonav.scene import Scene, clean_stale_temps, temp_dir
from geonav.tiles.coverage import (
    MAX_ALT_M,
    META_TASK_SIZE_M,
    MIN_ALT_M,
    CoverageNeeds,
    check_coverage,
    mask_coverage,
)
from geonav.tiles.grid import (
    GSD_TOLERANCE,
    MAX_GSD_M,
    MAX_ORIGIN_OFFSET_M,
    MIN_SCENE_PX,
    Progress,
    SceneGrid,
    heights_above_ground,
    plan_grid,
    reproject_heights,
    reproject_rgb,
)
from geonav.tiles.raster import (
    RasterSource,
    check_budget,
    native_gsd_m,
    open_raster,
    source_bounds_lonlat,
)
from geonav.tiles.sources import open_source

#: With the names that moved to :mod:`~geonav.tiles.grid` and
#: :mod:`~geonav.tiles.coverage`, still importable from here.
__all__ = ["GSD_TOLERANCE", "MAX_ALT_M", "MAX_GSD_M", "MAX_ORIGIN_OFFSET_M", "META_TASK_SIZE_M",
           "MIN_ALT_M", "MIN_SCENE_PX", "CoverageNeeds", "Progress", "RasterSource",
           "SceneGrid", "check_coverage", "heights_above_ground", "ingest", "ingest_synthetic",
           "native_gsd_m", "open_raster", "open_source", "plan_grid", "reproject_heights",
           "reproject_rgb", "source_bounds_lonlat"]

log = logging.getLogger(__name__)

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
        dsm_src = _height_source(dsm, bbox_lonlat, memory_budget_mb, dsm_units)
        dsm_abs = reproject_heights(dsm_src, grid)
        if not np.isfinite(dsm_abs).any():
            raise NoOverlap(f"the DSM {dsm_src.info.get('file', '')} does not overlap the "
                            "imagery; check its CRS and extent")
        dem_grid = None
        if dem is not None:
            dem_grid = reproject_heights(
                _height_source(dem, bbox_lonlat, memory_budget_mb, dsm_units), grid)
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
    for message in check_coverage(scene, needs) + mask_coverage(mask, bbox_lonlat, rotated):
        warnings.warn(f"scene {name}: {message}", GeonavWarning, stacklevel=3)
    scene.save(out, overwrite=overwrite, compress=compress)
    if progress:
        progress("write", 1.0)
    return scene


#: Default origins of the built-in synthetic scenes (lon, lat, ground alt AMSL m).
def _height_source(source: str | os.PathLike[str] | RasterSource,
                   bbox_lonlat: tuple[float, float, float, float] | None,
                   memory_budget_mb: float | None, units: str | None) -> RasterSource:
    """A DSM or DEM as a one-band :class:`RasterSource` (read from its file unless given)."""
    if isinstance(source, RasterSource):
        return source
    return open_raster(source, bands=1, bbox_lonlat=bbox_lonlat,
                       memory_budget_mb=memory_budget_mb, height_units=units)


SYNTH_ORIGINS: dict[str, LonLat] = {
    "residential": LonLat(4.4777, 51.9244, 2.0),
    "campus": LonLat(-84.3963, 33.7756, 290.0),
    "wild": LonLat(8.2275, 46.8182, 540.0),
    "mixed": LonLat(4.4777, 51.9244, 2.0),  # the residential band's place
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
        kind: "residential" (scene A), "campus" (scene B), "wild" or "mixed" (the three
            in bands).
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
