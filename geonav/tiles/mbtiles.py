"""MBTiles (SQLite) raster tilesets -> an EPSG:3857 mosaic RasterSource.

MBTiles 1.3 stores ``tiles(zoom_level, tile_column, tile_row, tile_data)`` with
``tile_row`` in TMS order, counted from the south (``2^z - 1 - y_xyz``); some
producers write a non-standard ``metadata`` row ``scheme=xyz``, which is
honoured. Tiles may be PNG, JPEG or WebP; vector tilesets (pbf/mvt) are
refused. Decoding and mosaicking are shared with :mod:`geonav.tiles.xyz`.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from geonav.errors import GeonavWarning, TileError
from geonav.scene import sha256_file
from geonav.tiles.raster import RasterSource
from geonav.tiles.xyz import (
    MAX_ZOOM,
    Progress,
    TileRef,
    build_mosaic,
    choose_zoom,
    flip_y,
    mosaic_info,
    parse_bounds,
    row_scheme_verdict,
)

log = logging.getLogger(__name__)

_VECTOR_FORMATS = {"pbf", "mvt", "application/x-protobuf", "application/vnd.mapbox-vector-tile"}


def _connect(path: Path) -> sqlite3.Connection:
    try:
        con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True,
                              check_same_thread=False)
        con.execute("SELECT 1 FROM sqlite_master LIMIT 1").fetchall()
        return con
    except sqlite3.DatabaseError as err:
        raise TileError(f"{path} is not an MBTiles (SQLite) file: {err}") from err


def read_metadata(con: sqlite3.Connection, path: Path) -> dict[str, str]:
    """The ``metadata`` table as a dict (empty when the table is missing)."""
    try:
        rows = con.execute("SELECT name, value FROM metadata").fetchall()
    except sqlite3.DatabaseError:
        log.info("%s has no metadata table", path)
        return {}
    return {str(k): str(v) for k, v in rows if k is not None and v is not None}


def read_mbtiles(
    path: str | os.PathLike[str],
    *,
    zoom: int | None = None,
    bbox_lonlat: Sequence[float] | None = None,
    progress: Progress | None = None,
    memory_budget_mb: float | None = None,
) -> RasterSource:
    """Read one zoom level of an MBTiles file into an EPSG:3857 RasterSource.

    Args:
        path: the ``.mbtiles`` file.
        zoom: the zoom level; default the highest present (warning when several).
        bbox_lonlat: read only the tiles meeting this (west, south, east, north).
        progress: callback (phase, fraction).
        memory_budget_mb: refuse mosaics above this many MiB (default 4096).

    Returns:
        A :class:`~geonav.tiles.raster.RasterSource`; ``info`` has the zoom, scheme,
        tile counts, estimated native GSD and the tileset's name/attribution metadata.

    Raises:
        TileError: not SQLite, no ``tiles`` table, vector tiles, no tiles at ``zoom``,
            nothing decodable, or a bbox that misses.
    """
    from rasterio.crs import CRS

    path = Path(path)
    if not path.is_file():
        raise TileError(f"{path} does not exist")
    con = _connect(path)
    try:
        meta = read_metadata(con, path)
        fmt = meta.get("format", "").lower()
        if fmt in _VECTOR_FORMATS:
            raise TileError(f"{path} holds vector tiles ({fmt}); geonav needs raster imagery")
        scheme = meta.get("scheme", "tms").strip().lower()
        if scheme not in ("tms", "xyz"):
            raise TileError(f"{path}: metadata scheme {scheme!r} is neither 'tms' nor 'xyz'")
        z = choose_zoom(_zoom_levels(con, path), zoom, str(path))
        n = 1 << z
        rows = con.execute(
            "SELECT tile_column, tile_row FROM tiles WHERE zoom_level = ?", (z,)).fetchall()
        bounds = parse_bounds(meta["bounds"]) if meta.get("bounds") else None
        if bounds is not None:
            good = [(c, r) for c, r in rows if isinstance(c, int) and isinstance(r, int)
                    and 0 <= c < n and 0 <= r < n]
            if row_scheme_verdict(z, good, [bounds],
                                  stored_as_tms=scheme == "tms") == "flipped":
                other = "xyz" if scheme == "tms" else "tms"
                warnings.warn(
                    f"{path}: read as {scheme.upper()} rows (metadata scheme "
                    f"{meta.get('scheme', 'missing, so TMS')!s}) the zoom-{z} tiles miss the "
                    f"file's own bounds {bounds}; read as {other.upper()} they meet them, "
                    f"so reading them as {other.upper()}. Fix the file with a metadata row "
                    f"scheme={other}", GeonavWarning, stacklevel=2)
                scheme = other
        refs = _tile_refs(con, path, z, rows, scheme)
        # sqlite3 connections serialise their calls; one decoding thread is enough
        # to overlap reads with decoding.
        data, mask, transform, stats, digest = build_mosaic(
            z, refs, where=str(path), bbox_lonlat=bbox_lonlat, progress=progress, workers=2,
            memory_budget_mb=memory_budget_mb)
    finally:
        con.close()
    info: dict[str, Any] = mosaic_info("mbtiles", path, z, transform, mask.shape, stats,
                                       digest, scheme)
    info["tiles_sha256"], info["sha256"] = digest, sha256_file(path)
    for key in ("name", "attribution", "description", "version"):
        if meta.get(key):
            info[f"mbtiles_{key}" if key != "attribution" else key] = meta[key]
    return RasterSource(data, CRS.from_epsg(3857), transform, mask, info)


def _zoom_levels(con: sqlite3.Connection, path: Path) -> list[int]:
    """The zoom levels (0..MAX_ZOOM) the file's ``tiles`` table holds; TileError when it has
    none or no readable table."""
    try:
        zooms = [int(r[0]) for r in con.execute(
            "SELECT DISTINCT zoom_level FROM tiles WHERE zoom_level BETWEEN 0 AND ?",
            (MAX_ZOOM,))]
    except sqlite3.DatabaseError as err:
        raise TileError(f"{path} has no readable 'tiles' table ({err}); is it an "
                        "MBTiles file?") from err
    if not zooms:
        raise TileError(f"{path} holds no tiles")
    return zooms


def _tile_refs(con: sqlite3.Connection, path: Path, z: int, rows: list[Any],
               scheme: str) -> list[TileRef]:
    """A lazy reader per (column, row) of zoom ``z``, rows turned to XYZ from ``scheme``;
    indices that are not integers inside the zoom's range are left out (and logged)."""
    n = 1 << z
    refs = []
    skipped = 0
    for col, row in rows:
        # Only integer indices inside the zoom's range make it into a mosaic.
        if not (isinstance(col, int) and isinstance(row, int) and 0 <= col < n
                and 0 <= row < n):
            skipped += 1
            continue
        y = flip_y(z, row) if scheme == "tms" else row

        def read(col: int = col, row: int = row) -> bytes:
            got = con.execute(
                "SELECT tile_data FROM tiles WHERE zoom_level = ? AND tile_column = ? "
                "AND tile_row = ?", (z, col, row)).fetchone()
            if got is None or not isinstance(got[0], (bytes, memoryview)):
                raise ValueError("no tile data")
            return bytes(got[0])

        refs.append(TileRef(col, y, f"z{z} column {col} row {row}", read))
    if skipped:
        log.warning("%s: ignored %d tiles with indices outside zoom %d", path, skipped, z)
    return refs
