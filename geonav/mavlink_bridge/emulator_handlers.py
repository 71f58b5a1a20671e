"""What the emulated autopilot does with what it receives: commands, setpoints, params.

:class:`HandlersMixin` answers every COMMAND_LONG/COMMAND_INT with a COMMAND_ACK (mode
changes with each autopilot's refusals, arming with its pre-arm checks, take-off,
LAND, RTL, message intervals and requests), takes position setpoints as each autopilot
does (PX4: proof of life for OFFBOARD; ArduPilot: only in GUIDED and airborne), sets
the EKF origin, ArduPilot's legacy stream requests, and a minimal parameter protocol.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from geonav.geo import LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge._mav import mavlink2
from geonav.mavlink_bridge.backend_common import decode_param, encode_param
from geonav.mavlink_bridge.emulator_config import (
    MSG_NAME,
    EmulatorFields,
    ReceivedCommand,
    ReceivedSetpoint,
    num,
)


class HandlersMixin(EmulatorFields):
    """Message handlers (mixed into :class:`Emulator`)."""

    def _handle(self, msg: Any) -> None:
        """Dispatch one received message to its handler."""
        kind = msg.get_type()
        target = getattr(msg, "target_system", 0)
        if target not in (0, self.cfg.system_id):
            return  # addressed to another system
        handler = _HANDLERS.get(kind)
        if handler is not None:
            handler(self, msg)
        elif kind.startswith("MISSION_"):
            self._mission(kind, msg)

    def _on_heartbeat(self, msg: Any) -> None:
        self.peer_heartbeats += 1
        self.peer_heartbeat_ids[(msg.get_srcSystem(), msg.get_srcComponent(), msg.type)] = (
            self.t_s)

    def _on_command(self, msg: Any) -> None:
        if msg.target_component not in (0, 1):
            return
        if msg.get_type() == "COMMAND_LONG":
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                      msg.param7)
        else:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x),
                      float(msg.y), msg.z)
        result = self._command(msg.command, params)
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        self.commands.append(ReceivedCommand(self.t_s, msg.command, params, result, source))
        self._send(self._mav.command_ack_encode(msg.command, result, 0, 0, *source))
        self._after_ack(msg.command, params, result)

    def _on_set_origin(self, msg: Any) -> None:
        if self.origin is not None:
            self._event("SET_GPS_GLOBAL_ORIGIN ignored: origin already set")
            return
        self._set_origin(
            LonLat(msg.longitude / 1e7, msg.latitude / 1e7, msg.altitude / 1000.0),
            source="SET_GPS_GLOBAL_ORIGIN",
        )
        if not self.cfg.gps and self.origin is not None:
            self.home = self.origin
            self._send_home()

    def _on_request_data_stream(self, msg: Any) -> None:
        # ArduPilot's legacy stream groups: 0 all, 2 extended status, 6 position.
        interval = 1.0 / msg.req_message_rate if msg.req_message_rate > 0 else 0.0
        if not msg.start_stop:
            interval = 0.0
        groups = {
            0: ["LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "SYS_STATUS",
                "EXTENDED_SYS_STATE", "ATTITUDE", "GPS_RAW_INT"],
            2: ["SYS_STATUS", "EXTENDED_SYS_STATE", "GPS_RAW_INT"],
            6: ["LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"],
            10: ["ATTITUDE"],
        }
        for name in groups.get(msg.req_stream_id, []):
            self._intervals[name] = interval

    # ------------------------------------------------------------- parameters
    def _params(self) -> dict[str, float]:
        cfg = self.cfg
        if self.flavour == M.PX4:
            base = {
                "COM_OF_LOSS_T": cfg.offboard_loss_s,
                "COM_OBL_RC_ACT": 4.0 if cfg.offboard_loss_action == "land" else 5.0,
                "COM_DISARM_PRFLT": cfg.disarm_delay_s,
                "MIS_TAKEOFF_ALT": 2.5,
                "MPC_XY_VEL_MAX": cfg.max_speed_mps,
                "NAV_DLL_ACT": 0.0,
                "GF_ACTION": 2.0,
                "GF_MAX_VER_DIST": 0.0,
            }
        else:
            base = {
                "DISARM_DELAY": cfg.disarm_delay_s,
                "RTL_ALT": cfg.rtl_alt_m * 100,
                "FS_GCS_ENABLE": 0.0,
                "WPNAV_SPEED": cfg.max_speed_mps * 100,
                "GUID_TIMEOUT": 3.0,
                "FENCE_ENABLE": 0.0,
                "FENCE_TYPE": 7.0,
                "FENCE_ACTION": 1.0,
                "FENCE_ALT_MAX": 100.0,
            }
        base.update(self._param_overrides)
        return base

    def _send_param(self, pid: str, value: float, index: int) -> None:
        is_int = pid in _INT_PARAMS
        raw, ptype = encode_param(self.flavour, value, is_int)
        if is_int and self.flavour == M.ARDUPILOT:
            ptype = mavlink2.MAV_PARAM_TYPE_INT8  # ArduPilot says the parameter's own type
        self._send(self._mav.param_value_encode(pid.encode()[:16], raw, ptype,
                                                len(self._params()), index))

    def _param_read(self, pid: str, index: int) -> None:
        params = self._params()
        names = list(params)
        if 0 <= index < len(names):
            pid = names[index]
        if pid in params:
            self._send_param(pid, params[pid], names.index(pid))

    def _on_param_request_list(self, msg: Any) -> None:
        for i, (pid, val) in enumerate(self._params().items()):
            self._send_param(pid, val, i)

    def _on_param_request_read(self, msg: Any) -> None:
        self._param_read(msg.param_id, msg.param_index)

    def _on_param_set(self, msg: Any) -> None:
        pid = msg.param_id
        if pid in self._params():
            self._param_overrides[pid] = decode_param(self.flavour, float(msg.param_value),
                                                      int(msg.param_type))
            self._event(f"param {pid} = {self._param_overrides[pid]:g}")
        self._param_read(pid, -1)

    def _setpoint(self, msg: Any) -> None:
        used = False
        mode = self.mode
        frame_ok = msg.coordinate_frame == M.MAV_FRAME_LOCAL_NED
        pos_given = (msg.type_mask & 0b111) == 0
        if self.flavour == M.PX4:
            # Any setpoint counts as proof of life for OFFBOARD.
            if self.t_s - self._last_sp_t > self.cfg.offboard_loss_s:
                self._sp_stream_start = self.t_s
            self._last_sp_t = self.t_s
            if mode == "offboard" and frame_ok and pos_given and self._position_valid():
                used = True
        else:
            # ArduCopter ignores position targets outside GUIDED, and on the ground
            # it needs MAV_CMD_NAV_TAKEOFF to leave it.
            if mode == "guided" and frame_ok and pos_given and not self.landed and self.armed:
                used = True
        if used:
            self.target = np.array([msg.x, msg.y, msg.z], dtype=float)
        self.setpoints.append(
            ReceivedSetpoint(
                self.t_s,
                msg.coordinate_frame,
                msg.type_mask,
                float(msg.x),
                float(msg.y),
                float(msg.z),
                math.degrees(msg.yaw),
                mode,
                used,
            )
        )

    def _offboard_stream_ok(self) -> bool:
        return (
            self.t_s - self._last_sp_t <= self.cfg.offboard_loss_s
            and self.t_s - self._sp_stream_start >= min(0.5, self.cfg.offboard_loss_s / 2)
        )

    def _command(self, command: int, p: tuple[float, ...]) -> int:
        if command == M.MAV_CMD_DO_SET_MODE:
            return self._cmd_set_mode(int(num(p[1])), int(num(p[2])))
        if command == M.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._cmd_arm(num(p[0]) >= 0.5, num(p[1]) == 21196)
        if command == M.MAV_CMD_NAV_TAKEOFF:
            return self._cmd_takeoff(p[6])
        if command == M.MAV_CMD_NAV_LAND:
            if not self.armed:
                return M.MAV_RESULT_DENIED
            self._set_mode("land", why="MAV_CMD_NAV_LAND")
            return M.MAV_RESULT_ACCEPTED
        if command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            if not self.armed:
                return M.MAV_RESULT_DENIED
            self._set_mode("rtl", why="MAV_CMD_NAV_RETURN_TO_LAUNCH")
            return M.MAV_RESULT_ACCEPTED
        if command == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            name = MSG_NAME.get(int(num(p[0])))
            if name is None:
                return M.MAV_RESULT_UNSUPPORTED
            if num(p[1]) < 0:
                self._intervals[name] = 0.0
            elif num(p[1]) == 0:
                self._intervals[name] = 1.0 / self.cfg.position_rate_hz
            else:
                self._intervals[name] = p[1] / 1e6
            self._next_due[name] = 0.0
            return M.MAV_RESULT_ACCEPTED
        if command in (
            M.MAV_CMD_REQUEST_MESSAGE,
            M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
            M.MAV_CMD_GET_HOME_POSITION,
        ):
            if command == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
                name = "AUTOPILOT_VERSION"
            elif command == M.MAV_CMD_GET_HOME_POSITION:
                name = "HOME_POSITION"
            else:
                name = MSG_NAME.get(int(num(p[0])), "")
            if name not in MSG_NAME.values():
                return M.MAV_RESULT_UNSUPPORTED
            if name in ("HOME_POSITION", "GPS_GLOBAL_ORIGIN") and self.origin is None:
                return M.MAV_RESULT_TEMPORARILY_REJECTED
            self._pending_reply = name
            return M.MAV_RESULT_ACCEPTED
        return M.MAV_RESULT_UNSUPPORTED

    def _after_ack(self, command: int, params: tuple[float, ...], result: int) -> None:
        if self._pending_reply is not None:
            msg = self._build(self._pending_reply)
            self._pending_reply = None
            if msg is not None:
                self._send(msg)

    def _cmd_set_mode(self, custom: int, sub: int) -> int:
        if self.flavour == M.PX4:
            name = M.decode_mode(M.PX4, (custom << 16) | (sub << 24))
            if name.startswith("px4:"):
                return M.MAV_RESULT_DENIED
            if name == "offboard" and not self._offboard_stream_ok():
                self._statustext(4, "Switching to Offboard is currently not available")
                return M.MAV_RESULT_TEMPORARILY_REJECTED
            if (
                name in ("offboard", "hold", "rtl", "land")
                and self.booted
                and not self._position_valid()
            ):
                self._statustext(4, f"Switching to {name} requires position")
                return M.MAV_RESULT_DENIED
        else:
            name = M.decode_mode(M.ARDUPILOT, custom)
            if name.startswith("ardupilot:"):
                return M.MAV_RESULT_DENIED
            if name in ("guided", "loiter", "rtl") and self.booted and not self._position_valid():
                self._statustext(4, f"Mode change to {name.upper()} failed: requires position")
                return M.MAV_RESULT_FAILED
        if not self.booted and self._boot_mode is not None:
            # Accepted now, undone when initialisation finishes (seen on ArduCopter SITL).
            self.mode = name
            self._event(f"mode {name} (during boot)")
            return M.MAV_RESULT_ACCEPTED
        self._set_mode(name, why="DO_SET_MODE")
        return M.MAV_RESULT_ACCEPTED

    def _prearm_failure(self) -> str | None:
        if self._refuse_arming is not None:
            return self._refuse_arming
        if self.flavour == M.PX4 and self.cfg.preflight_fail:
            return self.cfg.preflight_fail
        if not self.booted:
            return "System not ready (booting)"
        if self.t_s < self.cfg.prearm_s:
            return "Gyros still settling" if self.flavour == M.ARDUPILOT else "ekf2 not ready"
        if not self._position_valid():
            return "Need Position Estimate"
        return None

    def _cmd_arm(self, arm: bool, force: bool) -> int:
        if not arm:
            if not self.landed and not force:
                return M.MAV_RESULT_DENIED
            self._disarm("command")
            return M.MAV_RESULT_ACCEPTED
        if self.armed:
            return M.MAV_RESULT_ACCEPTED
        reason = self._prearm_failure()
        if reason is not None and not force:
            prefix = "PreArm: " if self.flavour == M.ARDUPILOT else "Preflight Fail: "
            self._statustext(2, prefix + reason)
            self._event(f"arming refused: {reason}")
            return M.MAV_RESULT_FAILED
        if self.flavour == M.ARDUPILOT and self.mode not in (
            "guided",
            "stabilize",
            "loiter",
            "althold",
            "poshold",
        ):
            self._statustext(2, f"Arm: Mode not armable ({self.mode})")
            return M.MAV_RESULT_FAILED
        self.armed = True
        self._armed_at = self.t_s
        self._took_off = False
        self.target = self.target if (self.flavour == M.PX4 and self.mode == "offboard") else None
        self._event("armed")
        return M.MAV_RESULT_ACCEPTED

    def _cmd_takeoff(self, alt_m: float) -> int:
        if self.flavour == M.PX4:
            alt = alt_m if math.isfinite(alt_m) and alt_m > 0 else self._params()["MIS_TAKEOFF_ALT"]
            if not self.armed or not self.landed:
                return M.MAV_RESULT_DENIED
            self.target = np.array([self.pos[0], self.pos[1], -alt])
            self._set_mode("takeoff", why="MAV_CMD_NAV_TAKEOFF")
            return M.MAV_RESULT_ACCEPTED
        # ArduCopter: p7 is the altitude above home; FAILED unless armed, landed, GUIDED.
        if not self.armed or not self.landed or self.mode != "guided":
            self._statustext(4, "Takeoff failed: not armed, not landed or not GUIDED")
            return M.MAV_RESULT_FAILED
        if not math.isfinite(alt_m) or alt_m <= 0:
            return M.MAV_RESULT_DENIED
        self.target = np.array([self.pos[0], self.pos[1], -alt_m])
        self._took_off = True
        self._event(f"takeoff to {alt_m:.1f} m")
        return M.MAV_RESULT_ACCEPTED


#: parameters that are integers (PX4 sends their bytes in the float field).
_INT_PARAMS = {"COM_OBL_RC_ACT", "NAV_DLL_ACT", "GF_ACTION", "FS_GCS_ENABLE", "FENCE_ENABLE",
               "FENCE_TYPE", "FENCE_ACTION"}

_HANDLERS = {
    "HEARTBEAT": HandlersMixin._on_heartbeat,
    "COMMAND_LONG": HandlersMixin._on_command,
    "COMMAND_INT": HandlersMixin._on_command,
    "SET_POSITION_TARGET_LOCAL_NED": HandlersMixin._setpoint,
    "SET_GPS_GLOBAL_ORIGIN": HandlersMixin._on_set_origin,
    "REQUEST_DATA_STREAM": HandlersMixin._on_request_data_stream,
    "PARAM_REQUEST_LIST": HandlersMixin._on_param_request_list,
    "PARAM_REQUEST_READ": HandlersMixin._on_param_request_read,
    "PARAM_SET": HandlersMixin._on_param_set,
}
