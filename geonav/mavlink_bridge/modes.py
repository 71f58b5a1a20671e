"""Autopilot flavours, flight-mode numbers and MAVLink constants (no pymavlink import).

Sources: PX4 ``src/modules/commander/px4_custom_mode.h`` (custom_mode packs
main mode in bits 16-23 and sub mode in bits 24-31) and ArduPilot
``ArduCopter/mode.h`` (custom_mode is the mode number); see
``shared/notes/mavlink.md`` sections 2.2 and 3.1.
"""

from __future__ import annotations

from geonav.errors import FlightError

PX4 = "px4"
ARDUPILOT = "ardupilot"

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_PX4 = 12
MAV_TYPE_QUADROTOR = 2
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_COMP_ID_AUTOPILOT1 = 1
MAV_COMP_ID_ONBOARD_COMPUTER = 191
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128

MAV_STATE_UNINIT = 0
MAV_STATE_BOOT = 1
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAV_STATE_CRITICAL = 5
MAV_STATE_EMERGENCY = 6
MAV_STATE_FLIGHT_TERMINATION = 8
#: HEARTBEAT system_status values an autopilot shows while a failsafe is active (PX4
#: ``HEARTBEAT.hpp``: armed and ``vehicle_status.failsafe`` -> CRITICAL; ArduCopter
#: ``GCS_MAVLink_Copter.cpp``: radio, battery, GCS, EKF, terrain failsafes -> CRITICAL).
FAILSAFE_STATES = (MAV_STATE_CRITICAL, MAV_STATE_EMERGENCY, MAV_STATE_FLIGHT_TERMINATION)

MAV_SEVERITY_CRITICAL = 2
MAV_SEVERITY_WARNING = 4

MAV_FRAME_LOCAL_NED = 1
#: position + yaw, ignore velocity, acceleration and yaw rate (0x09F8).
TYPE_MASK_POSITION_YAW = 2552

MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_NAV_LAND = 21
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_GET_HOME_POSITION = 410
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION = 5001
MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION = 5003

MAV_MISSION_TYPE_FENCE = 1
MAV_MISSION_ACCEPTED = 0
MAV_FRAME_GLOBAL = 0

#: the MAV_CMD names geonav sends, for messages ("MAV_CMD_NAV_LAND").
CMD_NAMES = {
    MAV_CMD_NAV_RETURN_TO_LAUNCH: "NAV_RETURN_TO_LAUNCH",
    MAV_CMD_NAV_LAND: "NAV_LAND",
    MAV_CMD_NAV_TAKEOFF: "NAV_TAKEOFF",
    MAV_CMD_DO_SET_MODE: "DO_SET_MODE",
    MAV_CMD_COMPONENT_ARM_DISARM: "COMPONENT_ARM_DISARM",
    MAV_CMD_SET_MESSAGE_INTERVAL: "SET_MESSAGE_INTERVAL",
    MAV_CMD_REQUEST_MESSAGE: "REQUEST_MESSAGE",
}


def command_name(command: int) -> str:
    """``MAV_CMD_*`` name of a command id."""
    return "MAV_CMD_" + CMD_NAMES.get(command, str(command))


MAV_RESULT_NAMES = {
    0: "ACCEPTED",
    1: "TEMPORARILY_REJECTED",
    2: "DENIED",
    3: "UNSUPPORTED",
    4: "FAILED",
    5: "IN_PROGRESS",
    6: "CANCELLED",
    7: "COMMAND_LONG_ONLY",
    8: "COMMAND_INT_ONLY",
    9: "COMMAND_UNSUPPORTED_MAV_FRAME",
}
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4
MAV_RESULT_IN_PROGRESS = 5

MAV_LANDED_STATE_UNDEFINED = 0
MAV_LANDED_STATE_ON_GROUND = 1
MAV_LANDED_STATE_IN_AIR = 2
MAV_LANDED_STATE_TAKEOFF = 3
MAV_LANDED_STATE_LANDING = 4

# Message ids used with SET_MESSAGE_INTERVAL / REQUEST_MESSAGE.
MSG_ID = {
    "HEARTBEAT": 0,
    "SYS_STATUS": 1,
    "GPS_RAW_INT": 24,
    "ATTITUDE": 30,
    "LOCAL_POSITION_NED": 32,
    "GLOBAL_POSITION_INT": 33,
    "GPS_GLOBAL_ORIGIN": 49,
    "POSITION_TARGET_LOCAL_NED": 85,
    "BATTERY_STATUS": 147,
    "AUTOPILOT_VERSION": 148,
    "HOME_POSITION": 242,
    "EXTENDED_SYS_STATE": 245,
    "STATUSTEXT": 253,
}

# PX4 (main, sub) per generic mode name.
PX4_MODES: dict[str, tuple[int, int]] = {
    "manual": (1, 0),
    "altctl": (2, 0),
    "posctl": (3, 0),
    "hold": (4, 3),
    "takeoff": (4, 2),
    "mission": (4, 4),
    "rtl": (4, 5),
    "land": (4, 6),
    "acro": (5, 0),
    "offboard": (6, 0),
    "stabilized": (7, 0),
}
# ArduCopter mode numbers per generic mode name.
ARDUPILOT_MODES: dict[str, int] = {
    "stabilize": 0,
    "acro": 1,
    "althold": 2,
    "auto": 3,
    "guided": 4,
    "loiter": 5,
    "hold": 5,  # generic name for LOITER (decoded as "loiter")
    "rtl": 6,
    "circle": 7,
    "land": 9,
    "poshold": 16,
    "brake": 17,
    "smart_rtl": 21,
}

#: the mode in which each autopilot follows SET_POSITION_TARGET_LOCAL_NED.
AUTONOMY_MODE = {PX4: "offboard", ARDUPILOT: "guided"}


def flavour_from_heartbeat(autopilot: int) -> str:
    """PX4 or ArduPilot from ``HEARTBEAT.autopilot``; FlightError for anything else."""
    if autopilot == MAV_AUTOPILOT_PX4:
        return PX4
    if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return ARDUPILOT
    raise FlightError(
        f"HEARTBEAT autopilot={autopilot} is neither PX4 (12) nor ArduPilot (3); "
        "geonav flies PX4 and ArduPilot Copter only"
    )


def encode_mode(flavour: str, name: str) -> tuple[int, int, int]:
    """``MAV_CMD_DO_SET_MODE`` params (base mode, custom mode, custom sub mode) for a mode name."""
    if flavour == PX4:
        if name not in PX4_MODES:
            raise FlightError(f"PX4 has no mode {name!r}; known: {sorted(PX4_MODES)}")
        main, sub = PX4_MODES[name]
        return MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub
    if name not in ARDUPILOT_MODES:
        raise FlightError(f"ArduPilot has no mode {name!r}; known: {sorted(ARDUPILOT_MODES)}")
    return MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ARDUPILOT_MODES[name], 0


def custom_mode_value(flavour: str, name: str) -> int:
    """``HEARTBEAT.custom_mode`` for a mode name."""
    if flavour == PX4:
        main, sub = PX4_MODES[name]
        return (main << 16) | (sub << 24)
    return ARDUPILOT_MODES[name]


def decode_mode(flavour: str, custom_mode: int) -> str:
    """Generic mode name from ``HEARTBEAT.custom_mode`` (``"px4:main.sub"`` style if unknown)."""
    if flavour == PX4:
        main = (custom_mode >> 16) & 0xFF
        sub = (custom_mode >> 24) & 0xFF
        for name, (m, s) in PX4_MODES.items():
            if m == main and (s == sub or (s == 0 and main != 4)):
                return name
        return f"px4:{main}.{sub}"
    for name, number in ARDUPILOT_MODES.items():
        if number == custom_mode:
            return name
    return f"ardupilot:{custom_mode}"
