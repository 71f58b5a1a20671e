"""Malformed and tricky inputs, built in fixtures (issue 13).

Each case asserts what a user gets: the correct result (rotated transforms,
nodata, units, band order, row schemes), or one error line with exit code 2 and
nothing left behind (bad CLI values, corrupt scene.json and task JSON fields,
unwritable outputs, a tile server that truncates, trickles, lies about
Content-Length or answers junk).
"""

from __future__ import annotations

import http.server
import json
import shutil
import socket
import sqlite3
import subprocess
import sys
import threading
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from affine import Affine

from geonav.cli import main
from geonav.errors import (
    GeonavWarning,
    IngestError,
    MissingCRS,
    SceneError,
    TaskError,
    TileError,
)
from geonav.geo import LonLat
from geonav.scene import Scene
from geonav.tiles.fetch import FetchIncomplete, fetch_tiles, tiles_in_bbox
from geonav.tiles.ingest import ingest
from geonav.tiles.mbtiles import read_mbtiles
from geonav.tiles.xyz import SIDECAR, decode_tile, read_xyz

try:
    from test_tiles_support import (
        encode,
        expected_px,
        find_marker,
        global_px_to_lonlat,
        marker_setup,
        tile_image,
        write_mbtiles,
        write_xyz,
    )
except ImportError:  # tests/ imported as a package
    from tests.test_tiles_support import (
        encode,
        expected_px,
        find_marker,
        global_px_to_lonlat,
        marker_setup,
        tile_image,
        write_mbtiles,
        write_xyz,
    )

rasterio = pytest.importorskip("rasterio")

from raster_helpers import UTM31, X0, Y0, make_utm_tif, texture, write_raster  # noqa: E402

OREGON_FT = "EPSG:2992"  # NAD83 / Oregon GIC Lambert (ft), the Autzen LiDAR's CRS


_write = write_raster


def _quiet_ingest(*args, **kw) -> Scene:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeonavWarning)
        return ingest(*args, compress="DEFLATE", **kw)


_texture = texture


@pytest.fixture(scope="module")
def utm_tif(tmp_path_factory) -> Path:
    return make_utm_tif(tmp_path_factory)


def _cli(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exit_:  # argparse refuses a value: exit 2 after one line
        rc = exit_.code
    out, err = capsys.readouterr()
    return rc, out, err


def _one_line_error(rc: int, err: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("warning: ")]
    assert rc == 2, err
    assert len(lines) == 1 and "error" in lines[0], err
    assert "Traceback" not in err


# -- silent wrong results, now right --------------------------------------------------------

def test_rotated_geotransform_keeps_whole_footprint_and_registration(tmp_path):
    """A 30-degree rotated GeoTIFF: the scene covers the whole rotated footprint and a
    marker lands on its own coordinates (the bounds used to ignore the rotation)."""
    from pyproj import Transformer

    w, h = 120, 80
    img = np.full((3, h, w), 90, np.uint8)
    img[:, 19:22, 89:92] = 255  # marker centred on pixel (90, 20)
    t = Affine.translation(X0, Y0) * Affine.rotation(30) * Affine.scale(1, -1)
    path = _write(tmp_path / "rot.tif", img, UTM31, t)
    scene = _quiet_ingest([path], name="R", out=tmp_path / "s")
    assert scene.gsd_m == pytest.approx(1.0, rel=0.01)
    # rotated 120 x 80 m box: about 144 x 129 m axis-aligned
    assert scene.size_m[0] == pytest.approx(120 * np.cos(np.pi / 6) + 80 * 0.5, abs=4)
    assert scene.size_m[1] == pytest.approx(120 * 0.5 + 80 * np.cos(np.pi / 6), abs=4)
    assert scene.mask.mean() == pytest.approx(120 * 80 / (scene.size_m[0] * scene.size_m[1]),
                                              abs=0.05)
    mx, my = t * (90.5, 20.5)
    lon, lat = Transformer.from_crs(UTM31, "EPSG:4326", always_xy=True).transform(mx, my)
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, lon, lat)
    assert abs(col - ecol) < 0.75 and abs(row - erow) < 0.75, (col, row, ecol, erow)


def test_float_imagery_with_nodata_is_stretched_from_valid_pixels(tmp_path):
    data = np.full((3, 100, 100), -9999.0, np.float32)
    data[:, :, 50:] = np.linspace(100.0, 200.0, 50, dtype=np.float32)[None, None, :]
    path = _write(tmp_path / "f.tif", data, UTM31, Affine(1, 0, X0, 0, -1, Y0),
                  nodata=-9999.0)
    with pytest.warns(GeonavWarning, match=r"stretched 100\.\.200 \(valid pixels\)"):
        scene = ingest([path], name="F", out=tmp_path / "s", compress="DEFLATE")
    valid = scene.rgb[scene.mask]
    assert 0.4 < scene.mask.mean() < 0.6
    assert valid.std() > 40 and 60 < valid.mean() < 200  # a gradient, not all white


def _oregon(tmp_path: Path, *, unit: str | None):
    """Ortho and a DSM (metres: ground 124.5, a 30 m building) in a feet CRS."""
    from pyproj import Transformer

    x, y = Transformer.from_crs("EPSG:4326", OREGON_FT, always_xy=True).transform(-123.07,
                                                                                  44.05)
    ft = 1 / 0.3048  # 1 m pixels
    t = Affine(ft, 0, x, 0, -ft, y)
    ortho = _write(tmp_path / "o.tif", _texture(120, 120), OREGON_FT, t)
    dsm = np.full((120, 120), 124.5, np.float32)
    dsm[50:70, 50:70] += 30.0
    path = _write(tmp_path / "dsm.tif", dsm, OREGON_FT, t, nodata=float("nan"))
    if unit:
        with rasterio.open(path, "r+") as d:
            d.units = (unit,)
    return ortho, path


def test_dsm_in_metres_under_a_feet_crs_is_not_scaled(tmp_path):
    ortho, dsm = _oregon(tmp_path, unit="metre")
    scene = _quiet_ingest([ortho], name="O", out=tmp_path / "s", dsm=dsm, ground_alt_m=124.5)
    assert np.nanmax(scene.dsm) == pytest.approx(30.0, abs=0.5)
    assert scene.manifest["dsm_source"]["height_unit_from"] == "band unit 'metre'"


def test_dsm_without_unit_under_feet_crs_warns_refuses_and_can_be_overridden(tmp_path):
    ortho, dsm = _oregon(tmp_path, unit=None)
    # taken as feet (x0.3048): the surface then lies below the stated ground
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(IngestError, match="below the ground.*--dsm-units"):
            ingest([ortho], name="O", out=tmp_path / "s", dsm=dsm, ground_alt_m=124.5)
    assert any("pass --dsm-units m" in str(w.message) for w in caught)
    assert not (tmp_path / "s").exists()
    scene = _quiet_ingest([ortho], name="O", out=tmp_path / "s", dsm=dsm, ground_alt_m=124.5,
                          dsm_units="m")
    assert np.nanmax(scene.dsm) == pytest.approx(30.0, abs=0.5)


def test_dsm_below_dem_and_far_origin_and_nan_ground_are_refused(tmp_path, utm_tif):
    t = Affine(1, 0, X0, 0, -1, Y0)
    dsm = _write(tmp_path / "dsm.tif", np.full((160, 160), 20.0, np.float32), UTM31, t)
    dem = _write(tmp_path / "dem.tif", np.full((160, 160), 50.0, np.float32), UTM31, t)
    with pytest.raises(IngestError, match="below the ground on 100%"):
        _quiet_ingest([utm_tif], name="D", out=tmp_path / "s", dsm=dsm, dem=dem)
    with pytest.raises(IngestError, match=r"km from the data"):
        _quiet_ingest([utm_tif], name="D", out=tmp_path / "s",
                      origin=LonLat(4.4 + 12.0, 51.9, 0.0))
    with pytest.raises(IngestError, match="finite"):
        _quiet_ingest([utm_tif], name="D", out=tmp_path / "s", ground_alt_m=float("nan"))
    assert not (tmp_path / "s").exists()


def test_mbtiles_xyz_rows_without_scheme_follow_their_bounds(tmp_path):
    lon, lat, mpx, tiles = marker_setup(4.4777, 51.9244, 18)
    path = write_mbtiles(tmp_path / "x.mbtiles", 18, tiles, mpx, scheme="xyz",
                         metadata=dict(bounds=f"{lon - 0.002},{lat - 0.002},{lon + 0.002},"
                                       f"{lat + 0.002}"))
    con = sqlite3.connect(path)
    con.execute("DELETE FROM metadata WHERE name = 'scheme'")
    con.commit()
    con.close()
    with pytest.warns(GeonavWarning, match="miss the file's own bounds.*reading them as XYZ"):
        src = read_mbtiles(path)
    assert src.info["scheme"] == "xyz"
    scene = _quiet_ingest([path], name="M", out=tmp_path / "s")
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, lon, lat)
    assert abs(col - ecol) < 0.5 and abs(row - erow) < 0.5


def test_tms_flag_contradicting_a_fetch_cache_is_refused(tmp_path):
    lon, lat, mpx, tiles = marker_setup(4.4777, 51.9244, 18)
    folder = write_xyz(tmp_path / "cache", 18, tiles, mpx)
    (folder / SIDECAR).write_text(json.dumps({"runs": [{"zoom": 18, "bbox_lonlat": [
        lon - 0.001, lat - 0.001, lon + 0.001, lat + 0.001]}]}))
    with pytest.raises(TileError, match="drop --tms"):
        read_xyz(folder, tms=True)
    assert read_xyz(folder).info["scheme"] == "xyz"


def test_band_order_colour_interpretation_and_bands_option(tmp_path):
    from rasterio.enums import ColorInterp

    t = Affine(1, 0, X0, 0, -1, Y0)
    bgr = np.stack([np.full((64, 64), v, np.uint8) for v in (30, 120, 210)])  # B, G, R
    path = _write(tmp_path / "bgr.tif", bgr, UTM31, t)
    with rasterio.open(path, "r+") as d:
        d.colorinterp = [ColorInterp.blue, ColorInterp.green, ColorInterp.red]
    scene = _quiet_ingest([path], name="B", out=tmp_path / "b")
    assert tuple(int(v) for v in np.median(scene.rgb[scene.mask], axis=0)) == (210, 120, 30)
    seven = np.stack([np.full((64, 64), 10 * k, np.uint8) for k in range(1, 8)])
    path7 = _write(tmp_path / "l8.tif", seven, UTM31, t)
    with pytest.warns(GeonavWarning, match="--bands 4,3,2"):
        ingest([path7], name="L", out=tmp_path / "l1", compress="DEFLATE")
    scene = _quiet_ingest([path7], name="L", out=tmp_path / "l2", rgb_bands=(4, 3, 2))
    assert tuple(int(v) for v in np.median(scene.rgb[scene.mask], axis=0)) == (40, 30, 20)
    with pytest.raises(IngestError, match="has bands 1..7"):
        _quiet_ingest([path7], name="L", out=tmp_path / "l3", rgb_bands=(9, 1, 2))


def test_grey_and_paletted_images_are_expanded_with_a_warning(tmp_path):
    t = Affine(1, 0, X0, 0, -1, Y0)
    grey = _write(tmp_path / "g.tif", np.full((64, 64), 77, np.uint8), UTM31, t)
    with pytest.warns(GeonavWarning, match="grey band"):
        scene = ingest([grey], name="G", out=tmp_path / "g", compress="DEFLATE")
    assert (np.median(scene.rgb[scene.mask], axis=0) == 77).all()
    idx = np.zeros((64, 64), np.uint8)
    idx[:, 32:] = 1
    pal = _write(tmp_path / "p.tif", idx, UTM31, t)
    with rasterio.open(pal, "r+") as d:
        d.write_colormap(1, {0: (255, 0, 0, 255), 1: (0, 0, 255, 255)})
    with pytest.warns(GeonavWarning, match="paletted"):
        scene = ingest([pal], name="P", out=tmp_path / "p", compress="DEFLATE")
    west, east = scene.rgb[32, 5], scene.rgb[32, -6]
    assert west[0] > 200 and west[2] < 50 and east[2] > 200 and east[0] < 50


def test_gcp_file_is_told_to_warp_not_to_assign_a_crs(tmp_path):
    from rasterio.control import GroundControlPoint

    path = tmp_path / "gcp.tif"
    with rasterio.open(path, "w", driver="GTiff", width=32, height=32, count=3,
                       dtype="uint8") as dst:
        dst.write(_texture(32, 32))
        dst.gcps = ([GroundControlPoint(0, 0, X0, Y0), GroundControlPoint(32, 0, X0 + 32, Y0),
                     GroundControlPoint(0, 32, X0, Y0 - 32)], rasterio.crs.CRS.from_string(UTM31))
    with pytest.raises(MissingCRS, match="ground control points.*gdalwarp"):
        ingest([path], name="G", out=tmp_path / "s")


def test_huge_declared_raster_is_refused_whole_and_read_by_window(tmp_path):
    """200,000^2 px declared (sparse, tiny on disk): no MemoryError; a bbox reads a window."""
    from pyproj import Transformer

    path = tmp_path / "huge.tif"
    with rasterio.open(path, "w", driver="GTiff", width=200_000, height=200_000, count=3,
                       dtype="uint8", crs=UTM31, transform=Affine(1, 0, X0, 0, -1, Y0),
                       tiled=True, blockxsize=1024, blockysize=1024, BIGTIFF="YES",
                       SPARSE_OK="TRUE", compress="DEFLATE"):
        pass
    assert path.stat().st_size < 4 << 20
    with pytest.raises(IngestError, match="memory budget"):
        ingest([path], name="H", out=tmp_path / "s")
    lon, lat = Transformer.from_crs(UTM31, "EPSG:4326", always_xy=True).transform(
        X0 + 50_000, Y0 - 50_000)
    scene = _quiet_ingest([path], name="H", out=tmp_path / "s",
                          bbox_lonlat=(lon, lat, lon + 0.003, lat + 0.002))
    assert scene.width < 400 and scene.height < 400
    window = scene.manifest["sources"][0]["read_window_px"]
    assert window[2] * window[3] < 400 * 400


def test_scene_crossing_the_antimeridian_records_west_greater_than_east(tmp_path):
    data = _texture(100, 100)
    path = _write(tmp_path / "am.tif", data, "EPSG:4326",
                  Affine(2e-5, 0, 179.999, 0, -2e-5, -17.0))
    scene = _quiet_ingest([path], name="AM", out=tmp_path / "s")
    west, south, east, north = scene.manifest["bounds_wgs84"]
    assert west > 179.99 and east < -179.99 and south < north


# -- Scene.open cross-checks ----------------------------------------------------------------

@pytest.fixture(scope="module")
def package(tmp_path_factory, utm_tif) -> Path:
    d = tmp_path_factory.mktemp("pkg")
    dsm = _write(d / "dsm.tif", np.full((160, 160), 12.0, np.float32), UTM31,
                 Affine(1, 0, X0, 0, -1, Y0))
    _quiet_ingest([utm_tif], name="P", out=d / "P", dsm=dsm, ground_alt_m=2.0)
    return d / "P"


def _tampered(package: Path, tmp_path: Path, edit) -> Path:
    out = tmp_path / "T"
    shutil.copytree(package, out)
    m = json.loads((out / "scene.json").read_text())
    edit(m, out)
    (out / "scene.json").write_text(json.dumps(m))
    return out


def _shift_dsm(m, out):
    with rasterio.open(out / "dsm.tif", "r+", IGNORE_COG_LAYOUT_BREAK="YES") as d:
        t = d.transform
        d.transform = Affine(t.a, t.b, t.c + 5000.0, t.d, t.e, t.f)


@pytest.mark.parametrize("edit,message", [
    (_shift_dsm, "not on the ortho grid.*5000.0 m"),
    (lambda m, o: m.update(gsd_m=m["gsd_m"] * 1.1), "disagrees with the transform"),
    (lambda m, o: m["origin"].update(lon_deg=m["origin"]["lon_deg"] + 0.016),
     "from the centre of crs_wkt2"),
    (lambda m, o: m["origin"].update(alt_m=float("nan")), "'origin.alt_m' is not a finite"),
    (lambda m, o: m["transform"].__setitem__(0, float("inf")), "not a finite number"),
    (lambda m, o: m["ortho"].update(file=5), "'ortho.file' must be the name"),
    (lambda m, o: m["ortho"].update(file="../../etc/passwd"), "'ortho.file' must be the name"),
    (lambda m, o: m.update(dsm="dsm.tif"), "'dsm' must be null or an object"),
    (lambda m, o: m["origin"].update(lon_deg="4.4"), "'origin.lon_deg' is missing or not"),
    (lambda m, o: m["origin"].update(lat_deg=95.0), "origin is invalid"),
    (lambda m, o: m.update(bounds_m=[0, 0, "a", 1]), "'bounds_m' must be a list of 4"),
])
def test_tampered_scene_is_refused_in_one_line(package, tmp_path, capsys, edit, message):
    out = _tampered(package, tmp_path, edit)
    with pytest.raises(SceneError, match=message):
        Scene.open(out)
    rc, _, err = _cli(["tiles", "info", out], capsys)
    _one_line_error(rc, err)


def test_intact_package_opens(package):
    scene = Scene.open(package, verify_checksums=True)
    assert scene.dsm is not None and np.nanmax(scene.dsm) == pytest.approx(10.0, abs=0.1)


# -- nothing left behind ---------------------------------------------------------------------

_KILLED_SAVE = """
import os, signal, sys
import numpy as np
import geonav.scene as scene_mod
from geonav.geo import LonLat
from geonav.scene import Scene

def die(*args, **kw):  # the ortho is written, the manifest not yet: SIGKILL now
    os.kill(os.getpid(), signal.SIGKILL)

scene_mod.sha256_file = die
rgb = np.full((64, 64, 3), 90, np.uint8)
Scene.from_arrays("S", rgb, LonLat(4.4777, 51.9244, 2.0), 1.0).save(sys.argv[1])
"""


def test_sigkilled_save_leaves_a_temp_folder_the_next_run_cleans(tmp_path, utm_tif):
    proc = subprocess.run([sys.executable, "-c", _KILLED_SAVE, str(tmp_path / "S")],
                          capture_output=True, text=True)
    assert proc.returncode == -9, proc.stderr
    stale = [p for p in tmp_path.iterdir() if p.name.startswith(".S.geonav-tmp-")]
    assert len(stale) == 1 and (stale[0] / "ortho.tif").is_file()
    assert not (tmp_path / "S").exists()
    with pytest.warns(GeonavWarning, match="left by a killed run"):
        ingest([utm_tif], name="S", out=tmp_path / "S", compress="DEFLATE")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["S"]
    assert Scene.open(tmp_path / "S").name == "S"


def test_failed_save_leaves_nothing(tmp_path, utm_tif):
    with pytest.raises(SceneError, match="non-finite number"):
        _quiet_ingest([utm_tif], name="N", out=tmp_path / "N",
                      extra_manifest=dict(bad=float("nan")))
    assert list(tmp_path.iterdir()) == []


# -- the CLI: one line, exit 2, nothing written ---------------------------------------------

BAD_CLI = [
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--gsd", "nan"], "--gsd"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--gsd", "inf"], "--gsd"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--gsd", "0"], "--gsd"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--gsd", "-1"], "--gsd"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--bbox", "1,2,3"], "--bbox"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--bbox", "a,b,c,d"],
     "--bbox"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--bbox", "5,2,4,3"],
     "west < east"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--origin", "200,10"],
     "--origin"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--origin", "1,2,nan"],
     "--origin"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--ground-alt", "nan"],
     "--ground-alt"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--bands", "0,1,2"],
     "--bands"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--memory-budget", "0"],
     "--memory-budget"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--origin", "20.0,51.9"],
     "km from the data"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--bbox",
      "-122.45,37.75,-122.40,37.80"], "misses the data"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{blocker}/sub"],
     "is a file, not a folder"),
    (["tiles", "synth", "--out", "{out}", "--size", "-5"], "--size"),
    (["tiles", "preview", "{src}", "-o", "{out}.png", "--max-px", "0"], "--max-px"),
    (["tiles", "preview", "{src}", "-o", "{out}.png", "--alts", ""], "--alts"),
    (["tasks", "make", "{src}", "-o", "{out}.json", "--step", "0"], "--step"),
    (["tasks", "make", "{src}", "-o", "{out}.json", "--alts", "75,,15"], "--alts"),
    (["tasks", "make", "{src}", "-o", "{out}.json", "--min-coverage", "1.5"], "--min-coverage"),
    (["tiles", "fetch", "http://127.0.0.1:9/{{z}}/{{x}}/{{y}}.png", "--bbox", "4,51,4.01,51.01",
      "--zoom", "18", "--out", "{out}", "--attribution", "x", "--timeout", "0"], "--timeout"),
    (["tiles", "fetch", "http://127.0.0.1:9/{{z}}/{{x}}/{{y}}.png", "--bbox", "4,51,4.01,51.01",
      "--zoom", "18", "--out", "{out}", "--attribution", "x", "--retries", "-1"], "--retries"),
    (["tiles", "fetch", "http://127.0.0.1:9/{{z}}/{{x}}/{{y}}.png", "--bbox", "4,51,4.01,51.01",
      "--zoom", "-3", "--out", "{out}", "--attribution", "x"], "--zoom"),
    (["emulator", "--home", "-33.9,nan"], "--home"),
    (["train", "--scene", "{src}", "--tasks", "t.json", "--out", "{out}", "--lr", "nan"],
     "--lr"),
    (["train", "--scene", "{src}", "--tasks", "t.json", "--out", "{out}", "--config",
      "{badtoml}"], "[net] must be a table"),
]


@pytest.mark.parametrize("argv,needle", BAD_CLI, ids=[" ".join(a[:2]) + f" {n}"
                                                      for a, n in BAD_CLI])
def test_bad_cli_value_is_one_line_exit_2_nothing_written(tmp_path, capsys, utm_tif, argv,
                                                          needle):
    work = tmp_path / "work"
    work.mkdir()
    blocker = work / "blocker"
    blocker.write_text("a file, not a folder")
    badtoml = work / "bad.toml"
    badtoml.write_text("net = 5\n")
    before = sorted(p.name for p in work.iterdir())
    args = [a.format(src=utm_tif, out=work / "out", blocker=blocker, badtoml=badtoml)
            for a in argv]
    rc, _, err = _cli(args, capsys)
    _one_line_error(rc, err)
    assert needle in err, err
    assert sorted(p.name for p in work.iterdir()) == before


@pytest.mark.parametrize("argv", [
    ["tasks", "make", "{pkg}", "--kind", "scene", "--alts", "15", "--step", "5",
     "-o", "{blocker}/t.json"],
    ["tiles", "preview", "{pkg}", "-o", "{blocker}/p.png"],
])
def test_unwritable_output_is_one_line(tmp_path, capsys, package, argv):
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    rc, _, err = _cli([a.format(pkg=package, blocker=blocker) for a in argv], capsys)
    _one_line_error(rc, err)
    assert "choose another output path" in err or "not a folder" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"]


def test_western_hemisphere_bbox_parses(capsys, tmp_path):
    from geonav.cliutil import GeonavParser, bbox_arg, lonlat_arg

    p = GeonavParser(prog="t")
    p.add_argument("--bbox", type=bbox_arg)
    p.add_argument("--origin", type=lonlat_arg)
    ns = p.parse_args(["--bbox", "-122.45,-37.8,-122.40,-37.75", "--origin", "-122.42,-37.77"])
    assert ns.bbox == (-122.45, -37.8, -122.40, -37.75)
    assert ns.origin == LonLat(-122.42, -37.77)


def test_malformed_task_json_is_one_line(tmp_path, capsys, package):
    from geonav.tasks import TaskSet

    bad = tmp_path / "t.json"
    for doc in ({"schema_version": 1, "scene_name": "P", "scene_id": "x",
                 "tasks": [{"name": "a", "kind": "meta", "region_m": "abc", "step_m": 15,
                            "alt_m": 300, "target_cell": [0, 0]}]},
                {"schema_version": 1, "scene_name": "P", "scene_id": "x", "tasks": 5},
                {"schema_version": 1, "scene_name": "P", "scene_id": "x", "camera": [1],
                 "tasks": []}):
        bad.write_text(json.dumps(doc))
        with pytest.raises(TaskError):
            TaskSet.load(bad)
        rc, _, err = _cli(["tiles", "preview", package, "--tasks", bad, "-o",
                           tmp_path / "p.png"], capsys)
        _one_line_error(rc, err)
    assert not (tmp_path / "p.png").exists()


def test_experiment_config_with_a_scalar_table_is_one_line(tmp_path):
    from geonav.errors import ConfigError
    from geonav.experiments.config import load_config

    path = tmp_path / "e.toml"
    path.write_text('name = "x"\nscenes = 5\n')
    with pytest.raises(ConfigError, match=r"\[scenes\] must be a table"):
        load_config(path)


def test_cli_warnings_are_single_lines(tmp_path, capsys, utm_tif):
    rc, _, err = _cli(["tiles", "ingest", utm_tif, "--name", "W", "--out", tmp_path / "w",
                       "--compress", "DEFLATE"], capsys)
    assert rc == 0
    lines = err.strip().splitlines()
    assert lines and all(ln.startswith("warning: ") for ln in lines), err
    assert "Deprecation" not in err and ".py:" not in err


# -- a hostile tile server on 127.0.0.1 ------------------------------------------------------

Z = 18


@pytest.fixture(scope="module")
def one_tile():
    """A bbox inside a single zoom-18 tile and that tile's PNG bytes."""
    lon, lat, mpx, tiles = marker_setup(4.4777, 51.9244, Z, n=1)
    (x, y), = tiles
    w, n = global_px_to_lonlat(x * 256 + 40, y * 256 + 40, Z)
    e, s = global_px_to_lonlat(x * 256 + 216, y * 256 + 216, Z)
    assert tiles_in_bbox((w, s, e, n), Z) == [(Z, x, y)]
    return (w, s, e, n), encode(tile_image(x, y, Z, mpx), "png")


@contextmanager
def hostile_server(body: bytes):
    """GET /MODE/z/x/y.png answers by MODE: ok, trunc (half the body, then close),
    lie (Content-Length 100 bytes too long, then close), short (Content-Length half),
    junk (HTML with status 200), chunked (a chunk cut short), trickle (a byte every
    0.25 s), missing (404)."""
    stop = threading.Event()

    class Handler(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def do_GET(self):  # noqa: N802 - http.server API
            mode = self.path.strip("/").split("/")[0]
            try:
                if mode == "missing":
                    self.send_response(404)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                payload = b"<html>rate limited</html>" if mode == "junk" else body
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("Connection", "close")
                if mode == "chunked":
                    self.send_header("Transfer-Encoding", "chunked")
                    self.end_headers()
                    self.wfile.write(f"{len(payload):x}\r\n".encode() + payload[:100])
                    self.wfile.flush()
                    self.connection.shutdown(socket.SHUT_RDWR)
                    return
                declared = {"lie": len(payload) + 100, "short": len(payload) // 2}.get(
                    mode, len(payload))
                self.send_header("Content-Length", str(declared))
                self.end_headers()
                if mode == "trunc":
                    self.wfile.write(payload[:len(payload) // 2])
                    self.wfile.flush()
                    self.connection.shutdown(socket.SHUT_RDWR)
                elif mode == "trickle":
                    for i in range(len(payload)):
                        if stop.wait(0.25):
                            return
                        self.wfile.write(payload[i:i + 1])
                        self.wfile.flush()
                else:
                    self.wfile.write(payload)
                    if mode == "lie":
                        self.wfile.flush()
                        self.connection.shutdown(socket.SHUT_RDWR)
            except (BrokenPipeError, ConnectionResetError, OSError):
                pass

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, kwargs=dict(poll_interval=0.05),
                              daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        stop.set()
        server.shutdown()
        server.server_close()
        thread.join(5)


FAST = dict(backoff_s=0.01, max_backoff_s=0.02, retries=1, attribution="test tiles, CC0")


def _cached(cache: Path) -> list[Path]:
    return [p for p in cache.rglob("*") if p.is_file() and p.name != SIDECAR]


@pytest.mark.parametrize("mode,detail", [
    ("trunc", "Content-Length"), ("lie", "Content-Length"), ("short", "truncated PNG"),
    ("junk", "not a PNG/JPEG/WebP"), ("chunked", "cut short"),
    ("trickle", "body not complete after 1 s"),
])
def test_bad_bodies_are_never_cached(tmp_path, one_tile, mode, detail):
    bbox, png = one_tile
    cache = tmp_path / "cache"
    with hostile_server(png) as base:
        with pytest.raises(FetchIncomplete) as info:
            fetch_tiles(base + f"/{mode}/{{z}}/{{x}}/{{y}}.png", bbox, Z, cache,
                        timeout_s=1.0, **FAST)
    assert info.value.result.failed == 1
    assert detail in info.value.result.failures[0], info.value.result.failures
    assert _cached(cache) == []  # nothing half-written, nothing junk


def test_all_missing_is_an_error_and_ok_fetch_works(tmp_path, one_tile, capsys):
    bbox, png = one_tile
    with hostile_server(png) as base:
        rc, _, err = _cli(["tiles", "fetch", base + "/missing/{z}/{x}/{y}.png", "--bbox",
                           ",".join(map(str, bbox)), "--zoom", Z, "--out", tmp_path / "c",
                           "--attribution", "x", "--timeout", "2"], capsys)
        _one_line_error(rc, err)
        assert "nothing fetched" in err
        result = fetch_tiles(base + "/ok/{z}/{x}/{y}.png", bbox, Z, tmp_path / "c2",
                             timeout_s=2.0, **FAST)
    assert result.downloaded == 1
    decode_tile(_cached(tmp_path / "c2")[0].read_bytes())


def test_verify_drops_a_bad_cached_tile_and_fetches_it_again(tmp_path, one_tile):
    bbox, png = one_tile
    (_, x, y), = tiles_in_bbox(bbox, Z)
    cache = tmp_path / "cache"
    bad = cache / str(Z) / str(x) / f"{y}.png"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(png[: len(png) // 2])  # left by an older geonav
    with hostile_server(png) as base:
        url = base + "/ok/{z}/{x}/{y}.png"
        plain = fetch_tiles(url, bbox, Z, cache, timeout_s=2.0, **FAST)
        assert (plain.cached, plain.downloaded) == (1, 0)
        checked = fetch_tiles(url, bbox, Z, cache, timeout_s=2.0, verify=True, **FAST)
    assert (checked.verified, checked.invalid_removed, checked.downloaded) == (1, 1, 1)
    assert bad.read_bytes() == png


def test_raster_outside_its_crs_domain_is_one_line(tmp_path, capsys):
    path = _write(tmp_path / "far.tif", _texture(10, 10), UTM31, Affine(1, 0, 5e7, 0, -1, 5e7))
    rc, _, err = _cli(["tiles", "ingest", path, "--name", "F", "--out", tmp_path / "s"], capsys)
    _one_line_error(rc, err)
    assert "outside the valid area of its CRS" in err and not (tmp_path / "s").exists()
