"""Correctness against an independent implementation: GDAL's own tools cut XYZ tiles
(``gdal2tiles --xyz``) and an MBTiles file (``gdal_translate -of MBTILES``) from a UTM
GeoTIFF; geonav ingests all three onto the same grid and they must agree (phase
correlation offset under half a pixel, small mean absolute difference), and a marker
at a known lon/lat must land on the expected scene pixel through each path.

gdal2tiles (GDAL 3.6) warps a non-Mercator source into a VRT on the source's own grid
and reads tile windows rounded to whole VRT pixels, which shifts its tiles by up to one
source pixel (measured here: 0.4-0.6 m at 0.5 m source pixels, while its tiles of the
same data pre-warped onto the zoom's pixel grid agree with the GeoTIFF to 0.01 px). So
the XYZ folder is cut from ``gdalwarp -t_srs EPSG:3857 -tr <z18 res> -tap`` output;
the MBTiles driver warps the UTM source itself.
"""

from __future__ import annotations

import shutil
import subprocess
import warnings

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import Transformer

from geonav.errors import GeonavWarning
from geonav.geo import LonLat
from geonav.tiles.ingest import ingest

try:
    from test_tiles_support import expected_px, find_marker
except ImportError:  # tests/ imported as a package
    from tests.test_tiles_support import expected_px, find_marker

pytestmark = pytest.mark.gdal

GDAL2TILES = shutil.which("gdal2tiles") or shutil.which("gdal2tiles.py")
GDAL_TRANSLATE = shutil.which("gdal_translate")
GDALWARP = shutil.which("gdalwarp")

LON0, LAT0 = 8.5, 47.4  # Zurich
N, RES = 1024, 0.5       # source: 512 m of UTM 32N at 0.5 m
ZOOM = 18                # 0.40 m/px here
MARKER_RC = (300, 700)   # source pixel of the 5x5 marker's centre


def _need_tools():
    missing = [name for name, exe in (("gdal2tiles", GDAL2TILES),
                                      ("gdal_translate", GDAL_TRANSLATE),
                                      ("gdalwarp", GDALWARP)) if exe is None]
    if missing:
        pytest.skip(f"GDAL command-line tools missing ({', '.join(missing)}); "
                    "install Debian's gdal-bin (apt-get install gdal-bin)")


def _run(args, cwd):
    proc = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"{' '.join(map(str, args))} failed: {proc.stderr[-2000:]}"


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    """(GeoTIFF, XYZ folder, MBTiles, marker lon/lat) made with GDAL's tools."""
    _need_tools()
    work = tmp_path_factory.mktemp("gdal")
    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True)
    x0, y0 = to_utm.transform(LON0, LAT0)
    transform = Affine(RES, 0.0, x0 - N * RES / 2, 0.0, -RES, y0 + N * RES / 2)
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.random((N, N)).astype(np.float32), (0, 0), 3)
    noise = (noise - noise.min()) / (noise.max() - noise.min())
    gx = np.arange(N, dtype=np.float32)[None, :]
    img = np.stack([noise * 190 + 20, (np.sin(gx / 13) * 0.5 + 0.5) * 100 + noise * 90,
                    np.roll(noise, 50, 0) * 200 + 10]).astype(np.uint8)
    r, c = MARKER_RC
    img[:, r - 2:r + 3, c - 2:c + 3] = 255
    tif = work / "src.tif"
    with rasterio.open(tif, "w", driver="GTiff", width=N, height=N, count=3, dtype="uint8",
                       crs="EPSG:32632", transform=transform) as dst:
        dst.write(img)
    mx, my = transform * (c + 0.5, r + 0.5)
    mlon, mlat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(mx, my)
    res = 2 * np.pi * 6378137.0 / 256 / 2 ** ZOOM  # the zoom's Web-Mercator pixel
    _run([GDALWARP, "-q", "-t_srs", "EPSG:3857", "-tr", repr(res), repr(res), "-tap",
          "-r", "average", "-dstalpha", str(tif), str(work / "src3857.tif")], work)
    _run([GDAL2TILES, "--xyz", "-z", str(ZOOM), "-r", "average", "--processes=1", "-w", "none",
          "-q", str(work / "src3857.tif"), str(work / "xyz")], work)
    _run([GDAL_TRANSLATE, "-q", "-of", "MBTILES", "-co", "TILE_FORMAT=PNG",
          "-co", "ZOOM_LEVEL_STRATEGY=UPPER", str(tif), str(work / "t.mbtiles")], work)
    return tif, work / "xyz", work / "t.mbtiles", (mlon, mlat)


@pytest.fixture(scope="module")
def scenes(sources, tmp_path_factory):
    tif, xyz, mbt, _ = sources
    out = tmp_path_factory.mktemp("scenes")
    bbox = (LON0 - 0.0025, LAT0 - 0.0017, LON0 + 0.0025, LAT0 + 0.0017)  # ~380 m square
    result = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeonavWarning)  # small, coarse test scenes
        for name, src in (("tif", tif), ("xyz", xyz), ("mbtiles", mbt)):
            result[name] = ingest([src], name=name, out=out / name, gsd_m=1.0,
                                  origin=LonLat(LON0, LAT0), bbox_lonlat=bbox,
                                  compress="DEFLATE")
    return result


def _grey(scene):
    g = scene.rgb.astype(np.float64).mean(axis=2)
    return g


def test_gdal_tiles_read_as_expected(scenes):
    for name in ("xyz", "mbtiles"):
        src = scenes[name].manifest["sources"][0]
        assert src["zoom"] == ZOOM and src["tiles"] > 20 and src["tiles_corrupt"] == 0
        assert src["scheme"] == ("xyz" if name == "xyz" else "tms")
    shapes = {(s.width, s.height, tuple(s.transform)[:6]) for s in scenes.values()}
    assert len(shapes) == 1, "all three paths must land on the same grid"


@pytest.mark.parametrize("name", ["xyz", "mbtiles"])
def test_gdal_tiles_agree_with_geotiff(scenes, name):
    ref, other = scenes["tif"], scenes[name]
    valid = ref.mask & other.mask
    assert valid.mean() > 0.98
    a, b = _grey(ref), _grey(other)
    window = cv2.createHanningWindow(a.shape[::-1], cv2.CV_64F)
    (dx, dy), response = cv2.phaseCorrelate(a, b, window)
    assert abs(dx) < 0.5 and abs(dy) < 0.5, f"{name} is offset by ({dx:.2f}, {dy:.2f}) px"
    assert response > 0.3
    mad = float(np.abs(ref.rgb.astype(np.int16) - other.rgb.astype(np.int16))[valid].mean())
    assert mad < 4.0, f"{name}: mean |diff| {mad:.2f} DN"


@pytest.mark.parametrize("name", ["tif", "xyz", "mbtiles"])
def test_known_lonlat_through_each_path(scenes, sources, name):
    lon, lat = sources[3]
    scene = scenes[name]
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, lon, lat)
    assert abs(col - ecol) < 0.5 and abs(row - erow) < 0.5, (name, col, row, ecol, erow)
