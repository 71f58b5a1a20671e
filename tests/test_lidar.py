"""LiDAR point clouds rasterised into colour, DSM and DEM (geonav.tiles.lidar), on small
clouds written here with laspy, and the real Autzen strip of the ``autzen-lidar`` sample
dataset (issue 32: a real surface model for obstacles) when the set-up fetched it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

laspy = pytest.importorskip("laspy", reason="the LiDAR extra is not installed: pip install "
                            "'geonav[lidar]' (scripts/setup_env.sh's dev set-up has it)")

import rasterio  # noqa: E402
from pyproj import CRS  # noqa: E402

from geonav.tiles import sample_data as sd  # noqa: E402
from geonav.tiles.lidar import LidarError, rasterise_point_cloud  # noqa: E402

FT = 0.3048
UTM10 = CRS.from_epsg(32610)


def _cloud(path: Path, pts: list[tuple[float, float, float, int, int, tuple[int, int, int]]],
           *, crs: CRS | None = UTM10, point_format: int = 3) -> Path:
    """A LAS file of (x, y, z, class, return number, rgb) points; rgb in 16 bits."""
    header = laspy.LasHeader(point_format=point_format, version="1.2")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([500000.0, 4000000.0, 0.0])
    if crs is not None:
        header.add_crs(crs)
    las = laspy.LasData(header)
    arr = np.array([p[:3] for p in pts], float)
    las.x, las.y, las.z = arr[:, 0], arr[:, 1], arr[:, 2]
    las.classification = np.array([p[3] for p in pts], np.uint8)
    las.return_number = np.array([p[4] for p in pts], np.uint8)
    las.number_of_returns = np.maximum(las.return_number, 1)
    if point_format in (2, 3):
        rgb = np.array([p[5] for p in pts], np.uint16) * 257
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.write(path)
    return path


def _grid_points(x0: float = 500000.0, y0: float = 4000000.0) -> list:
    """A 10 x 6 m field of 1 m cells: ground at 100 m (grey 100), a 2 x 2 m 'tree' at
    (3..5, 2..4) whose first return is at 118 m (green) over ground returns at 100.5 m,
    and cell (8, 1) left empty."""
    pts = []
    for ix in range(10):
        for iy in range(6):
            if (ix, iy) == (8, 1):
                continue
            x, y = x0 + ix + 0.5, y0 + iy + 0.5
            if 3 <= ix < 5 and 2 <= iy < 4:
                pts.append((x, y, 118.0, 1, 1, (20, 200, 40)))
                pts.append((x + 0.1, y, 100.5, 2, 2, (90, 90, 90)))
            else:
                pts.append((x, y, 100.0, 2, 1, (100, 100, 100)))
                pts.append((x - 0.2, y + 0.2, 100.2, 2, 1, (120, 120, 120)))
    return pts


def test_cells_hold_the_top_the_ground_and_the_first_returns_colour(tmp_path):
    las = _cloud(tmp_path / "c.las", _grid_points())
    res = rasterise_point_cloud(las, tmp_path / "rgb.tif", tmp_path / "dsm.tif",
                                tmp_path / "dem.tif", cell_m=1.0, fill_cells=2)
    assert (res.width, res.height, res.points) == (10, 6, 2 * 59 - 0)
    with rasterio.open(tmp_path / "dsm.tif") as src:
        dsm = src.read(1)
        assert src.units == ("m",) and src.crs.to_epsg() == 32610
        assert src.res == (1.0, 1.0)
    dem = rasterio.open(tmp_path / "dem.tif").read(1)
    rgb = rasterio.open(tmp_path / "rgb.tif").read()
    row = lambda iy: 5 - iy  # north-up: row 0 is the northern edge  # noqa: E731
    assert dsm[row(2), 3] == pytest.approx(118.0) and dsm[row(0), 0] == pytest.approx(100.2)
    assert dem[row(2), 3] == pytest.approx(100.5) and dem[row(0), 0] == pytest.approx(100.0)
    # colour: the mean of the first returns only (the tree's ground return is hidden)
    assert tuple(rgb[:, row(2), 3]) == (20, 200, 40)
    assert tuple(rgb[:, row(0), 0]) == (110, 110, 110)
    # the empty cell is filled from its neighbours
    assert 100.0 <= dsm[row(1), 8] <= 100.2 and rgb[0, row(1), 8] == 110
    assert res.filled_fraction == pytest.approx(1 / 60) and res.masked_fraction == 0
    assert res.top_above_ground_m == pytest.approx(17.5)


def test_heights_in_feet_become_metres_and_far_gaps_stay_empty(tmp_path):
    """Oregon Lambert in international feet, as the Autzen file: x, y and z in feet."""
    pts = [(p[0] / FT, p[1] / FT, p[2] / FT, *p[3:]) for p in _grid_points(1000.0, 2000.0)]
    pts += [(1000.0 / FT + 30.5 / FT, 2000.0 / FT + 0.5 / FT, 100.0 / FT, 2, 1,
             (100, 100, 100))]  # a lone point 20 m east of the field
    las = _cloud(tmp_path / "ft.las", pts, crs=CRS.from_epsg(2994))
    res = rasterise_point_cloud(las, tmp_path / "rgb.tif", tmp_path / "dsm.tif",
                                tmp_path / "dem.tif", cell_m=1.0, fill_cells=3)
    with rasterio.open(tmp_path / "dsm.tif") as src:
        dsm = src.read(1)
        assert src.res[0] == pytest.approx(1.0 / FT)  # a 1 m cell in feet
        mask = rasterio.open(tmp_path / "rgb.tif").read_masks(1)
    assert np.nanmax(dsm) == pytest.approx(118.0, abs=0.01)  # metres, not 387 ft
    assert res.ground_m[0] == pytest.approx(100.0, abs=0.01)
    gap = np.isnan(dsm[:, 13:28])  # 3 cells of fill from each side of the 20 m gap
    assert gap.any() and (mask[:, 13:28][gap] == 0).all()


@pytest.mark.parametrize("problem, match", [
    ("no colour", "no colour"), ("no crs", "no projected CRS"), ("no ground", "no ground")])
def test_clouds_it_cannot_use_are_refused_clearly(tmp_path, problem, match):
    pts = _grid_points()
    kwargs = {}
    if problem == "no colour":
        kwargs["point_format"] = 1
    elif problem == "no crs":
        kwargs["crs"] = None
    else:
        pts = [(*p[:3], 1, *p[4:]) for p in pts]
    las = _cloud(tmp_path / "bad.las", pts, **kwargs)
    with pytest.raises(LidarError, match=match):
        rasterise_point_cloud(las, tmp_path / "a.tif", tmp_path / "b.tif", tmp_path / "c.tif")


def test_without_laspy_the_fetch_stops_before_downloading(tmp_path, monkeypatch):
    import geonav.tiles.lidar as lidar

    def missing():
        raise LidarError("reading LiDAR (LAS/LAZ) needs laspy and lazrs: pip install "
                         "'geonav[lidar]'")

    monkeypatch.setattr(lidar, "require_laspy", missing)
    monkeypatch.setattr("urllib.request.urlopen", lambda *a, **k: pytest.fail("downloaded"))
    with pytest.raises(sd.SampleDataUnavailable, match=r"geonav\[lidar\]"):
        sd.fetch("autzen-lidar", tmp_path)
    assert "geonav[lidar]" in sd.unavailable_reason("autzen-lidar", tmp_path)


# -- the real strip --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def autzen(tmp_path_factory):
    cache = sd.default_cache_dir()
    if not sd.cached("autzen-lidar", cache):
        pytest.skip(sd.unavailable_reason("autzen-lidar", cache))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 1 m is coarse for 15 m views; 80 % has imagery
        return sd.ingest_sample("autzen-lidar", cache,
                                out=tmp_path_factory.mktemp("z") / "autzen")


def test_autzen_rasters_are_real_and_on_one_grid():
    folder = sd.dataset_dir("autzen-lidar")
    if not sd.cached("autzen-lidar"):
        pytest.skip(sd.unavailable_reason("autzen-lidar"))
    ds = sd.dataset("autzen-lidar")
    grids = []
    for name in (ds.raster, ds.dsm, ds.dem):
        with rasterio.open(folder / name) as src:
            grids.append((src.width, src.height, src.transform, src.crs))
    assert grids[0] == grids[1] == grids[2]
    rgb = rasterio.open(folder / ds.raster).read()
    dsm = rasterio.open(folder / ds.dsm).read(1)
    dem = rasterio.open(folder / ds.dem).read(1)
    assert rgb.std() > 15  # texture, not a fill
    above = dsm - dem
    # Eugene, Oregon lies about 130 m above sea level; its trees stand 20-33 m tall
    assert 120 < np.nanmedian(dem) < 140 and 20 < np.nanmax(above) < 40
    assert np.nanmin(above) > -0.5
    record = json.loads((folder / "sample.json").read_text())
    assert {"autzen-rgb.tif", "autzen-dsm.tif", "autzen-dem.tif"} <= set(record["files"])


def test_autzen_scene_blocks_cells_at_15_m_with_its_real_trees(autzen):
    from geonav.lattice import Lattice, ObstacleModel, blocked_cells

    assert autzen.manifest["licence"]["name"].startswith("BSD-2-Clause")
    assert "laspy 2.7.0" in autzen.manifest["attribution"]
    assert autzen.manifest["dsm_source"]["height_unit_from"] == "band unit 'm'"
    w, h = autzen.size_m
    lattice = Lattice((-w / 2 + 10, -h / 2 + 10, w / 2 - 10, h / 2 - 10), 5.0)
    at15 = blocked_cells(autzen, lattice, 15.0, ObstacleModel())
    at45 = blocked_cells(autzen, lattice, 45.0, ObstacleModel())
    assert 0.01 < at15.mean() < 0.3 and not at45.any()


def test_tiles_lidar_command_writes_three_rasters_and_guards_them(tmp_path, capsys):
    from geonav.cli import main

    las = _cloud(tmp_path / "field.las", _grid_points())
    out = tmp_path / "out"
    assert main(["tiles", "lidar", str(las), "--out", str(out), "--fill", "2"]) == 0
    said = capsys.readouterr().out
    assert "118 returns -> 10 x 6 cells of 1 m" in said and "--dsm" in said
    names = sorted(p.name for p in out.glob("*.tif"))
    assert names == ["field-dem.tif", "field-dsm.tif", "field-rgb.tif"]
    assert main(["tiles", "lidar", str(las), "--out", str(out)]) == 2  # exists: no --force
    assert "pass --force" in capsys.readouterr().err
    assert main(["tiles", "lidar", str(las), "--out", str(out), "--force"]) == 0
    (out / "field-dsm.tif").write_bytes(b"someone else's file")
    assert main(["tiles", "lidar", str(las), "--out", str(out), "--force"]) == 2
    assert "not a raster" in capsys.readouterr().err
    assert (out / "field-dsm.tif").read_bytes() == b"someone else's file"


def test_a_grid_too_large_for_memory_is_refused(tmp_path, monkeypatch):
    import geonav.tiles.lidar as lidar

    monkeypatch.setattr(lidar, "MAX_CELLS", 50)
    las = _cloud(tmp_path / "c.las", _grid_points())
    with pytest.raises(LidarError, match=r"10 x 6 cells.*--cell 1.1"):
        rasterise_point_cloud(las, tmp_path / "a.tif", tmp_path / "b.tif", tmp_path / "c.tif")


def test_an_uncompressed_las_needs_no_laz_backend(tmp_path, monkeypatch):
    las = _cloud(tmp_path / "c.las", _grid_points())
    laz = _cloud(tmp_path / "c.laz", _grid_points())  # written compressed, by its suffix
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    res = rasterise_point_cloud(las, tmp_path / "a.tif", tmp_path / "b.tif", tmp_path / "c.tif")
    assert res.points == 118
    with pytest.raises(LidarError, match="no LAZ backend"):
        rasterise_point_cloud(laz, tmp_path / "d.tif", tmp_path / "e.tif", tmp_path / "f.tif")
