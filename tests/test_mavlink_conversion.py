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
from geonav.mavlink_bridge.frames import local_frame
from geonav.mavlink_bridge.pump import SetpointPump
from geonav.mavlink_bridge.safety import Geofence, PumpFault, Watchdog
from geonav.mavlink_bridge.vehicle import VehicleState, parse_connection

SCENE_ORIGIN = LonLat(4.4777, 51.9244, 2.0)
# An EKF origin ~420 m east and ~330 m north of the scene origin, 3 m higher.
EKF_ORIGIN = LonLat(4.4838, 51.9274, 5.0)


def _sphere_crs(autopilot: str, o: LonLat) -> CRS:
    """The autopilot's local frame written as a PROJ projection (independent of geonav)."""
    if autopilot == "px4":  # geo.cpp MapProjection: azimuthal equidistant, R = 6371000 m
        return CRS.from_proj4(
            f"+proj=aeqd +lat_0={o.lat_deg} +lon_0={o.lon_deg} +R=6371000 +units=m +type=crs"
        )
    # Location.cpp: north = dlat * R, east = dlon * R * cos(lat_origin), R = 6378100 m
    return CRS.from_proj4(
        f"+proj=eqc +lat_ts={o.lat_deg} +lat_0={o.lat_deg} +lon_0={o.lon_deg} +R=6378100 "
        "+units=m +type=crs"
    )


def _independent_ned(p: ScenePoint, ekf: LonLat, autopilot: str) -> tuple[float, float]:
    """Scene point -> (north, east) about ``ekf`` with plain pyproj, not geonav."""
    tmerc = CRS.from_proj4(
        f"+proj=tmerc +lat_0={SCENE_ORIGIN.lat_deg} +lon_0={SCENE_ORIGIN.lon_deg} +k=1 "
        "+x_0=0 +y_0=0 +datum=WGS84 +units=m +type=crs"
    )
    lon, lat = Transformer.from_crs(tmerc, "EPSG:4326", always_xy=True).transform(p.x_m, p.y_m)
    to_local = Transformer.from_crs("EPSG:4326", _sphere_crs(autopilot, ekf), always_xy=True)
    east, north = to_local.transform(lon, lat)
    return north, east


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
@pytest.mark.parametrize("action,dx,dy", [(0, 0, 1), (1, 1, 0), (2, -1, 0), (3, 0, -1)])
def test_action_to_ned_at_foreign_ekf_origin_matches_the_autopilot(
    action: int, dx: int, dy: int, autopilot: str
) -> None:
    frame = SceneFrame(SCENE_ORIGIN)
    planner = TargetPlanner(frame, EKF_ORIGIN, home_down_m=-1.5, alt_m=30.0, autopilot=autopilot)
    previous = ScenePoint(-120.0, 85.0)
    nxt = planner.next_target(previous, action, 15.0)
    assert (nxt.x_m - previous.x_m, nxt.y_m - previous.y_m) == (dx * 15.0, dy * 15.0)
    ned = planner.to_ned(nxt)
    north, east = _independent_ned(nxt, EKF_ORIGIN, autopilot)
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


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_local_frame_is_the_autopilots_within_5_cm_at_1_km(autopilot: str) -> None:
    """geonav's NED about the EKF origin vs the autopilot's formula, 1 km out in 8 directions."""
    frame = SceneFrame(SCENE_ORIGIN)
    planner = TargetPlanner(frame, EKF_ORIGIN, 0.0, 30.0, autopilot=autopilot)
    ekf_scene = frame.from_lonlat(EKF_ORIGIN)
    worst_geonav = worst_ellipsoid = 0.0
    for k in range(8):
        a = math.radians(45 * k)
        p = ScenePoint(ekf_scene.x_m + 1000 * math.sin(a), ekf_scene.y_m + 1000 * math.cos(a))
        truth = _independent_ned(p, EKF_ORIGIN, autopilot)
        ned = planner.to_ned(p)
        worst_geonav = max(worst_geonav, math.dist((ned.north_m, ned.east_m), truth))
        # What geonav did before: exact ellipsoidal metres (geonav.geo.SceneFrame.to_ned).
        old = frame.to_ned(p, 0.0, LonLat(EKF_ORIGIN.lon_deg, EKF_ORIGIN.lat_deg, 2.0))
        worst_ellipsoid = max(worst_ellipsoid, math.dist((old.north_m, old.east_m), truth))
    assert worst_geonav < 0.05
    assert worst_ellipsoid > 0.5  # the error this test exists to catch


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_frames_round_trip_and_the_emulator_uses_them(autopilot: str) -> None:
    from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig

    f = local_frame(autopilot, EKF_ORIGIN)
    lon, lat = f.to_lonlat(700.0, -400.0)
    assert f.to_ne(LonLat(lon, lat)) == pytest.approx((700.0, -400.0), abs=1e-6)
    emu = Emulator(EmulatorConfig(autopilot=autopilot, home=EKF_ORIGIN))
    try:
        emu._set_origin(EKF_ORIGIN, "test")
        q = emu.lonlat_of(700.0, -400.0)
        assert (q.lon_deg, q.lat_deg) == pytest.approx((lon, lat), abs=1e-12)
    finally:
        emu.stop()


def test_step_in_ned_is_one_lattice_step_north_or_east() -> None:
    planner = TargetPlanner(SceneFrame(SCENE_ORIGIN), EKF_ORIGIN, 0.0, 20.0, autopilot="px4")
    a = planner.to_ned(ScenePoint(10.0, 10.0))
    b = planner.to_ned(step_scene(ScenePoint(10.0, 10.0), 0, 15.0))
    c = planner.to_ned(step_scene(ScenePoint(10.0, 10.0), 1, 15.0))
    # Scene axes are local north/east; a 15 m step is 15 m of the autopilot's sphere
    # (PX4's 6,371 km sphere is 0.3 % small for east-west metres at 52 degrees N).
    assert b.east_m - a.east_m == pytest.approx(0.0, abs=0.01)
    assert c.north_m - a.north_m == pytest.approx(0.0, abs=0.01)
    assert b.north_m - a.north_m == pytest.approx(15.0, rel=0.005)
    assert c.east_m - a.east_m == pytest.approx(15.0, rel=0.005)


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


def test_position_fence_allows_half_the_margin_of_overshoot() -> None:
    fence = Geofence.from_bounds((-50, -50, 50, 50), 10.0, overshoot_m=5.0)
    assert fence.violation(ScenePoint(42, 0)) is not None  # a setpoint there is refused
    assert fence.position_violation(ScenePoint(44.9, 0)) is None  # overshoot tolerated
    assert "breached" in fence.position_violation(ScenePoint(45.1, 0))


def test_ardupilot_loiter_is_reported_as_loiter() -> None:
    assert M.decode_mode(M.ARDUPILOT, 5) == "loiter"
    assert M.encode_mode(M.ARDUPILOT, "hold") == (1, 5, 0)
    assert M.decode_mode(M.PX4, (4 << 16) | (3 << 24)) == "hold"


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


def test_a_send_that_raises_is_a_pump_fault_the_loop_sees() -> None:
    v = _FakeVehicle()
    calls = [0]

    def send(target: LocalNED, yaw_deg: float) -> None:
        calls[0] += 1
        if calls[0] > 3:
            raise RuntimeError("MAVSDK: setpoint not done within 1.0 s")
        v.sent.append(target)

    v.send_position_target = send  # type: ignore[method-assign]
    pump = SetpointPump(v, rate_hz=50, deadline_s=5.0)
    pump.set_target(LocalNED(0, 0, -10), 0.0)
    pump.start()
    deadline = time.monotonic() + 2.0
    while pump.running and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not pump.running
    with pytest.raises(PumpFault, match="setpoint send failed: RuntimeError"):
        pump.raise_if_fault()
    with pytest.raises(PumpFault):
        pump.set_target(LocalNED(1, 0, -10), 0.0)  # the loop's next call fails too
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
