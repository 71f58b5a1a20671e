"""Flights against the MAVLink emulator: both autopilot flavours, both backends, and faults."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from flight_helpers import FAST, META, START, TARGET

from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.backends import open_vehicle
from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig
from geonav.mavlink_bridge.flight import FlightConfig, ScriptedPolicy, path_actions, run_flight
from geonav.mavlink_bridge.record import read_record
from geonav.mavlink_bridge.sequence import Timeouts
from geonav.tasks import Lattice
from geonav.testing import textured_scene


@pytest.fixture(scope="module")
def scene() -> Any:
    return textured_scene(60.0, 0.5, towers=False)


def _lattice(scene: Any) -> Lattice:
    return Lattice(scene.bounds_m, META["step_m"])


def _emulator(scene: Any, autopilot: str, **kw: Any) -> Emulator:
    """A (not yet started) emulator with home at START; use it as ``with _emulator(...)``."""
    home = scene.frame.to_lonlat(_lattice(scene).center(START), 0.0)
    # Emulated time runs 6x faster than the wall clock and advances by at most ~0.12 s
    # per emulator iteration, so a paused process pauses the vehicle (no jumps).
    # COM_OF_LOSS_T: 3 emulated s = 0.5 s of wall time without a setpoint.
    kw.setdefault("offboard_loss_s", 3.0)
    cfg = EmulatorConfig(
        autopilot=autopilot,
        home=home,
        time_scale=6.0,
        boot_s=1.0,
        prearm_s=3.0,
        origin_s=0.6,
        local_position_s=1.2,
        **kw,
    )
    return Emulator(cfg)


def _fly(scene: Any, emu: Emulator, policy: Any, backend: str, out: Path, **cfg: Any):
    vehicle = open_vehicle(emu.connect_url, backend)
    cfg.setdefault("target_cell", TARGET)
    config = FlightConfig(start_cell=START, timeouts=FAST, **cfg)
    return run_flight(vehicle, scene, policy, config, out)


def _scene_xy(scene: Any, emu: Emulator, north_m: float, east_m: float) -> tuple[float, float]:
    p = scene.frame.from_lonlat(emu.lonlat_of(north_m, east_m))
    return p.x_m, p.y_m


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_full_flight_reaches_target_and_lands(
    scene: Any, tmp_path: Path, autopilot: str, backend: str
) -> None:
    actions = path_actions(START, TARGET)
    with _emulator(scene, autopilot) as emu:
        result = _fly(scene, emu, ScriptedPolicy(actions, META), backend, tmp_path)
        assert result.success, result.reason
        assert result.steps == len(actions) == 3
        assert result.final_cell == TARGET
        assert result.end_action == "land" and result.disarmed
        assert not emu.armed and emu.landed
        # The vehicle really is over... the ground under the target cell.
        x, y = _scene_xy(scene, emu, emu.pos[0], emu.pos[1])
        c = _lattice(scene).center(TARGET)
        assert math.hypot(x - c.x_m, y - c.y_m) < 1.0
        used = emu.used_setpoints()
        assert used, "no setpoint was used by the vehicle"
        assert all(s.coordinate_frame == 1 and s.type_mask == 2552 for s in emu.setpoints)
        assert all(abs(s.yaw_deg) < 1e-6 for s in emu.setpoints)
        if autopilot == "ardupilot":
            # ArduPilot streams nothing by default: the bridge asked for LOCAL_POSITION_NED.
            asked = emu.commands_named(M.MAV_CMD_SET_MESSAGE_INTERVAL)
            assert any(int(c.params[0]) == 32 and c.result == 0 for c in asked)
            assert emu.commands_named(M.MAV_CMD_NAV_TAKEOFF)[-1].params[6] == pytest.approx(10.0)
            assert "mode guided (DO_SET_MODE)" in emu.mode_history()
        else:
            assert "mode offboard (DO_SET_MODE)" in emu.mode_history()
            assert not emu.commands_named(M.MAV_CMD_NAV_TAKEOFF)
    rows = read_record(result.record_path)
    steps = [r for r in rows if r["kind"] == "step"]
    assert [r["action"] for r in steps] == actions
    lattice = _lattice(scene)
    cell = START
    for r, a in zip(steps, actions, strict=True):
        dx, dy = {0: (0, 1), 1: (1, 0), 2: (-1, 0), 3: (0, -1)}[a]
        cell = (cell[0] + dx, cell[1] + dy)
        c = lattice.center(cell)
        assert tuple(r["cell"]) == cell
        assert r["target_scene"] == pytest.approx((c.x_m, c.y_m), abs=1e-6)
        # Recorded track matches the lattice steps within the arrival tolerance.
        assert math.dist(r["measured_scene"], (c.x_m, c.y_m)) <= 0.5 + 1e-6
        assert r["measured_alt_m"] == pytest.approx(10.0, abs=1.0)
        assert r["arrival_s"] > 0
    assert result.png_path is not None and result.png_path.stat().st_size > 10_000
    assert rows[-1]["kind"] == "result" and rows[-1]["success"] is True


class _Eastward(ScriptedPolicy):
    """Always 'right' (east)."""

    def __init__(self) -> None:
        super().__init__([1], META)


def test_target_outside_fence_is_never_sent(scene: Any, tmp_path: Path, caplog: Any) -> None:
    lattice = _lattice(scene)
    home = lattice.center(START)
    max_dist = 11.0  # two 5 m steps east are inside, the third is not
    # Issue 36: the result line is the one line at the default level; the bridge logs
    # how the flight ended at INFO (geonav -v).
    with _emulator(scene, "px4") as emu, caplog.at_level(logging.INFO):
        result = _fly_target(scene, emu, tmp_path, max_dist)
        assert not result.success
        assert "geofence" in result.reason or "from home" in result.reason
        assert result.steps == 3
        assert result.outcome == "safety_stop" and result.exit_code == 6
        assert result.end_action == "land" and result.disarmed and not emu.armed
        assert emu.setpoints
        for s in emu.setpoints:
            x, y = _scene_xy(scene, emu, s.north_m, s.east_m)
            assert math.hypot(x - home.x_m, y - home.y_m) <= max_dist + 1e-6, (x, y)
    assert any("safety" in r.getMessage() for r in caplog.records)


def _fly_target(scene: Any, emu: Emulator, out: Path, max_dist: float):
    vehicle = open_vehicle(emu.connect_url, "pymavlink")
    config = FlightConfig(
        target_cell=(5, 7), start_cell=START, timeouts=FAST, max_distance_m=max_dist
    )
    return run_flight(vehicle, scene, _Eastward(), config, out)


class _Hook(ScriptedPolicy):
    """Scripted policy that runs ``hook`` at call number ``at``."""

    def __init__(self, actions: list[int], at: int, hook: Any, delay_s: float = 0.0) -> None:
        super().__init__(actions, META)
        self.at, self.hook, self.hook_delay_s = at, hook, delay_s

    def act(self, image: np.ndarray, target: np.ndarray) -> int:
        if self.calls == self.at:
            self.hook()
            if self.hook_delay_s:
                import time

                time.sleep(self.hook_delay_s)
        return super().act(image, target)


def test_link_loss_ends_in_landing(scene: Any, tmp_path: Path, caplog: Any) -> None:
    # Issue 36: the result line is the one line at the default level; the bridge logs
    # how the flight ended at INFO (geonav -v).
    with _emulator(scene, "px4") as emu, caplog.at_level(logging.INFO):
        policy = _Hook(path_actions(START, TARGET), 1, lambda: emu.drop_link(2.5))
        result = _fly(
            scene,
            emu,
            policy,
            "pymavlink",
            tmp_path,
            heartbeat_timeout_s=1.0,
            position_timeout_s=5.0,
        )
        assert not result.success
        assert result.reason.startswith("link lost: no autopilot heartbeat")
        assert result.outcome == "link_lost" and result.exit_code == 4
        # PX4 left OFFBOARD after COM_OF_LOSS_T and landed; the bridge's LAND confirmed it.
        assert any("offboard loss" in m for m in emu.mode_history())
        assert result.end_action == "land" and result.disarmed
        assert not emu.armed and emu.landed
    assert any("link lost" in r.getMessage() for r in caplog.records)
    # the second step was cut short by the link loss: one step flown, as the record says
    # (the summary said "2 steps" with 1 done)
    flown = [r for r in read_record(result.record_path) if r["kind"] == "step"]
    assert result.steps == len(flown) == 1 and "; 1 steps;" in result.summary()
    result_row = read_record(result.record_path)[-1]
    assert result_row["kind"] == "result" and result_row["steps"] == 1


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_arming_refusal_is_reported_and_nothing_flies(
    scene: Any, tmp_path: Path, backend: str
) -> None:
    with _emulator(scene, "ardupilot") as emu:
        emu.refuse_arming("Battery below minimum")
        timeouts = Timeouts(**{**FAST.__dict__, "arm_s": 2.0})
        vehicle = open_vehicle(emu.connect_url, backend)
        cfg = FlightConfig(target_cell=TARGET, start_cell=START, timeouts=timeouts)
        result = run_flight(vehicle, scene, ScriptedPolicy([1], META), cfg, tmp_path)
        assert not result.success
        assert "refused to arm" in result.reason
        assert "PreArm: Battery below minimum" in result.reason
        assert len(emu.commands_named(M.MAV_CMD_COMPONENT_ARM_DISARM)) >= 2  # retried
        assert not emu.armed and not any(e == "armed" for _, e in emu.events)
        assert not emu.used_setpoints()
        assert result.end_action == "none"


def test_prearm_failures_are_retried_until_ready(scene: Any, tmp_path: Path) -> None:
    with _emulator(scene, "ardupilot") as emu:
        emu.cfg.prearm_s = 12.0  # ~2 s of wall time of PreArm failures
        result = _fly(
            scene, emu, ScriptedPolicy([1, 1], META), "pymavlink", tmp_path, target_cell=(7, 5)
        )
        assert result.success, result.reason
        assert result.steps == 2
        refused = [c for c in emu.commands_named(M.MAV_CMD_COMPONENT_ARM_DISARM) if c.result == 4]
        assert refused, "arming was expected to fail at first"


def test_stalled_policy_stops_setpoints_and_lands(scene: Any, tmp_path: Path, caplog: Any) -> None:
    # Issue 36: the result line is the one line at the default level; the bridge logs
    # how the flight ended at INFO (geonav -v).
    with _emulator(scene, "px4") as emu, caplog.at_level(logging.INFO):
        policy = _Hook(path_actions(START, TARGET), 1, lambda: None, delay_s=2.5)
        result = _fly(scene, emu, policy, "pymavlink", tmp_path, policy_deadline_s=0.8)
        assert not result.success
        assert "stalled" in result.reason
        assert result.end_action == "land" and result.disarmed and not emu.armed
        land_t = next(t for t, e in emu.events if e.startswith("mode land"))
        # The pump stopped before commanding LAND and never resumed.
        assert all(s.t_s <= land_t for s in emu.setpoints)
        assert result.steps == 1
    assert any("stalled" in r.getMessage() for r in caplog.records)


def test_operator_takeover_ends_autonomy_without_fighting(scene: Any, tmp_path: Path) -> None:
    with _emulator(scene, "ardupilot") as emu:
        policy = _Hook(path_actions(START, TARGET), 1, lambda: emu.operator_mode("hold"))
        result = _fly(scene, emu, policy, "pymavlink", tmp_path)
        assert not result.success
        assert "operator takeover" in result.reason
        assert result.end_action == "none"
        takeover_t = next(t for t, e in emu.events if "(operator)" in e)
        later = [
            c
            for c in emu.commands
            if c.t_s > takeover_t
            and c.command
            in (M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_NAV_LAND, M.MAV_CMD_NAV_RETURN_TO_LAUNCH)
        ]
        assert later == []
        assert emu.mode == "loiter" and emu.armed  # still the operator's (LOITER)
        assert result.outcome == "takeover" and result.exit_code == 5


def test_rtl_end_action(scene: Any, tmp_path: Path) -> None:
    with _emulator(scene, "ardupilot", rtl_alt_m=12.0) as emu:
        result = _fly(
            scene,
            emu,
            ScriptedPolicy([0], META),
            "pymavlink",
            tmp_path,
            end="rtl",
            target_cell=(5, 6),
        )
        assert result.success and result.end_action == "rtl" and result.disarmed
        assert "mode rtl (MAV_CMD_NAV_RETURN_TO_LAUNCH)" in emu.mode_history()
        assert math.hypot(emu.pos[0], emu.pos[1]) < 1.0  # back home
