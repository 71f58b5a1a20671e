"""What both Vehicle backends share: the telemetry store, the state snapshot, the
autopilot's text messages, the checked command path, stream requests, parameters and
the autopilot fence's parameters.

A backend (pymavlink or MAVSDK) owns its link and turns what it receives into calls
of the ``_on_*`` methods here (raw SYS_STATUS, BATTERY_STATUS, GPS_RAW_INT and
PARAM_VALUE fields through :meth:`LinkState._on_fields`); :meth:`LinkState.state` turns
the store into a :class:`~geonav.mavlink_bridge.vehicle.VehicleState`. Commands a
backend sends as COMMAND_LONG go through its ``_command`` (send, wait for the matching
COMMAND_ACK, return its result) and :meth:`LinkState._checked`, which turns a result
other than ACCEPTED into :class:`~geonav.errors.CommandRejected` quoting the
autopilot's latest STATUSTEXT, so both backends refuse in the same words. Parameters go
over the plain parameter protocol (PARAM_REQUEST_READ / PARAM_SET, answered by
PARAM_VALUE) through the backend's ``_send_raw``, with each autopilot's encoding of
integers (PX4 byte-wise in the float field, ArduPilot cast).

The autopilot's STATUSTEXTs are logged on ``geonav.mavlink_bridge.autopilot`` (WARNING
and worse at WARNING, the rest at INFO) and passed to ``on_statustext``, both folded:
the same text (numbers aside) at most once per 10 s, with the count of repeats.
"""

from __future__ import annotations

import collections
import logging
import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from geonav.errors import CommandRejected, FlightError, FlightTimeout
from geonav.geo import LocalNED, LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.folding import RepeatFolder, same_but_numbers
from geonav.mavlink_bridge.vehicle import Connection, FenceSpec, VehicleState

log = logging.getLogger(__name__)
#: the logger the autopilot's own STATUSTEXT lines go to ("autopilot: ...").
AUTOPILOT_LOG = logging.getLogger("geonav.mavlink_bridge.autopilot")


@dataclass(frozen=True)
class Heartbeat:
    """The HEARTBEAT fields the bridge reads."""

    system_status: int
    custom_mode: int
    base_mode: int


class LinkState:
    """The telemetry store and command checks both backends inherit.

    Args:
        conn: the parsed connection.
        system_id: only accept this autopilot system id (None: the first autopilot seen).
    """

    def __init__(self, conn: Connection, system_id: int | None = None) -> None:
        self.conn = conn
        self.autopilot = ""
        self.on_statustext: Callable[[int, str], None] | None = None
        self._want_sysid = system_id
        # A Condition is a lock that waiters (ACKs, the first heartbeat) can wait on.
        self._lock = threading.Condition()
        self._hb: Heartbeat | None = None
        self._hb_t = -math.inf
        self._pos: LocalNED | None = None
        self._vel: tuple[float, float, float] | None = None
        self._pos_t = -math.inf
        self._origin: LonLat | None = None
        self._home: LonLat | None = None
        self._landed_state = 0
        self._texts: collections.deque[tuple[float, int, str]] = collections.deque(maxlen=20)
        self._text_folder = RepeatFolder(10.0, key=same_but_numbers)
        self._battery: tuple[float | None, float | None] = (None, None)
        self._gps_fix: int | None = None
        self._params: dict[str, tuple[float, float, int]] = {}  # name -> (t, value, type)
        self._fence_saved: dict[str, tuple[float, bool]] = {}  # name -> (old value, int)

    # ------------------------------------------------------------- receiving
    def _on_heartbeat(self, hb: Heartbeat) -> None:
        with self._lock:
            self._hb = hb
            self._hb_t = time.monotonic()
            self._lock.notify_all()

    def _on_position(self, pos: LocalNED, vel: tuple[float, float, float]) -> None:
        with self._lock:
            self._pos, self._vel, self._pos_t = pos, vel, time.monotonic()

    def _on_origin(self, origin: LonLat) -> None:
        with self._lock:
            self._origin = origin

    def _on_home(self, home: LonLat) -> None:
        with self._lock:
            self._home = home

    def _on_landed_state(self, landed_state: int) -> None:
        with self._lock:
            self._landed_state = int(landed_state)

    def _on_statustext(self, severity: int, text: str) -> None:
        """One STATUSTEXT, ``severity`` in MAVLink's numbering (0 EMERGENCY .. 7 DEBUG):
        stored, then logged and passed on folded (a repeat within 10 s is counted)."""
        text = text.rstrip("\x00").strip()
        with self._lock:
            self._texts.append((time.monotonic(), int(severity), text))
        folded = self._text_folder.admit(text)
        if folded is None:
            AUTOPILOT_LOG.debug("autopilot (repeat): %s", text)
            return
        shown = self._text_folder.with_count(text, folded)
        level = logging.WARNING if severity <= 4 else logging.INFO
        AUTOPILOT_LOG.log(level, "autopilot: %s", shown)
        if self.on_statustext is not None:
            self.on_statustext(severity, shown)

    def _on_fields(self, kind: str, f: dict[str, Any]) -> None:
        """A raw message's fields (both backends): battery, GPS fix, parameter values."""
        if kind == "SYS_STATUS":
            pct = f.get("battery_remaining", -1)
            mv = f.get("voltage_battery", 65535)
            self._set_battery(None if pct is None or pct < 0 else float(pct),
                              None if mv in (None, 65535, -1) else mv / 1000.0)
        elif kind == "BATTERY_STATUS":
            pct = f.get("battery_remaining", -1)
            cells = [v for v in f.get("voltages", []) if v not in (65535, -1)]
            self._set_battery(None if pct is None or pct < 0 else float(pct),
                              sum(cells) / 1000.0 if cells else None)
        elif kind == "GPS_RAW_INT":
            with self._lock:
                self._gps_fix = int(f.get("fix_type", 0))
        elif kind == "PARAM_VALUE":
            name = f.get("param_id", "")
            name = name.decode(errors="replace") if isinstance(name, bytes) else str(name)
            with self._lock:
                self._params[name.rstrip("\x00")] = (time.monotonic(), float(f["param_value"]),
                                                     int(f.get("param_type", 9)))
                self._lock.notify_all()

    def _set_battery(self, pct: float | None, volts: float | None) -> None:
        with self._lock:
            old_pct, old_v = self._battery
            self._battery = (pct if pct is not None else old_pct,
                             volts if volts is not None else old_v)

    # --------------------------------------------------------------- state
    def state(self) -> VehicleState:
        """The latest telemetry snapshot.

        Raises:
            FlightError: no autopilot heartbeat yet.
        """
        now = time.monotonic()
        with self._lock:
            hb = self._hb
            if hb is None:
                raise FlightError("not connected: no autopilot heartbeat yet")
            last = self._texts[-1] if self._texts else None
            return VehicleState(
                autopilot=self.autopilot,
                system_status=hb.system_status,
                mode=M.decode_mode(self.autopilot, hb.custom_mode),
                armed=bool(hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED),
                heartbeat_age_s=now - self._hb_t,
                position=self._pos,
                velocity_ned_mps=self._vel,
                position_age_s=now - self._pos_t,
                origin=self._origin,
                home=self._home,
                landed_state=self._landed_state,
                last_statustext=last[2] if last else "",
                statustext_age_s=now - last[0] if last else math.inf,
                battery_pct=self._battery[0],
                battery_v=self._battery[1],
                gps_fix_type=self._gps_fix,
                recent_texts=tuple((now - t, sev, text) for t, sev, text in self._texts),
            )

    def _recent_text(self, since: float) -> str:
        """The newest STATUSTEXT received after ``since`` (monotonic), else ''."""
        with self._lock:
            return self._texts[-1][2] if self._texts and self._texts[-1][0] >= since else ""

    # ------------------------------------------------------------ commands
    def _command(self, command: int, params: tuple[float, ...], timeout_s: float) -> int:
        """Send COMMAND_LONG and return its COMMAND_ACK's result (a backend's job)."""
        raise NotImplementedError

    def _checked(
        self, command: int, params: tuple[float, ...], timeout_s: float, what: str
    ) -> None:
        """A command that must be ACCEPTED; CommandRejected quotes the autopilot's reason."""
        sent_t = time.monotonic()
        result = self._command(command, params, timeout_s)
        if result != M.MAV_RESULT_ACCEPTED:
            raise self._rejected(f"{what}: {M.command_name(command)} answered "
                                 f"{M.MAV_RESULT_NAMES.get(result, result)}", sent_t)

    def _rejected(self, text: str, sent_t: float) -> CommandRejected:
        """CommandRejected for ``text``, with the autopilot's STATUSTEXT of the moment."""
        reason = self._recent_text(since=sent_t - 1.0)
        return CommandRejected(text + (f" (autopilot says: {reason!r})" if reason else ""))

    def set_mode(self, name: str, timeout_s: float) -> None:
        """DO_SET_MODE by generic name; ACK checked."""
        params = M.encode_mode(self.autopilot, name)
        self._checked(
            M.MAV_CMD_DO_SET_MODE, tuple(float(v) for v in params), timeout_s, f"mode {name}"
        )

    def takeoff(self, alt_m: float, timeout_s: float) -> None:
        """MAV_CMD_NAV_TAKEOFF, p7 = altitude above home (ArduPilot GUIDED semantics)."""
        self._checked(
            M.MAV_CMD_NAV_TAKEOFF,
            (0, 0, 0, math.nan, math.nan, math.nan, float(alt_m)),
            timeout_s,
            f"take-off to {alt_m:.1f} m",
        )

    def _request_intervals(self, streams: dict[str, float], timeout_s: float) -> None:
        """SET_MESSAGE_INTERVAL (µs) for each named message; a refusal is logged, not raised."""
        for name, us in streams.items():
            result = self._command(M.MAV_CMD_SET_MESSAGE_INTERVAL, (M.MSG_ID[name], us), timeout_s)
            if result != M.MAV_RESULT_ACCEPTED:
                log.warning("SET_MESSAGE_INTERVAL %s answered %s", name,
                            M.MAV_RESULT_NAMES.get(result, result))

    # ---------------------------------------------------------- parameters
    def _send_raw(self, name: str, fields: dict[str, Any]) -> None:
        """Send one MAVLink message by name and fields (a backend's job)."""
        raise NotImplementedError

    def get_param(self, name: str, timeout_s: float) -> float:
        """A parameter's value (PARAM_REQUEST_READ, answered by PARAM_VALUE).

        Raises:
            FlightTimeout: no PARAM_VALUE for ``name`` within ``timeout_s``.
        """
        return self._param_exchange(name, None, timeout_s)

    def set_param(self, name: str, value: float, is_int: bool, timeout_s: float) -> None:
        """Set a parameter and check the autopilot's PARAM_VALUE echo.

        Raises:
            FlightTimeout: no echo; CommandRejected: the echo shows another value.
        """
        got = self._param_exchange(name, (value, is_int), timeout_s)
        if abs(got - value) > 1e-3 * max(1.0, abs(value)):
            raise CommandRejected(f"parameter {name}: set to {value:g}, autopilot kept {got:g}")

    def _param_exchange(self, name: str, new: tuple[float, bool] | None,
                        timeout_s: float) -> float:
        sent_t = time.monotonic()
        deadline = sent_t + timeout_s
        while True:
            if new is None:
                self._send_raw("PARAM_REQUEST_READ", {"param_id": name, "param_index": -1})
            else:
                raw, ptype = encode_param(self.autopilot, *new)
                self._send_raw("PARAM_SET", {"param_id": name, "param_value": raw,
                                             "param_type": ptype})
            resend = min(deadline, time.monotonic() + 1.0)
            with self._lock:
                while True:
                    got = self._params.get(name)
                    if got is not None and got[0] >= sent_t:
                        return decode_param(self.autopilot, got[1], got[2])
                    left = resend - time.monotonic()
                    if left <= 0:
                        break
                    self._lock.wait(left)
            if time.monotonic() >= deadline:
                raise FlightTimeout(f"no PARAM_VALUE for {name} within {timeout_s:.1f} s")

    # --------------------------------------------------------------- fence
    def _send_fence_items(self, fence: FenceSpec, timeout_s: float) -> None:
        """Upload ``fence`` as mission items of type FENCE (a backend's job)."""
        raise NotImplementedError

    def _clear_fence_items(self, timeout_s: float) -> None:
        """MISSION_CLEAR_ALL of type FENCE (a backend's job)."""
        raise NotImplementedError

    def upload_fence(self, fence: FenceSpec, timeout_s: float) -> None:
        """Fence items, then the parameters that make the autopilot enforce them (their
        old values remembered for :meth:`clear_fence`)."""
        self._send_fence_items(fence, timeout_s)
        for name, (value, is_int) in fence_params(self.autopilot, fence).items():
            if name not in self._fence_saved:
                self._fence_saved[name] = (self.get_param(name, timeout_s), is_int)
            self.set_param(name, value, is_int, timeout_s)

    def clear_fence(self, timeout_s: float) -> None:
        """Put the fence parameters back (enable first), then remove the fence items."""
        for name, (old, is_int) in reversed(list(self._fence_saved.items())):
            self.set_param(name, old, is_int, timeout_s)
            del self._fence_saved[name]
        self._clear_fence_items(timeout_s)


#: MAV_PARAM_TYPE values used here.
PARAM_INT32 = 6
PARAM_REAL32 = 9
_INT_TYPES = {1, 2, 3, 4, 5, 6}


def encode_param(autopilot: str, value: float, is_int: bool) -> tuple[float, int]:
    """(param_value, param_type) for PARAM_SET: PX4 puts an integer's bytes into the
    float field, ArduPilot takes the number itself."""
    if not is_int:
        return float(value), PARAM_REAL32
    if autopilot == M.PX4:
        return struct.unpack("<f", struct.pack("<i", int(value)))[0], PARAM_INT32
    return float(int(value)), PARAM_INT32


def decode_param(autopilot: str, raw: float, ptype: int) -> float:
    """A PARAM_VALUE's number (PX4 integers byte-wise, ArduPilot's as they are)."""
    if autopilot == M.PX4 and ptype in _INT_TYPES:
        return float(struct.unpack("<i", struct.pack("<f", raw))[0])
    return float(raw)


def fence_params(autopilot: str, fence: FenceSpec) -> dict[str, tuple[float, bool]]:
    """The parameters that make the autopilot enforce uploaded fence items, in the order
    they are set: name -> (value, is an integer).

    PX4 (``src/modules/navigator/geofence_params.yaml``): ``GF_ACTION`` 5 Land or 3
    Return, ``GF_MAX_VER_DIST`` the ceiling above home. ArduPilot
    (``libraries/AC_Fence/AC_Fence.cpp``): ``FENCE_TYPE`` polygon (4) plus the ceiling
    (1), ``FENCE_ALT_MAX``, ``FENCE_ACTION`` 2 always land or 1 RTL, then
    ``FENCE_ENABLE`` 1 last.
    """
    land = fence.action == "land"
    if autopilot == M.PX4:
        out: dict[str, tuple[float, bool]] = {}
        if fence.max_alt_m is not None:
            out["GF_MAX_VER_DIST"] = (float(fence.max_alt_m), False)
        out["GF_ACTION"] = (5.0 if land else 3.0, True)
        return out
    out = {"FENCE_TYPE": (4.0 + (1.0 if fence.max_alt_m is not None else 0.0), True)}
    if fence.max_alt_m is not None:
        out["FENCE_ALT_MAX"] = (float(fence.max_alt_m), False)
    out["FENCE_ACTION"] = (2.0 if land else 1.0, True)
    out["FENCE_ENABLE"] = (1.0, True)
    return out
