import math

import pytest
from pyproj import CRS, Geod, Transformer

from geonav.errors import GeoError
from geonav.geo import LocalNED, LonLat, SceneFrame, ScenePoint, crs_unit_factor, parse_crs

ORIGIN = LonLat(4.4777, 51.9244, 2.0)


def test_scene_crs_is_local_tmerc_and_matches_enu():
    frame = SceneFrame(ORIGIN)
    assert "Transverse Mercator" in frame.crs.to_wkt()
    # Exact ENU through ECEF + topocentric (independent pipeline): scene (x, y) = (e, n).
    enu = Transformer.from_pipeline(
        f"+proj=pipeline +step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lon_0={ORIGIN.lon_deg} +lat_0={ORIGIN.lat_deg} "
        "+h_0=0")
    for x, y in [(1000.0, 0.0), (0.0, 1000.0), (-700.0, 700.0)]:
        q = frame.to_lonlat(ScenePoint(x, y))
        e, n, _ = enu.transform(q.lon_deg, q.lat_deg, 0.0)
        assert abs(e - x) < 0.005 and abs(n - y) < 0.005


def test_round_trip_and_geodesic_distance():
    frame = SceneFrame(ORIGIN)
    p = ScenePoint(350.0, -420.0)
    q = frame.to_lonlat(p, 30.0)
    back = frame.from_lonlat(q)
    assert math.isclose(back.x_m, p.x_m, abs_tol=1e-6) and math.isclose(back.y_m, p.y_m,
                                                                         abs_tol=1e-6)
    assert q.alt_m == pytest.approx(32.0)
    _, _, dist = Geod(ellps="WGS84").inv(ORIGIN.lon_deg, ORIGIN.lat_deg, q.lon_deg, q.lat_deg)
    assert dist == pytest.approx(math.hypot(350, 420), abs=0.01)


def test_ned_at_scene_origin_is_y_x():
    frame = SceneFrame(ORIGIN)
    n = frame.to_ned(ScenePoint(10.0, 20.0), 15.0)
    assert n == LocalNED(20.0, 10.0, -15.0)


def test_ned_at_other_ekf_origin_matches_pyproj_aeqd():
    frame = SceneFrame(ORIGIN)
    ekf = LonLat(4.4800, 51.9250, 5.0)
    p = ScenePoint(120.0, -45.0)
    ned = frame.to_ned(p, 30.0, ekf)
    q = frame.to_lonlat(p)
    aeqd = CRS.from_proj4(f"+proj=aeqd +lat_0={ekf.lat_deg} +lon_0={ekf.lon_deg} +datum=WGS84")
    e, n = Transformer.from_crs("EPSG:4326", aeqd, always_xy=True).transform(q.lon_deg, q.lat_deg)
    assert ned.north_m == pytest.approx(n, abs=1e-6)
    assert ned.east_m == pytest.approx(e, abs=1e-6)
    assert ned.down_m == pytest.approx(-(2.0 + 30.0 - 5.0))
    back, alt = frame.from_ned(ned, ekf)
    assert back.x_m == pytest.approx(120.0, abs=1e-6) and alt == pytest.approx(30.0)
    # the EKF origin is ~160 m east and ~67 m north of the scene origin
    assert ned.east_m == pytest.approx(120.0 - 158.5, abs=2.0)


def test_bad_lonlat_and_crs():
    with pytest.raises(GeoError, match="longitude first"):
        LonLat(51.9, 200.0)
    with pytest.raises(GeoError, match="unknown CRS"):
        parse_crs("EPSG:999999")


def test_feet_unit_factor():
    assert crs_unit_factor(CRS.from_epsg(2227)) == pytest.approx(0.3048006096)  # US survey ft
    assert crs_unit_factor(CRS.from_epsg(32631)) == 1.0


@pytest.mark.parametrize("values", [(float("nan"), 10.0, 0.0), (4.0, float("inf"), 0.0),
                                    (4.0, 51.0, float("nan")), ("4", 51.0, 0.0),
                                    (True, 51.0, 0.0)])
def test_lonlat_refuses_non_finite_and_non_numbers(values):
    from geonav.errors import GeoError
    from geonav.geo import LonLat

    with pytest.raises(GeoError):
        LonLat(*values)
