"""XYZ tile folders (``{z}/{x}/{y}.{png,jpg,jpeg,webp}``) -> an EPSG:3857 mosaic.

Web-map tiles come in the XYZ ("Google", OSM slippy map) numbering, rows
counted from the north; TMS folders count rows from the south
(``y_tms = 2^z - 1 - y_xyz``). Tile bounds come from morecantile's
``WebMercatorQuad`` tile matrix set. The mosaic is one
:class:`~geonav.tiles.raster.RasterSource` in EPSG:3857 with a mask that is
False where a tile is missing, could not be decoded, or is transparent, so it
goes through :func:`geonav.tiles.ingest.ingest` like any GeoTIFF.

The tile decoding and mosaicking here is shared with
:mod:`geonav.tiles.mbtiles`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
import warnings
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geonav.errors import GeonavWarning, TileError
from geonav.tiles.raster import RasterSource, check_budget

log = logging.getLogger(__name__)

#: File name endings of image tiles, in the order a folder is searched.
TILE_EXTS = ("png", "jpg", "jpeg", "webp")
#: Deepest zoom level accepted (z24 is ~1 cm/px; anything beyond is not imagery).
MAX_ZOOM = 24
#: Sidecar JSON written by ``geonav tiles fetch`` into a tile cache (provenance, attribution).
SIDECAR = "geonav-tiles.json"
#: Largest mosaic (pixels) built in memory; beyond that, cut with a bbox.
MAX_MOSAIC_PX = 40_000 * 40_000
#: Equatorial Web-Mercator metres per pixel of a 256 px tile at zoom 0 (2*pi*6378137/256).
WEBMERC_RES0_M = 156543.03392804097

_INT = re.compile(r"^(0|[1-9][0-9]{0,8})$")
_TILE_NAME = re.compile(r"^(0|[1-9][0-9]{0,8})\.(png|jpg|jpeg|webp)$", re.IGNORECASE)

Progress = Callable[[str, float], None]


def web_mercator_tms():
    """morecantile's WebMercatorQuad tile matrix set (XYZ numbering, rows from the north)."""
    import morecantile

    return morecantile.tms.get("WebMercatorQuad")


def check_tile(z: int, x: int, y: int) -> tuple[int, int, int]:
    """Validate a tile index; returns plain ints. TileError if out of range."""
    if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (z, x, y)):
        raise TileError(f"tile index must be integers, got z={z!r} x={x!r} y={y!r}")
    z, x, y = int(z), int(x), int(y)
    if not 0 <= z <= MAX_ZOOM:
        raise TileError(f"zoom {z} is outside 0..{MAX_ZOOM}")
    n = 1 << z
    if not (0 <= x < n and 0 <= y < n):
        raise TileError(f"tile {z}/{x}/{y} is outside the 0..{n - 1} range of zoom {z}")
    return z, x, y


def flip_y(z: int, y: int) -> int:
    """XYZ row <-> TMS row (the same formula both ways)."""
    return (1 << z) - 1 - y


def ground_gsd_m(z: int, lat_deg: float, tile_px: int = 256) -> float:
    """Ground metres per pixel of a Web-Mercator tile at zoom ``z`` and latitude."""
    return WEBMERC_RES0_M * (256 / tile_px) * math.cos(math.radians(lat_deg)) / (1 << z)


# -- decoding --------------------------------------------------------------------------------

def sniff_format(data: bytes) -> str | None:
    """'png', 'jpg' or 'webp' from the magic bytes, else None."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    if data[:3] == b"\xff\xd8\xff":
        return "jpg"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    return None


def _complete(data: bytes, fmt: str) -> bool:
    # Truncation checks the decoders do not all make (libjpeg pads a cut-off JPEG
    # with grey and only warns).
    if fmt == "png":
        return data.rstrip(b"\0")[-8:] == b"IEND\xaeB`\x82"
    if fmt == "jpg":
        return data.rstrip(b"\0")[-2:] == b"\xff\xd9"
    if fmt == "webp":
        return len(data) >= 12 and int.from_bytes(data[4:8], "little") + 8 <= len(data)
    return False


def decode_tile(data: bytes) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode one tile image: (H, W, 3) uint8 RGB and an (H, W) bool alpha mask or None.

    Raises:
        ValueError: not a PNG/JPEG/WebP image, truncated, or undecodable.
    """
    import cv2

    fmt = sniff_format(data)
    if fmt is None:
        raise ValueError("not a PNG, JPEG or WebP image")
    label = {"png": "PNG", "jpg": "JPEG", "webp": "WebP"}[fmt]
    if not _complete(data, fmt):
        raise ValueError(f"truncated {label}")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ValueError(f"undecodable {label}")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ValueError(f"unsupported sample type {img.dtype}")
    alpha = None
    if img.ndim == 2:
        rgb = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 2:  # grey + alpha
        rgb, alpha = np.repeat(img[:, :, :1], 3, axis=2), img[:, :, 1] >= 128
    elif img.shape[2] == 3:
        rgb = img[:, :, ::-1]
    elif img.shape[2] == 4:
        rgb, alpha = img[:, :, 2::-1], img[:, :, 3] >= 128
    else:
        raise ValueError(f"unsupported channel count {img.shape[2]}")
    if alpha is not None and alpha.all():
        alpha = None
    return rgb, alpha


# -- mosaicking ------------------------------------------------------------------------------

@dataclass(frozen=True)
class TileRef:
    """One tile to place: XYZ index, a name for messages, and a reader of its bytes."""

    x: int
    y: int
    name: str
    read: Callable[[], bytes]


@dataclass
class MosaicStats:
    """What happened while building a mosaic (all counts are tiles)."""

    placed: int = 0
    corrupt: int = 0
    missing: int = 0
    outside: int = 0
    tile_px: int = 256
    corrupt_names: tuple[str, ...] = ()


def choose_zoom(zooms: Iterable[int], zoom: int | None, where: str) -> int:
    """The zoom to read: ``zoom`` if given (must exist), else the highest; warn if mixed."""
    levels = sorted(set(zooms))
    if not levels:
        raise TileError(f"{where} holds no image tiles")
    if zoom is not None:
        if zoom not in levels:
            raise TileError(f"{where} has no tiles at zoom {zoom}; it has zoom "
                            f"{', '.join(map(str, levels))}")
        chosen = zoom
    else:
        chosen = levels[-1]
    if len(levels) > 1:
        warnings.warn(
            f"{where} mixes zoom levels {', '.join(map(str, levels))}; using zoom {chosen} "
            f"({'requested' if zoom is not None else 'the highest; choose with --zoom'}), "
            "ignoring the others", GeonavWarning, stacklevel=3)
    return chosen


def tile_range_for_bbox(bbox_lonlat: Sequence[float], z: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) inclusive XYZ tile range covering a lon/lat bbox at zoom ``z``."""
    w, s, e, n = bbox_lonlat
    if not (w < e and s < n):
        raise TileError(f"bbox {tuple(bbox_lonlat)} must be west,south,east,north with w<e, s<n")
    tms = web_mercator_tms()
    lat_max = 85.0511287798066
    ul = tms.tile(max(w, -180.0), min(n, lat_max), z)
    # A hair inside the east/south edges so a bbox ending on a tile edge takes no extra tile.
    lr = tms.tile(min(e, 180.0) - 1e-9, max(s, -lat_max) + 1e-9, z)
    hi = (1 << z) - 1
    return (max(0, ul.x), max(0, ul.y), min(hi, lr.x), min(hi, lr.y))


def build_mosaic(
    z: int,
    refs: Sequence[TileRef],
    *,
    where: str,
    bbox_lonlat: Sequence[float] | None = None,
    progress: Progress | None = None,
    workers: int = 4,
    memory_budget_mb: float | None = None,
) -> tuple[np.ndarray, np.ndarray, Any, MosaicStats, str]:
    """Decode tiles at zoom ``z`` and paste them into one EPSG:3857 mosaic.

    Returns:
        (data (3, H, W) uint8, mask (H, W) bool, affine transform, stats, sha256 of
        the tiles placed (their indices and bytes)).

    Raises:
        TileError: no tiles, no decodable tile, or a bbox that misses every tile.
    """
    if not refs:
        raise TileError(f"{where} holds no image tiles at zoom {z}")
    stats = MosaicStats()
    if bbox_lonlat is not None:
        refs = _refs_in_bbox(refs, bbox_lonlat, z, where, stats)
    x0, x1 = min(r.x for r in refs), max(r.x for r in refs)
    y0, y1 = min(r.y for r in refs), max(r.y for r in refs)
    nx, ny = x1 - x0 + 1, y1 - y0 + 1

    data = mask = None
    tile_px = 0
    digests: list[tuple[int, int, str]] = []
    corrupt: list[str] = []
    done = 0
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:  # cv2 decodes without the GIL
        for ref, rgb, alpha, digest, error in pool.map(_load_tile, refs):
            done += 1
            if progress and (done % 32 == 0 or done == len(refs)):
                progress("tiles", done / len(refs))
            if error is None and data is None:
                tile_px = rgb.shape[0]
                if rgb.shape[1] != tile_px:
                    error = f"tile is not square ({rgb.shape[1]}x{rgb.shape[0]})"
                elif nx * ny * tile_px * tile_px > MAX_MOSAIC_PX:
                    raise TileError(
                        f"{where}: the zoom {z} tiles span {nx}x{ny} tiles "
                        f"({nx * tile_px}x{ny * tile_px} px); cut with --bbox")
                else:
                    # the mosaic, its mask, and the alpha copy the reprojection makes
                    check_budget(nx * ny * tile_px * tile_px * 9, memory_budget_mb,
                                 f"the {nx}x{ny} zoom-{z} tiles of {where}")
                    data = np.zeros((3, ny * tile_px, nx * tile_px), np.uint8)
                    mask = np.zeros((ny * tile_px, nx * tile_px), bool)
            if error is None and rgb.shape[:2] != (tile_px, tile_px):
                error = f"tile is {rgb.shape[1]}x{rgb.shape[0]} px, the others {tile_px} px"
            if error is not None:
                corrupt.append(f"{ref.name} ({error})")
                log.debug("skipping tile %s: %s", ref.name, error)
                continue
            r0, c0 = (ref.y - y0) * tile_px, (ref.x - x0) * tile_px
            data[:, r0:r0 + tile_px, c0:c0 + tile_px] = np.moveaxis(rgb, 2, 0)
            mask[r0:r0 + tile_px, c0:c0 + tile_px] = True if alpha is None else alpha
            digests.append((ref.x, ref.y, digest))
            stats.placed += 1
    stats.corrupt = len(corrupt)
    stats.tile_px = tile_px or 256
    stats.corrupt_names = tuple(corrupt[:5])
    stats.missing = nx * ny - len(refs)
    if data is None:
        raise TileError(f"none of the {len(refs)} zoom-{z} tiles of {where} could be decoded, "
                        f"e.g. {corrupt[0]}")
    if corrupt:
        warnings.warn(
            f"{where}: skipped {len(corrupt)} of {len(refs)} zoom-{z} tiles that could not be "
            f"decoded (masked as no data), e.g. {'; '.join(corrupt[:3])}",
            GeonavWarning, stacklevel=3)
    if stats.missing:
        log.info("%s: %d tiles missing inside the %dx%d tile rectangle (masked)", where,
                 stats.missing, nx, ny)
    return data, mask, _mosaic_transform(z, x0, y0, tile_px), stats, _mosaic_digest(z, digests)


def _refs_in_bbox(refs: Sequence[TileRef], bbox_lonlat: Sequence[float], z: int, where: str,
                  stats: MosaicStats) -> list[TileRef]:
    """The tiles inside a lon/lat bbox (those outside counted in ``stats.outside``);
    TileError when it misses them all."""
    bx0, by0, bx1, by1 = tile_range_for_bbox(bbox_lonlat, z)
    inside = [r for r in refs if bx0 <= r.x <= bx1 and by0 <= r.y <= by1]
    stats.outside = len(refs) - len(inside)
    if not inside:
        xs, ys = [r.x for r in refs], [r.y for r in refs]
        raise TileError(
            f"bbox {tuple(bbox_lonlat)} misses the tiles of {where}: zoom {z} has x "
            f"{min(xs)}..{max(xs)}, y {min(ys)}..{max(ys)}, the bbox needs x {bx0}..{bx1}, "
            f"y {by0}..{by1}")
    return inside


def _load_tile(ref: TileRef) -> tuple[TileRef, Any, Any, Any, str | None]:
    """(ref, rgb, alpha, sha256 of the bytes, None) of a decoded tile, or (ref, None, None,
    None, why) when it cannot be read or decoded."""
    try:
        raw = ref.read()
        rgb, alpha = decode_tile(raw)
        return ref, rgb, alpha, hashlib.sha256(raw).hexdigest(), None
    except (OSError, ValueError) as err:
        return ref, None, None, None, str(err)


def _mosaic_transform(z: int, x0: int, y0: int, tile_px: int) -> Any:
    """EPSG:3857 affine transform of a mosaic whose upper-left tile is (x0, y0) at zoom z."""
    from affine import Affine
    from morecantile import Tile

    ul = web_mercator_tms().xy_bounds(Tile(x0, y0, z))
    res = (ul.right - ul.left) / tile_px
    return Affine(res, 0.0, ul.left, 0.0, -res, ul.top)


def _mosaic_digest(z: int, digests: list[tuple[int, int, str]]) -> str:
    """sha256 over the placed tiles' indices and bytes (in index order)."""
    h = hashlib.sha256()
    for x, y, digest in sorted(digests):
        h.update(f"{z}/{x}/{y}:{digest}\n".encode())
    return h.hexdigest()


def mosaic_info(kind: str, where: Path, z: int, transform, shape: tuple[int, int],
                stats: MosaicStats, digest: str, scheme: str) -> dict[str, Any]:
    """The provenance a tile mosaic records in the manifest."""
    from rasterio.crs import CRS

    from geonav.geo import parse_crs

    tms = web_mercator_tms()
    h, w = shape
    cx, cy = transform.c + transform.a * w / 2, transform.f + transform.e * h / 2
    lon, lat = tms.lnglat(cx, cy)
    tile_px = stats.tile_px
    return dict(
        kind=kind, file=where.name, path=str(where.resolve()), sha256=digest,
        crs=parse_crs(CRS.from_epsg(3857).to_wkt()).to_wkt(), size_px=[w, h],
        zoom=z, scheme=scheme, tile_px=tile_px,
        est_native_gsd_m=round(ground_gsd_m(z, lat, tile_px), 4),
        tiles=stats.placed, tiles_corrupt=stats.corrupt, tiles_missing=stats.missing,
    )


# -- folders ---------------------------------------------------------------------------------

def scan_folder(folder: Path) -> dict[int, dict[tuple[int, int], Path]]:
    """Every image tile under ``folder`` as {z: {(x, y as stored): path}}.

    Only names made of decimal integers within the zoom's range are taken; any
    other file or folder is ignored (logged at debug level).
    """
    found: dict[int, dict[tuple[int, int], Path]] = {}
    for zdir in sorted(folder.iterdir()):
        if not (zdir.is_dir() and _INT.match(zdir.name)) or int(zdir.name) > MAX_ZOOM:
            continue
        z = int(zdir.name)
        n = 1 << z
        level: dict[tuple[int, int], Path] = {}
        for xdir in zdir.iterdir():
            if not (xdir.is_dir() and _INT.match(xdir.name)) or int(xdir.name) >= n:
                log.debug("ignoring %s", xdir)
                continue
            x = int(xdir.name)
            for entry in xdir.iterdir():
                m = _TILE_NAME.match(entry.name)
                if not m or int(m.group(1)) >= n or not entry.is_file():
                    log.debug("ignoring %s", entry)
                    continue
                key = (x, int(m.group(1)))
                prev = level.get(key)
                # Two formats of one tile: keep the one first in TILE_EXTS order.
                if prev is None or (TILE_EXTS.index(m.group(2).lower())
                                    < TILE_EXTS.index(prev.suffix[1:].lower())):
                    level[key] = entry
        if level:
            found[z] = level
    return found


def read_sidecar(folder: Path) -> dict[str, Any]:
    """The fetch sidecar of a tile cache ({} when there is none or it is unreadable)."""
    path = folder / SIDECAR
    if not path.is_file():
        return {}
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        warnings.warn(f"{path} is unreadable ({err}); attribution not taken from it",
                      GeonavWarning, stacklevel=3)
        return {}
    return meta if isinstance(meta, dict) else {}


def read_xyz(
    folder: str | os.PathLike[str],
    *,
    zoom: int | None = None,
    tms: bool = False,
    bbox_lonlat: Sequence[float] | None = None,
    progress: Progress | None = None,
    memory_budget_mb: float | None = None,
) -> RasterSource:
    """Read a ``{z}/{x}/{y}.{png,jpg,jpeg,webp}`` folder into an EPSG:3857 RasterSource.

    Args:
        folder: the tile folder (the one holding the zoom folders).
        zoom: the zoom level to read; default the highest present (with a warning
            when several are present).
        tms: rows are in TMS order (counted from the south) instead of XYZ.
        bbox_lonlat: read only the tiles meeting this (west, south, east, north).
        progress: callback (phase, fraction).
        memory_budget_mb: refuse mosaics above this many MiB (default 4096).

    Returns:
        A :class:`~geonav.tiles.raster.RasterSource` (3 bands uint8, mask False on
        missing, corrupt and transparent pixels); ``info`` has the zoom, scheme,
        tile counts, the estimated native GSD (``156543.03 * cos(lat) / 2^z`` for
        256 px tiles) and, for a ``geonav tiles fetch`` cache, the attribution.

    Raises:
        TileError: not a folder, no tiles, no tiles at ``zoom``, nothing decodable, or
            ``tms`` contradicting the bbox the cache was fetched for.
    """
    from rasterio.crs import CRS

    folder = Path(folder)
    if not folder.is_dir():
        raise TileError(f"{folder} is not a folder of {{z}}/{{x}}/{{y}} tiles")
    levels = scan_folder(folder)
    if not levels:
        raise TileError(f"{folder} holds no tiles laid out as {{z}}/{{x}}/{{y}}."
                        f"{{{','.join(TILE_EXTS)}}}; point at the folder holding the zoom "
                        "folders")
    z = choose_zoom(levels, zoom, str(folder))
    sidecar = read_sidecar(folder)
    fetched = _fetched_bboxes(sidecar, z)
    if tms and fetched:
        verdict = row_scheme_verdict(z, list(levels[z]), fetched, stored_as_tms=True)
        if verdict == "flipped":
            raise TileError(
                f"{folder}: with --tms the zoom-{z} tiles land outside the bbox "
                f"{fetched[0]} this cache was fetched for; its rows are XYZ, drop --tms")
    # The latitude the data states (an export's metadata.json) or the user's --bbox: rows
    # read in the wrong order put the scene in the other hemisphere, which both reveal.
    for what, box in [("the bounds in its metadata.json", b) for b in _metadata_bounds(folder)] \
            + ([("--bbox", tuple(bbox_lonlat))] if bbox_lonlat is not None else []):
        if row_scheme_verdict(z, list(levels[z]), [box], stored_as_tms=tms) == "flipped":
            raise TileError(
                f"{folder}: read as {'TMS (--tms)' if tms else 'XYZ'} rows, its zoom-{z} "
                f"tiles lie at latitudes away from {what} {_fmt_box(box)}, and read the other "
                f"way they meet it; {'drop --tms' if tms else 'pass --tms'}")
    refs = []
    for (x, y_stored), path in levels[z].items():
        y = flip_y(z, y_stored) if tms else y_stored
        refs.append(TileRef(x, y, f"{z}/{x}/{y_stored}{path.suffix}", path.read_bytes))
    data, mask, transform, stats, digest = build_mosaic(
        z, refs, where=str(folder), bbox_lonlat=bbox_lonlat, progress=progress,
        memory_budget_mb=memory_budget_mb)
    info = mosaic_info("xyz", folder, z, transform, mask.shape, stats, digest,
                       "tms" if tms else "xyz")
    for key in ("attribution", "url_template", "fetched_utc", "user_agent"):
        if sidecar.get(key):
            info[key] = sidecar[key]
    if tms and not fetched and not _metadata_bounds(folder) and bbox_lonlat is None:
        # nothing states where the data lies: the row order cannot be checked, so say where
        # --tms puts it (read the other way it lands in the other hemisphere)
        h, w = mask.shape
        lon, lat = web_mercator_tms().lnglat(transform.c + transform.a * w / 2,
                                             transform.f + transform.e * h / 2)
        other = _other_hemisphere_lat(z, list(levels[z]))
        warnings.warn(
            f"{folder}: --tms could not be checked (no fetch record, metadata.json bounds or "
            f"--bbox): read as TMS rows the scene is centred at {lat:.4f}, {lon:.4f} "
            f"(lat, lon); read as XYZ it would be at latitude {other:.4f}. If the first is "
            "wrong, drop --tms", GeonavWarning, stacklevel=2)
    return RasterSource(data, CRS.from_epsg(3857), transform, mask, info)


def _other_hemisphere_lat(z: int, tiles: list[tuple[int, int]]) -> float:
    """Centre latitude of ``tiles`` (stored (x, y) rows) read as XYZ rows."""
    ys = [y for _, y in tiles]
    y_mid = (min(ys) + max(ys) + 1) / 2  # rows counted from the north, fractional
    return float(math.degrees(math.atan(math.sinh(math.pi * (1 - 2 * y_mid / 2 ** z)))))



# -- row scheme checks -----------------------------------------------------------------------

def _metadata_bounds(folder: Path) -> list[tuple[float, float, float, float]]:
    """The 'bounds' of a tile export's ``metadata.json`` (mb-util, tippecanoe), if any."""
    path = folder / "metadata.json"
    try:
        meta = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        return []
    bounds = meta.get("bounds") if isinstance(meta, dict) else None
    if isinstance(bounds, list):
        bounds = ",".join(str(v) for v in bounds)
    box = parse_bounds(bounds) if isinstance(bounds, str) else None
    return [box] if box is not None else []


def _fmt_box(box: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:.4f}" for v in box) + ")"


def _fetched_bboxes(sidecar: dict[str, Any], z: int) -> list[tuple[float, ...]]:
    """The lon/lat bboxes a fetch cache was filled for at zoom ``z`` (from its sidecar)."""
    boxes = []
    for run in sidecar.get("runs", []) if isinstance(sidecar.get("runs"), list) else []:
        try:
            if int(run.get("zoom")) == z:
                box = tuple(float(v) for v in run["bbox_lonlat"])
                if len(box) == 4:
                    boxes.append(box)
        except (AttributeError, KeyError, TypeError, ValueError):
            continue
    return boxes


def parse_bounds(text: str) -> tuple[float, float, float, float] | None:
    """An MBTiles ``bounds`` value 'w,s,e,n' (None when unusable)."""
    try:
        w, s, e, n = (float(v) for v in str(text).split(","))
    except ValueError:
        return None
    if not all(map(math.isfinite, (w, s, e, n))) or not (w < e and s < n):
        return None
    return w, s, e, n


def row_scheme_verdict(z: int, stored: Sequence[tuple[int, int]],
                       bounds: Sequence[Sequence[float]], *, stored_as_tms: bool) -> str:
    """Whether stored (x, row) indices read in the stated scheme meet the stated bounds.

    Returns "ok" (they do, or the check cannot tell), or "flipped" (none meets the
    bounds as stated, but some do with the rows counted from the other side).
    """
    hits = {False: 0, True: 0}
    for box in bounds:
        try:
            x0, y0, x1, y1 = tile_range_for_bbox(box, z)
        except TileError:
            continue
        for x, row in stored:
            y_stated = flip_y(z, row) if stored_as_tms else row
            for flipped, y in ((False, y_stated), (True, flip_y(z, y_stated))):
                if x0 <= x <= x1 and y0 <= y <= y1:
                    hits[flipped] += 1
    return "flipped" if hits[False] == 0 and hits[True] > 0 else "ok"
