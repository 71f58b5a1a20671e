"""Frames and coordinate transforms: lon/lat <-> scene CRS <-> local NED.

The scene CRS is a local transverse Mercator (scale 1, false origin 0)
centred on the scene origin, so scene ``(x_m, y_m)`` is local east/north to
the millimetre within a few km (DESIGN.md "Frames"). The MAVLink local frame
is NED about the vehicle's EKF origin, which need not be the scene origin;
:meth:`SceneFrame.to_ned` converts through lon/lat. All pyproj transformers
are built with ``always_xy=True`` (lon, lat order), which avoids the EPSG:4326
lat/lon axis-order trap.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from functools import lru_cache

from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from geonav.errors import GeoError

WGS84 = "EPSG:4326"


@dataclass(frozen=True)
class LonLat:
    """A WGS 84 position: degrees, and altitude in metres (AMSL unless stated)."""

    lon_deg: float
    lat_deg: float
    alt_m: float = 0.0

    def __post_init__(self) -> None:
        values = (self.lon_deg, self.lat_deg, self.alt_m)
        if not all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in values):
            raise GeoError(f"lon/lat/alt must be numbers, got {values!r}")
        if not all(math.isfinite(v) for v in values):
            raise GeoError(f"lon/lat/alt {values} must be finite numbers (no nan/inf)")
        if not (-180.0 <= self.lon_deg <= 180.0) or not (-90.0 <= self.lat_deg <= 90.0):
            raise GeoError(
                f"lon/lat ({self.lon_deg}, {self.lat_deg}) is outside WGS 84 range; "
                "give longitude first, in degrees"
            )
        if abs(self.lat_deg) > 84.0:
            raise GeoError(f"latitude {self.lat_deg} is too close to a pole for a scene")
        if not ALT_RANGE_M[0] <= self.alt_m <= ALT_RANGE_M[1]:
            raise GeoError(f"altitude {self.alt_m} m is outside {ALT_RANGE_M[0]:g}.."
                           f"{ALT_RANGE_M[1]:g} m; give metres above mean sea level")


#: Altitudes (m AMSL) a position may have: the deepest ocean floor to the edge of space.
ALT_RANGE_M = (-11_000.0, 100_000.0)
#: Ground heights (m AMSL) a scene origin may have: the Dead Sea shore to above Everest.
GROUND_ALT_RANGE_M = (-500.0, 9_000.0)


@dataclass(frozen=True)
class ScenePoint:
    """A point in the scene CRS: metres east (x) and north (y) of the scene origin."""

    x_m: float
    y_m: float


@dataclass(frozen=True)
class LocalNED:
    """A point in a MAVLink local NED frame: metres north, east, down of the EKF origin."""

    north_m: float
    east_m: float
    down_m: float = 0.0


def scene_crs(origin: LonLat) -> CRS:
    """The local transverse Mercator CRS centred on ``origin`` (x east, y north, metres)."""
    return CRS.from_proj4(
        f"+proj=tmerc +lat_0={origin.lat_deg:.10f} +lon_0={origin.lon_deg:.10f} "
        "+k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs +type=crs"
    )


def _ned_crs(origin: LonLat) -> CRS:
    # PX4 and ArduPilot project lon/lat to their local frame with an azimuthal
    # equidistant projection about the EKF origin; do the same.
    return CRS.from_proj4(
        f"+proj=aeqd +lat_0={origin.lat_deg:.10f} +lon_0={origin.lon_deg:.10f} "
        "+x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs +type=crs"
    )


def parse_crs(value: object) -> CRS:
    """A pyproj CRS from WKT, an EPSG code, a PROJ string or a CRS; GeoError if unknown."""
    if isinstance(value, CRS):
        return value
    try:
        return CRS.from_user_input(value)
    except CRSError as err:
        raise GeoError(f"unknown CRS {str(value)[:80]!r}: give WKT, 'EPSG:nnnn' or PROJ") from err


@lru_cache(maxsize=64)
def _transformer(src_wkt: str, dst_wkt: str) -> Transformer:
    return Transformer.from_crs(CRS.from_wkt(src_wkt), CRS.from_wkt(dst_wkt), always_xy=True)


def transformer(src: CRS, dst: CRS) -> Transformer:
    """A cached pyproj Transformer in (x=lon/east, y=lat/north) order."""
    return _transformer(src.to_wkt(), dst.to_wkt())


def crs_unit_factor(crs: CRS) -> float:
    """Metres per unit of the CRS's first axis (0.3048 for international feet)."""
    axis = crs.axis_info[0]
    factor = axis.unit_conversion_factor
    if factor is None or factor <= 0:
        raise GeoError(f"CRS {crs.name!r} has no usable linear unit")
    return float(factor)


class SceneFrame:
    """Transforms between WGS 84, the scene CRS and NED about any EKF origin.

    Args:
        origin: the scene origin; its ``alt_m`` is the ground height AMSL there.
    """

    def __init__(self, origin: LonLat) -> None:
        self.origin = origin
        self.crs = scene_crs(origin)
        self._wgs84 = CRS.from_user_input(WGS84)

    @classmethod
    def from_wkt(cls, wkt: str, origin: LonLat) -> SceneFrame:
        frame = cls(origin)
        frame.crs = parse_crs(wkt)
        return frame

    def to_lonlat(self, p: ScenePoint, alt_m: float = 0.0) -> LonLat:
        """Scene point (and altitude above the scene origin) -> WGS 84."""
        lon, lat = transformer(self.crs, self._wgs84).transform(p.x_m, p.y_m)
        return LonLat(float(lon), float(lat), self.origin.alt_m + alt_m)

    def from_lonlat(self, q: LonLat) -> ScenePoint:
        """WGS 84 -> scene point (altitude ignored)."""
        x, y = transformer(self._wgs84, self.crs).transform(q.lon_deg, q.lat_deg)
        if not (math.isfinite(x) and math.isfinite(y)):
            raise GeoError(f"{q} cannot be projected into the scene CRS")
        return ScenePoint(float(x), float(y))

    def to_ned(self, p: ScenePoint, alt_m: float, ekf_origin: LonLat | None = None) -> LocalNED:
        """Scene point at ``alt_m`` above the scene origin's ground -> NED at ``ekf_origin``.

        With no ``ekf_origin`` (or one equal to the scene origin) NED is
        (north, east) = scene (y, x) exactly; otherwise the point goes through
        lon/lat into an azimuthal equidistant frame about the EKF origin.
        """
        if ekf_origin is None or ekf_origin == self.origin:
            return LocalNED(p.y_m, p.x_m, -alt_m)
        q = self.to_lonlat(p, alt_m)
        east, north = transformer(self._wgs84, _ned_crs(ekf_origin)).transform(
            q.lon_deg, q.lat_deg
        )
        return LocalNED(float(north), float(east), -(q.alt_m - ekf_origin.alt_m))

    def from_ned(self, n: LocalNED, ekf_origin: LonLat | None = None) -> tuple[ScenePoint, float]:
        """NED at ``ekf_origin`` -> (scene point, altitude above the scene origin's ground)."""
        if ekf_origin is None or ekf_origin == self.origin:
            return ScenePoint(n.east_m, n.north_m), -n.down_m
        lon, lat = transformer(_ned_crs(ekf_origin), self._wgs84).transform(n.east_m, n.north_m)
        alt_amsl = ekf_origin.alt_m - n.down_m
        p = self.from_lonlat(LonLat(float(lon), float(lat)))
        return p, alt_amsl - self.origin.alt_m
