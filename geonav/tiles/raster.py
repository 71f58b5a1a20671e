"""Georeferenced rasters held in memory, and the GDAL reader that fills them.

:class:`RasterSource` is what every input becomes (GeoTIFF, tile mosaic,
synthetic scene) before :func:`geonav.tiles.ingest.ingest` puts it on the scene
grid. :func:`open_raster` reads a GDAL raster with the care real files need:

* any geotransform, rotated ones included (bounds from the four corners);
* only the window a lon/lat bbox needs, decimated through the overviews when
  the scene GSD is coarser than the file, and refused above a memory budget;
* band choice: ``bands`` (1-based, like GDAL) or the file's colour
  interpretation; grey and paletted images are expanded to RGB with a warning;
* 16-bit and float imagery stretched from the percentiles of valid pixels only
  (nodata and masked pixels excluded);
* the vertical unit of a height raster from the band's unit or the vertical CRS,
  overridable, with a warning whenever a factor is applied.
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geonav.errors import GeonavWarning, IngestError, MissingCRS, NoOverlap
from geonav.geo import LonLat, parse_crs, scene_crs, transformer
from geonav.scene import sha256_file
from geonav.tiles import DEFAULT_MEMORY_BUDGET_MB, DSM_UNIT_CHOICES

log = logging.getLogger(__name__)


#: Metres per unit of a height raster, by the names GDAL files use for units.
HEIGHT_UNITS: dict[str, float] = {
    "m": 1.0, "metre": 1.0, "meter": 1.0, "metres": 1.0, "meters": 1.0,
    "ft": 0.3048, "foot": 0.3048, "feet": 0.3048, "international foot": 0.3048,
    "us-ft": 1200.0 / 3937.0, "ftus": 1200.0 / 3937.0, "us survey foot": 1200.0 / 3937.0,
    "us_survey_foot": 1200.0 / 3937.0, "foot_us": 1200.0 / 3937.0,
}


@dataclass
class RasterSource:
    """One georeferenced input raster held in memory.

    Attributes:
        data: (bands, H, W) array; 3 bands uint8 for imagery, 1 band float for a DSM.
        crs: rasterio CRS of the source.
        transform: affine pixel -> source CRS (upper-left corner convention); may rotate.
        mask: (H, W) bool validity mask, or None when every pixel is valid.
        info: provenance recorded in the manifest (file, sha256, zoom, ...).
    """

    data: np.ndarray
    crs: Any
    transform: Affine
    mask: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.data.shape[1]), int(self.data.shape[2])

    def corners(self) -> list[tuple[float, float]]:
        """The four pixel-grid corners in the source CRS (rotation included)."""
        h, w = self.shape
        return [self.transform @ (c, r) for c, r in ((0, 0), (w, 0), (w, h), (0, h))]

    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the four corners in the source CRS."""
        xs, ys = zip(*self.corners(), strict=True)
        return min(xs), min(ys), max(xs), max(ys)


def memory_budget_bytes(budget_mb: float | None) -> int:
    """The budget in bytes (``None``: :data:`DEFAULT_MEMORY_BUDGET_MB`)."""
    mb = DEFAULT_MEMORY_BUDGET_MB if budget_mb is None else budget_mb
    if not (isinstance(mb, (int, float)) and math.isfinite(mb) and mb > 0):
        raise IngestError(f"memory budget must be a positive number of MiB, got {budget_mb!r}")
    return int(mb * (1 << 20))


def check_budget(need_bytes: float, budget_mb: float | None, what: str) -> None:
    """IngestError when ``need_bytes`` exceed the budget, saying how to get under it."""
    budget = memory_budget_bytes(budget_mb)
    if need_bytes > budget:
        raise IngestError(
            f"{what} needs about {need_bytes / (1 << 30):.1f} GiB, over the memory budget of "
            f"{budget / (1 << 30):.1f} GiB; cut it with --bbox, use a coarser --gsd, or raise "
            "--memory-budget (MiB)")


def native_gsd_m(src: RasterSource, origin: LonLat) -> float:
    """The source's pixel size in ground metres at its centre, in the local tmerc at ``origin``.

    Maps a pixel's two edge vectors through the projection, so rotation, degrees,
    feet and Web-Mercator's 1/cos(lat) scale are all taken into account.
    """
    h, w = src.shape
    t = src.transform
    c, r = w / 2, h / 2
    pts = [t @ (c, r), t @ (c + 1, r), t @ (c, r + 1)]
    tr = transformer(parse_crs(src.crs.to_wkt()), scene_crs(origin))
    xs, ys = tr.transform([p[0] for p in pts], [p[1] for p in pts])
    ux, uy = xs[1] - xs[0], ys[1] - ys[0]
    vx, vy = xs[2] - xs[0], ys[2] - ys[0]
    area = abs(ux * vy - uy * vx)
    if not (math.isfinite(area) and area > 0):
        raise IngestError(f"cannot measure the pixel size of {src.info.get('file', 'a source')} "
                          "in metres; is its CRS right?")
    return float(math.sqrt(area))


def source_bounds_lonlat(src: RasterSource) -> tuple[float, float, float, float]:
    """(west, south, east, north) of the source; west > east when it crosses 180 degrees."""
    from rasterio.warp import transform_bounds

    try:
        box = tuple(transform_bounds(src.crs, "EPSG:4326", *src.bounds(), densify_pts=21))
    except Exception as err:  # noqa: BLE001 - PROJ cannot place it on the globe
        raise IngestError(f"{src.info.get('file', 'a source')}: its extent cannot be turned "
                          f"into lon/lat ({err}); check its CRS and geotransform") from err
    if not all(map(math.isfinite, box)):
        raise IngestError(f"{src.info.get('file', 'a source')}: its extent lies outside the "
                          "valid area of its CRS; check its CRS and geotransform")
    return box


# -- reading GDAL rasters --------------------------------------------------------------------

def _parse_bands(bands: Sequence[int] | None, count: int, path: Path) -> list[int] | None:
    if bands is None:
        return None
    picked = [int(b) for b in bands]
    if len(picked) not in (1, 3) or any(not 1 <= b <= count for b in picked):
        raise IngestError(f"--bands {','.join(map(str, picked))}: {path.name} has bands "
                          f"1..{count}; give three (R,G,B) or one (grey), 1-based like GDAL")
    return picked


def _rgb_bands(src: Any, path: Path, bands: Sequence[int] | None) -> tuple[list[int], str]:
    """(1-based band indexes, how the image is read: 'rgb', 'grey' or 'palette')."""
    from rasterio.enums import ColorInterp

    picked = _parse_bands(bands, src.count, path)
    if picked is not None:
        return picked, "rgb" if len(picked) == 3 else "grey"
    interp = list(src.colorinterp)
    if ColorInterp.palette in interp[:1]:
        return [1], "palette"
    named = {ci: i + 1 for i, ci in reversed(list(enumerate(interp)))}
    if all(ci in named for ci in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)):
        order = [named[ColorInterp.red], named[ColorInterp.green], named[ColorInterp.blue]]
        if order != [1, 2, 3]:
            log.info("%s: colour interpretation puts R,G,B in bands %s", path, order)
        return order, "rgb"
    colour_bands = [i + 1 for i, ci in enumerate(interp)
                    if ci not in (ColorInterp.alpha, ColorInterp.undefined)]
    if src.count >= 3:
        if src.count > 3:
            warnings.warn(
                f"{path.name} has {src.count} bands and no red/green/blue colour "
                "interpretation; using bands 1,2,3 as R,G,B (choose with --bands, e.g. "
                "--bands 4,3,2 for Landsat 8)", GeonavWarning, stacklevel=4)
        return [1, 2, 3], "rgb"
    first = colour_bands[0] if colour_bands else 1
    return [first], "grey"


def _to_uint8(data: np.ndarray, valid: np.ndarray, path: Path) -> np.ndarray:
    """16-bit/float imagery -> 8 bit: the 0.2-99.8 percentiles of *valid* pixels to 0-255."""
    good = valid[None] & np.isfinite(data)
    if not good.any():
        raise IngestError(f"{path.name} has no valid pixel to take a stretch from (all nodata)")
    lo, hi = np.percentile(data[good], [0.2, 99.8])
    warnings.warn(f"{path.name} is {data.dtype}; stretched {lo:.4g}..{hi:.4g} (valid pixels) "
                  "to 8 bit", GeonavWarning, stacklevel=4)
    scaled = (data.astype(np.float32) - np.float32(lo)) / np.float32(max(hi - lo, 1e-9)) * 255
    out = np.clip(np.nan_to_num(scaled), 0, 255).astype(np.uint8)
    out[~good] = 0
    return out


def _window_for(src: Any, bbox_lonlat: Sequence[float] | None, path: Path):
    """The pixel window of ``src`` that covers the bbox (whole raster for None)."""
    from rasterio.warp import transform_bounds
    from rasterio.windows import Window

    full = Window(0, 0, src.width, src.height)
    if bbox_lonlat is None:
        return full
    try:
        left, bottom, right, top = transform_bounds("EPSG:4326", src.crs, *bbox_lonlat,
                                                    densify_pts=21)
    except Exception as err:  # noqa: BLE001 - outside the CRS's domain, PROJ errors
        raise NoOverlap(f"bbox {tuple(bbox_lonlat)} cannot be projected into the CRS of "
                        f"{path.name} ({err}); is it lon,lat near the data?") from err
    if not all(map(math.isfinite, (left, bottom, right, top))):
        raise NoOverlap(f"bbox {tuple(bbox_lonlat)} lies outside the valid area of the CRS "
                        f"of {path.name}")
    inv = ~src.transform
    cols, rows = zip(*(inv @ (x, y) for x in (left, right) for y in (bottom, top)), strict=True)
    c0, c1 = max(0, math.floor(min(cols)) - 2), min(src.width, math.ceil(max(cols)) + 2)
    r0, r1 = max(0, math.floor(min(rows)) - 2), min(src.height, math.ceil(max(rows)) + 2)
    if c1 <= c0 or r1 <= r0:
        w, s, e, n = transform_bounds(src.crs, "EPSG:4326", *src.bounds, densify_pts=21)
        raise NoOverlap(f"bbox {tuple(bbox_lonlat)} misses the data of {path.name}, which "
                        f"covers lon {w:.6f}..{e:.6f}, lat {s:.6f}..{n:.6f}")
    return Window(c0, r0, c1 - c0, r1 - r0)


def _decimation(src: Any, window: Any, target_gsd_m: float | None) -> int:
    """Integer read decimation so the pixels stay at least as fine as ``target_gsd_m``."""
    if target_gsd_m is None:
        return 1
    probe = RasterSource(np.zeros((1, int(window.height), int(window.width)), np.uint8),
                         src.crs, src.window_transform(window))
    bounds = probe.bounds()
    try:
        from rasterio.warp import transform_bounds

        w, s, e, n = transform_bounds(src.crs, "EPSG:4326", *bounds, densify_pts=5)
        native = native_gsd_m(probe, LonLat((w + e) / 2 if w <= e else w, (s + n) / 2))
    except Exception:  # noqa: BLE001 - no decimation is always correct, only slower
        return 1
    ratio = target_gsd_m / native
    if not math.isfinite(ratio):  # a GSD like 1e308: read every pixel, plan_grid refuses it
        return 1
    return max(1, min(int(ratio + 1e-6), max(int(window.width), int(window.height), 1)))


def open_raster(
    path: str | os.PathLike[str],
    *,
    bands: int | None = None,
    rgb_bands: Sequence[int] | None = None,
    bbox_lonlat: Sequence[float] | None = None,
    target_gsd_m: float | None = None,
    memory_budget_mb: float | None = None,
    height_units: str | None = None,
) -> RasterSource:
    """Read a GeoTIFF (or any GDAL raster) into a :class:`RasterSource`.

    Args:
        path: the file.
        bands: 3 for imagery (RGB, alpha or mask band used as mask), 1 for a height raster.
        rgb_bands: 1-based bands to use as R,G,B (or one grey band); default: the
            file's colour interpretation, else bands 1,2,3.
        bbox_lonlat: read only the window covering (west, south, east, north).
        target_gsd_m: the scene GSD; a file finer than half of it is read decimated
            (through its overviews when it has them).
        memory_budget_mb: refuse reads above this many MiB (default 4096).
        height_units: unit of a height raster's values ("m", "ft", "us-ft"); default:
            the band's unit, the vertical CRS, else the horizontal CRS unit (warned).
    """
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.errors import RasterioError

    path = Path(path)
    if not path.is_file():
        raise IngestError(f"{path} does not exist")
    try:
        with rasterio.open(path) as src:
            _check_georeferenced(src, path)
            window = _window_for(src, bbox_lonlat, path)
            step = _decimation(src, window, target_gsd_m) if bands == 3 else 1
            out_h = max(1, math.ceil(window.height / step))
            out_w = max(1, math.ceil(window.width / step))
            transform = src.window_transform(window) @ Affine.scale(window.width / out_w,
                                                                    window.height / out_h)
            read = dict(window=window, out_shape=None, resampling=Resampling.average)
            if bands == 3:
                indexes, mode = _rgb_bands(src, path, rgb_bands)
                itemsize = np.dtype(src.dtypes[indexes[0] - 1]).itemsize
                # the read, the mask, the 8-bit result and (16-bit/float) a float32 copy
                need = out_h * out_w * (3 * itemsize + 1 + 3 + (12 if itemsize > 1 else 0))
                check_budget(need, memory_budget_mb, f"reading {path.name} "
                             f"({out_w}x{out_h} px)")
                read["out_shape"] = (len(indexes), out_h, out_w)
                data = src.read(indexes, **read)
                mask = _valid_mask(src, window, (out_h, out_w))
                if mode == "palette":
                    data, mask = _expand_palette(src, data[0], mask, path)
                elif mode == "grey":
                    warnings.warn(f"{path.name}: one grey band (band {indexes[0]}) expanded "
                                  "to RGB", GeonavWarning, stacklevel=2)
                if data.dtype != np.uint8:
                    data = _to_uint8(data, mask, path)
                if data.shape[0] == 1:
                    data = np.repeat(data, 3, axis=0)
                info_bands = indexes
            else:
                data, mask = _read_heights(src, path, read, (out_h, out_w), memory_budget_mb,
                                           height_units)
                info_bands = [1]
            info = dict(file=path.name, path=str(path.resolve()), sha256=sha256_file(path),
                        crs=parse_crs(src.crs.to_wkt()).to_wkt(), size_px=[src.width, src.height],
                        bands=info_bands)
            if (window.width, window.height) != (src.width, src.height) or step > 1:
                info["read_window_px"] = [int(window.col_off), int(window.row_off),
                                          int(window.width), int(window.height)]
                info["read_decimation"] = step
            if bands != 3:
                factor, why = height_unit_factor(src, path, height_units)
                info["height_unit_factor"], info["height_unit_from"] = factor, why
            return RasterSource(data, src.crs, transform, mask, info)
    except RasterioError as err:
        raise IngestError(f"cannot read {path}: {err}") from err
    except MemoryError as err:
        raise IngestError(f"{path} does not fit in memory; cut it with --bbox or use a "
                          "coarser --gsd") from err


def _check_georeferenced(src: Any, path: Path) -> None:
    """MissingCRS for a raster without a CRS or geotransform (ground control points only,
    or nothing); a rotated geotransform is logged (it is warped north-up)."""
    gcps, _gcp_crs = src.gcps
    if src.crs is None and gcps:
        raise MissingCRS(
            f"{path} is georeferenced by {len(gcps)} ground control points, not a "
            f"geotransform; warp it onto a grid first, e.g. 'gdalwarp -r bilinear "
            f"{path.name} warped.tif'")
    if src.crs is None:
        raise MissingCRS(
            f"{path} has no CRS; assign one first, e.g. "
            f"'gdal_edit.py -a_srs EPSG:xxxx {path.name}'")
    if src.transform == Affine.identity():
        raise MissingCRS(f"{path} has no geotransform; it is not georeferenced")
    if src.transform.b or src.transform.d:
        log.info("%s has a rotated geotransform; it is warped north-up", path)


def _read_heights(src: Any, path: Path, read: dict[str, Any], shape: tuple[int, int],
                  memory_budget_mb: float | None, height_units: str | None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(1, H, W) float32 heights (NaN where invalid) and their (H, W) validity of band 1,
    read with ``read``'s window and resampling at ``shape``."""
    out_h, out_w = shape
    check_height_raster(src, path, height_units)
    check_budget(out_h * out_w * 4 * 3, memory_budget_mb,
                 f"reading {path.name} ({out_w}x{out_h} px)")
    read["out_shape"] = (1, out_h, out_w)
    data = src.read([1], **read).astype(np.float32)
    valid = _valid_mask(src, read["window"], (out_h, out_w), band=1)
    valid &= np.isfinite(data[0])
    data[0][~valid] = np.nan
    return data, valid


def _valid_mask(src: Any, window: Any, shape: tuple[int, int],
                band: int | None = None) -> np.ndarray:
    """Validity of the window at ``shape``; no read at all when every pixel is valid
    (GDAL would otherwise build the all-valid mask at full resolution, about 1 GB
    for a 16000^2 px file read decimated)."""
    from rasterio.enums import MaskFlags, Resampling

    flags = src.mask_flag_enums if band is None else [src.mask_flag_enums[band - 1]]
    if all(MaskFlags.all_valid in f for f in flags):
        return np.ones(shape, bool)
    if band is not None:
        return src.read_masks(band, window=window, out_shape=shape) > 0
    return src.dataset_mask(window=window, out_shape=shape, resampling=Resampling.nearest) > 0


def _expand_palette(src: Any, index: np.ndarray, mask: np.ndarray,
                    path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        cmap = src.colormap(1)
    except ValueError as err:
        raise IngestError(f"{path.name} says it is paletted but has no colour table") from err
    lut = np.zeros((max(256, max(cmap) + 1), 4), np.uint8)
    for k, rgba in cmap.items():
        lut[k] = rgba[:4] if len(rgba) >= 4 else (*rgba[:3], 255)
    rgba = lut[index.astype(np.int64)]
    warnings.warn(f"{path.name}: paletted image ({len(cmap)} colours) expanded to RGB",
                  GeonavWarning, stacklevel=3)
    return np.moveaxis(rgba[..., :3], 2, 0), mask & (rgba[..., 3] >= 128)


def check_height_raster(src: Any, path: Path, override: str | None) -> None:
    """Refuse a --dsm/--dem that is not a height raster: more than one band, a palette, or
    integer values whose unit nothing states (8-bit imagery looks exactly like that).

    Raises:
        IngestError: naming the file, what it looks like and what to pass instead.
    """
    from rasterio.enums import ColorInterp

    if src.count != 1:
        interp = ",".join(c.name for c in src.colorinterp)
        raise IngestError(
            f"{path.name} has {src.count} bands ({interp}): a surface model (--dsm, --dem) has "
            "one band of heights, so this looks like an image; give the height raster, or "
            f"extract its band first, e.g. 'gdal_translate -b 1 {path.name} heights.tif'")
    if src.colorinterp and src.colorinterp[0] == ColorInterp.palette:
        raise IngestError(f"{path.name} is a paletted image, not a raster of heights; give "
                          "the surface model (--dsm, --dem)")
    if np.dtype(src.dtypes[0]).kind in "iu" and override is None and not _stated_unit(src):
        raise IngestError(
            f"{path.name} holds {src.dtypes[0]} values and states no height unit: an image "
            "rather than heights? If it holds heights, say their unit with --dsm-units m "
            "(or ft, us-ft)")


def _stated_unit(src: Any) -> bool:
    """The raster states its height unit (a known band unit, or a vertical CRS)."""
    unit = (src.units[0] or "").strip().lower() if src.units else ""
    if unit in HEIGHT_UNITS:
        return True
    crs = parse_crs(src.crs.to_wkt())
    return any(sub.is_vertical for sub in crs.sub_crs_list or [])


def height_unit_factor(src: Any, path: Path, override: str | None) -> tuple[float, str]:
    """(metres per stored unit, where that came from) for a height raster.

    Order: ``override`` (``--dsm-units``), the band's unit, the vertical axis of a
    compound CRS, else the horizontal CRS unit (heights of a feet-based CRS are
    usually feet, but not always: warned so the user can override).
    """
    if override is not None:
        key = override.strip().lower()
        if key not in HEIGHT_UNITS:
            raise IngestError(f"--dsm-units {override!r}: use one of {DSM_UNIT_CHOICES}")
        return _applied(HEIGHT_UNITS[key], f"--dsm-units {override}", path, warn=False)
    unit = (src.units[0] or "").strip().lower() if src.units else ""
    if unit:
        if unit in HEIGHT_UNITS:
            return _applied(HEIGHT_UNITS[unit], f"band unit {unit!r}", path)
        log.warning("%s: unknown band unit %r; reading heights by the CRS", path, unit)
    crs = parse_crs(src.crs.to_wkt())
    for sub in crs.sub_crs_list or []:
        if sub.is_vertical and sub.axis_info:
            factor = sub.axis_info[0].unit_conversion_factor
            if factor:
                return _applied(float(factor), f"vertical CRS {sub.name!r}", path)
    if crs.is_projected and crs.axis_info:
        factor = float(crs.axis_info[0].unit_conversion_factor or 1.0)
        if not math.isclose(factor, 1.0):
            warnings.warn(
                f"{path.name}: heights have no unit of their own; taking the CRS unit "
                f"({crs.axis_info[0].unit_name}, x{factor:g} to metres). If they are metres, "
                "pass --dsm-units m", GeonavWarning, stacklevel=4)
            return factor, f"horizontal CRS unit {crs.axis_info[0].unit_name!r}"
    return 1.0, "default (metres)"


def _applied(factor: float, why: str, path: Path, warn: bool = True) -> tuple[float, str]:
    if warn and not math.isclose(factor, 1.0):
        warnings.warn(f"{path.name}: heights are in {why}; multiplied by {factor:g} to metres",
                      GeonavWarning, stacklevel=5)
    return factor, why
