"""The pymavlink backend of :class:`~geonav.mavlink_bridge.vehicle.Vehicle` (PX4 and ArduPilot).

Threads: one receiver thread owns ``recv_match`` and keeps the latest
telemetry; one thread sends our own 1 Hz HEARTBEAT (some autopilot services
start only after they see one); senders share a lock. Neither thread can die
of an exception, and ``close()`` never raises.

Link ownership: pymavlink's ``autoreconnect`` is off (it reconnects inside
both threads at once and they die with AttributeError when the port is
gone). The receiver thread is the one owner of reconnection: on a TCP or
serial link that errors, or is silent for ``RECONNECT_AFTER_S``, it reopens
the link about once a second. ``connect()`` retries opening a TCP or serial
link until its timeout (a companion computer often boots before the
autopilot's port listens), as MAVSDK does.

Identity: geonav sends its 1 Hz HEARTBEAT as an onboard controller from system 255
(the GCS id ArduPilot's ``MAV_GCS_SYSID`` expects) and, on PX4, a second one from the
autopilot's own system id: PX4's STATUSTEXT stream sends only to a link that has seen a
GCS heartbeat, or (PX4 main) an onboard-controller heartbeat from its own system
(``mavlink_receiver.cpp`` ``handle_message_heartbeat``, ``streams/STATUSTEXT.hpp``), so
a heartbeat from system 255 alone got no autopilot text on PX4's onboard link.

Commands go out as COMMAND_LONG and wait for the matching COMMAND_ACK: same
command id, addressed to us, and received after this request was first
sent (an older request's late ACK is never taken); resent with an
incremented ``confirmation`` when none arrives; IN_PROGRESS extends the wait.
LAND and RTL are MAV_CMD_NAV_LAND / NAV_RETURN_TO_LAUNCH, so their ACKs cannot
be confused with a DO_SET_MODE's. Parameters and the autopilot fence use the
plain parameter and mission protocols (:mod:`~geonav.mavlink_bridge.backend_common`,
:mod:`~geonav.mavlink_bridge.pymavlink_mission`).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from typing import Any

from geonav.errors import FlightError, FlightTimeout
from geonav.geo import LocalNED, LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge import pymavlink_mission
from geonav.mavlink_bridge._mav import mavlink2, mavutil
from geonav.mavlink_bridge.backend_common import Heartbeat, LinkState
from geonav.mavlink_bridge.vehicle import Connection, FenceSpec

log = logging.getLogger(__name__)

#: reopen a silent TCP/serial link after this many seconds without any message.
RECONNECT_AFTER_S = 3.0

def _raise_eof() -> None:
    raise ConnectionAbortedError("EOF on TCP socket (the autopilot closed the link)")


def _raise_reset() -> None:
    raise ConnectionResetError("TCP connection reset by the autopilot")


command_name = M.command_name


class PymavlinkVehicle(LinkState):
    """A Vehicle over pymavlink.

    Args:
        conn: parsed connection.
        system_id: only accept this autopilot system id (None: first autopilot seen).
        source_system: our MAVLink system id (255 = GCS, what ArduPilot's
            ``MAV_GCS_SYSID`` expects by default).
        source_component: our component id (191 = onboard computer).
    """

    def __init__(
        self,
        conn: Connection,
        *,
        system_id: int | None = None,
        source_system: int = 255,
        source_component: int = M.MAV_COMP_ID_ONBOARD_COMPUTER,
    ) -> None:
        super().__init__(conn, system_id)
        self._src = (source_system, source_component)
        self._m: Any = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._target = (0, 0)
        self._acks: dict[int, tuple[float, Any]] = {}
        self.mission_rx: collections.deque[tuple[float, str, Any]] = collections.deque(maxlen=64)
        """(time, kind, message) of the mission protocol's replies (MISSION_REQUEST*, _ACK)."""
        self._t0 = time.monotonic()
        self._last_rx = -math.inf
        self._closed = False

    # ---------------------------------------------------------------- link
    def connect(self, timeout_s: float) -> None:
        """Open the link and wait for an autopilot HEARTBEAT.

        Raises:
            FlightTimeout: no autopilot heartbeat within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        waited = False
        while True:
            try:
                self._m = self._open()
                break
            except OSError as err:
                retry = self.conn.kind in ("tcp", "serial")
                if not retry or time.monotonic() > deadline:
                    raise FlightError(
                        f"cannot open MAVLink connection {self.conn.raw!r}: {err}"
                        + (f" (retried for {timeout_s:.0f} s)" if retry else "")
                    ) from err
                if not waited:
                    log.warning(
                        "%s not available yet (%s); retrying until the connect timeout (%.0f s)",
                        self.conn.raw,
                        err,
                        timeout_s,
                    )
                    waited = True
                time.sleep(0.5)
        timeout_s = max(0.5, deadline - time.monotonic())
        self._stop.clear()
        for target, name in ((self._recv_loop, "mav-recv"), (self._heartbeat_loop, "mav-hb")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        with self._lock:
            ok = self._lock.wait_for(lambda: self._hb is not None, timeout=timeout_s)
        if not ok:
            self.close()
            raise FlightTimeout(
                f"no autopilot HEARTBEAT on {self.conn.raw!r} within {timeout_s:.0f} s; check the "
                "connection string (udpin: listens, udpout:/tcp: connect) and the baud rate"
            )
        log.info(
            "connected to %s autopilot sysid %d compid %d on %s",
            self.autopilot,
            self._target[0],
            self._target[1],
            self.conn.raw,
        )

    def _open(self) -> Any:
        device, baud = self.conn.pymavlink()
        m = mavutil.mavlink_connection(
            device,
            baud=baud,
            source_system=self._src[0],
            source_component=self._src[1],
            autoreconnect=False,
            retries=0,
        )
        if isinstance(m, mavutil.mavtcp):
            # pymavlink prints "EOF on TCP socket" on stdout and returns b"" at every
            # read of a closed peer: recv_match then spins and prints it thousands of
            # times a second (649,379 lines in 17 s when ArduCopter SITL was killed).
            # Raise instead: the receiver thread sees a broken link and reopens it.
            m.handle_eof = _raise_eof
            m.handle_disconnect = _raise_reset
        return m

    def close(self) -> None:
        """Stop the threads and close the link (never raises; safe to call twice)."""
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        self._threads.clear()
        with self._send_lock:
            m, self._m = self._m, None
            self._closed = True
        if m is not None:
            try:
                m.close()
            except Exception as err:  # noqa: BLE001 - a dead port must not raise at exit
                log.debug("closing MAVLink connection: %s", err)

    def _send(self, fn_name: str, *args: Any) -> None:
        with self._send_lock:
            if self._m is None:
                raise FlightError("MAVLink connection is closed")
            try:
                getattr(self._m.mav, fn_name)(*args)
            except (OSError, AttributeError, ValueError) as err:
                # A dead link: the watchdogs see the silence; the sender must not crash.
                log.debug("MAVLink send %s failed: %s", fn_name, err)

    def _heartbeat_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._send_heartbeats()
            except FlightError:
                return
            except Exception:  # noqa: BLE001 - the heartbeat thread never dies
                log.exception("sending our HEARTBEAT failed")
            if self._stop.wait(1.0):
                return

    def _send_heartbeats(self) -> None:
        """Our HEARTBEAT (onboard controller, system 255); on PX4 also one from the
        autopilot's own system, which PX4's STATUSTEXT stream needs to see."""
        args = (M.MAV_TYPE_ONBOARD_CONTROLLER, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        self._send("heartbeat_send", *args)
        if self.autopilot == M.PX4 and self._target[0] != self._src[0]:
            as_vehicle = mavlink2.MAVLink(None, srcSystem=self._target[0],
                                          srcComponent=self._src[1])
            with self._send_lock:
                if self._m is None:
                    raise FlightError("MAVLink connection is closed")
                try:
                    self._m.write(self._m.mav.heartbeat_encode(*args).pack(as_vehicle))
                except (OSError, AttributeError, ValueError) as err:
                    log.debug("MAVLink send HEARTBEAT failed: %s", err)

    def _recv_loop(self) -> None:
        last_reopen = time.monotonic()
        while not self._stop.is_set():
            m = self._m
            if m is None:
                return
            broken = False
            try:
                msg = m.recv_match(blocking=True, timeout=0.1)
            except Exception as err:  # noqa: BLE001 - the receiver never dies
                log.debug("MAVLink receive error: %s", err)
                msg, broken = None, True
                time.sleep(0.05)
            if msg is not None:
                self._last_rx = time.monotonic()
                try:
                    self._on_message(msg)
                except Exception:  # noqa: BLE001
                    log.exception("handling %s failed", msg.get_type())
                continue
            silent = time.monotonic() - max(self._last_rx, last_reopen) > RECONNECT_AFTER_S
            if self.conn.kind in ("tcp", "serial") and (broken or silent):
                if time.monotonic() - last_reopen >= 1.0:
                    last_reopen = time.monotonic()
                    self._reopen()

    def _reopen(self) -> None:
        """Reopen a TCP/serial link (the receiver thread is its one owner)."""
        try:
            new = self._open()
        except OSError as err:
            log.debug("reconnecting %s: %s", self.conn.raw, err)
            return
        with self._send_lock:
            if self._closed:
                new.close()
                return
            old, self._m = self._m, new
            new.target_system, new.target_component = self._target
        log.warning("MAVLink link %s reopened", self.conn.raw)
        try:
            if old is not None:
                old.close()
        except Exception as err:  # noqa: BLE001
            log.debug("closing the old link: %s", err)

    def _on_message(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HEARTBEAT":
            if msg.autopilot == M.MAV_AUTOPILOT_INVALID or msg.type == M.MAV_TYPE_GCS:
                return
            if self._hb is None:
                if self._want_sysid is not None and src[0] != self._want_sysid:
                    return
                try:
                    self.autopilot = M.flavour_from_heartbeat(msg.autopilot)
                except FlightError as err:
                    log.warning("ignoring heartbeat from %s: %s", src, err)
                    return
                # pymavlink's wait_heartbeat leaves target_component at 0: take it
                # from the heartbeat's source component.
                self._target = src
                self._m.target_system, self._m.target_component = src
                if self.autopilot == M.PX4:
                    threading.Thread(target=self._send_heartbeats, daemon=True).start()
            if src != self._target:
                return
            self._on_heartbeat(Heartbeat(msg.system_status, msg.custom_mode, msg.base_mode))
            return
        if self._hb is None or src[0] != self._target[0]:
            return
        self._on_telemetry(kind, msg)

    def _on_telemetry(self, kind: str, msg: Any) -> None:
        """A message of the autopilot's system (not a HEARTBEAT) into the store."""
        if kind == "LOCAL_POSITION_NED":
            self._on_position(LocalNED(msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz))
        elif kind == "GPS_GLOBAL_ORIGIN":
            self._on_origin(LonLat(msg.longitude / 1e7, msg.latitude / 1e7, msg.altitude / 1e3))
        elif kind == "HOME_POSITION":
            self._on_home(LonLat(msg.longitude / 1e7, msg.latitude / 1e7, msg.altitude / 1e3))
        elif kind == "EXTENDED_SYS_STATE":
            self._on_landed_state(msg.landed_state)
        elif kind == "COMMAND_ACK":
            if msg.target_system in (0, self._src[0]) and msg.target_component in (0, self._src[1]):
                with self._lock:
                    self._acks[msg.command] = (time.monotonic(), msg)
                    self._lock.notify_all()
        elif kind == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
            self._on_statustext(int(msg.severity), text)
        elif kind in ("SYS_STATUS", "BATTERY_STATUS", "GPS_RAW_INT", "PARAM_VALUE"):
            self._on_fields(kind, msg.to_dict())
        elif kind in ("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"):
            if msg.target_system in (0, self._src[0]):
                with self._lock:
                    self.mission_rx.append((time.monotonic(), kind, msg))
                    self._lock.notify_all()

    # ------------------------------------------------------------ commands
    def command(
        self, command: int, params: tuple[float, ...], timeout_s: float, tries: int = 3
    ) -> int:
        """Send COMMAND_LONG and return the ACK's result (any result, not only ACCEPTED).

        Raises:
            FlightTimeout: no ACK after ``tries`` sends spread over ``timeout_s``.
        """
        p = tuple(params) + (0.0,) * (7 - len(params))
        per_try = timeout_s / tries
        sent_t = time.monotonic()
        with self._lock:
            self._acks.pop(command, None)
        for attempt in range(tries):
            self._send("command_long_send", self._target[0], self._target[1], command, attempt, *p)
            deadline = time.monotonic() + per_try
            with self._lock:
                while True:
                    left = deadline - time.monotonic()
                    got = self._acks.pop(command, None)
                    # Only an ACK received after this request was first sent is its answer.
                    ack = got[1] if got is not None and got[0] >= sent_t else None
                    if ack is not None and ack.result == M.MAV_RESULT_IN_PROGRESS:
                        deadline = time.monotonic() + per_try
                        continue
                    if ack is not None:
                        return int(ack.result)
                    if left <= 0:
                        break
                    self._lock.wait(left)
        raise FlightTimeout(
            f"no COMMAND_ACK for {command_name(command)} after {tries} tries in {timeout_s:.1f} s"
        )

    def _command(self, command: int, params: tuple[float, ...], timeout_s: float) -> int:
        return self.command(command, params, timeout_s)

    def request_telemetry(self, rate_hz: float, timeout_s: float) -> None:
        """SET_MESSAGE_INTERVAL for the streams the bridge reads; request origin and home once."""
        interval_us = 1e6 / rate_hz
        self._request_intervals({
            "LOCAL_POSITION_NED": interval_us,
            "GLOBAL_POSITION_INT": interval_us,
            "EXTENDED_SYS_STATE": 1e6,
            "SYS_STATUS": 1e6,
            "BATTERY_STATUS": 1e6,
            "GPS_RAW_INT": 1e6,
            "HOME_POSITION": 2e6,
        }, timeout_s)
        self.request_message("GPS_GLOBAL_ORIGIN", timeout_s)
        self.request_message("HOME_POSITION", timeout_s)

    def request_message(self, name: str, timeout_s: float) -> bool:
        """MAV_CMD_REQUEST_MESSAGE; True when accepted."""
        result = self.command(M.MAV_CMD_REQUEST_MESSAGE, (M.MSG_ID[name],), timeout_s)
        return result == M.MAV_RESULT_ACCEPTED

    def set_origin(self, origin: LonLat) -> None:
        """SET_GPS_GLOBAL_ORIGIN (a message, no ACK: watch GPS_GLOBAL_ORIGIN)."""
        self._send(
            "set_gps_global_origin_send",
            self._target[0],
            int(round(origin.lat_deg * 1e7)),
            int(round(origin.lon_deg * 1e7)),
            int(round(origin.alt_m * 1000)),
        )

    def arm(self, timeout_s: float) -> None:
        """One arming attempt."""
        self._checked(M.MAV_CMD_COMPONENT_ARM_DISARM, (1.0,), timeout_s, "arming")

    def disarm(self, timeout_s: float) -> None:
        """Disarm."""
        self._checked(M.MAV_CMD_COMPONENT_ARM_DISARM, (0.0,), timeout_s, "disarming")

    def land(self, timeout_s: float) -> None:
        """MAV_CMD_NAV_LAND (p4 yaw NaN = keep); the caller confirms LAND on the heartbeat."""
        self._checked(M.MAV_CMD_NAV_LAND, (0, 0, 0, math.nan, 0, 0, 0), timeout_s, "LAND")

    def return_to_launch(self, timeout_s: float) -> None:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH; the caller confirms RTL on the heartbeat."""
        self._checked(M.MAV_CMD_NAV_RETURN_TO_LAUNCH, (), timeout_s, "RTL")

    def send_position_target(self, target: LocalNED, yaw_deg: float) -> None:
        """One SET_POSITION_TARGET_LOCAL_NED, MAV_FRAME_LOCAL_NED, type_mask 2552."""
        t_ms = int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF
        self._send(
            "set_position_target_local_ned_send",
            t_ms,
            self._target[0],
            self._target[1],
            M.MAV_FRAME_LOCAL_NED,
            M.TYPE_MASK_POSITION_YAW,
            float(target.north_m),
            float(target.east_m),
            float(target.down_m),
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            math.radians(yaw_deg),
            0.0,
        )

    def stop_setpoints(self) -> None:
        """Nothing to stop: this backend sends only what the pump sends."""

    # ------------------------------------------------- parameters, fence
    def _send_raw(self, name: str, fields: dict[str, Any]) -> None:
        """One message by name; ``target_system``/``target_component`` filled in."""
        cls = getattr(mavlink2, f"MAVLink_{name.lower()}_message")
        kw = {"target_system": self._target[0], "target_component": self._target[1], **fields}
        args = [kw[f] if not isinstance(kw[f], str) else kw[f].encode() for f in cls.fieldnames]
        with self._send_lock:
            if self._m is None:
                raise FlightError("MAVLink connection is closed")
            try:
                self._m.mav.send(cls(*args))
            except (OSError, AttributeError, ValueError) as err:
                log.debug("MAVLink send %s failed: %s", name, err)

    def _send_fence_items(self, fence: FenceSpec, timeout_s: float) -> None:
        pymavlink_mission.upload_fence_items(self, fence, timeout_s)

    def _clear_fence_items(self, timeout_s: float) -> None:
        pymavlink_mission.clear_fence_items(self, timeout_s)
