"""Lattice actions -> scene targets -> NED setpoints at the vehicle's EKF origin.

Actions follow DESIGN.md "Frames": 0 forward = +y (north), 1 right = +x
(east), 2 left = -x, 3 backward = -y, one lattice step each, heading fixed
north. Each new target is the previous *target* plus one step (not the
measured position), so tracking error never accumulates. Horizontal
positions go scene -> lon/lat (exact, :mod:`geonav.geo`) -> NED about the EKF
origin with the autopilot's own formula (:mod:`geonav.mavlink_bridge.frames`:
ArduPilot flat earth, PX4 azimuthal equidistant, each on its own sphere);
altitude is held relative to the take-off point (home), because the GPS
altitude of the EKF origin and the scene's ground altitude can disagree by
metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from geonav.errors import FlightError
from geonav.geo import LocalNED, LonLat, SceneFrame, ScenePoint
from geonav.mavlink_bridge.frames import LocalFrame, local_frame

#: (east cells, north cells) per action.
ACTION_STEPS: dict[int, tuple[int, int]] = {0: (0, 1), 1: (1, 0), 2: (-1, 0), 3: (0, -1)}
ACTION_NAMES = {0: "forward", 1: "right", 2: "left", 3: "backward"}


def step_scene(p: ScenePoint, action: int, step_m: float) -> ScenePoint:
    """The scene point one lattice step from ``p`` in the direction of ``action``."""
    if action not in ACTION_STEPS:
        raise FlightError(f"policy returned action {action!r}; expected 0..3")
    dx, dy = ACTION_STEPS[action]
    return ScenePoint(p.x_m + dx * step_m, p.y_m + dy * step_m)


@dataclass
class TargetPlanner:
    """Converts scene points to NED setpoints for one vehicle.

    Args:
        frame: the scene's frame (scene CRS at the scene origin).
        ekf_origin: the vehicle's EKF origin (GPS_GLOBAL_ORIGIN).
        home_down_m: the take-off point's down coordinate in the EKF frame.
        alt_m: flight altitude above the take-off point, metres.
        yaw_deg: the fixed heading (0 = north, so image up = north as in training).
        autopilot: ``"px4"`` or ``"ardupilot"``: whose local-frame formula to use.
    """

    frame: SceneFrame
    ekf_origin: LonLat
    home_down_m: float
    alt_m: float
    yaw_deg: float = 0.0
    autopilot: str = field(default="", kw_only=True)

    def __post_init__(self) -> None:
        if not self.autopilot:
            raise FlightError("TargetPlanner needs autopilot='px4' or 'ardupilot' (its NED frame)")
        self._local: LocalFrame = local_frame(self.autopilot, self.ekf_origin)

    def to_ned(self, p: ScenePoint) -> LocalNED:
        """Scene point at the flight altitude -> NED about the EKF origin."""
        north, east = self._local.to_ne(self.frame.to_lonlat(p, 0.0))
        return LocalNED(north, east, self.home_down_m - self.alt_m)

    def to_scene(self, ned: LocalNED) -> tuple[ScenePoint, float]:
        """NED about the EKF origin -> (scene point, altitude above the take-off point)."""
        lon, lat = self._local.to_lonlat(ned.north_m, ned.east_m)
        return self.frame.from_lonlat(LonLat(lon, lat)), self.home_down_m - ned.down_m

    def next_target(self, previous: ScenePoint, action: int, step_m: float) -> ScenePoint:
        """Previous target plus one lattice step."""
        return step_scene(previous, action, step_m)
