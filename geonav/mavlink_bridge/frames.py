"""Each autopilot's own lon/lat <-> local NED conversion about its EKF origin.

The local frame of ``LOCAL_POSITION_NED`` and ``SET_POSITION_TARGET_LOCAL_NED``
is not exact ellipsoidal metres: each autopilot converts with its own formula,
and geonav must use the same one or its idea of the vehicle's position drifts
from the autopilot's (measured on ArduCopter SITL with the ellipsoidal
conversion: 0.36 % of the distance north of the EKF origin, issue 14).

* ArduPilot (``libraries/AP_Common/Location.cpp``,
  ``Location::get_vector_xy_from_origin_NE`` and ``Location::offset``): flat
  earth on a sphere of ``RADIUS_OF_EARTH`` = 6,378,100 m; north = dlat * R,
  east = dlon * R * cos(lat of the EKF origin) (angles in radians).
* PX4 (``src/lib/geo/geo.cpp``, ``MapProjection::project`` / ``reproject``):
  azimuthal equidistant projection on a sphere of ``CONSTANTS_RADIUS_OF_EARTH``
  = 6,371,000 m about the reference (EKF origin).

The formulas are re-derived here in double precision (the autopilots use
float32 for the metres, a centimetre at 1 km, and ArduPilot rounds lat/lon to
1e-7 degrees, about a centimetre). The emulator uses the same classes, so
its tests see the frame the real autopilot would use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from geonav.errors import FlightError
from geonav.geo import LonLat

#: ArduPilot ``RADIUS_OF_EARTH`` (``libraries/AP_Math/definitions.h``), metres.
ARDUPILOT_EARTH_RADIUS_M = 6_378_100.0
#: PX4 ``CONSTANTS_RADIUS_OF_EARTH`` (``src/lib/geo/geo.h``), metres.
PX4_EARTH_RADIUS_M = 6_371_000.0


class LocalFrame(Protocol):
    """Horizontal lon/lat <-> (north, east) metres about an EKF origin."""

    @property
    def origin(self) -> LonLat:
        """The EKF origin."""

    def to_ne(self, q: LonLat) -> tuple[float, float]:
        """(north_m, east_m) of ``q``."""

    def to_lonlat(self, north_m: float, east_m: float) -> tuple[float, float]:
        """(lon_deg, lat_deg) of a local point."""


@dataclass(frozen=True)
class ArduPilotFrame:
    """ArduPilot's flat-earth frame about ``origin`` (see the module docstring)."""

    origin: LonLat
    radius_m: float = ARDUPILOT_EARTH_RADIUS_M

    def _lon_scale(self) -> float:
        # Location::longitude_scale(): cos(lat), constrained to [0.01, 1].
        return min(max(math.cos(math.radians(self.origin.lat_deg)), 0.01), 1.0)

    def to_ne(self, q: LonLat) -> tuple[float, float]:
        dlat = math.radians(q.lat_deg - self.origin.lat_deg)
        dlon = math.radians(_wrap180(q.lon_deg - self.origin.lon_deg))
        return dlat * self.radius_m, dlon * self.radius_m * self._lon_scale()

    def to_lonlat(self, north_m: float, east_m: float) -> tuple[float, float]:
        lat = self.origin.lat_deg + math.degrees(north_m / self.radius_m)
        lon = self.origin.lon_deg + math.degrees(east_m / (self.radius_m * self._lon_scale()))
        return _wrap180(lon), lat


@dataclass(frozen=True)
class PX4Frame:
    """PX4's azimuthal equidistant projection about ``origin`` (see the module docstring)."""

    origin: LonLat
    radius_m: float = PX4_EARTH_RADIUS_M

    def to_ne(self, q: LonLat) -> tuple[float, float]:
        lat0, lon0 = math.radians(self.origin.lat_deg), math.radians(self.origin.lon_deg)
        lat, lon = math.radians(q.lat_deg), math.radians(q.lon_deg)
        sin0, cos0 = math.sin(lat0), math.cos(lat0)
        cos_dlon = math.cos(lon - lon0)
        arg = min(max(sin0 * math.sin(lat) + cos0 * math.cos(lat) * cos_dlon, -1.0), 1.0)
        c = math.acos(arg)
        k = c / math.sin(c) if c > 0 else 1.0
        north = k * (cos0 * math.sin(lat) - sin0 * math.cos(lat) * cos_dlon) * self.radius_m
        east = k * math.cos(lat) * math.sin(lon - lon0) * self.radius_m
        return north, east

    def to_lonlat(self, north_m: float, east_m: float) -> tuple[float, float]:
        lat0, lon0 = math.radians(self.origin.lat_deg), math.radians(self.origin.lon_deg)
        x, y = north_m / self.radius_m, east_m / self.radius_m
        c = math.hypot(x, y)
        if c == 0:
            return self.origin.lon_deg, self.origin.lat_deg
        sin_c, cos_c = math.sin(c), math.cos(c)
        sin0, cos0 = math.sin(lat0), math.cos(lat0)
        lat = math.asin(min(max(cos_c * sin0 + x * sin_c * cos0 / c, -1.0), 1.0))
        lon = lon0 + math.atan2(y * sin_c, c * cos0 * cos_c - x * sin0 * sin_c)
        return _wrap180(math.degrees(lon)), math.degrees(lat)


def local_frame(autopilot: str, origin: LonLat) -> LocalFrame:
    """The local frame ``autopilot`` (``"px4"`` or ``"ardupilot"``) uses about ``origin``."""
    if autopilot == "ardupilot":
        return ArduPilotFrame(origin)
    if autopilot == "px4":
        return PX4Frame(origin)
    raise FlightError(f"no local-frame formula for autopilot {autopilot!r}: use px4 or ardupilot")


def _wrap180(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0
