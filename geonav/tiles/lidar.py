"""A coloured LiDAR point cloud (LAS/LAZ) rasterised into the three rasters ingest reads.

``rasterise_point_cloud`` turns the points into, on one north-up grid in the cloud's own
CRS:

* an RGB orthophoto: the mean colour of the first returns in each cell (what a camera
  looking down sees first);
* a DSM: the highest return in each cell (the surface: roofs, stands, tree tops);
* a DEM: the lowest ground-classified return (ASPRS class 2) in each cell, interpolated
  under buildings and trees, where the laser did not reach the ground.

Cells without a return are filled from their neighbours (GDAL's inverse-distance fill,
``rasterio.fill.fillnodata``) up to ``fill_cells`` away; what stays empty is masked
(RGB) or NaN (DSM). Heights are written in metres (band unit ``m``): LAS stores them in
the CRS's linear unit, and the Oregon Lambert grid of the Autzen sample is in
international feet.

Reading LAZ needs laspy with its lazrs backend (``pip install 'geonav[lidar]'``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geonav.errors import IngestError

GROUND_CLASS = 2
"""ASPRS LAS classification code of ground points."""
MAX_CELLS = 25_000_000
"""The largest grid rasterised (about 1 GB of working arrays)."""


class LidarError(IngestError):
    """A point cloud cannot be read or rasterised (the message says why)."""


def require_laspy(laz: bool = True) -> Any:
    """laspy (with a LAZ backend when ``laz``), or a LidarError that says how to get it."""
    try:
        import laspy
    except ImportError as err:
        raise LidarError("reading LiDAR (LAS/LAZ) needs laspy and lazrs: pip install "
                         "'geonav[lidar]' (scripts/setup_env.sh installs them)") from err
    if laz and not laspy.LazBackend.detect_available():
        raise LidarError("laspy is installed but has no LAZ backend: pip install lazrs "
                         "(or 'geonav[lidar]')")
    return laspy


@dataclass(frozen=True)
class RasterisedCloud:
    """What :func:`rasterise_point_cloud` wrote, and how full the grid is."""

    rgb: Path
    dsm: Path
    dem: Path
    width: int
    height: int
    cell_m: float
    points: int
    filled_fraction: float
    """Cells with no return of their own, filled from neighbours (0..1)."""
    masked_fraction: float
    """Cells with no return within ``fill_cells``: masked (RGB) and NaN (DSM) (0..1)."""
    ground_m: tuple[float, float]
    """(min, max) of the DEM in metres."""
    top_above_ground_m: float
    """The highest surface above the ground under it (metres)."""


def rasterise_point_cloud(path: str | Path, rgb_out: str | Path, dsm_out: str | Path,
                          dem_out: str | Path, *, cell_m: float = 1.0,
                          fill_cells: int = 6) -> RasterisedCloud:
    """Rasterise a coloured LAS/LAZ file (see the module docstring).

    Args:
        path: the point cloud; it needs a CRS (GeoTIFF keys or WKT), RGB and a
            classification with ground points.
        rgb_out, dsm_out, dem_out: the GeoTIFFs to write (RGB uint8 with an internal mask;
            float32 metres, NaN where empty).
        cell_m: the grid's cell in metres (rounded to the CRS unit).
        fill_cells: how far (cells) an empty cell is filled from its neighbours; the DEM
            is filled everywhere (ground under a roof).
    """
    path = Path(path)
    laspy = require_laspy(laz=path.suffix.lower() == ".laz")
    if not math.isfinite(cell_m) or cell_m <= 0:
        raise LidarError(f"cell_m must be a positive number of metres, got {cell_m}")
    try:
        las = laspy.read(path)
    except (OSError, ValueError, laspy.errors.LaspyException) as err:
        raise LidarError(f"cannot read {path.name}: {err}") from err
    crs = las.header.parse_crs()
    if crs is None or not crs.is_projected:
        raise LidarError(f"{path.name} has no projected CRS (GeoTIFF keys or WKT); a grid in "
                         "metres or feet is needed")
    names = set(las.point_format.dimension_names)
    if not {"red", "green", "blue"} <= names:
        raise LidarError(f"{path.name} has no colour (point format {las.point_format.id}); an "
                         "orthophoto needs RGB points")
    unit_m = float(crs.axis_info[0].unit_conversion_factor or 1.0)
    x, y = np.asarray(las.x, np.float64), np.asarray(las.y, np.float64)
    z = np.asarray(las.z, np.float64) * unit_m
    cls = np.asarray(las.classification)
    first = np.asarray(las.return_number) <= 1
    if not (cls == GROUND_CLASS).any():
        raise LidarError(f"{path.name} has no ground-classified points (class 2): the DEM "
                         "cannot be made")
    cell = cell_m / unit_m
    x0, y1 = math.floor(x.min() / cell) * cell, math.ceil(y.max() / cell) * cell
    w = max(1, math.ceil((x.max() - x0) / cell))
    h = max(1, math.ceil((y1 - y.min()) / cell))
    if w * h > MAX_CELLS:
        raise LidarError(f"{path.name}: a {cell_m:g} m grid over its extent has {w} x {h} cells, "
                         f"more than the {MAX_CELLS:,} this rasteriser holds in memory; use a "
                         f"larger cell (--cell {cell_m * math.sqrt(w * h / MAX_CELLS):.2g}) or "
                         "crop the cloud first")
    col = np.minimum(((x - x0) / cell).astype(np.int64), w - 1)
    row = np.minimum(((y1 - y) / cell).astype(np.int64), h - 1)
    idx = row * w + col

    dsm = _reduce(idx, z, h * w, np.maximum, -np.inf)
    ground = cls == GROUND_CLASS
    dem = _reduce(idx[ground], z[ground], h * w, np.minimum, np.inf)
    colour = np.stack([np.asarray(getattr(las, c), np.float64) for c in ("red", "green",
                                                                          "blue")])
    if colour.max() > 255:  # 16-bit colour (the LAS standard's scale)
        colour /= 257.0
    counts = np.bincount(idx[first], minlength=h * w).astype(np.float64)
    rgb = np.stack([np.bincount(idx[first], c[first], minlength=h * w) for c in colour])
    rgb = np.divide(rgb, counts, out=np.zeros_like(rgb), where=counts > 0)
    has = counts > 0

    dsm_g, dsm_ok = _fill(dsm.reshape(h, w), np.isfinite(dsm).reshape(h, w), fill_cells)
    dem_g, _ = _fill(dem.reshape(h, w), np.isfinite(dem).reshape(h, w), max(h, w))
    rgb_g = np.empty((3, h, w), np.float32)
    rgb_ok = has.reshape(h, w)
    for b in range(3):  # the same cells reach a value in every band
        rgb_g[b], rgb_ok = _fill(rgb[b].reshape(h, w), has.reshape(h, w), fill_cells)
    dsm_g = np.where(dsm_ok, np.maximum(dsm_g, dem_g), np.nan).astype(np.float32)

    from rasterio.crs import CRS
    from rasterio.transform import from_origin

    meta = dict(driver="GTiff", width=w, height=h, crs=CRS.from_wkt(crs.to_wkt()),
                transform=from_origin(x0, y1, cell, cell), compress="DEFLATE", tiled=True,
                blockxsize=256, blockysize=256)
    _write_rgb(Path(rgb_out), rgb_g, rgb_ok, meta, path.name)
    for out, grid, what in ((dsm_out, dsm_g, "highest return"),
                            (dem_out, dem_g.astype(np.float32), "lowest ground return")):
        _write_heights(Path(out), grid, meta, f"{what} per cell of {path.name}")
    valid = dsm_ok & np.isfinite(dem_g)
    top = float(np.nanmax(np.where(valid, dsm_g - dem_g, np.nan))) if valid.any() else 0.0
    return RasterisedCloud(
        rgb=Path(rgb_out), dsm=Path(dsm_out), dem=Path(dem_out), width=w, height=h,
        cell_m=cell_m, points=int(len(x)),
        filled_fraction=float((dsm_ok & ~np.isfinite(dsm).reshape(h, w)).mean()),
        masked_fraction=float(1.0 - dsm_ok.mean()),
        ground_m=(float(np.nanmin(dem_g)), float(np.nanmax(dem_g))),
        top_above_ground_m=top)


def _reduce(idx: np.ndarray, values: np.ndarray, size: int, op: Any,
            empty: float) -> np.ndarray:
    """``op`` (np.maximum / np.minimum) of ``values`` per cell index; ``empty`` elsewhere."""
    out = np.full(size, empty, np.float64)
    op.at(out, idx, values)
    out[~np.isfinite(out)] = np.nan
    return out


def _fill(grid: np.ndarray, valid: np.ndarray, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """GDAL's inverse-distance fill of the invalid cells up to ``cells`` away; (grid, the
    cells that now hold a value)."""
    from rasterio.fill import fillnodata

    if valid.all():
        return grid.astype(np.float32), valid
    src = np.where(valid, grid, 0.0).astype(np.float32)
    mask = valid.astype(np.uint8)
    filled = fillnodata(src, mask=mask, max_search_distance=float(cells),
                        smoothing_iterations=0)
    reach = fillnodata(mask.astype(np.float32), mask=mask.copy(),
                       max_search_distance=float(cells), smoothing_iterations=0)
    ok = valid | (reach > 0.5)
    return filled, ok


def _write_rgb(out: Path, rgb: np.ndarray, valid: np.ndarray, meta: dict[str, Any],
               source: str) -> None:
    import rasterio
    from rasterio.enums import ColorInterp

    data = np.where(valid, np.clip(np.rint(rgb), 0, 255), 0).astype(np.uint8)
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), \
            rasterio.open(out, "w", count=3, dtype="uint8", **meta) as dst:
        dst.write(data)
        dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue]
        dst.write_mask(np.where(valid, 255, 0).astype(np.uint8))
        dst.update_tags(SOURCE=source, METHOD="mean colour of first returns per cell (geonav)")


def _write_heights(out: Path, grid: np.ndarray, meta: dict[str, Any], what: str) -> None:
    import rasterio

    with rasterio.open(out, "w", count=1, dtype="float32", nodata=float("nan"),
                       **meta) as dst:
        dst.write(grid, 1)
        dst.units = ("m",)
        dst.update_tags(METHOD=f"{what} (geonav)", UNITS="metre")


# -- command line: geonav tiles lidar --------------------------------------------------------
KIND = "rasterised point cloud"


def _not_ours(path: Path) -> str | None:
    """Why ``path`` is not a raster this module wrote (None when it is)."""
    import rasterio

    try:
        with rasterio.open(path) as src:
            method = src.tags().get("METHOD", "")
    except rasterio.errors.RasterioError:
        return "it is not a raster"
    return None if method.endswith("(geonav)") else "it is not a raster geonav rasterised"


def add_parser(tsub: Any) -> None:
    """Register ``lidar`` under ``geonav tiles``."""
    from geonav.cliutil import nonneg_int, positive_float

    p = tsub.add_parser(
        "lidar", help="rasterise a coloured LAS/LAZ point cloud into RGB, DSM and DEM GeoTIFFs",
        description="Rasterise a coloured LiDAR point cloud (LAS/LAZ with RGB, a CRS and "
        "ground-classified points) onto one north-up grid in its CRS: the mean colour of the "
        "first returns (an orthophoto), the highest return (DSM) and the lowest ground return "
        "(DEM, interpolated under cover), heights in metres. Then 'geonav tiles ingest "
        "OUT/NAME-rgb.tif --dsm OUT/NAME-dsm.tif --dem OUT/NAME-dem.tif' (printed). Needs "
        "'geonav[lidar]'.")
    p.add_argument("cloud", help="the .las or .laz file")
    p.add_argument("--out", required=True, help="folder for NAME-rgb.tif, NAME-dsm.tif and "
                   "NAME-dem.tif")
    p.add_argument("--name", help="file prefix (default: the cloud's file stem)")
    p.add_argument("--cell", type=positive_float, default=1.0,
                   help="grid cell in metres (default 1; about 1/sqrt(returns per m^2))")
    p.add_argument("--fill", type=nonneg_int, default=6,
                   help="cells an empty cell may be filled from (default 6); farther stays "
                   "masked")
    p.add_argument("--force", action="store_true",
                   help="replace rasters this command wrote before")
    p.set_defaults(handler=run)


def run(args: Any) -> int:
    """The ``lidar`` command: rasterise, then print the ingest command."""
    import contextlib
    import shlex

    from geonav.outputs import check_replaceable, output_lock

    cloud = Path(args.cloud)
    if not cloud.is_file():
        raise LidarError(f"{cloud} does not exist")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = args.name or cloud.stem
    paths = [out / f"{name}-{kind}.tif" for kind in ("rgb", "dsm", "dem")]
    with contextlib.ExitStack() as stack:
        for path in paths:
            stack.enter_context(output_lock(path, "--out"))
            check_replaceable(path, KIND, force=args.force, why_not=_not_ours, error=LidarError)
        res = rasterise_point_cloud(cloud, *paths, cell_m=args.cell, fill_cells=args.fill)
    print(f"{cloud.name}: {res.points:,} returns -> {res.width} x {res.height} cells of "
          f"{res.cell_m:g} m ({res.filled_fraction:.0%} filled from neighbours, "
          f"{res.masked_fraction:.0%} masked); ground "
          f"{res.ground_m[0]:.1f}-{res.ground_m[1]:.1f} m, surface up to "
          f"{res.top_above_ground_m:.1f} m above it")
    for path in paths:
        print(f"  {path}")
    q = [shlex.quote(str(p)) for p in paths]
    print(f"  next: geonav tiles ingest {q[0]} --dsm {q[1]} --dem {q[2]} --name "
          f"{shlex.quote(name)} --out scenes/{shlex.quote(name)} --attribution '...'")
    return 0
