"""The messages the emulated autopilot sends: heartbeat, telemetry streams, replies.

:class:`MessagesMixin` builds each message from the vehicle's state (one small builder
per message) and sends the streams that are due: PX4's default streams, or only what a
client asked for on ArduPilot (every ``SRn_*`` default rate is 0 on ArduCopter).
"""

from __future__ import annotations

from typing import Any

from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge._mav import mavlink2
from geonav.mavlink_bridge.emulator_config import EmulatorFields


class MessagesMixin(EmulatorFields):
    """Message builders and the stream scheduler (mixed into :class:`Emulator`)."""

    def _setup_streams(self) -> None:
        if self.flavour == M.PX4:
            pos = 1.0 / self.cfg.position_rate_hz
            self._intervals = {
                "LOCAL_POSITION_NED": pos,
                "GLOBAL_POSITION_INT": pos,
                "SYS_STATUS": 1.0,
                "EXTENDED_SYS_STATE": 1.0,
                "HOME_POSITION": 2.0,
                "ATTITUDE": pos,
                "GPS_RAW_INT": 1.0,
                "BATTERY_STATUS": 2.0,
            }
        else:
            # ArduCopter: every SRn_* default stream rate is 0.
            self._intervals = {}

    def _time_boot_ms(self) -> int:
        return int(self.t_s * 1000) & 0xFFFFFFFF

    def _heartbeat(self) -> Any:
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            M.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
        )
        if not self.booted:
            status = M.MAV_STATE_BOOT
        elif self.armed:
            # PX4 HEARTBEAT.hpp: armed and a failsafe active -> CRITICAL (ArduCopter alike).
            status = M.MAV_STATE_CRITICAL if self.failsafe else M.MAV_STATE_ACTIVE
        elif self.flavour == M.PX4 and self.cfg.preflight_fail:
            # PX4's HEARTBEAT.hpp: STANDBY only while pre_flight_checks_pass, else UNINIT.
            status = M.MAV_STATE_UNINIT
            if self.t_s - self._preflight_text_t >= 5.0:
                self._preflight_text_t = self.t_s
                self._statustext(4, self.cfg.preflight_fail)
        else:
            status = M.MAV_STATE_STANDBY
        autopilot = M.MAV_AUTOPILOT_PX4 if self.flavour == M.PX4 else M.MAV_AUTOPILOT_ARDUPILOTMEGA
        custom = M.custom_mode_value(self.flavour, self.mode)
        return self._mav.heartbeat_encode(M.MAV_TYPE_QUADROTOR, autopilot, base, custom, status, 3)

    def _build(self, name: str) -> Any | None:
        """The message ``name`` as the vehicle would send it now (None: it has none)."""
        builder = getattr(self, "_msg_" + name.lower(), None)
        return None if builder is None else builder()

    def _msg_heartbeat(self) -> Any:
        return self._heartbeat()

    def _msg_local_position_ned(self) -> Any | None:
        if not self._position_valid():
            return None
        p, v = self.pos, self.vel
        return self._mav.local_position_ned_encode(
            self._time_boot_ms(), p[0], p[1], p[2], v[0], v[1], v[2]
        )

    def _msg_global_position_int(self) -> Any | None:
        if not self._position_valid():
            return None
        q = self.lonlat_of(self.pos[0], self.pos[1], self.pos[2])
        return self._mav.global_position_int_encode(
            self._time_boot_ms(), int(q.lat_deg * 1e7), int(q.lon_deg * 1e7),
            int(q.alt_m * 1000), int(-self.pos[2] * 1000), int(self.vel[0] * 100),
            int(self.vel[1] * 100), int(self.vel[2] * 100), 0,
        )

    def _msg_home_position(self) -> Any | None:
        if self.origin is None:
            return None
        h = self._home_ned()
        q = self.home
        return self._mav.home_position_encode(
            int(q.lat_deg * 1e7), int(q.lon_deg * 1e7), int(q.alt_m * 1000),
            h[0], h[1], h[2], [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
        )

    def _msg_gps_global_origin(self) -> Any | None:
        if self.origin is None:
            return None
        o = self.origin
        return self._mav.gps_global_origin_encode(
            int(o.lat_deg * 1e7), int(o.lon_deg * 1e7), int(o.alt_m * 1000)
        )

    def _msg_sys_status(self) -> Any:
        sensors = 0x3F | (0x20 if self._position_valid() else 0)
        volts_mv = int(round((13.2 + 3.6 * self.battery / 100.0) * 1000))
        return self._mav.sys_status_encode(
            sensors, sensors, sensors, 100, volts_mv, 500, int(round(self.battery)),
            0, 0, 0, 0, 0, 0
        )

    def _msg_battery_status(self) -> Any:
        cell_mv = int(round((13.2 + 3.6 * self.battery / 100.0) * 1000 / 4))
        return self._mav.battery_status_encode(
            0, 0, 0, 32767, [cell_mv] * 4 + [65535] * 6, 500, -1, -1, int(round(self.battery)),
        )

    def _msg_extended_sys_state(self) -> Any:
        if self.landed:
            state = M.MAV_LANDED_STATE_ON_GROUND
        elif self.mode == "land" or (self.mode == "rtl" and self._rtl_phase == "land"):
            state = M.MAV_LANDED_STATE_LANDING
        else:
            state = M.MAV_LANDED_STATE_IN_AIR
        return self._mav.extended_sys_state_encode(0, state)

    def _msg_attitude(self) -> Any:
        return self._mav.attitude_encode(self._time_boot_ms(), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def _msg_gps_raw_int(self) -> Any:
        q = self.home if self.origin is None else self.lonlat_of(*self.pos)
        fix = 0 if self._gps_lost or self.t_s < self.cfg.origin_s else 3
        return self._mav.gps_raw_int_encode(
            int(self.t_s * 1e6), fix, int(q.lat_deg * 1e7), int(q.lon_deg * 1e7),
            int(q.alt_m * 1000), 80, 120, 0, 0, 12 if fix else 0,
        )

    def _msg_position_target_local_ned(self) -> Any | None:
        if self.target is None:
            return None
        t = self.target
        return self._mav.position_target_local_ned_encode(
            self._time_boot_ms(), M.MAV_FRAME_LOCAL_NED, M.TYPE_MASK_POSITION_YAW,
            t[0], t[1], t[2], 0, 0, 0, 0, 0, 0, 0, 0,
        )

    def _msg_autopilot_version(self) -> Any:
        caps = (
            mavlink2.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            | mavlink2.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | mavlink2.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | mavlink2.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
            | mavlink2.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        )
        version = (1 << 24) | (15 << 16) if self.flavour == M.PX4 else (4 << 24) | (7 << 16)
        return self._mav.autopilot_version_encode(
            caps, version | 0xFF, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0,
            0x47454F4E4156 + self.cfg.system_id,
        )

    def _send_origin(self) -> None:
        msg = self._build("GPS_GLOBAL_ORIGIN")
        if msg is not None:
            self._send(msg)

    def _send_home(self) -> None:
        msg = self._build("HOME_POSITION")
        if msg is not None:
            self._send(msg)

    def _send_due(self) -> None:
        due = dict(self._intervals)
        due["HEARTBEAT"] = 1.0
        for name, interval in due.items():
            if interval <= 0:
                continue
            if self.t_s >= self._next_due.get(name, 0.0):
                self._next_due[name] = self.t_s + interval
                msg = self._build(name)
                if msg is not None:
                    self._send(msg)
