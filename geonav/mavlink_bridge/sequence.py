"""Flight phases on top of a Vehicle, each gated on telemetry with a timeout.

Connect -> heartbeat in STANDBY -> telemetry requested -> EKF origin and
position known -> home inside the fence -> take-off (PX4: stream setpoints,
OFFBOARD, arm, climb by setpoint; ArduPilot: GUIDED, arm, NAV_TAKEOFF within
the auto-disarm delay) -> ... -> LAND or RTL -> disarmed. Modes are
re-checked on the heartbeat after every change (LAND and RTL included),
because an autopilot that is still booting can ACK a mode change and undo
it. A mode that neither geonav asked for nor the vehicle had before is
someone else's choice: geonav raises :class:`OperatorTakeover` at once and
re-sends nothing. On a dead link LAND/RTL is retried for
``Timeouts.dead_link_s`` only; then the autopilot's failsafe must act.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from geonav.errors import CommandRejected, FlightError, FlightTimeout
from geonav.geo import LocalNED, LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.pump import SetpointPump
from geonav.mavlink_bridge.safety import LinkLost, OperatorTakeover, Watchdog
from geonav.mavlink_bridge.vehicle import Vehicle, VehicleState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Timeouts:
    """Seconds allowed for each phase (wall clock).

    Attributes:
        connect_s: first autopilot heartbeat.
        ready_s: HEARTBEAT system_status STANDBY (boot finished).
        position_s: EKF origin and LOCAL_POSITION_NED present.
        command_s: one COMMAND_ACK (split over retries).
        mode_s: a mode change visible in the heartbeat.
        arm_s: arming retried until this deadline (PreArm checks take ~25 s in SITL).
        arm_retry_s: pause between arming attempts.
        takeoff_s: reach the flight altitude.
        landing_s: land (or return and land) and disarm.
        dead_link_s: with no autopilot heartbeat, how long LAND/RTL is retried
            (and disarm awaited) before geonav gives up and leaves it to the
            autopilot's own failsafe.
    """

    connect_s: float = 30.0
    ready_s: float = 60.0
    position_s: float = 90.0
    command_s: float = 3.0
    mode_s: float = 5.0
    arm_s: float = 60.0
    arm_retry_s: float = 1.0
    takeoff_s: float = 60.0
    landing_s: float = 180.0
    dead_link_s: float = 12.0


def wait_until(
    vehicle: Vehicle,
    predicate: Callable[[VehicleState], bool],
    timeout_s: float,
    what: str,
    poll_s: float = 0.05,
    check: Callable[[], None] | None = None,
) -> VehicleState:
    """Poll the vehicle state until ``predicate`` holds.

    Raises:
        FlightTimeout: not within ``timeout_s``; the message names ``what`` and the last state.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        s = vehicle.state()
        if predicate(s):
            return s
        if check is not None:
            check()
        if time.monotonic() > deadline:
            raise FlightTimeout(
                f"{what}: not seen within {timeout_s:.1f} s (mode {s.mode}, armed {s.armed}, "
                f"status {s.system_status}, position {s.position}, origin {s.origin}"
                + (f", autopilot says {s.last_statustext!r})" if _fresh_text(s) else ")")
            )
        time.sleep(poll_s)


def wait_ready(vehicle: Vehicle, t: Timeouts) -> VehicleState:
    """Wait until the autopilot left BOOT (HEARTBEAT system_status STANDBY or ACTIVE).

    PX4 reports STANDBY only while its pre-flight checks pass, and UNINIT
    otherwise, also long after boot (seen on PX4 SIH after a landing:
    "Preflight: GPS Vertical Pos Drift too high" for minutes): the timeout
    then says so instead of naming the number.
    """
    try:
        return wait_until(
            vehicle,
            lambda s: s.system_status in (M.MAV_STATE_STANDBY, M.MAV_STATE_ACTIVE),
            t.ready_s,
            "autopilot ready (HEARTBEAT system_status STANDBY)",
        )
    except FlightTimeout as err:
        s = vehicle.state()
        if s.autopilot == M.PX4 and s.system_status == M.MAV_STATE_UNINIT:
            text = _fresh_text(s)
            raise FlightTimeout(
                f"PX4's pre-flight checks did not pass within {t.ready_s:.0f} s (HEARTBEAT "
                f"system_status UNINIT, mode {s.mode}, armed {s.armed}"
                + (f", autopilot says {text!r}" if text else "")
                + "); see its health report in QGroundControl, or restart the SITL"
            ) from err
        raise


def wait_position(vehicle: Vehicle, t: Timeouts, set_origin: LonLat | None = None) -> VehicleState:
    """Wait for the EKF origin and LOCAL_POSITION_NED; optionally set the origin first."""
    if set_origin is not None:
        vehicle.set_origin(set_origin)
    deadline = time.monotonic() + t.position_s
    requested = time.monotonic()
    while True:
        s = vehicle.state()
        if s.origin is not None and s.position is not None and s.position_age_s < 1.0:
            return s
        if time.monotonic() > deadline:
            missing = "GPS_GLOBAL_ORIGIN" if s.origin is None else "LOCAL_POSITION_NED"
            raise FlightTimeout(
                f"no {missing} within {t.position_s:.0f} s: the vehicle has no position "
                "estimate (GPS fix, or SET_GPS_GLOBAL_ORIGIN for GPS-less vehicles: --set-origin)"
            )
        if s.origin is None and time.monotonic() - requested > 2.0:
            # Autopilots send GPS_GLOBAL_ORIGIN once when it is set; ask again.
            requested = time.monotonic()
            if set_origin is not None:
                vehicle.set_origin(set_origin)
            _request_origin(vehicle, t)
        time.sleep(0.05)


def _request_origin(vehicle: Vehicle, t: Timeouts) -> None:
    request = getattr(vehicle, "request_message", None)
    if request is None:
        return
    try:
        request("GPS_GLOBAL_ORIGIN", t.command_s)
    except FlightError as err:
        log.debug("GPS_GLOBAL_ORIGIN request: %s", err)


def _fresh_text(s: VehicleState, max_age_s: float = 10.0) -> str:
    """The autopilot's last STATUSTEXT if it is recent, else ''."""
    return s.last_statustext if s.statustext_age_s <= max_age_s else ""


def _takeover(mode: str, wanted: tuple[str, ...]) -> OperatorTakeover:
    return OperatorTakeover(
        f"operator takeover: mode changed to {mode!r} outside geonav while it was switching "
        f"to {'/'.join(wanted)} (by an RC pilot, a GCS or the autopilot's failsafe)"
    )


def confirm_mode(
    vehicle: Vehicle,
    wanted: tuple[str, ...],
    previous: str,
    timeout_s: float,
    check: Callable[[], None] | None = None,
) -> bool:
    """Wait until the heartbeat shows one of ``wanted``; False when it still shows ``previous``.

    Raises:
        OperatorTakeover: the heartbeat shows a third mode (someone else's choice).
    """
    deadline = time.monotonic() + timeout_s
    while True:
        s = vehicle.state()
        if s.mode in wanted:
            return True
        if s.mode != previous:
            raise _takeover(s.mode, wanted)
        if check is not None:
            check()
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)


def set_mode_confirmed(
    vehicle: Vehicle,
    name: str,
    t: Timeouts,
    alive: Callable[[], None] | None = None,
    watchdog: Watchdog | None = None,
) -> None:
    """Change mode, then confirm it on the heartbeat; retry a rejected or undone change.

    A change is re-sent only while the heartbeat still shows the mode the
    vehicle had before; any third mode is someone else's and ends geonav's
    control (:class:`OperatorTakeover`).

    Raises:
        CommandRejected: the autopilot kept refusing until ``t.mode_s`` ran out.
        FlightTimeout: accepted but never shown by the heartbeat.
        OperatorTakeover: someone else changed the mode meanwhile.
    """
    previous = vehicle.state().mode
    if previous == name:
        if watchdog is not None:
            watchdog.expect(name)
        return
    if watchdog is not None:
        watchdog.commanding(name)
    deadline = time.monotonic() + t.mode_s
    last: FlightError | None = None
    while time.monotonic() < deadline:
        if alive is not None:
            alive()
        mode_now = vehicle.state().mode
        if mode_now not in (previous, name):
            raise _takeover(mode_now, (name,))
        try:
            vehicle.set_mode(name, t.command_s)
        except CommandRejected as err:
            last = err
            time.sleep(0.3)
            continue
        if confirm_mode(vehicle, (name,), previous, min(1.5, t.mode_s), alive):
            time.sleep(0.1)
            s = vehicle.state()
            if s.mode == name:
                if watchdog is not None:
                    watchdog.expect(name)
                return
            if s.mode != previous:
                raise _takeover(s.mode, (name,))
        last = FlightTimeout(f"mode {name} not shown by the heartbeat")
    if isinstance(last, CommandRejected):
        raise CommandRejected(f"mode {name} refused for {t.mode_s:.0f} s: {last}") from last
    raise FlightTimeout(
        f"mode {name} not confirmed by the heartbeat within {t.mode_s:.0f} s"
    ) from last


def arm_with_retry(vehicle: Vehicle, t: Timeouts, alive: Callable[[], None] | None = None) -> None:
    """Arm, retrying while pre-arm checks fail, until ``t.arm_s``.

    ``alive`` runs before every attempt and while waiting (it ticks the pump
    and raises on a takeover or a lost link, which stops the retries at once).

    Raises:
        CommandRejected: never armed; the message carries the last reason.
    """
    deadline = time.monotonic() + t.arm_s
    attempts = 0
    last = ""
    while True:
        attempts += 1
        if alive is not None:
            alive()
        try:
            vehicle.arm(t.command_s)
            wait_until(
                vehicle, lambda s: s.armed, t.mode_s, "armed state in HEARTBEAT", check=alive
            )
            log.info("armed after %d attempt(s)", attempts)
            return
        except CommandRejected as err:
            last = str(err)
            log.info("arming attempt %d refused: %s", attempts, err)
        if time.monotonic() + t.arm_retry_s > deadline:
            raise CommandRejected(
                f"vehicle refused to arm for {t.arm_s:.0f} s ({attempts} attempts); "
                f"last reason: {last}"
            )
        _sleep_alive(t.arm_retry_s, alive)


def take_off(
    vehicle: Vehicle,
    pump: SetpointPump,
    climb_target: LocalNED,
    yaw_deg: float,
    alt_tolerance_m: float,
    t: Timeouts,
    watchdog: Watchdog | None = None,
    check: Callable[[], None] | None = None,
    on_armed: Callable[[], None] | None = None,
) -> None:
    """Arm and climb to ``climb_target`` (NED about the EKF origin) in the autonomy mode.

    PX4: the pump streams the climb target before OFFBOARD (main mode 6), then
    arm; the setpoint itself lifts the vehicle. ArduPilot: GUIDED (4), arm,
    then MAV_CMD_NAV_TAKEOFF with the altitude above home straight away (it
    disarms after DISARM_DELAY otherwise); the pump starts once airborne.
    ``watchdog`` (mode and link) and ``check`` (e.g. the position fence) run
    in every wait, so an operator's mode change during arming or the climb
    stops geonav at once.
    """
    s = vehicle.state()
    home_down = s.position.down_m if s.position is not None else 0.0
    alt_above_home = home_down - climb_target.down_m

    def alive() -> None:
        pump.tick()
        pump.raise_if_fault()
        if watchdog is not None:
            watchdog.check(vehicle.state(), check_armed=False)
        if check is not None:
            check()

    if vehicle.autopilot == M.PX4:
        pump.set_target(climb_target, yaw_deg)
        pump.start()
        # PX4 enables OFFBOARD only after the stream ran for a while.
        _sleep_alive(min(1.2, t.mode_s / 2), pump.tick)
        set_mode_confirmed(vehicle, "offboard", t, alive=pump.tick, watchdog=watchdog)
        arm_with_retry(vehicle, t, alive=alive)
        if on_armed is not None:
            on_armed()
    else:
        set_mode_confirmed(vehicle, "guided", t, watchdog=watchdog)
        arm_with_retry(vehicle, t, alive=alive)
        if on_armed is not None:
            on_armed()
        alive()
        vehicle.takeoff(alt_above_home, t.command_s)
        pump.set_target(climb_target, yaw_deg)

    def reached(st: VehicleState) -> bool:
        return (
            st.position is not None
            and abs(st.position.down_m - climb_target.down_m) < alt_tolerance_m
        )

    def guard() -> None:
        alive()
        st = vehicle.state()
        if not st.armed:
            raise FlightError(
                f"vehicle disarmed during take-off (mode {st.mode})"
                + (f"; autopilot says {_fresh_text(st)!r}" if _fresh_text(st) else "")
            )

    if vehicle.autopilot != M.PX4:
        # Wait until clearly airborne before streaming position targets.
        wait_until(
            vehicle,
            lambda st: (
                st.position is not None
                and home_down - st.position.down_m > min(1.0, alt_above_home / 2)
            ),
            t.takeoff_s,
            "climb after NAV_TAKEOFF",
            check=guard,
        )
        pump.start()
    wait_until(vehicle, reached, t.takeoff_s, f"take-off to {alt_above_home:.1f} m", check=guard)


def _sleep_alive(seconds: float, alive: Callable[[], None] | None) -> None:
    end = time.monotonic() + seconds
    while True:
        if alive is not None:
            alive()
        left = end - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(0.1, left))


#: the modes each end action may show on the heartbeat (RTL ends in a landing).
END_MODES = {"land": ("land",), "rtl": ("rtl", "land")}


def end_flight(
    vehicle: Vehicle,
    end: str,
    t: Timeouts,
    watchdog: Watchdog | None = None,
    sample: Callable[[VehicleState], None] | None = None,
) -> VehicleState:
    """LAND or RTL (MAV_CMD_NAV_LAND / _RETURN_TO_LAUNCH), confirmed on the heartbeat; disarm.

    The command is resent while it gets no ACK or the heartbeat does not show
    it: up to ``t.landing_s`` while the autopilot is heard, but only
    ``t.dead_link_s`` while its heartbeat is missing. While waiting for the
    disarm, a mode other than LAND/RTL is an operator's choice: geonav stops.

    Raises:
        LinkLost: no heartbeat for ``t.dead_link_s``; the autopilot's failsafe must act.
        OperatorTakeover: someone else changed the mode during the landing.
        FlightTimeout: still armed after ``t.landing_s``.
        CommandRejected: the autopilot kept refusing LAND/RTL.
    """
    wanted = END_MODES[end]
    hb_limit = watchdog.heartbeat_timeout_s if watchdog is not None else 3.0
    start = time.monotonic()
    deadline = start + t.landing_s
    if watchdog is not None:
        watchdog.commanding(*wanted)
    previous = vehicle.state().mode
    last: FlightError | None = None

    def poll() -> tuple[VehicleState, bool]:
        """The state, and whether the vehicle is down (disarmed on a live link)."""
        s = vehicle.state()
        if sample is not None:
            sample(s)
        if not s.armed and s.heartbeat_age_s <= hb_limit:
            return s, True
        if s.heartbeat_age_s > hb_limit and time.monotonic() - start > t.dead_link_s:
            raise LinkLost(
                f"link lost: no autopilot heartbeat for {s.heartbeat_age_s:.0f} s; "
                f"{end.upper()} tried for {t.dead_link_s:.0f} s; the autopilot's own "
                "failsafe must act"
            )
        return s, False

    while True:
        s, down = poll()
        if down:
            return s
        if time.monotonic() > deadline:
            raise last or FlightTimeout(f"{end.upper()} not confirmed within {t.landing_s:.0f} s")
        if s.mode in wanted:
            break
        if s.mode != previous and s.heartbeat_age_s <= hb_limit:
            raise _takeover(s.mode, wanted)
        try:
            if end == "rtl":
                vehicle.return_to_launch(t.command_s)
            else:
                vehicle.land(t.command_s)
        except (FlightTimeout, CommandRejected) as err:
            last = err
            log.info("%s not acknowledged (%s); retrying", end.upper(), err)
            time.sleep(0.2)
            continue
        if confirm_mode(vehicle, wanted, previous, min(2.0, t.mode_s)):
            break
        last = FlightTimeout(f"{end.upper()} accepted but not shown by the heartbeat")
    if watchdog is not None:
        watchdog.expect(*wanted)
    log.info("%s confirmed on the heartbeat; waiting for disarm", end.upper())
    while True:
        s, down = poll()
        if down:
            return s
        if s.armed and s.mode not in wanted and s.heartbeat_age_s <= hb_limit:
            raise OperatorTakeover(
                f"operator takeover during {end.upper()}: mode changed to {s.mode!r} "
                "outside geonav; geonav sends nothing more"
            )
        if time.monotonic() > deadline:
            raise FlightTimeout(
                f"{end} and disarm: still armed after {t.landing_s:.0f} s (mode {s.mode})"
            )
        time.sleep(0.1)


def horizontal_distance_m(a: LocalNED, b: LocalNED) -> float:
    """Horizontal distance between two NED points."""
    return math.hypot(a.north_m - b.north_m, a.east_m - b.east_m)
