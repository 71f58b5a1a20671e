"""Safety rules that never depend on the policy: geofence, altitude clamp, watchdogs.

The geofence is a box from the scene bounds shrunk by a margin, optionally
intersected with a maximum distance from home. A setpoint outside it is
never sent (:class:`SetpointPump` checks every target). The watchdogs watch
the autopilot heartbeat, the position stream, the armed state and the mode:
a mode other than the autonomy mode once autonomy started means an operator
(RC or GCS) took over, and the bridge stops commanding without fighting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from geonav.errors import SafetyViolation
from geonav.geo import ScenePoint
from geonav.mavlink_bridge.vehicle import VehicleState

TAKEOVER = "operator takeover"


@dataclass(frozen=True)
class Geofence:
    """A software fence in scene metres.

    Args:
        xmin_m, ymin_m, xmax_m, ymax_m: allowed box (scene CRS).
        home: take-off point (scene CRS), for ``max_distance_m``.
        max_distance_m: maximum horizontal distance from home (inf = off).
        min_alt_m, max_alt_m: allowed altitude above the take-off point.
    """

    xmin_m: float
    ymin_m: float
    xmax_m: float
    ymax_m: float
    home: ScenePoint | None = None
    max_distance_m: float = math.inf
    min_alt_m: float = 2.0
    max_alt_m: float = 120.0

    @classmethod
    def from_bounds(
        cls,
        bounds_m: tuple[float, float, float, float],
        margin_m: float = 0.0,
        **kwargs: object,
    ) -> Geofence:
        """A fence from scene bounds ``(xmin, ymin, xmax, ymax)`` shrunk by ``margin_m``."""
        xmin, ymin, xmax, ymax = bounds_m
        return cls(xmin + margin_m, ymin + margin_m, xmax - margin_m, ymax - margin_m, **kwargs)  # type: ignore[arg-type]

    def violation(self, p: ScenePoint) -> str | None:
        """Why ``p`` is outside the fence, or None when inside."""
        if not (self.xmin_m <= p.x_m <= self.xmax_m and self.ymin_m <= p.y_m <= self.ymax_m):
            return (
                f"scene point ({p.x_m:.1f}, {p.y_m:.1f}) m is outside the geofence box "
                f"x {self.xmin_m:.1f}..{self.xmax_m:.1f}, y {self.ymin_m:.1f}..{self.ymax_m:.1f} m"
            )
        if self.home is not None and math.isfinite(self.max_distance_m):
            d = math.hypot(p.x_m - self.home.x_m, p.y_m - self.home.y_m)
            if d > self.max_distance_m:
                return (
                    f"scene point ({p.x_m:.1f}, {p.y_m:.1f}) m is {d:.1f} m from home "
                    f"(max {self.max_distance_m:.1f} m)"
                )
        return None

    def contains(self, p: ScenePoint) -> bool:
        """Whether ``p`` is inside."""
        return self.violation(p) is None

    def check(self, p: ScenePoint) -> None:
        """Raise SafetyViolation when ``p`` is outside."""
        reason = self.violation(p)
        if reason is not None:
            raise SafetyViolation(reason)

    def clamp_alt(self, alt_m: float) -> float:
        """Altitude clamped into the fence's altitude band."""
        return float(min(max(alt_m, self.min_alt_m), self.max_alt_m))


@dataclass
class Watchdog:
    """Link, position and mode watchdogs.

    Args:
        heartbeat_timeout_s: autopilot heartbeat older than this -> fault.
        position_timeout_s: LOCAL_POSITION_NED older than this -> fault.
        autonomy_mode: the mode we fly in (``offboard`` / ``guided``).
    """

    heartbeat_timeout_s: float = 3.0
    position_timeout_s: float = 2.0
    autonomy_mode: str = "offboard"
    engaged: bool = False

    def engage(self) -> None:
        """Start watching mode and armed state (after take-off in the autonomy mode)."""
        self.engaged = True

    def violation(self, s: VehicleState) -> str | None:
        """The first rule ``s`` breaks, or None."""
        if s.heartbeat_age_s > self.heartbeat_timeout_s:
            return (
                f"autopilot heartbeat lost for {s.heartbeat_age_s:.1f} s "
                f"(limit {self.heartbeat_timeout_s:.1f} s)"
            )
        if s.position_age_s > self.position_timeout_s:
            return (
                f"LOCAL_POSITION_NED stream lost for {s.position_age_s:.1f} s "
                f"(limit {self.position_timeout_s:.1f} s)"
            )
        if self.engaged:
            if s.mode != self.autonomy_mode:
                return f"{TAKEOVER}: mode changed to {s.mode!r} outside geonav"
            if not s.armed:
                return "vehicle disarmed during autonomous flight"
        return None
