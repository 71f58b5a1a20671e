"""The MAVSDK backend (native ``mavsdk>=4``: ``from mavsdk.asyncio import Mavsdk``).

MAVSDK's asyncio API runs on an event loop in a thread of our own; the
synchronous :class:`~geonav.mavlink_bridge.vehicle.Vehicle` methods submit
coroutines to it and wait with a timeout. Plugins used:

* ``TelemetryAsync``: LOCAL_POSITION_NED (``subscribe_position_velocity_ned``
  with ``set_rate_position_velocity_ned``, which sends
  SET_MESSAGE_INTERVAL, so ArduPilot streams it), home, EKF origin
  (``get_gps_global_origin``), STATUSTEXT, landed state.
* ``ActionAsync``: arm, disarm, land, return to launch, set_gps_global_origin.
* ``MavlinkDirectAsync``: the HEARTBEAT itself (``system_status`` and the raw
  ``custom_mode``, which MAVSDK's telemetry does not expose; we must gate on
  STANDBY), DO_SET_MODE and NAV_TAKEOFF with their COMMAND_ACK, the
  SET_POSITION_TARGET_LOCAL_NED setpoints, SYS_STATUS, BATTERY_STATUS and
  GPS_RAW_INT as they are (battery and fix read exactly as the pymavlink backend
  reads them), and the parameter protocol (PARAM_SET / PARAM_REQUEST_READ,
  PARAM_VALUE) that :class:`~geonav.mavlink_bridge.backend_common.LinkState` runs.
* ``GeofenceAsync``: upload and clear the autopilot fence's items.

Setpoints go out one per call through ``MavlinkDirect`` rather than
``OffboardAsync.set_position_ned`` by default: the Offboard plugin resends
the last setpoint at 20 Hz on its own, and the only way to stop that is
``Offboard.stop()``, which also commands Hold. That hidden resender defeats
the policy-liveness pump (MAVSDK-Python#374) and the Hold would fight an
operator takeover. ``use_offboard_plugin=True`` selects the plugin anyway
(same message: LOCAL_NED, type_mask 2552), and then ``stop_setpoints``
calls ``Offboard.stop()``. ``health.is_global_position_ok``/``is_armable`` are
not used: they can stay false on ArduPilot while it flies.

MAVSDK's own C++ log is routed into Python logging (logger ``mavsdk``,
``mavsdk.logging.log_subscribe``) instead of raw lines on stdout, with
repeats folded (:class:`MavsdkLogForwarder`); the
telemetry watchers restart after an error, and ``close()`` never raises.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import json
import logging
import math
import threading
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from geonav.errors import CommandRejected, FlightError, FlightTimeout
from geonav.geo import LocalNED, LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.backend_common import Heartbeat, LinkState
from geonav.mavlink_bridge.folding import RepeatFolder
from geonav.mavlink_bridge.vehicle import Connection, FenceSpec

log = logging.getLogger(__name__)
T = TypeVar("T")
_MAVSDK_LOG = logging.getLogger("mavsdk")
_log_routed = False


class MavsdkLogForwarder:
    """MAVSDK's C++ log lines into the ``mavsdk`` Python logger, one level down and
    repeats folded.

    geonav says in its own words everything that refuses or ends a flight (a
    timeout, a lost link: one line and the exit code), so MAVSDK's own lines are
    the diagnosis behind it, not a second report: its warnings and errors go out
    at INFO (``geonav -v``; "Callback took more than 1 second" on a loaded
    machine, "Sending message failed" after a link loss reached the console),
    its info and debug lines at DEBUG (``-vv``). The recent warnings and errors
    are kept (:attr:`problems`) for geonav's own messages to quote.

    A link that is down makes MAVSDK log the same ERROR once or twice a second
    (``Connect error: Connection refused`` while geonav waits for the autopilot,
    ``Sending message failed`` after it died: about 100 lines in 17 s on
    ArduCopter SITL). So a message is logged at its level the first time, and
    again at most once per ``window_s`` with the number of repeats folded into
    it; every repeat in between still goes out at DEBUG (``geonav -vv``).

    Args:
        logger: where the lines go (``mavsdk``).
        window_s: how long identical messages are folded, s.
        clock: monotonic seconds (tests pass a fake one).
    """

    #: MAVSDK ``LogLevel`` values (DEBUG 0, INFO 1, WARN 2, ERROR 3) -> logging levels.
    LEVELS = {0: logging.DEBUG, 1: logging.DEBUG, 2: logging.INFO, 3: logging.INFO}

    def __init__(
        self,
        logger: logging.Logger = _MAVSDK_LOG,
        window_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.logger, self.window_s, self.clock = logger, window_s, clock
        self._folder = RepeatFolder(window_s, clock)
        self.problems: collections.deque[tuple[float, str]] = collections.deque(maxlen=64)
        """(clock time, message) of MAVSDK's recent warnings and errors, oldest first."""

    def __call__(self, level: Any, message: str, file: str | None, line: int) -> bool:
        """MAVSDK's callback (called on MAVSDK's threads); True: MAVSDK prints nothing."""
        try:
            py_level = self.LEVELS.get(int(level), logging.DEBUG)
            if int(level) >= 2:
                self.problems.append((self.clock(), message))
            folded = self._folder.admit(message)
            where = f" ({file}:{line})" if file else ""
            if folded is None:
                self.logger.debug("%s (repeat)%s", message, where)
            else:
                self.logger.log(py_level, "%s", self._folder.with_count(message, folded))
        except Exception:  # noqa: BLE001 - never raise into MAVSDK's C++ thread
            return False
        return True


def route_mavsdk_log() -> None:
    """Send MAVSDK's C++ log lines to the ``mavsdk`` Python logger (once per process).

    Without this MAVSDK prints coloured ``[hh:mm:ss|Error] ...`` lines straight
    to stdout, outside logging's levels and handlers.
    """
    global _log_routed
    if _log_routed:
        return
    try:
        from mavsdk.logging import log_subscribe
    except ImportError:
        return
    log_subscribe(FORWARDER)
    _log_routed = True


FORWARDER = MavsdkLogForwarder()
"""The process's forwarder (MAVSDK takes one log callback)."""


def mavsdk_said(since: float, within_s: float = 30.0) -> str:
    """'; MAVSDK: <the first two distinct warnings or errors it logged>' in the
    ``within_s`` after ``since`` (clock seconds), for geonav's own messages (the first is
    usually the cause: 'Connect error: Connection refused'); '' when there were none."""
    said: list[str] = []
    for t, message in list(FORWARDER.problems):
        if since <= t <= since + within_s + 5.0 and message not in said:
            said.append(message)
    return f"; MAVSDK: {'; '.join(said[:2])}" if said else ""


#: the messages read as they are (MavlinkDirect), for battery, GPS fix and parameters.
RAW_FIELDS = ("SYS_STATUS", "BATTERY_STATUS", "GPS_RAW_INT", "PARAM_VALUE")

EXECUTOR_DRAIN_S = 10.0
"""On close, how long MAVSDK's blocking calls still running get to return (its commands
time out within a few seconds) before MAVSDK is destroyed."""


class MavsdkVehicle(LinkState):
    """A Vehicle over native MAVSDK.

    Args:
        conn: parsed connection.
        system_id: only accept this autopilot system id (None: the first autopilot).
        use_offboard_plugin: stream setpoints with ``OffboardAsync`` (see module docs).
    """

    def __init__(
        self,
        conn: Connection,
        *,
        system_id: int | None = None,
        use_offboard_plugin: bool = False,
    ) -> None:
        super().__init__(conn, system_id)
        self._use_offboard = use_offboard_plugin
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="mavsdk-loop", daemon=True
        )
        self._tasks: list[asyncio.Task[Any]] = []
        self._mav: Any = None
        self._sys: Any = None
        self._sysid = 0
        self._hb_autopilot: int | None = None
        self._closed = False
        self._offboard_streaming = False

    # ------------------------------------------------------------ plumbing
    def _run(self, coro: Awaitable[T], timeout_s: float, what: str) -> T:
        if self._closed and what != "shutdown":
            if hasattr(coro, "close"):
                coro.close()  # type: ignore[union-attr]
            raise FlightError(f"MAVSDK: {what}: the connection is closed")
        fut: concurrent.futures.Future[T] = asyncio.run_coroutine_threadsafe(coro, self._loop)  # type: ignore[arg-type]
        try:
            return fut.result(timeout_s)
        except concurrent.futures.TimeoutError as err:
            fut.cancel()
            raise FlightTimeout(f"MAVSDK: {what} not done within {timeout_s:.1f} s") from err

    def connect(self, timeout_s: float) -> None:
        """Add the connection, wait for ``first_autopilot`` and its HEARTBEAT."""
        try:
            from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
            from mavsdk.asyncio.plugins.action import ActionAsync
            from mavsdk.asyncio.plugins.geofence import GeofenceAsync
            from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
            from mavsdk.asyncio.plugins.offboard import OffboardAsync
            from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
        except ImportError as err:
            raise FlightError(
                f"the MAVSDK backend needs the native mavsdk>=4 package ({err}); "
                "pip install 'mavsdk>=4.1,<5' or use --backend pymavlink"
            ) from err
        route_mavsdk_log()
        self._thread.start()
        t_start = time.monotonic()

        async def setup() -> None:
            self._mav = Mavsdk(
                Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
            )
            await self._mav.add_any_connection(self.conn.mavsdk())
            deadline = time.monotonic() + timeout_s
            while True:
                system = await self._mav.first_autopilot(
                    timeout_s=max(0.1, deadline - time.monotonic())
                )
                if system is None:
                    raise FlightTimeout(
                        f"no autopilot on {self.conn.mavsdk()!r} within {timeout_s:.0f} s "
                        "(MAVSDK first_autopilot); check the connection URL"
                        + mavsdk_said(t_start, timeout_s)
                    )
                sysid = await system.get_system_id()
                if self._want_sysid is None or sysid == self._want_sysid:
                    break
                if time.monotonic() > deadline:
                    raise FlightTimeout(f"autopilot system id {self._want_sysid} not found")
                await asyncio.sleep(0.2)
            self._sys, self._sysid = system, sysid
            self._act = ActionAsync(system)
            self._telemetry = TelemetryAsync(system)
            self._direct = MavlinkDirectAsync(system)
            self._offboard = OffboardAsync(system)
            self._geofence = GeofenceAsync(system)
            kind = await system.autopilot_type()
            self.autopilot = {1: M.PX4, 2: M.ARDUPILOT}.get(int(kind), "")
            loop = asyncio.get_running_loop()
            for watch in (
                self._watch_heartbeat,
                self._watch_position,
                self._watch_texts,
                self._watch_home,
                self._watch_landed,
                *(self._raw_watcher(name) for name in RAW_FIELDS),
            ):
                self._tasks.append(loop.create_task(self._keep(watch)))

        self._run(setup(), timeout_s + 5.0, "connect")
        deadline = time.monotonic() + timeout_s
        while self._hb is None:
            if time.monotonic() > deadline:
                raise FlightTimeout(
                    "MAVSDK saw the autopilot but no HEARTBEAT from its component 1"
                )
            time.sleep(0.02)
        if not self.autopilot and self._hb_autopilot is not None:
            self.autopilot = M.flavour_from_heartbeat(self._hb_autopilot)
        log.info(
            "MAVSDK connected to %s autopilot sysid %d on %s",
            self.autopilot,
            self._sysid,
            self.conn.mavsdk(),
        )

    async def _keep(self, watch: Callable[[], Awaitable[None]]) -> None:
        """Run a telemetry watcher; restart it after an error (never dies silently)."""
        while not self._closed:
            try:
                await watch()
            except asyncio.CancelledError:
                raise
            except Exception as err:  # noqa: BLE001
                log.warning("MAVSDK %s stopped (%s); restarting", watch.__name__, err)
            await asyncio.sleep(0.5)

    async def _watch_heartbeat(self) -> None:
        async for msg in self._direct.subscribe_message("HEARTBEAT"):
            if msg.system_id != self._sysid or msg.component_id != M.MAV_COMP_ID_AUTOPILOT1:
                continue
            fields = json.loads(msg.fields_json)
            if fields.get("autopilot") == M.MAV_AUTOPILOT_INVALID:
                continue
            self._hb_autopilot = int(fields["autopilot"])
            self._on_heartbeat(Heartbeat(int(fields["system_status"]), int(fields["custom_mode"]),
                                         int(fields["base_mode"])))

    def _raw_watcher(self, name: str) -> Callable[[], Awaitable[None]]:
        """A watcher that passes every ``name`` message of the autopilot's system to
        :meth:`LinkState._on_fields` as its fields."""

        async def watch() -> None:
            async for msg in self._direct.subscribe_message(name):
                if msg.system_id == self._sysid:
                    self._on_fields(name, json.loads(msg.fields_json))

        watch.__name__ = f"_watch_{name.lower()}"
        return watch

    async def _watch_position(self) -> None:
        async for pv in self._telemetry.subscribe_position_velocity_ned():
            p, v = pv.position, pv.velocity
            self._on_position(LocalNED(p.north_m, p.east_m, p.down_m),
                              (v.north_m_s, v.east_m_s, v.down_m_s))

    async def _watch_texts(self) -> None:
        async for st in self._telemetry.subscribe_status_text():
            # MAVSDK's StatusTextType counts up from DEBUG 0 to EMERGENCY 7: the reverse
            # of MAVLink's MAV_SEVERITY (EMERGENCY 0 .. DEBUG 7).
            self._on_statustext(7 - int(getattr(st.type, "value", 1)), str(st.text))

    async def _watch_home(self) -> None:
        async for h in self._telemetry.subscribe_home():
            if math.isfinite(h.latitude_deg) and (h.latitude_deg or h.longitude_deg):
                self._on_home(LonLat(h.longitude_deg, h.latitude_deg, h.absolute_altitude_m))

    async def _watch_landed(self) -> None:
        async for ls in self._telemetry.subscribe_landed_state():
            # MAVSDK LandedState: UNKNOWN 0, ON_GROUND 1, IN_AIR 2, TAKING_OFF 3, LANDING 4.
            self._on_landed_state(int(ls))

    def close(self) -> None:
        """Cancel subscriptions, destroy MAVSDK and stop the loop."""
        if self._closed:
            return
        self._closed = True
        if self._thread.is_alive():

            async def shutdown() -> None:
                for task in self._tasks:
                    task.cancel()
                await asyncio.gather(*self._tasks, return_exceptions=True)
                # MAVSDK's asyncio plugins run its blocking calls in the loop's executor. One
                # still waiting (a LAND retried on a dead link) never returned once MAVSDK
                # was destroyed, and Python joins executor threads at exit: the command
                # hung after its result line. MAVSDK times its commands out within seconds.
                try:
                    await asyncio.wait_for(self._loop.shutdown_default_executor(),
                                           EXECUTOR_DRAIN_S)
                except asyncio.TimeoutError:
                    log.warning("MAVSDK shutdown: a MAVSDK call still blocks after %.0f s",
                                EXECUTOR_DRAIN_S)
                if self._mav is not None:
                    self._mav.destroy()

            try:
                self._run(shutdown(), EXECUTOR_DRAIN_S + 5.0, "shutdown")
            except Exception as err:  # noqa: BLE001 - close never raises
                log.warning("MAVSDK shutdown: %s", err)
            try:
                self._loop.call_soon_threadsafe(self._loop.stop)
            except RuntimeError as err:
                log.debug("MAVSDK loop already closed: %s", err)
            self._thread.join(timeout=2.0)
        if not self._thread.is_alive() and not self._loop.is_closed():
            # A stopped but unclosed loop prints "unclosed event loop" at exit
            # (seen after every MAVSDK flight on ArduCopter SITL).
            try:
                self._loop.close()
            except RuntimeError as err:
                log.debug("closing the MAVSDK loop: %s", err)

    # ------------------------------------------------------------ commands
    def _command(self, command: int, params: tuple[float, ...], timeout_s: float) -> int:
        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        p = tuple(params) + (0.0,) * (7 - len(params))
        fields: dict[str, Any] = {
            "target_system": self._sysid,
            "target_component": M.MAV_COMP_ID_AUTOPILOT1,
            "command": command,
            "confirmation": 0,
        }
        for i, v in enumerate(p, start=1):
            # JSON has no NaN; 0 means "unchanged/default" for the params used here.
            fields[f"param{i}"] = 0.0 if math.isnan(float(v)) else float(v)
        msg = MavlinkMessage(
            "COMMAND_LONG", 0, 0, self._sysid, M.MAV_COMP_ID_AUTOPILOT1, json.dumps(fields)
        )
        ack = self._run(self._direct.send_command(msg), timeout_s,
                        f"command {M.command_name(command)}")
        if not ack.fields_json:
            raise FlightTimeout(f"no COMMAND_ACK for {M.command_name(command)} (MAVSDK)")
        return int(json.loads(ack.fields_json)["result"])

    def _action(self, name: str, timeout_s: float) -> None:
        from mavsdk.plugins.action import ActionError

        coro = getattr(self._act, name)()
        sent_t = time.monotonic()
        try:
            self._run(coro, timeout_s, f"action {name}")
        except ActionError as err:
            raise self._rejected(f"{name}: MAVSDK action failed ({err})", sent_t) from err

    def request_telemetry(self, rate_hz: float, timeout_s: float) -> None:
        """MAVSDK ``set_rate_*`` (SET_MESSAGE_INTERVAL) and the EKF origin."""
        from mavsdk.plugins.telemetry import TelemetryError

        async def rates() -> None:
            for name, hz in (
                ("set_rate_position_velocity_ned", rate_hz),
                ("set_rate_home", 0.5),
                ("set_rate_landed_state", 1.0),
            ):
                try:
                    await getattr(self._telemetry, name)(hz)
                except TelemetryError as err:
                    log.warning("MAVSDK %s: %s", name, err)

        self._run(rates(), timeout_s * 4, "telemetry rates")
        self._request_intervals({"SYS_STATUS": 1e6, "BATTERY_STATUS": 1e6, "GPS_RAW_INT": 1e6},
                                timeout_s)
        self.request_message("GPS_GLOBAL_ORIGIN", timeout_s)

    def request_message(self, name: str, timeout_s: float) -> bool:
        """Ask for the EKF origin (``get_gps_global_origin``) or any message by id."""
        if name == "GPS_GLOBAL_ORIGIN":
            from mavsdk.plugins.telemetry import TelemetryError

            try:
                o = self._run(self._telemetry.get_gps_global_origin(), timeout_s, "GPS origin")
            except (TelemetryError, FlightError) as err:
                log.debug("GPS_GLOBAL_ORIGIN not available yet: %s", err)
                return False
            self._on_origin(LonLat(o.longitude_deg, o.latitude_deg, o.altitude_m))
            return True
        return self._command(M.MAV_CMD_REQUEST_MESSAGE, (M.MSG_ID[name],), timeout_s) == 0

    def set_origin(self, origin: LonLat) -> None:
        """SET_GPS_GLOBAL_ORIGIN through ``Action.set_gps_global_origin``."""
        from mavsdk.plugins.action import ActionError

        try:
            self._run(
                self._act.set_gps_global_origin(origin.lat_deg, origin.lon_deg, origin.alt_m),
                5.0,
                "set origin",
            )
        except ActionError as err:
            raise CommandRejected(f"SET_GPS_GLOBAL_ORIGIN failed: {err}") from err

    def arm(self, timeout_s: float) -> None:
        """``Action.arm``."""
        self._action("arm", timeout_s)

    def disarm(self, timeout_s: float) -> None:
        """``Action.disarm``."""
        self._action("disarm", timeout_s)

    def land(self, timeout_s: float) -> None:
        """``Action.land`` (MAV_CMD_NAV_LAND)."""
        self._action("land", timeout_s)

    def return_to_launch(self, timeout_s: float) -> None:
        """``Action.return_to_launch``."""
        self._action("return_to_launch", timeout_s)

    def send_position_target(self, target: LocalNED, yaw_deg: float) -> None:
        """SET_POSITION_TARGET_LOCAL_NED, frame 1, type_mask 2552."""
        if self._use_offboard:
            from mavsdk.plugins.offboard import PositionNedYaw

            sp = PositionNedYaw(target.north_m, target.east_m, target.down_m, yaw_deg)
            self._run(self._offboard.set_position_ned(sp), 1.0, "offboard setpoint")
            self._offboard_streaming = True
            return
        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        fields = {
            "time_boot_ms": 0,
            "target_system": self._sysid,
            "target_component": M.MAV_COMP_ID_AUTOPILOT1,
            "coordinate_frame": M.MAV_FRAME_LOCAL_NED,
            "type_mask": M.TYPE_MASK_POSITION_YAW,
            "x": target.north_m,
            "y": target.east_m,
            "z": target.down_m,
            "vx": 0.0,
            "vy": 0.0,
            "vz": 0.0,
            "afx": 0.0,
            "afy": 0.0,
            "afz": 0.0,
            "yaw": math.radians(yaw_deg),
            "yaw_rate": 0.0,
        }
        msg = MavlinkMessage(
            "SET_POSITION_TARGET_LOCAL_NED",
            0,
            0,
            self._sysid,
            M.MAV_COMP_ID_AUTOPILOT1,
            json.dumps(fields),
        )
        self._run(self._direct.send_message(msg), 1.0, "setpoint")

    # ------------------------------------------------- parameters, fence
    def _send_raw(self, name: str, fields: dict[str, Any]) -> None:
        """One message by name through MavlinkDirect (targets filled in)."""
        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        body = {"target_system": self._sysid, "target_component": M.MAV_COMP_ID_AUTOPILOT1,
                **fields}
        msg = MavlinkMessage(name, 0, 0, self._sysid, M.MAV_COMP_ID_AUTOPILOT1,
                             json.dumps(body))
        self._run(self._direct.send_message(msg), 2.0, name)

    def _send_fence_items(self, fence: FenceSpec, timeout_s: float) -> None:
        """``Geofence.upload_geofence``: one inclusion polygon, an inclusion circle."""
        from mavsdk.plugins.geofence import (
            Circle,
            FenceType,
            GeofenceData,
            GeofenceError,
            Point,
            Polygon,
        )

        polygon = Polygon([Point(v.lat_deg, v.lon_deg) for v in fence.polygon],
                          FenceType.INCLUSION)
        circles = []
        if fence.circle is not None:
            centre, radius_m = fence.circle
            circles.append(Circle(Point(centre.lat_deg, centre.lon_deg), float(radius_m),
                                  FenceType.INCLUSION))
        try:
            self._run(self._geofence.upload_geofence(GeofenceData([polygon], circles)),
                      timeout_s, "geofence upload")
        except GeofenceError as err:
            raise CommandRejected(f"fence upload: MAVSDK geofence failed ({err})") from err

    def _clear_fence_items(self, timeout_s: float) -> None:
        """``Geofence.clear_geofence``."""
        from mavsdk.plugins.geofence import GeofenceError

        try:
            self._run(self._geofence.clear_geofence(), timeout_s, "geofence clear")
        except GeofenceError as err:
            raise CommandRejected(f"fence clear: MAVSDK geofence failed ({err})") from err

    def stop_setpoints(self) -> None:
        """Stop the Offboard plugin's own 20 Hz resend (only with ``use_offboard_plugin``)."""
        if self._use_offboard and self._offboard_streaming:
            from mavsdk.plugins.offboard import OffboardError

            self._offboard_streaming = False
            try:
                self._run(self._offboard.stop(), 3.0, "offboard stop")
            except OffboardError as err:
                log.warning("Offboard.stop: %s", err)
