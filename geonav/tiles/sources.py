"""Every imagery source by its kind: the one module :mod:`geonav.tiles.ingest` reads through.

A folder of XYZ tiles (:mod:`geonav.tiles.xyz`), an MBTiles file
(:mod:`geonav.tiles.mbtiles`) or a GDAL raster (:mod:`geonav.tiles.raster`)
becomes one :class:`~geonav.tiles.raster.RasterSource`. The arrows run one way:
ingest -> sources -> {raster, xyz, mbtiles}; xyz and mbtiles -> raster.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from pathlib import Path

from geonav.tiles.mbtiles import read_mbtiles
from geonav.tiles.raster import RasterSource, open_raster
from geonav.tiles.xyz import read_xyz

log = logging.getLogger(__name__)

Progress = Callable[[str, float], None]

__all__ = ["RasterSource", "open_raster", "open_source"]


def open_source(
    path: str | os.PathLike[str],
    *,
    tms: bool = False,
    zoom: int | None = None,
    bbox_lonlat: tuple[float, float, float, float] | None = None,
    progress: Progress | None = None,
    rgb_bands: Sequence[int] | None = None,
    target_gsd_m: float | None = None,
    memory_budget_mb: float | None = None,
) -> RasterSource:
    """Open any imagery source by its kind: a folder of XYZ tiles, an MBTiles file,
    or a GDAL raster (GeoTIFF, COG, ...).

    Args:
        path: the folder or file.
        tms: a tile folder's rows are in TMS order (counted from the south).
        zoom: the zoom level of a tile folder or MBTiles (default: the highest).
        bbox_lonlat: read only the part meeting this bbox.
        progress: callback (phase, fraction).
        rgb_bands: 1-based bands of a GDAL raster to use as R,G,B (``--bands``).
        target_gsd_m: the scene GSD (a much finer GDAL raster is read decimated).
        memory_budget_mb: refuse reads above this many MiB.
    """
    path = Path(path)
    if path.is_dir():
        return read_xyz(path, zoom=zoom, tms=tms, bbox_lonlat=bbox_lonlat, progress=progress,
                        memory_budget_mb=memory_budget_mb)
    if path.suffix.lower() == ".mbtiles":
        if tms:
            log.info("--tms is ignored for %s: MBTiles says its own scheme", path)
        return read_mbtiles(path, zoom=zoom, bbox_lonlat=bbox_lonlat, progress=progress,
                            memory_budget_mb=memory_budget_mb)
    return open_raster(path, bands=3, rgb_bands=rgb_bands, bbox_lonlat=bbox_lonlat,
                       target_gsd_m=target_gsd_m, memory_budget_mb=memory_budget_mb)
