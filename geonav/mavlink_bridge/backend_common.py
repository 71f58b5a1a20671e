"""What both Vehicle backends share: the telemetry store, the state snapshot, the
autopilot's text messages, and the checked command path.

A backend (pymavlink or MAVSDK) owns its link and turns what it receives into calls
of the ``_on_*`` methods here; :meth:`LinkState.state` turns the store into a
:class:`~geonav.mavlink_bridge.vehicle.VehicleState`. Commands a backend sends as
COMMAND_LONG go through its ``_command`` (send, wait for the matching COMMAND_ACK,
return its result) and :meth:`LinkState._checked`, which turns a result other than
ACCEPTED into :class:`~geonav.errors.CommandRejected` quoting the autopilot's latest
STATUSTEXT, so both backends refuse in the same words.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from geonav.errors import CommandRejected
from geonav.geo import LocalNED, LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.vehicle import Connection, VehicleState

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
        self._texts: collections.deque[tuple[float, str]] = collections.deque(maxlen=20)

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
        """One STATUSTEXT, ``severity`` in MAVLink's numbering (0 EMERGENCY .. 7 DEBUG)."""
        with self._lock:
            self._texts.append((time.monotonic(), text))
        level = logging.WARNING if severity <= 4 else logging.INFO
        AUTOPILOT_LOG.log(level, "autopilot: %s", text)
        if self.on_statustext is not None:
            self.on_statustext(severity, text)

    # --------------------------------------------------------------- state
    def state(self) -> VehicleState:
        """The latest telemetry snapshot.

        Raises:
            FlightError: no autopilot heartbeat yet.
        """
        from geonav.errors import FlightError

        now = time.monotonic()
        with self._lock:
            hb = self._hb
            if hb is None:
                raise FlightError("not connected: no autopilot heartbeat yet")
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
                last_statustext=self._texts[-1][1] if self._texts else "",
                statustext_age_s=now - self._texts[-1][0] if self._texts else math.inf,
            )

    def _recent_text(self, since: float) -> str:
        """The newest STATUSTEXT received after ``since`` (monotonic), else ''."""
        with self._lock:
            return self._texts[-1][1] if self._texts and self._texts[-1][0] >= since else ""

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
