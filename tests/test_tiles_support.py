"""Helpers shared by the tests/test_tiles_*.py files (tile writers, marker finder, a local
tile server), and tests of the tile math they rely on.

The tile math here is written from the OSM wiki "Slippy map tilenames" and Bing's
"Tile System" pages on purpose, independent of morecantile, which geonav uses.
"""

from __future__ import annotations

import contextlib
import http.server
import math
import sqlite3
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from geonav.errors import TileError

TILE = 256
BG = 40  # background grey of synthetic tiles


# -- independent slippy-map math -------------------------------------------------------------

def lonlat_to_global_px(lon: float, lat: float, z: int) -> tuple[float, float]:
    """Global Web-Mercator pixel (x right, y down from the north edge) at zoom z."""
    n = (1 << z) * TILE
    lat_r = math.radians(lat)
    return (lon + 180.0) / 360.0 * n, (1.0 - math.asinh(math.tan(lat_r)) / math.pi) / 2.0 * n


def global_px_to_lonlat(px: float, py: float, z: int) -> tuple[float, float]:
    n = (1 << z) * TILE
    lon = px / n * 360.0 - 180.0
    lat = math.degrees(math.atan(math.sinh(math.pi * (1.0 - 2.0 * py / n))))
    return lon, lat


def bing_quadkey(x: int, y: int, z: int) -> str:
    key = ""
    for i in range(z, 0, -1):
        digit = 0
        if x & (1 << (i - 1)):
            digit += 1
        if y & (1 << (i - 1)):
            digit += 2
        key += str(digit)
    return key


# -- synthetic tiles -------------------------------------------------------------------------

def tile_image(x: int, y: int, z: int, marker_px: tuple[int, int] | None = None,
               texture: bool = False) -> np.ndarray:
    """A (256, 256, 3) RGB tile; a 3x3 white marker centred on global pixel ``marker_px``."""
    if texture:
        gy, gx = np.mgrid[0:TILE, 0:TILE].astype(np.float32)
        gx += x * TILE
        gy += y * TILE
        v = 100 + 60 * np.sin(gx / 7.0) * np.cos(gy / 11.0) + 40 * np.sin((gx + gy) / 23.0)
        img = np.repeat(v[:, :, None], 3, axis=2).clip(0, 255).astype(np.uint8)
    else:
        img = np.full((TILE, TILE, 3), BG, np.uint8)
        img[:, :, 1] = BG + (x % 5) * 3  # tiles differ a little
    if marker_px is not None:
        mx, my = marker_px[0] - x * TILE, marker_px[1] - y * TILE
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if 0 <= mx + dx < TILE and 0 <= my + dy < TILE:
                    img[my + dy, mx + dx] = 255
    return img


def encode(img_rgb: np.ndarray, fmt: str) -> bytes:
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if fmt in ("jpg", "jpeg") else []
    if fmt == "webp":
        params = [cv2.IMWRITE_WEBP_QUALITY, 101]  # lossless
    ok, buf = cv2.imencode(f".{fmt}", img_rgb[:, :, ::-1], params)
    assert ok
    return buf.tobytes()


def marker_setup(lon: float, lat: float, z: int, n: int = 3):
    """Snap (lon, lat) to a global pixel centre; return (lon, lat, marker_px, tiles)."""
    gx, gy = lonlat_to_global_px(lon, lat, z)
    px, py = int(gx), int(gy)
    # Keep the marker away from tile edges (its 3x3 blob stays inside one tile).
    px = px - px % TILE + TILE // 2 + 17
    py = py - py % TILE + TILE // 2 - 29
    mlon, mlat = global_px_to_lonlat(px + 0.5, py + 0.5, z)
    tx, ty = px // TILE, py // TILE
    tiles = [(x, y) for y in range(ty - n // 2, ty + n // 2 + 1)
             for x in range(tx - n // 2, tx + n // 2 + 1)]
    return mlon, mlat, (px, py), tiles


def write_xyz(folder: Path, z: int, tiles, marker_px=None, fmt: str = "png", tms: bool = False,
              texture: bool = False) -> Path:
    for x, y in tiles:
        row = (1 << z) - 1 - y if tms else y
        path = folder / str(z) / str(x) / f"{row}.{fmt}"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(encode(tile_image(x, y, z, marker_px, texture), fmt))
    return folder


def write_mbtiles(path: Path, z: int, tiles, marker_px=None, fmt: str = "png",
                  scheme: str | None = None, metadata: dict | None = None) -> Path:
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE metadata (name text, value text)")
    con.execute("CREATE TABLE tiles (zoom_level integer, tile_column integer, "
                "tile_row integer, tile_data blob)")
    meta = dict(name="test", format=fmt, **(metadata or {}))
    if scheme:
        meta["scheme"] = scheme
    con.executemany("INSERT INTO metadata VALUES (?, ?)", list(meta.items()))
    for x, y in tiles:
        row = y if scheme == "xyz" else (1 << z) - 1 - y
        con.execute("INSERT INTO tiles VALUES (?, ?, ?, ?)",
                    (z, x, row, encode(tile_image(x, y, z, marker_px), fmt)))
    con.commit()
    con.close()
    return path


def find_marker(rgb: np.ndarray, mask: np.ndarray | None = None) -> tuple[float, float]:
    """(col, row) of the bright marker's intensity centroid (pixel-index coordinates)."""
    grey = rgb.astype(np.float32).mean(axis=2)
    if mask is not None:
        grey[~mask] = 0
    r, c = np.unravel_index(np.argmax(grey), grey.shape)
    r0, c0 = max(0, r - 6), max(0, c - 6)
    win = grey[r0:r + 7, c0:c + 7]
    base = np.median(grey[max(0, r - 20):r + 21, max(0, c - 20):c + 21])
    w = np.clip(win - base, 0, None)
    w[w < 0.1 * w.max()] = 0
    ys, xs = np.mgrid[0:win.shape[0], 0:win.shape[1]]
    return float((w * xs).sum() / w.sum() + c0), float((w * ys).sum() / w.sum() + r0)


def expected_px(scene, lon: float, lat: float) -> tuple[float, float]:
    """Pixel-index (col, row) of a lon/lat in a scene (centre of pixel i is i)."""
    from geonav.geo import LonLat

    p = scene.frame.from_lonlat(LonLat(lon, lat))
    col, row = scene.to_pixel(p.x_m, p.y_m)
    return col - 0.5, row - 0.5


# -- a local tile server ---------------------------------------------------------------------

@contextlib.contextmanager
def tile_server(respond: Callable[[str, int], tuple[int, bytes, dict]],
                lifetime_s: float = 60.0) -> Iterator[tuple[str, list[str]]]:
    """Serve GET requests on 127.0.0.1 with ``respond(path, nth_request_for_path)``.

    ``respond`` returns (status, body, headers); a status of 0 means "hang": the
    handler sleeps without answering (until the client times out or the server
    stops). Yields (base URL, list of request paths with their User-Agent). The
    server stops when the block ends, or by itself after ``lifetime_s``.
    """
    counts: dict[str, int] = {}
    log: list[str] = []
    lock = threading.Lock()
    stopping = threading.Event()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - http.server API
            with lock:
                counts[self.path] = counts.get(self.path, 0) + 1
                nth = counts[self.path]
                log.append(f"{self.path} {self.headers.get('User-Agent', '')}")
            status, body, headers = respond(self.path, nth)
            if status == 0:
                stopping.wait(float(headers.get("hang_s", 10)))
                return
            try:
                self.send_response(status)
                for k, v in headers.items():
                    if k != "trickle_s":
                        self.send_header(k, v)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if "trickle_s" in headers:  # send half, then stall
                    self.wfile.write(body[:len(body) // 2])
                    self.wfile.flush()
                    stopping.wait(float(headers["trickle_s"]))
                    return
                self.wfile.write(body)
            except (BrokenPipeError, ConnectionResetError):
                pass

        def log_message(self, *args):  # keep test output clean
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, kwargs=dict(poll_interval=0.05),
                              daemon=True)
    thread.start()
    killer = threading.Timer(lifetime_s, server.shutdown)
    killer.daemon = True
    killer.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", log
    finally:
        stopping.set()
        killer.cancel()
        server.shutdown()
        server.server_close()
        thread.join(5)


# -- tests of the tile math ------------------------------------------------------------------

@pytest.mark.parametrize("lon,lat,z", [(4.4777, 51.9244, 18), (-84.3963, 33.7756, 17),
                                       (151.2093, -33.8688, 19), (0.0, 0.0, 3)])
def test_slippy_math_matches_morecantile(lon, lat, z):
    from morecantile import Tile

    from geonav.tiles.xyz import web_mercator_tms

    tms = web_mercator_tms()
    gx, gy = lonlat_to_global_px(lon, lat, z)
    tile = tms.tile(lon, lat, z)
    assert (tile.x, tile.y) == (int(gx // TILE), int(gy // TILE))
    b = tms.bounds(Tile(tile.x, tile.y, z))
    assert global_px_to_lonlat(tile.x * TILE, tile.y * TILE, z) == pytest.approx(
        (b.left, b.top), abs=1e-9)


def test_quadkey_and_url_template():
    from geonav.tiles.fetch import quadkey, tile_url
    from geonav.tiles.xyz import web_mercator_tms

    assert quadkey(3, 3, 5) == "213"  # Bing's documented example
    tms = web_mercator_tms()
    for z, x, y in [(18, 134332, 86679), (1, 0, 1), (12, 2101, 1361)]:
        assert quadkey(z, x, y) == bing_quadkey(x, y, z)
        from morecantile import Tile

        assert quadkey(z, x, y) == tms.quadkey(Tile(x, y, z))
    url = tile_url("https://{s}.t.example/{z}/{x}/{y}.png?tms={-y}&q={q}", 2, 1, 0, "ab")
    assert url == "https://b.t.example/2/1/0.png?tms=3&q=01"


def test_template_and_tile_validation():
    from geonav.tiles.fetch import check_template, redact, tile_path, tile_url

    for bad in ["ftp://x/{z}/{x}/{y}", "https://x/{z}/{x}.png", "https://x/{z}/{x}/{y}/{r}",
                "file:///etc/{z}/{x}/{y}"]:
        with pytest.raises(TileError):
            check_template(bad)
    assert redact("https://u:pw@t.example/{z}/{x}/{y}.png?key=SECRET&x={x}") == \
        "https://t.example/{z}/{x}/{y}.png?key=REDACTED&x={x}"
    for args in [(2, 4, 0), (2, 0, -1), (25, 0, 0), ("1", 0, 0), (1.0, 0, 0)]:
        with pytest.raises(TileError):
            tile_url("https://t/{z}/{x}/{y}", *args)
    with pytest.raises(TileError):
        tile_path(Path("/tmp"), 1, 0, 0, "png/../../x")
    assert tile_path(Path("c"), 3, 2, 1, "png") == Path("c/3/2/1.png")


def test_decode_rejects_truncated_and_foreign_data():
    from geonav.tiles.xyz import decode_tile

    img = tile_image(1, 1, 2, texture=True)
    for fmt in ("png", "jpg", "webp"):
        data = encode(img, fmt)
        rgb, alpha = decode_tile(data)
        assert rgb.shape == (256, 256, 3) and alpha is None
        for cut in (len(data) // 2, len(data) - 2):
            with pytest.raises(ValueError):
                decode_tile(data[:cut])
    with pytest.raises(ValueError, match="not a PNG"):
        decode_tile(b"<html>rate limited</html>")
    rgba = np.dstack([img, np.where(np.arange(256)[None, :] < 128, 255, 0).repeat(256, 0)])
    ok, buf = cv2.imencode(".png", rgba[:, :, [2, 1, 0, 3]].astype(np.uint8))
    rgb, alpha = decode_tile(buf.tobytes())
    assert alpha is not None and alpha[:, :128].all() and not alpha[:, 128:].any()
