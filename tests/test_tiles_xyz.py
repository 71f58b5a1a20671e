"""XYZ tile folders and MBTiles: orientation (XYZ/TMS rows), known lon/lat points,
bad input (empty, mixed zooms, corrupt tiles, bbox misses, DSM off the imagery),
and the CLI (ingest, info, preview)."""

from __future__ import annotations

import json
import sqlite3
import warnings

import numpy as np
import pytest

from geonav.errors import GeonavWarning, NoOverlap, TileError
from geonav.scene import Scene
from geonav.tiles.ingest import ingest
from geonav.tiles.mbtiles import read_mbtiles
from geonav.tiles.xyz import ground_gsd_m, read_xyz

try:
    from test_tiles_support import (
        expected_px,
        find_marker,
        marker_setup,
        write_mbtiles,
        write_xyz,
    )
except ImportError:  # tests/ imported as a package
    from tests.test_tiles_support import (
        expected_px,
        find_marker,
        marker_setup,
        write_mbtiles,
        write_xyz,
    )

Z = 18
LON, LAT = 4.4777, 51.9244  # Rotterdam


@pytest.fixture(scope="module")
def marker():
    return marker_setup(LON, LAT, Z)


def _ingest(tmp_path, source, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeonavWarning)  # small scenes: coverage warnings
        return ingest([source], name="t", out=tmp_path / "scene", compress="DEFLATE", **kw)


@pytest.mark.parametrize("fmt,tms", [("png", False), ("jpg", False), ("webp", False),
                                     ("png", True)])
def test_xyz_marker_lands_on_its_lonlat(tmp_path, marker, fmt, tms):
    lon, lat, mpx, tiles = marker
    folder = write_xyz(tmp_path / "tiles", Z, tiles, mpx, fmt=fmt, tms=tms)
    src = read_xyz(folder, tms=tms)
    assert src.info["zoom"] == Z and src.info["tiles"] == 9 and src.info["scheme"] == (
        "tms" if tms else "xyz")
    assert src.info["est_native_gsd_m"] == pytest.approx(ground_gsd_m(Z, LAT), rel=2e-3)
    assert src.info["est_native_gsd_m"] == pytest.approx(
        156543.03 * np.cos(np.radians(LAT)) / 2 ** Z, rel=2e-3)
    scene = _ingest(tmp_path, folder, tms=tms)
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, lon, lat)
    assert abs(col - ecol) < 0.5 and abs(row - erow) < 0.5, (col, row, ecol, erow)
    assert scene.manifest["sources"][0]["zoom"] == Z


def test_tms_folder_read_as_xyz_is_flipped(tmp_path, marker):
    lon, lat, mpx, tiles = marker
    folder = write_xyz(tmp_path / "tiles", Z, tiles, mpx, tms=True)
    # Read without --tms, the rows are far away (other hemisphere): no overlap with the bbox,
    # which read the other way they meet (issue 33: the message says so).
    with pytest.raises(TileError, match="read the other way they meet it; pass --tms"):
        read_xyz(folder, bbox_lonlat=(LON - 0.01, LAT - 0.01, LON + 0.01, LAT + 0.01))


@pytest.mark.parametrize("scheme", [None, "tms", "xyz"])
def test_mbtiles_marker_lands_on_its_lonlat(tmp_path, marker, scheme):
    lon, lat, mpx, tiles = marker
    path = write_mbtiles(tmp_path / "t.mbtiles", Z, tiles, mpx, scheme=scheme,
                         metadata=dict(attribution="(c) test tiles, CC-BY"))
    src = read_mbtiles(path)
    assert src.info["scheme"] == (scheme or "tms") and src.info["tiles"] == 9
    scene = _ingest(tmp_path, path)
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, lon, lat)
    assert abs(col - ecol) < 0.5 and abs(row - erow) < 0.5, (col, row, ecol, erow)
    assert scene.manifest["attribution"] == "(c) test tiles, CC-BY"


def test_empty_folder_and_bad_mbtiles(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(TileError, match="no tiles"):
        read_xyz(tmp_path / "empty")
    junk = tmp_path / "junk"
    (junk / "18" / "abc").mkdir(parents=True)
    (junk / "18" / "1").mkdir(parents=True)
    (junk / "18" / "1" / "2.txt").write_text("x")
    (junk / "18" / "1" / "-3.png").write_bytes(b"x")
    with pytest.raises(TileError, match="no tiles"):
        read_xyz(junk)
    with pytest.raises(TileError, match="not a folder"):
        read_xyz(tmp_path / "nope")
    bad = tmp_path / "bad.mbtiles"
    bad.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(TileError, match="not an MBTiles"):
        read_mbtiles(bad)
    con = sqlite3.connect(tmp_path / "empty.mbtiles")
    con.execute("CREATE TABLE tiles (zoom_level, tile_column, tile_row, tile_data)")
    con.commit()
    con.close()
    with pytest.raises(TileError, match="no tiles"):
        read_mbtiles(tmp_path / "empty.mbtiles")
    vec = write_mbtiles(tmp_path / "vec.mbtiles", 1, [(0, 0)], metadata=None)
    con = sqlite3.connect(vec)
    con.execute("UPDATE metadata SET value='pbf' WHERE name='format'")
    con.commit()
    con.close()
    with pytest.raises(TileError, match="vector"):
        read_mbtiles(vec)


def test_mixed_zooms_take_highest_or_requested_and_warn(tmp_path, marker):
    lon, lat, mpx, tiles = marker
    folder = write_xyz(tmp_path / "tiles", Z, tiles, mpx)
    low = [(x // 2, y // 2) for x, y in tiles]
    write_xyz(folder, Z - 1, sorted(set(low)))
    with pytest.warns(GeonavWarning, match=r"mixes zoom levels 17, 18; using zoom 18"):
        assert read_xyz(folder).info["zoom"] == Z
    with pytest.warns(GeonavWarning, match="using zoom 17 .requested"):
        assert read_xyz(folder, zoom=Z - 1).info["zoom"] == Z - 1
    with pytest.raises(TileError, match="no tiles at zoom 16"):
        read_xyz(folder, zoom=16)
    mb = write_mbtiles(tmp_path / "m.mbtiles", Z, tiles, mpx)
    con = sqlite3.connect(mb)
    con.execute("INSERT INTO tiles SELECT 17, tile_column / 2, tile_row / 2, tile_data "
                "FROM tiles LIMIT 1")
    con.commit()
    con.close()
    with pytest.warns(GeonavWarning, match="mixes zoom levels 17, 18"):
        assert read_mbtiles(mb).info["zoom"] == Z


def test_corrupt_tiles_are_skipped_masked_and_counted(tmp_path, marker):
    lon, lat, mpx, tiles = marker
    folder = write_xyz(tmp_path / "tiles", Z, tiles, mpx, fmt="jpg")
    (x0, y0), (x1, y1) = tiles[0], tiles[1]
    t0 = folder / str(Z) / str(x0) / f"{y0}.jpg"
    t0.write_bytes(t0.read_bytes()[:-400])  # truncated
    (folder / str(Z) / str(x1) / f"{y1}.jpg").write_bytes(b"<html>quota</html>")
    with pytest.warns(GeonavWarning, match=r"skipped 2 of 9 zoom-18 tiles") as rec:
        src = read_xyz(folder)
    assert "truncated JPEG" in str(rec[0].message)
    assert src.info["tiles"] == 7 and src.info["tiles_corrupt"] == 2
    assert not src.mask[:256, :512].any() and src.mask[256:, :].all()
    # the marker tile is intact, so the scene still finds it; the gap is masked
    with pytest.warns(GeonavWarning):
        scene = ingest([folder], name="t", out=tmp_path / "s", compress="DEFLATE")
    assert 0.6 < scene.mask.mean() < 0.85
    assert scene.manifest["sources"][0]["tiles_corrupt"] == 2


def test_bbox_cuts_and_misses(tmp_path, marker):
    lon, lat, mpx, tiles = marker
    folder = write_xyz(tmp_path / "tiles", Z, tiles, mpx)
    bbox = (lon - 0.0003, lat - 0.0002, lon + 0.0003, lat + 0.0002)
    scene = _ingest(tmp_path, folder, bbox_lonlat=bbox)
    w, s, e, n = scene.manifest["bounds_wgs84"]
    assert w >= bbox[0] - 1e-5 and e <= bbox[2] + 1e-5 and s >= bbox[1] - 1e-5
    assert scene.manifest["sources"][0]["tiles"] <= 4  # only the tiles the bbox needs
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, lon, lat)
    assert abs(col - ecol) < 0.5 and abs(row - erow) < 0.5
    with pytest.raises((TileError, NoOverlap), match="misses"):
        ingest([folder], name="t", out=tmp_path / "s2", bbox_lonlat=(10.0, 40.0, 10.1, 40.1))


def test_dsm_that_does_not_overlap(tmp_path, marker):
    import rasterio
    from affine import Affine

    lon, lat, mpx, tiles = marker
    folder = write_xyz(tmp_path / "tiles", Z, tiles, mpx)
    dsm = tmp_path / "dsm.tif"
    with rasterio.open(dsm, "w", driver="GTiff", width=50, height=50, count=1, dtype="float32",
                       crs="EPSG:32632", transform=Affine(1, 0, 500000, 0, -1, 5200000)) as dst:
        dst.write(np.full((1, 50, 50), 30.0, np.float32))
    with pytest.raises(NoOverlap, match="DSM"):
        _ingest(tmp_path, folder, dsm=dsm)
    assert not (tmp_path / "scene").exists()


def test_fetch_sidecar_attribution_reaches_manifest(tmp_path, marker):
    from geonav.tiles.xyz import SIDECAR

    lon, lat, mpx, tiles = marker
    folder = write_xyz(tmp_path / "tiles", Z, tiles, mpx)
    (folder / SIDECAR).write_text(json.dumps(dict(attribution="Imagery (c) Example, CC-BY 4.0",
                                                  url_template="https://t.example/{z}/{x}/{y}")))
    scene = _ingest(tmp_path, folder)
    assert scene.manifest["attribution"] == "Imagery (c) Example, CC-BY 4.0"
    assert scene.manifest["sources"][0]["url_template"] == "https://t.example/{z}/{x}/{y}"
    reopened = Scene.open(tmp_path / "scene")
    assert reopened.manifest["attribution"] == "Imagery (c) Example, CC-BY 4.0"


def test_cli_ingest_and_info(tmp_path, marker, capsys):
    from geonav.cli import main

    lon, lat, mpx, tiles = marker
    folder = write_xyz(tmp_path / "tiles", Z, tiles, mpx, tms=True)
    out = tmp_path / "scene"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeonavWarning)
        assert main(["tiles", "ingest", str(folder), "--tms", "--zoom", str(Z), "--name", "X",
                     "--out", str(out), "--attribution", "mine", "--compress", "DEFLATE"]) == 0
    assert "scene X:" in capsys.readouterr().out
    scene = Scene.open(out)
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, lon, lat)
    assert abs(col - ecol) < 0.5 and abs(row - erow) < 0.5
    assert main(["tiles", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "zoom 18 (tms, 9 tiles, 0 missing, 0 corrupt)" in text and "attribution mine" in text
    assert "0 disjoint 150 m tasks fit with the 300 m margin" in text
    assert main(["tiles", "info", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["meta_tasks"]["fit"] == 0
    assert [a["fits"] for a in summary["altitudes"]] == [False, True, True, True]
    assert summary["altitudes"][3]["obs"]["84"]["sharp"] is False  # 0.37 m > 0.357 m
    assert main(["tiles", "info", str(tmp_path / "missing")]) == 2


def test_info_counts_meta_tasks_and_preview_draws_tasks(tmp_path, capsys):
    from geonav.cli import main
    from geonav.geo import LonLat
    from geonav.tasks import sample_meta_tasks
    from geonav.tiles.info import count_meta_tasks, summarize

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (500, 500, 3), dtype=np.uint8)  # 1000 m at 2 m/px
    dsm = np.zeros((500, 500), np.float32)
    dsm[100:120, 100:120] = 35.0
    scene = Scene.from_arrays("big", rgb, LonLat(8.5, 47.4, 400.0), 2.0, dsm=dsm)
    assert count_meta_tasks(scene) == 4  # floor((1000 - 600) / 150) ** 2
    scene.mask[:, :50] = False  # 100 m of no imagery on the west edge
    assert count_meta_tasks(scene) == 2
    scene.mask[:] = True
    s = summarize(scene)
    assert s["dsm"]["max_m"] == 35.0 and s["dsm"]["min_m"] == 0.0
    assert [a["fits"] for a in s["altitudes"]] == [True] * 4
    assert s["altitudes"][0]["obs"]["84"]["sharp"] and not s["altitudes"][3]["obs"]["84"]["sharp"]
    scene.save(tmp_path / "big", compress="DEFLATE")
    tasks = sample_meta_tasks(scene, 2, seed=0)
    tasks.save(tmp_path / "tasks.json")
    png = tmp_path / "p.png"
    assert main(["tiles", "preview", str(tmp_path / "big"), "--tasks",
                 str(tmp_path / "tasks.json"), "-o", str(png)]) == 0
    out = capsys.readouterr().out
    assert "2 tasks" in out and "random-walk success 0." in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["tiles", "info", str(tmp_path / "big")]) == 0
    text = capsys.readouterr().out
    assert "4 disjoint 150 m tasks" in text and "DSM         0.0..35.0 m" in text


def test_unverifiable_tms_says_where_each_reading_puts_the_scene(tmp_path, marker):
    """A bare tile folder states no latitude: --tms cannot be checked, so a warning names
    the centre it gives and the latitude the XYZ reading would give (issue 33)."""
    lon, lat, mpx, tiles = marker
    tms_folder = write_xyz(tmp_path / "tms", Z, tiles, mpx, tms=True)
    with pytest.warns(GeonavWarning, match=r"--tms could not be checked") as rec:
        read_xyz(tms_folder, tms=True)
    import re

    text = str(rec[0].message)
    centre = float(re.search(r"centred at (-?[\d.]+),", text).group(1))
    other = float(re.search(r"it would be at latitude (-?[\d.]+)\.", text).group(1))
    assert abs(centre - lat) < 0.01       # the TMS reading: where the data really is
    assert abs(other + lat) < 1.0         # the XYZ reading: the other hemisphere
    with warnings.catch_warnings():
        warnings.simplefilter("error", GeonavWarning)
        read_xyz(write_xyz(tmp_path / "xyz", Z, tiles, mpx), tms=False)   # no warning
