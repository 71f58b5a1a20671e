"""The emulator's settings and the records it keeps of what it received.

:class:`EmulatorConfig` holds the emulated vehicle's settings (times are emulated
seconds); :class:`ReceivedSetpoint` and :class:`ReceivedCommand` are what the emulator
records of every setpoint and command, for tests to assert on.
"""

from __future__ import annotations

import math
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from geonav.errors import FlightError
from geonav.geo import LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.frames import LocalFrame

#: wall seconds the emulator's loop waits for packets per iteration.
TICK_WALL_S = 0.01


@dataclass
class EmulatorConfig:
    """Settings of the emulated vehicle. Times are emulated seconds.

    Attributes:
        autopilot: ``"px4"`` or ``"ardupilot"``.
        home: home position (also the EKF origin when ``gps`` is true).
        listen: where to listen: ``udp:127.0.0.1:PORT`` (replies to every
            peer that sent a packet), ``tcp:127.0.0.1:PORT`` (server), or
            ``udpout:HOST:PORT`` (send there first, as PX4 SITL does to
            14540). Port 0 picks a free port (see ``Emulator.port``).
        system_id: MAVLink system id of the vehicle (component id is 1).
        time_scale: emulated seconds per wall second.
        boot_s: time in MAV_STATE_BOOT.
        prearm_s: arming fails with a PreArm STATUSTEXT before this time.
        origin_s: time at which the EKF origin (GPS_GLOBAL_ORIGIN) is set.
        local_position_s: time from which LOCAL_POSITION_NED is valid.
        gps: whether the vehicle sets its EKF origin from GPS; if false the
            origin must come from SET_GPS_GLOBAL_ORIGIN.
        max_speed_mps: horizontal speed limit.
        max_climb_mps: vertical speed limit.
        max_accel_mps2: acceleration limit (per axis group).
        natural_freq_hz: natural frequency of the position loop.
        damping: damping ratio of the position loop (< 1 overshoots).
        offboard_loss_s: PX4 COM_OF_LOSS_T.
        offboard_loss_action: mode PX4 takes after offboard loss
            (COM_OBL_RC_ACT; ``"land"`` or ``"hold"``).
        disarm_delay_s: auto-disarm when armed on the ground without taking
            off (PX4 COM_DISARM_PRFLT, ArduPilot DISARM_DELAY).
        land_disarm_s: disarm this long after touching down.
        land_speed_mps: descent speed in LAND/RTL.
        rtl_alt_m: RTL return altitude above home (ArduPilot RTL_ALT).
        position_rate_hz: default rate of position messages (PX4 flavour).
        max_dt_s: most emulated seconds one loop iteration may advance (at
            least two 10 ms ticks at ``time_scale``), so a process freeze
            pauses the vehicle instead of jumping it.
        airborne_alt_m: start already armed and hovering this high above
            home in the hold mode (a vehicle someone else is flying); 0: on the ground.
        preflight_fail: PX4 only: a pre-flight check that keeps failing with
            this text (the HEARTBEAT then shows UNINIT, not STANDBY, and the
            text is repeated every 5 s, as PX4 SIH did after a landing with
            "Preflight: GPS Vertical Pos Drift too high"); "" for none.
        battery_pct: battery charge at start, percent.
        battery_drain_pct_per_s: charge used per second while armed.
        battery_low_pct: below this the autopilot warns once (PX4 ``BAT_LOW_THR``,
            ArduPilot ``BATT_LOW_MAH``); 0: never.
        battery_critical_pct: below this it warns again and runs ``battery_failsafe``
            (PX4 ``BAT_CRIT_THR``, ArduPilot ``BATT_CRT_MAH``).
        battery_failsafe: ``"none"`` (a warning only: PX4's default
            ``COM_LOW_BAT_ACT`` 0), ``"rtl"`` or ``"land"``; the HEARTBEAT then shows
            CRITICAL, as both autopilots do while a failsafe is active.
        gps_failsafe_s: after a GPS loss (:meth:`Emulator.lose_gps`) in the air, the
            position estimate is gone at once and the autopilot lands this much later
            (its EKF failsafe), showing CRITICAL.
        statustext_gate: PX4 only: STATUSTEXT goes out only while a GCS heartbeat
            (any system) or an onboard-controller heartbeat from the vehicle's own system
            id was heard within 2.5 s (``streams/STATUSTEXT.hpp``,
            ``mavlink_receiver.cpp``); ArduPilot always sends it.
    """

    autopilot: str = M.PX4
    home: LonLat = field(default_factory=lambda: LonLat(4.4777, 51.9244, 0.0))
    listen: str = "udp:127.0.0.1:0"
    system_id: int = 1
    time_scale: float = 1.0
    boot_s: float = 2.0
    prearm_s: float = 5.0
    origin_s: float = 3.0
    local_position_s: float = 4.0
    gps: bool = True
    max_speed_mps: float = 5.0
    max_climb_mps: float = 3.0
    max_accel_mps2: float = 4.0
    natural_freq_hz: float = 0.35
    damping: float = 0.6
    offboard_loss_s: float = 1.0
    offboard_loss_action: str = "land"
    disarm_delay_s: float = 10.0
    land_disarm_s: float = 1.0
    land_speed_mps: float = 1.5
    rtl_alt_m: float = 15.0
    position_rate_hz: float = 10.0
    max_dt_s: float = 0.1
    airborne_alt_m: float = 0.0
    preflight_fail: str = ""
    battery_pct: float = 100.0
    battery_drain_pct_per_s: float = 0.0
    battery_low_pct: float = 15.0
    battery_critical_pct: float = 7.0
    battery_failsafe: str = "none"
    gps_failsafe_s: float = 2.0
    statustext_gate: bool = True

    def __post_init__(self) -> None:
        if self.battery_failsafe not in ("none", "rtl", "land"):
            raise FlightError(f"battery_failsafe {self.battery_failsafe!r}: none, rtl or land")
        if self.autopilot not in (M.PX4, M.ARDUPILOT):
            raise FlightError(f"emulator autopilot {self.autopilot!r}: use 'px4' or 'ardupilot'")
        if self.time_scale <= 0:
            raise FlightError(f"time_scale {self.time_scale} must be > 0")


@dataclass(frozen=True)
class ReceivedSetpoint:
    """A SET_POSITION_TARGET_LOCAL_NED as the emulator received it."""

    t_s: float
    coordinate_frame: int
    type_mask: int
    north_m: float
    east_m: float
    down_m: float
    yaw_deg: float
    mode: str
    used: bool


@dataclass(frozen=True)
class ReceivedCommand:
    """A COMMAND_LONG / COMMAND_INT and the result the emulator answered."""

    t_s: float
    command: int
    params: tuple[float, ...]
    result: int
    source: tuple[int, int] = (0, 0)


class EmulatorFields:
    """The emulated vehicle's state and the methods one part calls on another,
    declared once for the parts of :class:`~geonav.mavlink_bridge.emulator.Emulator`
    (its mixins) that share them; ``Emulator.__init__`` sets them."""

    cfg: EmulatorConfig
    flavour: str
    port: int
    t_s: float
    pos: np.ndarray
    vel: np.ndarray
    target: np.ndarray | None
    armed: bool
    landed: bool
    mode: str
    origin: LonLat | None
    home: LonLat
    setpoints: list[ReceivedSetpoint]
    commands: list[ReceivedCommand]
    events: list[tuple[float, str]]
    track: list[tuple[float, float, float, float]]
    peer_heartbeats: int
    _lock: threading.RLock
    _mav: Any
    _peers: dict[Any, Any]
    _udp: socket.socket | None
    _tcp_listen: socket.socket | None
    _udpout_addr: tuple[str, int] | None
    _link_down_until: float
    _intervals: dict[str, float]
    _next_due: dict[str, float]
    _boot_mode: str | None
    _armed_at: float | None
    _took_off: bool
    _touchdown_at: float | None
    _last_sp_t: float
    _sp_stream_start: float
    _rtl_phase: str
    _refuse_arming: str | None
    _preflight_text_t: float
    _gps_lost: bool
    _param_overrides: dict[str, float]
    _pending_reply: str | None
    _frame: LocalFrame | None
    battery: float
    failsafe: str
    fence_items: list[Any]
    fence_breached: bool
    texts: list[tuple[float, int, str, bool]]
    peer_heartbeat_ids: dict[tuple[int, int, int], float]
    _battery_warned: int
    _gps_lost_at: float | None
    _upload: dict[str, Any] | None

    _handle: Callable[[Any], None]
    _send: Callable[[Any], None]
    _statustext: Callable[[int, str], None]
    _event: Callable[[str], None]
    _position_valid: Callable[[], bool]
    _set_mode: Callable[..., None]
    _disarm: Callable[[str], None]
    _set_origin: Callable[..., None]
    _send_origin: Callable[[], None]
    _send_home: Callable[[], None]
    _home_ned: Callable[[], np.ndarray]
    _build: Callable[[str], Any | None]
    _safety_step: Callable[[float], None]
    _mission: Callable[[str, Any], None]
    _params: Callable[[], dict[str, float]]
    lonlat_of: Callable[..., LonLat]

    @property
    def booted(self) -> bool:
        """Whether the boot delay is over."""
        return self.t_s >= self.cfg.boot_s


#: message id -> name of the messages the emulator can send.
MSG_NAME = {v: k for k, v in M.MSG_ID.items()}


def num(value: float) -> float:
    """A command parameter with NaN ("unset") read as 0."""
    return 0.0 if value is None or math.isnan(value) else float(value)
