"""The ``Vehicle`` protocol both backends implement, its state record, and connection URLs.

This module owns the contract only and imports no backend (the factory that picks
one is :func:`geonav.mavlink_bridge.backends.open_vehicle`). The protocol is
synchronous and thread-safe: the flight loop, the setpoint pump and the watchdogs
call it from their own threads. Every method that sends a command returns only
after the autopilot's ``COMMAND_ACK`` was checked; a result other than ACCEPTED
raises :class:`geonav.errors.CommandRejected`, no answer raises
:class:`geonav.errors.FlightTimeout`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from geonav.errors import ConfigError
from geonav.geo import LocalNED, LonLat


@dataclass(frozen=True)
class VehicleState:
    """A snapshot of what the vehicle last reported.

    Attributes:
        autopilot: ``"px4"`` or ``"ardupilot"`` (from HEARTBEAT.autopilot).
        system_status: HEARTBEAT.system_status (MAV_STATE; 3 STANDBY, 4 ACTIVE).
        mode: generic mode name (``"offboard"``, ``"guided"``, ``"land"``, ...).
        armed: whether the motors are armed.
        heartbeat_age_s: seconds since the last autopilot HEARTBEAT.
        position: last LOCAL_POSITION_NED (metres about the EKF origin) or None.
        velocity_ned_mps: last (vn, ve, vd) in m/s or None.
        position_age_s: seconds since the last LOCAL_POSITION_NED (inf if none).
        origin: EKF origin (GPS_GLOBAL_ORIGIN) or None.
        home: HOME_POSITION or None.
        landed_state: MAV_LANDED_STATE (0 when unknown).
        last_statustext: the most recent STATUSTEXT, "" if none.
        statustext_age_s: seconds since that STATUSTEXT (inf if none): quote only fresh ones.
        battery_pct: remaining battery, percent (SYS_STATUS / BATTERY_STATUS
            ``battery_remaining``); None when the autopilot does not say.
        battery_v: battery voltage, volts; None when unknown.
        gps_fix_type: GPS_RAW_INT ``fix_type`` (0-1 no fix, 2 2D, 3 3D, ...); None when
            no GPS_RAW_INT was seen.
        recent_texts: the last STATUSTEXTs as (age s, MAV_SEVERITY, text), oldest first.
    """

    autopilot: str
    system_status: int
    mode: str
    armed: bool
    heartbeat_age_s: float
    position: LocalNED | None
    velocity_ned_mps: tuple[float, float, float] | None
    position_age_s: float
    origin: LonLat | None
    home: LonLat | None
    landed_state: int = 0
    last_statustext: str = ""
    statustext_age_s: float = float("inf")
    battery_pct: float | None = None
    battery_v: float | None = None
    gps_fix_type: int | None = None
    recent_texts: tuple[tuple[float, int, str], ...] = ()

    @property
    def speed_mps(self) -> float:
        """Norm of the NED velocity (inf when unknown)."""
        if self.velocity_ned_mps is None:
            return float("inf")
        vn, ve, vd = self.velocity_ned_mps
        return float((vn * vn + ve * ve + vd * vd) ** 0.5)


@dataclass(frozen=True)
class FenceSpec:
    """A fence for the autopilot to enforce itself (MAVLink fence items and parameters).

    Attributes:
        polygon: inclusion polygon vertices, WGS 84, in order.
        circle: (centre, radius m) of an inclusion circle, or None.
        max_alt_m: ceiling above home, metres (None: none).
        action: what the autopilot does on a breach: ``"land"`` or ``"rtl"``.
    """

    polygon: tuple[LonLat, ...]
    circle: tuple[LonLat, float] | None = None
    max_alt_m: float | None = None
    action: str = "land"


@runtime_checkable
class Vehicle(Protocol):
    """What the flight loop needs from an autopilot link."""

    autopilot: str
    on_statustext: Callable[[int, str], None] | None

    def connect(self, timeout_s: float) -> None:
        """Open the link and wait for the autopilot's HEARTBEAT; sets ``autopilot``."""

    def state(self) -> VehicleState:
        """The latest telemetry snapshot."""

    def request_telemetry(self, rate_hz: float, timeout_s: float) -> None:
        """Ask for position, origin, home and status streams (ArduPilot sends none by default)."""

    def set_origin(self, origin: LonLat) -> None:
        """Send SET_GPS_GLOBAL_ORIGIN (for vehicles without GPS)."""

    def set_mode(self, name: str, timeout_s: float) -> None:
        """Change flight mode by generic name (``"offboard"``, ``"guided"``, ``"land"``, ...)."""

    def arm(self, timeout_s: float) -> None:
        """One arming attempt; CommandRejected carries the autopilot's reason."""

    def disarm(self, timeout_s: float) -> None:
        """Disarm (only on the ground)."""

    def takeoff(self, alt_m: float, timeout_s: float) -> None:
        """MAV_CMD_NAV_TAKEOFF to ``alt_m`` above home (ArduPilot, in GUIDED)."""

    def land(self, timeout_s: float) -> None:
        """MAV_CMD_NAV_LAND (ACK checked; the caller confirms the mode on the heartbeat)."""

    def return_to_launch(self, timeout_s: float) -> None:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH (ACK checked; the caller confirms the mode)."""

    def send_position_target(self, target: LocalNED, yaw_deg: float) -> None:
        """One SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED, type_mask 2552)."""

    def stop_setpoints(self) -> None:
        """Stop any setpoint resending the backend itself does (MAVSDK's 20 Hz offboard)."""

    def upload_fence(self, fence: FenceSpec, timeout_s: float) -> None:
        """Give the autopilot ``fence`` (mission protocol, fence items) and enable it with
        its breach action (PX4 ``GF_ACTION``; ArduPilot ``FENCE_ENABLE``/``FENCE_ACTION``),
        remembering the parameters it changed."""

    def clear_fence(self, timeout_s: float) -> None:
        """Remove geonav's fence items and put the changed parameters back."""

    def close(self) -> None:
        """Close the link; safe to call twice, never raises."""


@dataclass(frozen=True)
class Connection:
    """A parsed connection string.

    Attributes:
        kind: ``udpin``, ``udpout``, ``tcp`` (client), ``tcpin`` (server) or ``serial``.
        host: host or serial device path.
        port: UDP/TCP port, or the serial baud rate.
    """

    kind: str
    host: str
    port: int
    raw: str = field(default="", compare=False)

    def pymavlink(self) -> tuple[str, int]:
        """(device, baud) for ``mavutil.mavlink_connection``."""
        if self.kind == "serial":
            return self.host, self.port
        return f"{self.kind}:{self.host}:{self.port}", 115200

    def mavsdk(self) -> str:
        """The MAVSDK connection URL."""
        if self.kind == "serial":
            return f"serial://{self.host}:{self.port}"
        kind = "tcpout" if self.kind == "tcp" else self.kind
        return f"{kind}://{self.host}:{self.port}"


_URL = re.compile(r"^(?P<kind>[a-z]+):(?://)?(?P<host>[^:]*):(?P<port>\d+)$")


def parse_connection(url: str, baud: int | None = None) -> Connection:
    """Parse a connection string as users know them.

    Accepts pymavlink style (``udpin:0.0.0.0:14540``, ``udpout:10.0.0.2:14550``,
    ``tcp:127.0.0.1:5760``, ``tcpin:0.0.0.0:5760``, ``/dev/ttyACM0:921600``,
    ``serial:/dev/ttyUSB0:57600``) and MAVSDK style (``udpin://0.0.0.0:14540``,
    ``tcpout://host:port``, ``serial:///dev/ttyACM0:57600``).

    Args:
        url: the connection string.
        baud: baud rate for a serial device given without one.

    Raises:
        ConfigError: the string is not understood; the message shows examples.
    """
    text = url.strip()
    if text.startswith("serial:") or text.startswith("/dev/") or text.upper().startswith("COM"):
        path = text.removeprefix("serial:").removeprefix("//")
        dev, sep, rate = path.rpartition(":")
        if sep and rate.isdigit():
            return Connection("serial", dev, _baud(int(rate), url), raw=url)
        if baud is None:
            raise ConfigError(f"serial connection {url!r} needs a baud rate, e.g. {url}:921600")
        return Connection("serial", path, _baud(int(baud), url), raw=url)
    m = _URL.match(text)
    if m is None:
        raise ConfigError(
            f"connection {url!r} not understood; use udpin:0.0.0.0:14540, udpout:HOST:PORT, "
            "tcp:127.0.0.1:5760 or /dev/ttyACM0:921600"
        )
    kind = m["kind"]
    kind = {"udp": "udpin", "tcpout": "tcp", "tcpclient": "tcp"}.get(kind, kind)
    if kind not in ("udpin", "udpout", "tcp", "tcpin"):
        raise ConfigError(
            f"connection kind {m['kind']!r} in {url!r}: use udpin, udpout, tcp, tcpin"
        )
    port = int(m["port"])
    if not 1 <= port <= 65535:
        raise ConfigError(f"connection {url!r}: port {port} is not a port (1..65535); PX4 SITL "
                          "listens on 14540, ArduPilot SITL on tcp 5760")
    return Connection(kind, m["host"] or "0.0.0.0", port, raw=url)


#: Serial baud rates geonav accepts (the common ones run from 9600 to 921600; USB links
#: reach a few Mbaud).
BAUD_RANGE = (50, 20_000_000)


def _baud(rate: int, url: str) -> int:
    if not BAUD_RANGE[0] <= rate <= BAUD_RANGE[1]:
        raise ConfigError(f"serial connection {url!r}: baud rate {rate} is out of range "
                          f"{BAUD_RANGE[0]}..{BAUD_RANGE[1]}; autopilots use 57600 or 921600")
    return rate
