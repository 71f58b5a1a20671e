"""Action -> NED conversion, connection strings, modes, geofence and pump (no emulator)."""

from __future__ import annotations

import math
import threading
import time

import pytest
from pyproj import CRS, Transformer

from geonav.errors import ConfigError, SafetyViolation
from geonav.geo import LocalNED, LonLat, SceneFrame, ScenePoint
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.conversion import TargetPlanner, step_scene
from geonav.mavlink_bridge.pump import SetpointPump
from geonav.mavlink_bridge.safety import Geofence, Watchdog
from geonav.mavlink_bridge.vehicle import VehicleState, parse_connection

SCENE_ORIGIN = LonLat(4.4777, 51.9244, 2.0)
# An EKF origin ~420 m east and ~330 m north of the scene origin, 3 m higher.
EKF_ORIGIN = LonLat(4.4838, 51.9274, 5.0)


def _independent_ned(p: ScenePoint, ekf: LonLat) -> tuple[float, float]:
    """Scene point -> (north, east) about ``ekf`` with plain pyproj, not geonav.geo."""
    tmerc = CRS.from_proj4(
        f"+proj=tmerc +lat_0={SCENE_ORIGIN.lat_deg} +lon_0={SCENE_ORIGIN.lon_deg} +k=1 "
        "+x_0=0 +y_0=0 +datum=WGS84 +units=m +type=crs"
    )
    aeqd = CRS.from_proj4(
        f"+proj=aeqd +lat_0={ekf.lat_deg} +lon_0={ekf.lon_deg} +x_0=0 +y_0=0 +datum=WGS84 "
        "+units=m +type=crs"
    )
    lon, lat = Transformer.from_crs(tmerc, "EPSG:4326", always_xy=True).transform(p.x_m, p.y_m)
    east, north = Transformer.from_crs("EPSG:4326", aeqd, always_xy=True).transform(lon, lat)
    return north, east


@pytest.mark.parametrize("action,dx,dy", [(0, 0, 1), (1, 1, 0), (2, -1, 0), (3, 0, -1)])
def test_action_to_ned_at_foreign_ekf_origin_matches_pyproj(action: int, dx: int, dy: int) -> None:
    frame = SceneFrame(SCENE_ORIGIN)
    planner = TargetPlanner(frame, EKF_ORIGIN, home_down_m=-1.5, alt_m=30.0)
    previous = ScenePoint(-120.0, 85.0)
    nxt = planner.next_target(previous, action, 15.0)
    assert (nxt.x_m - previous.x_m, nxt.y_m - previous.y_m) == (dx * 15.0, dy * 15.0)
    ned = planner.to_ned(nxt)
    north, east = _independent_ned(nxt, EKF_ORIGIN)
    assert ned.north_m == pytest.approx(north, abs=1e-3)
    assert ned.east_m == pytest.approx(east, abs=1e-3)
    # Altitude is held relative to the take-off point: 30 m above home (down -1.5).
    assert ned.down_m == pytest.approx(-31.5)
    # The naive mapping NED = (y, x) would be hundreds of metres off here.
    assert math.hypot(ned.north_m - nxt.y_m, ned.east_m - nxt.x_m) > 400.0
    # And back again.
    back, alt = planner.to_scene(ned)
    assert back.x_m == pytest.approx(nxt.x_m, abs=1e-3)
    assert back.y_m == pytest.approx(nxt.y_m, abs=1e-3)
    assert alt == pytest.approx(30.0)


def test_step_in_ned_is_one_lattice_step_north_or_east() -> None:
    planner = TargetPlanner(SceneFrame(SCENE_ORIGIN), EKF_ORIGIN, 0.0, 20.0)
    a = planner.to_ned(ScenePoint(10.0, 10.0))
    b = planner.to_ned(step_scene(ScenePoint(10.0, 10.0), 0, 15.0))
    c = planner.to_ned(step_scene(ScenePoint(10.0, 10.0), 1, 15.0))
    # Scene axes equal local north/east to well under a centimetre per 15 m step.
    assert (b.north_m - a.north_m, b.east_m - a.east_m) == pytest.approx((15.0, 0.0), abs=0.01)
    assert (c.north_m - a.north_m, c.east_m - a.east_m) == pytest.approx((0.0, 15.0), abs=0.01)


def test_bad_action_is_refused() -> None:
    with pytest.raises(Exception, match="expected 0..3"):
        step_scene(ScenePoint(0, 0), 7, 5.0)


@pytest.mark.parametrize(
    "url,kind,host,port,pym,msdk",
    [
        (
            "udpin:0.0.0.0:14540",
            "udpin",
            "0.0.0.0",
            14540,
            "udpin:0.0.0.0:14540",
            "udpin://0.0.0.0:14540",
        ),
        (
            "udpin://0.0.0.0:14540",
            "udpin",
            "0.0.0.0",
            14540,
            "udpin:0.0.0.0:14540",
            "udpin://0.0.0.0:14540",
        ),
        (
            "tcp:127.0.0.1:5760",
            "tcp",
            "127.0.0.1",
            5760,
            "tcp:127.0.0.1:5760",
            "tcpout://127.0.0.1:5760",
        ),
        (
            "udpout:10.0.0.2:14550",
            "udpout",
            "10.0.0.2",
            14550,
            "udpout:10.0.0.2:14550",
            "udpout://10.0.0.2:14550",
        ),
        (
            "/dev/ttyACM0:921600",
            "serial",
            "/dev/ttyACM0",
            921600,
            "/dev/ttyACM0",
            "serial:///dev/ttyACM0:921600",
        ),
        (
            "serial:///dev/ttyUSB0:57600",
            "serial",
            "/dev/ttyUSB0",
            57600,
            "/dev/ttyUSB0",
            "serial:///dev/ttyUSB0:57600",
        ),
    ],
)
def test_connection_strings(url: str, kind: str, host: str, port: int, pym: str, msdk: str) -> None:
    c = parse_connection(url)
    assert (c.kind, c.host, c.port) == (kind, host, port)
    assert c.pymavlink()[0] == pym
    assert c.mavsdk() == msdk


def test_bad_connection_strings() -> None:
    with pytest.raises(ConfigError, match="baud"):
        parse_connection("/dev/ttyACM0")
    with pytest.raises(ConfigError, match="not understood"):
        parse_connection("localhost")


def test_mode_numbers() -> None:
    assert M.encode_mode(M.PX4, "offboard") == (1, 6, 0)
    assert M.encode_mode(M.ARDUPILOT, "guided") == (1, 4, 0)
    assert M.custom_mode_value(M.PX4, "offboard") == 6 << 16
    assert M.decode_mode(M.PX4, (4 << 16) | (6 << 24)) == "land"
    assert M.decode_mode(M.ARDUPILOT, 9) == "land"
    assert M.TYPE_MASK_POSITION_YAW == 0x09F8


def test_geofence_box_and_radius() -> None:
    fence = Geofence.from_bounds(
        (-50, -50, 50, 50), 5.0, home=ScenePoint(0, 0), max_distance_m=30.0
    )
    assert fence.contains(ScenePoint(20, 20))
    assert "outside the geofence box" in fence.violation(ScenePoint(46, 0))
    assert "from home" in fence.violation(ScenePoint(25, 25))
    assert fence.clamp_alt(500.0) == 120.0


class _FakeVehicle:
    autopilot = M.PX4
    on_statustext = None

    def __init__(self) -> None:
        self.sent: list[LocalNED] = []
        self.landed = threading.Event()
        self.mode = "offboard"

    def send_position_target(self, target: LocalNED, yaw_deg: float) -> None:
        self.sent.append(target)

    def stop_setpoints(self) -> None:
        pass

    def land(self, timeout_s: float) -> None:
        self.landed.set()

    def state(self) -> VehicleState:
        return VehicleState(
            M.PX4, 4, self.mode, True, 0.1, LocalNED(0, 0, -10), (0, 0, 0), 0.1, None, None
        )


def _fence_check(ned: LocalNED) -> None:
    Geofence(-10, -10, 10, 10).check(ScenePoint(ned.east_m, ned.north_m))


def test_pump_never_sends_a_target_outside_the_fence() -> None:
    v = _FakeVehicle()
    pump = SetpointPump(v, rate_hz=50, deadline_s=5.0, fence_check=_fence_check)
    pump.set_target(LocalNED(5, 5, -10), 0.0)
    pump.start()
    time.sleep(0.1)
    with pytest.raises(SafetyViolation, match="outside the geofence"):
        pump.set_target(LocalNED(15, 0, -10), 0.0)
    time.sleep(0.1)
    pump.stop()
    assert len(v.sent) >= 5
    assert all(abs(t.north_m) <= 10 and abs(t.east_m) <= 10 for t in v.sent)


def test_pump_stops_and_lands_when_the_loop_stalls() -> None:
    v = _FakeVehicle()
    pump = SetpointPump(v, rate_hz=50, deadline_s=0.3)
    pump.set_target(LocalNED(0, 0, -10), 0.0)
    pump.start()
    assert v.landed.wait(2.0)
    n = len(v.sent)
    time.sleep(0.2)
    assert len(v.sent) == n  # nothing sent after the stall
    assert "stalled" in (pump.fault or "")
    with pytest.raises(SafetyViolation, match="stalled"):
        pump.raise_if_fault()
    pump.stop()


def test_pump_stops_on_operator_takeover_without_commanding() -> None:
    v = _FakeVehicle()
    wd = Watchdog(autonomy_mode="offboard")
    wd.engage()
    pump = SetpointPump(v, rate_hz=50, deadline_s=5.0, watchdog=wd)
    pump.set_target(LocalNED(0, 0, -10), 0.0)
    pump.start()
    time.sleep(0.1)
    v.mode = "posctl"
    time.sleep(0.2)
    assert not pump.running
    assert "operator takeover" in (pump.fault or "")
    assert not v.landed.is_set()
    pump.stop()
