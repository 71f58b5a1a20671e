import json
import warnings

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from geonav.errors import GeonavWarning, MissingCRS, NoOverlap, SceneError
from geonav.scene import Scene
from geonav.testing import textured_scene
from geonav.tiles.ingest import ingest


@pytest.fixture(scope="module")
def package(tmp_path_factory):
    s = textured_scene(300.0, 0.5, seed=3)
    out = tmp_path_factory.mktemp("pkg") / "A"
    s.save(out, compress="DEFLATE")
    return s, out


def test_package_round_trip(package):
    s, out = package
    t = Scene.open(out, verify_checksums=True)
    assert (t.width, t.height, t.gsd_m) == (s.width, s.height, s.gsd_m)
    assert np.array_equal(t.rgb, s.rgb)  # DEFLATE is lossless
    assert t.mask.all() and t.dsm is not None and np.allclose(t.dsm, s.dsm)
    assert t.bounds_m == pytest.approx(s.bounds_m)
    m = json.loads((out / "scene.json").read_text())
    assert m["dsm"]["height_reference"].startswith("height above ground")
    assert m["bounds_wgs84"][0] < s.origin.lon_deg < m["bounds_wgs84"][2]
    with rasterio.open(out / "ortho.tif") as src:
        assert src.overviews(1), "COG must have overviews"
        assert src.crs.to_wkt()


def test_refuses_to_overwrite(package, tmp_path):
    s, out = package
    with pytest.raises(SceneError, match="exists"):
        s.save(out)


@pytest.mark.parametrize("breakage,message", [
    (lambda m: m.pop("gsd_m"), "missing 'gsd_m'"),
    (lambda m: m.update(width="wide"), "'width' has the wrong type"),
    (lambda m: m.update(schema_version=99), "schema_version 99"),
    (lambda m: m.update(transform=[1, 2, 3]), "6 coefficients"),
    (lambda m: m.update(crs_wkt2="not a crs"), "not a valid CRS"),
    (lambda m: m.update(width=m["width"] + 1), "px but scene.json says"),
])
def test_invalid_manifest_is_named(package, tmp_path, breakage, message):
    import shutil

    _, out = package
    broken = tmp_path / "B"
    shutil.copytree(out, broken)
    m = json.loads((broken / "scene.json").read_text())
    breakage(m)
    (broken / "scene.json").write_text(json.dumps(m))
    with pytest.raises(SceneError, match=message):
        Scene.open(broken)


def test_corrupt_json_and_missing_files(package, tmp_path):
    import shutil

    _, out = package
    broken = tmp_path / "C"
    shutil.copytree(out, broken)
    (broken / "dsm.tif").unlink()
    with pytest.raises(SceneError, match="dsm.tif is missing"):
        Scene.open(broken)
    (broken / "scene.json").write_text("{not json")
    with pytest.raises(SceneError, match="not valid JSON"):
        Scene.open(broken)
    with pytest.raises(SceneError, match="does not exist"):
        Scene.open(tmp_path / "nowhere")


def _write(path, data, crs, transform, nodata=None):
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[-1], height=data.shape[-2],
                       count=data.shape[0], dtype=data.dtype, crs=crs, transform=transform,
                       nodata=nodata) as dst:
        dst.write(data)


def test_ingest_errors_and_warnings(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 255, (3, 200, 200), dtype=np.uint8)
    _write(tmp_path / "nocrs.tif", rgb, None, from_origin(0, 200, 1, 1))
    with pytest.raises(MissingCRS, match="has no CRS"):
        ingest([tmp_path / "nocrs.tif"], name="X", out=tmp_path / "x")
    assert not (tmp_path / "x").exists()
    # 200 m at 1 m/px in UTM 31N near Rotterdam
    t = from_origin(593000, 5754000, 1.0, 1.0)
    _write(tmp_path / "utm.tif", rgb, "EPSG:32631", t)
    far = np.full((1, 50, 50), 30.0, np.float32)
    _write(tmp_path / "far_dsm.tif", far, "EPSG:32631", from_origin(600000, 5760000, 1, 1))
    with pytest.raises(NoOverlap, match="does not overlap"):
        ingest([tmp_path / "utm.tif"], name="X", out=tmp_path / "x",
               dsm=tmp_path / "far_dsm.tif")
    assert not (tmp_path / "x").exists()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = ingest([tmp_path / "utm.tif"], name="X", out=tmp_path / "x")
    text = " ".join(str(w.message) for w in caught if issubclass(w.category, GeonavWarning))
    assert "2.80x coarser than the 0.357 m/px" in text
    assert "short of the 750 m" in text
    assert s.gsd_m == pytest.approx(1.0, abs=0.01)
    with pytest.raises(NoOverlap, match="misses the data"):
        ingest([tmp_path / "utm.tif"], name="Y", out=tmp_path / "y",
               bbox_lonlat=(10.0, 40.0, 10.1, 40.1))
    with pytest.raises(Exception, match="2x finer"):
        ingest([tmp_path / "utm.tif"], name="Y", out=tmp_path / "y", gsd_m=0.25)


def test_ingest_dsm_max_resampling_keeps_roofs(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 255, (3, 400, 400), dtype=np.uint8)
    t = from_origin(593000, 5754000, 0.25, 0.25)
    _write(tmp_path / "img.tif", rgb, "EPSG:32631", t)
    dsm = np.full((1, 400, 400), 10.0, np.float32)  # ground at 10 m AMSL
    dsm[0, 200, 200] = 40.0  # a one-pixel mast
    _write(tmp_path / "dsm.tif", dsm, "EPSG:32631", t)
    s = ingest([tmp_path / "img.tif"], name="D", out=tmp_path / "d", dsm=tmp_path / "dsm.tif",
               gsd_m=1.0)
    assert s.dsm is not None
    assert np.nanmax(s.dsm) == pytest.approx(30.0, abs=0.01)  # survives 4x downsampling
    assert s.origin.alt_m == pytest.approx(10.0)  # ground estimated from the DSM
    assert s.manifest["resampling"] == "average"
