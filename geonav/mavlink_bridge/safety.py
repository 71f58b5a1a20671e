"""Safety rules that never depend on the policy: geofence, altitude clamp, watchdogs,
and telling an autopilot's failsafe from an operator's mode change.

The geofence is a box from the scene bounds shrunk by a margin, optionally
intersected with a maximum distance from home. A setpoint outside it is
never sent (:class:`SetpointPump` checks every target), and the vehicle's
*measured* position is checked every cycle against the same fence widened
by ``overshoot_m`` (half the margin by default: a breach ends the flight
while the vehicle is still inside the scene). The watchdogs watch the
autopilot heartbeat, the position stream, the armed state and the mode:
from the first mode geonav commands, any other mode (set by an RC pilot, a
GCS or the autopilot's own failsafe) means someone else has control, and
the bridge stops commanding without fighting. Who changed it is decided by
:func:`attribute_mode_change`: the autopilot's failsafe when its HEARTBEAT shows
CRITICAL (or worse) or it just said why in a STATUSTEXT (battery, fence, GPS/EKF,
link...), an operator otherwise. A position stream that stops while the heartbeat
goes on, or a GPS fix lost in the air, is a position loss: geonav stops commanding
and leaves the vehicle to the autopilot's failsafe.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field

from geonav.errors import FlightError, SafetyViolation
from geonav.geo import ScenePoint
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.vehicle import Vehicle, VehicleState

TAKEOVER = "operator takeover"


class OperatorTakeover(SafetyViolation):
    """Someone else has control (an operator changed the flight mode): geonav sends
    nothing more."""


class AutopilotFailsafe(OperatorTakeover):
    """The autopilot's own failsafe changed the mode: geonav sends nothing more."""


class PositionLost(OperatorTakeover):
    """The position estimate (or the GPS fix) is gone while the link lives: geonav stops
    commanding and leaves the vehicle to the autopilot's failsafe."""


class BatteryLow(SafetyViolation):
    """The battery fell below ``--min-battery``: geonav ends the flight (LAND/RTL)."""


class LinkLost(FlightError):
    """The autopilot's heartbeat stopped (link or autopilot lost)."""


class PreflightRefused(FlightError):
    """geonav refused to start (vehicle state, home, plan) before arming anything."""


class PumpFault(SafetyViolation):
    """The setpoint pump stopped on an error or a stalled policy loop."""


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
    overshoot_m: float = 0.0

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

    def position_violation(self, p: ScenePoint) -> str | None:
        """Why a *measured* position breaches the fence widened by ``overshoot_m``, or None."""
        o = self.overshoot_m
        if not (
            self.xmin_m - o <= p.x_m <= self.xmax_m + o
            and self.ymin_m - o <= p.y_m <= self.ymax_m + o
        ):
            return (
                f"vehicle position ({p.x_m:.1f}, {p.y_m:.1f}) m breached the geofence box "
                f"x {self.xmin_m:.1f}..{self.xmax_m:.1f}, y {self.ymin_m:.1f}..{self.ymax_m:.1f} m "
                f"(+{o:.1f} m overshoot allowance)"
            )
        if self.home is not None and math.isfinite(self.max_distance_m):
            d = math.hypot(p.x_m - self.home.x_m, p.y_m - self.home.y_m)
            if d > self.max_distance_m + o:
                return (
                    f"vehicle position is {d:.1f} m from home "
                    f"(fence {self.max_distance_m:.1f} m + {o:.1f} m overshoot allowance)"
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

    The mode watch starts with the first mode geonav commands
    (:meth:`expect`): from then on the heartbeat must show that mode (or the
    one being commanded right now, :meth:`commanding`); anything else is an
    :class:`OperatorTakeover`. The armed watch starts with :meth:`engage`
    (airborne in the autonomy mode).

    Args:
        heartbeat_timeout_s: autopilot heartbeat older than this -> LinkLost.
        position_timeout_s: LOCAL_POSITION_NED older than this -> fault.
        autonomy_mode: the mode we fly in (``offboard`` / ``guided``).
    """

    heartbeat_timeout_s: float = 3.0
    position_timeout_s: float = 2.0
    autonomy_mode: str = "offboard"
    engaged: bool = False
    expected: frozenset[str] = field(default_factory=frozenset)
    pending: frozenset[str] = field(default_factory=frozenset)
    gps_required: bool = False
    """Watch the GPS fix too (set when the vehicle had a 3D fix before take-off)."""
    _no_fix_since: float | None = None

    def engage(self) -> None:
        """Start watching the armed state too (airborne in the autonomy mode)."""
        self.engaged = True
        self.expect(self.autonomy_mode)

    def commanding(self, *modes: str) -> None:
        """geonav is switching to ``modes`` now: accept them besides the expected ones."""
        self.pending = frozenset(modes)

    def expect(self, *modes: str) -> None:
        """geonav's mode change is confirmed: only ``modes`` are geonav's from now on."""
        self.expected = frozenset(modes)
        self.pending = frozenset()

    def error(self, s: VehicleState, *, check_armed: bool = True) -> FlightError | None:
        """The first rule ``s`` breaks as a typed error, or None."""
        if s.heartbeat_age_s > self.heartbeat_timeout_s:
            return LinkLost(
                f"link lost: no autopilot heartbeat for {s.heartbeat_age_s:.1f} s "
                f"(limit {self.heartbeat_timeout_s:.1f} s)"
            )
        if self.expected and s.mode not in self.expected | self.pending:
            return OperatorTakeover(
                f"{TAKEOVER}: mode changed to {s.mode!r} outside geonav "
                f"(geonav flies in {'/'.join(sorted(self.expected))}; by an RC pilot, "
                "a GCS or the autopilot's failsafe)"
            )
        lost = self._position_lost(s)
        if lost is not None:
            return lost
        if self.engaged and check_armed and not s.armed:
            return SafetyViolation("vehicle disarmed during autonomous flight")
        return None

    def _position_lost(self, s: VehicleState) -> FlightError | None:
        """A position stream that stopped while heartbeats still come (a dead link shows
        both stale: that is the link watchdog's), or the GPS fix lost in the air."""
        if s.position_age_s > self.position_timeout_s:
            if s.heartbeat_age_s + 0.5 < s.position_age_s:
                return PositionLost(
                    f"position lost: no LOCAL_POSITION_NED for {s.position_age_s:.1f} s "
                    "while the autopilot's heartbeat goes on (GPS or EKF)"
                )
            return None
        fix = s.gps_fix_type
        if self.gps_required and fix is not None and fix < 3:
            if self._no_fix_since is None:
                self._no_fix_since = time.monotonic()
            elif time.monotonic() - self._no_fix_since > self.position_timeout_s:
                return PositionLost(f"position lost: GPS fix type {fix} (no 3D fix) for "
                                    f"{time.monotonic() - self._no_fix_since:.1f} s")
        else:
            self._no_fix_since = None
        return None

    def violation(self, s: VehicleState) -> str | None:
        """The first rule ``s`` breaks, or None."""
        err = self.error(s)
        return None if err is None else str(err)

    def check(self, s: VehicleState, *, check_armed: bool = True) -> None:
        """Raise the first rule ``s`` breaks."""
        err = self.error(s, check_armed=check_armed)
        if err is not None:
            raise err


#: What an autopilot's failsafe says (PX4 commander/navigator, ArduCopter's failsafes):
#: battery, fence, GPS/EKF, radio and link loss, offboard loss, termination.
FAILSAFE_WORDS = re.compile(
    r"fail.?safe|battery|fence|gps|ekf|position (estimate )?lost|no position|navigation"
    r"|rc (lost|loss)|radio|data ?link|gcs (lost|failsafe)|offboard.*lost|terminat|crash",
    re.IGNORECASE,
)
#: Pre-arm complaints are no failsafe (an operator may switch modes while they repeat).
_NOT_FAILSAFE = re.compile(r"^(PreArm|Arm:|Preflight)", re.IGNORECASE)


def failsafe_evidence(s: VehicleState, within_s: float = 5.0) -> str:
    """Why ``s`` looks like the autopilot's own failsafe ('' when it does not): the
    HEARTBEAT's CRITICAL/EMERGENCY (both autopilots show it while a failsafe is active)
    and the failsafe's STATUSTEXT of the last ``within_s`` seconds."""
    said = [text for age, _, text in reversed(s.recent_texts)
            if age <= within_s and FAILSAFE_WORDS.search(text) and not _NOT_FAILSAFE.match(text)]
    parts = []
    if said:
        parts.append(f"autopilot says {said[0]!r}")
    if s.system_status in M.FAILSAFE_STATES:
        name = {5: "CRITICAL", 6: "EMERGENCY", 8: "FLIGHT_TERMINATION"}[s.system_status]
        parts.append(f"HEARTBEAT system status {name}")
    return "; ".join(parts)


def attribute_mode_change(vehicle: Vehicle, err: OperatorTakeover,
                          grace_s: float = 1.5) -> OperatorTakeover:
    """An :class:`AutopilotFailsafe` when the mode change was the autopilot's failsafe,
    else ``err`` (an operator's). Its STATUSTEXT can come just after the HEARTBEAT that
    shows the new mode, so the evidence is awaited ``grace_s`` seconds."""
    if isinstance(err, (AutopilotFailsafe, PositionLost)):
        return err
    deadline = time.monotonic() + grace_s
    while True:
        try:
            s = vehicle.state()
        except FlightError:
            return err
        why = failsafe_evidence(s)
        if why:
            return AutopilotFailsafe(
                f"autopilot failsafe: mode changed to {s.mode!r} by the autopilot ({why})"
            )
        if time.monotonic() > deadline:
            return err
        time.sleep(0.05)
