"""A known lon/lat lands on the expected scene pixel for GeoTIFFs in EPSG:3857,
EPSG:4326 (authority lat/lon axis order), UTM and a US-feet state plane; the source
positions come from closed-form formulas or pyproj (cross-checked with GDAL's
``gdaltransform`` when installed). Also: missing CRS / geotransform, feet DSMs."""

from __future__ import annotations

import math
import shutil
import subprocess
import warnings

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS, Transformer

from geonav.errors import GeonavWarning, MissingCRS
from geonav.tiles.ingest import ingest

try:
    from test_tiles_support import expected_px, find_marker
except ImportError:  # tests/ imported as a package
    from tests.test_tiles_support import expected_px, find_marker

R = 6378137.0
SIZE, R0, C0 = 240, 113, 127  # raster side, marker pixel (row, col)
US_FT = 1200 / 3937


def _gdaltransform(epsg: int, lon: float, lat: float) -> tuple[float, float] | None:
    exe = shutil.which("gdaltransform")
    if exe is None:
        return None
    out = subprocess.run([exe, "-s_srs", "EPSG:4326", "-t_srs", f"EPSG:{epsg}",
                          "-output_xy"], input=f"{lon!r} {lat!r}\n", capture_output=True,
                         text=True, timeout=30, check=True).stdout.split()
    return float(out[0]), float(out[1])


def _position(epsg: int, lon: float, lat: float) -> tuple[float, float]:
    """The marker's coordinates in the source CRS, in the GeoTIFF's (x=east, y=north) order."""
    if epsg == 3857:  # spherical Mercator, closed form
        return R * math.radians(lon), R * math.log(math.tan(math.pi / 4 + math.radians(lat) / 2))
    if epsg == 4326:  # GeoTIFF geotransforms are lon (x), lat (y) whatever the axis order
        return lon, lat
    x, y = Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True).transform(lon, lat)
    gdal = _gdaltransform(epsg, lon, lat)
    if gdal is not None:
        assert gdal == pytest.approx((x, y), abs=1e-3), "pyproj and gdaltransform disagree"
    return x, y


def _pixel_size(epsg: int, lat: float, gsd_m: float) -> tuple[float, float]:
    if epsg == 3857:
        return gsd_m / math.cos(math.radians(lat)), gsd_m / math.cos(math.radians(lat))
    if epsg == 4326:
        return gsd_m / (111320.0 * math.cos(math.radians(lat))), gsd_m / 110574.0
    factor = CRS.from_epsg(epsg).axis_info[0].unit_conversion_factor
    return gsd_m / factor, gsd_m / factor


def _write_marker_tif(path, epsg, lon, lat, gsd_m=0.5, crs=True):
    x, y = _position(epsg, lon, lat)
    rx, ry = _pixel_size(epsg, lat, gsd_m)
    transform = Affine(rx, 0.0, x - (C0 + 0.5) * rx, 0.0, -ry, y + (R0 + 0.5) * ry)
    data = np.full((3, SIZE, SIZE), 50, np.uint8)
    data[1] += (np.arange(SIZE) % 7).astype(np.uint8)[None, :]
    data[:, R0 - 1:R0 + 2, C0 - 1:C0 + 2] = 255
    with rasterio.open(path, "w", driver="GTiff", width=SIZE, height=SIZE, count=3,
                       dtype="uint8", crs=f"EPSG:{epsg}" if crs else None,
                       transform=transform) as dst:
        dst.write(data)
    return path


@pytest.mark.parametrize("epsg,lon,lat", [
    (3857, 4.4777, 51.9244),     # Web-Mercator, Rotterdam
    (4326, 4.4777, 51.9244),     # geographic, authority axis order lat/lon
    (32631, 4.4777, 51.9244),    # UTM 31N
    (32616, -84.3963, 33.7756),  # UTM 16N, Atlanta
    (2263, -73.9654, 40.7829),   # NAD83 / New York Long Island (ftUS)
])
def test_known_lonlat_lands_on_expected_pixel(tmp_path, epsg, lon, lat):
    src = _write_marker_tif(tmp_path / f"m{epsg}.tif", epsg, lon, lat)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeonavWarning)
        scene = ingest([src], name="m", out=tmp_path / "scene", compress="DEFLATE")
    assert scene.gsd_m == pytest.approx(0.5, rel=0.02)  # feet and degrees became metres
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, lon, lat)
    assert abs(col - ecol) < 0.5 and abs(row - erow) < 0.5, (col, row, ecol, erow)


def test_4326_axis_order_is_respected():
    crs = CRS.from_epsg(4326)
    assert [a.abbrev for a in crs.axis_info] == ["Lat", "Lon"]
    # geonav's transformers are lon/lat whatever the authority order says
    from geonav.geo import LonLat, SceneFrame

    frame = SceneFrame(LonLat(4.4777, 51.9244))
    p = frame.from_lonlat(LonLat(4.4777 + 0.001, 51.9244))
    assert p.x_m == pytest.approx(68.8, abs=0.2) and abs(p.y_m) < 0.01


def test_missing_crs_and_transform(tmp_path):
    from geonav.cli import main

    no_crs = _write_marker_tif(tmp_path / "nocrs.tif", 32631, 4.4777, 51.9244, crs=False)
    with pytest.raises(MissingCRS, match="has no CRS"):
        ingest([no_crs], name="m", out=tmp_path / "s")
    plain = tmp_path / "plain.tif"
    with rasterio.open(plain, "w", driver="GTiff", width=8, height=8, count=3,
                       dtype="uint8") as dst:
        dst.write(np.zeros((3, 8, 8), np.uint8))
    with pytest.raises(MissingCRS):
        ingest([plain], name="m", out=tmp_path / "s")
    assert main(["tiles", "ingest", str(no_crs), "--name", "m", "--out",
                 str(tmp_path / "s")]) == 2
    assert not (tmp_path / "s").exists()


def test_feet_dsm_becomes_metres(tmp_path):
    lon, lat = -73.9654, 40.7829
    ortho = _write_marker_tif(tmp_path / "o.tif", 2263, lon, lat)
    with rasterio.open(ortho) as src:
        profile = src.profile | dict(count=1, dtype="float32", nodata=float("nan"))
    heights = np.full((1, SIZE, SIZE), 100.0, np.float32)  # ground at 100 ftUS
    heights[0, 50:90, 50:90] = 200.0  # a 100 ft building
    with rasterio.open(tmp_path / "dsm.tif", "w", **profile) as dst:
        dst.write(heights)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeonavWarning)
        scene = ingest([ortho], name="f", out=tmp_path / "s", dsm=tmp_path / "dsm.tif",
                       compress="DEFLATE")
    assert np.nanmax(scene.dsm) == pytest.approx(100 * US_FT, abs=0.01)
    assert scene.manifest["ground_alt_m"] == pytest.approx(100 * US_FT, abs=0.01)


def test_half_the_nominal_gsd_of_a_projected_source_is_accepted(tmp_path):
    """A 0.5 m UTM pixel is 0.5001 m on the ground here (UTM's scale factor is below 1 near
    the central meridian): --gsd 0.25 is 2x, not more, and was refused with "use >=
    0.250". A finer --gsd is refused with a value that then works."""
    from geonav.errors import IngestError

    src = _write_marker_tif(tmp_path / "utm.tif", 32631, 4.4777, 51.9244, gsd_m=0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeonavWarning)
        scene = ingest([src], name="u", out=tmp_path / "scene", compress="DEFLATE",
                       gsd_m=0.25)
        assert scene.gsd_m == 0.25
        with pytest.raises(IngestError, match=r"use --gsd 0\.2476 or more") as err:
            ingest([src], name="u", out=tmp_path / "fine", compress="DEFLATE", gsd_m=0.2)
        assert "native 0.5001 m/px" in str(err.value)  # more than 0.5: the scale factor
        scene = ingest([src], name="u", out=tmp_path / "ok", compress="DEFLATE", gsd_m=0.2476)
    assert scene.gsd_m == 0.2476
