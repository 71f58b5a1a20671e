"""Issue 36 against the emulator: the battery, the autopilot's own words, its failsafes
told from an operator, the fence the autopilot holds, a position loss, one line a fault."""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path
from typing import Any

import pytest
from flight_helpers import FAST, META, START, TARGET, fast_emulator, hook_policy

from geonav.geo import ScenePoint
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge._mav import mavutil
from geonav.mavlink_bridge.backends import open_vehicle
from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig
from geonav.mavlink_bridge.flight import FlightConfig, ScriptedPolicy, path_actions, run_flight
from geonav.mavlink_bridge.record import read_record
from geonav.testing import textured_scene

#: the policy of the long flights: back and forth, never at the target (9, 9).
BACK_AND_FORTH = [0, 3] * 30


@pytest.fixture(scope="module")
def scene() -> Any:
    return textured_scene(60.0, 0.5, towers=False)




def _fly(scene: Any, emu: Emulator, policy: Any, out: Path, backend: str = "pymavlink",
         **cfg: Any):
    cfg.setdefault("target_cell", (9, 9))
    cfg.setdefault("max_steps", 60)
    cfg.setdefault("timeouts", FAST)
    config = FlightConfig(start_cell=START, **cfg)
    return run_flight(open_vehicle(emu.connect_url, backend), scene, policy, config, out,
                      plot=False)




def _geonav_after(emu: Emulator, t_s: float) -> list[Any]:
    """Mode, arming and landing commands geonav sent after emulated time ``t_s``."""
    moving = (M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_NAV_LAND, M.MAV_CMD_NAV_RETURN_TO_LAUNCH,
              M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_NAV_TAKEOFF)
    return [c for c in emu.commands if c.t_s > t_s and c.command in moving]


def _event_t(emu: Emulator, start: str) -> float:
    return next(t for t, e in emu.events if e.startswith(start))


_CLASS_NAME = re.compile(r"\b[A-Z][A-Za-z]+(Error|Timeout|Rejected|Refused|Lost|Violation|"
                         r"Fault|Takeover|Failsafe|Low):")


# ---------------------------------------------------------------------------- battery
@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_low_battery_ends_the_flight_before_the_autopilots_critical_level(
        scene: Any, tmp_path: Path, backend: str) -> None:
    with fast_emulator(scene, "px4", battery_pct=40.0, battery_drain_pct_per_s=0.5) as emu:
        result = _fly(scene, emu, ScriptedPolicy(BACK_AND_FORTH, META), tmp_path, backend)
        assert result.outcome == "safety_stop" and result.exit_code == 6, result.reason
        assert "below --min-battery 25%" in result.reason
        assert result.end_action == "land" and result.end_ok and not emu.armed
        land_t = _event_t(emu, "mode land")
        # geonav's LAND came before the autopilot's own critical level (7 %)
        assert not any("Critical battery" in text for t, _, text, _ in emu.texts if t <= land_t)
        assert emu.failsafe == "" and "failsafe" not in " ".join(emu.mode_history())
    rows = read_record(result.record_path)
    series = [r["pct"] for r in rows if r["kind"] == "battery"]
    assert len(series) >= 5 and series[0] > series[-1] and min(series) < 25.0
    steps = [r for r in rows if r["kind"] == "step"]
    assert all(r["battery_pct"] is not None for r in steps)
    assert rows[-1]["battery_pct"] < 25.0


def test_a_battery_below_the_floor_is_refused_before_arming(scene: Any, tmp_path: Path) -> None:
    with fast_emulator(scene, "ardupilot", battery_pct=20.0) as emu:
        result = _fly(scene, emu, ScriptedPolicy([1], META), tmp_path)
        assert result.outcome == "refused" and result.exit_code == 3
        assert "battery at 20% is below --min-battery 25%" in result.reason
        assert not emu.commands_named(M.MAV_CMD_COMPONENT_ARM_DISARM) and not emu.setpoints
        assert emu.fence_items == []  # refused before the fence was given
    with fast_emulator(scene, "ardupilot", battery_pct=20.0) as emu:  # --min-battery 0: off
        result = _fly(scene, emu, ScriptedPolicy([1], META), tmp_path / "off",
                      target_cell=(6, 5), min_battery_pct=0.0)
        assert result.outcome == "reached", result.reason


# --------------------------------------------------------------- the autopilot speaks
@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_the_autopilots_texts_reach_the_console_and_the_record(
        scene: Any, tmp_path: Path, backend: str, caplog: Any) -> None:
    with fast_emulator(scene, "px4") as emu, caplog.at_level(logging.WARNING):
        policy = hook_policy([1, 1], 1, lambda: emu.say(4, "Wind speed is above limit"))
        result = _fly(scene, emu, policy, tmp_path, backend, target_cell=(7, 5))
        assert result.outcome == "reached", result.reason
        # PX4 sent it: geonav's heartbeat opened PX4's STATUSTEXT gate
        assert [sent for _, _, text, sent in emu.texts if text.startswith("Wind")] == [True]
    shown = [r.getMessage() for r in caplog.records
             if r.name == "geonav.mavlink_bridge.autopilot"]
    assert shown == ["autopilot: Wind speed is above limit"]
    rows = read_record(result.record_path)
    assert {"kind": "statustext", "severity": 4, "text": "Wind speed is above limit"}.items() \
        <= next(r for r in rows if r["kind"] == "statustext").items()


def test_px4_sends_its_texts_only_to_a_link_with_a_heartbeat_it_counts() -> None:
    """PX4's STATUSTEXT stream sends to a link that has a GCS heartbeat, or an onboard
    controller's from its own system: a listener with system 255 got none (issue 36)."""
    cfg = EmulatorConfig(time_scale=4, boot_s=0.1, origin_s=0.1, local_position_s=0.1)
    with Emulator(cfg) as emu:
        link = mavutil.mavlink_connection(emu.connect_url, source_system=255,
                                          source_component=191)
        try:
            for sysid, mav_type, expected in ((255, M.MAV_TYPE_ONBOARD_CONTROLLER, False),
                                              (1, M.MAV_TYPE_ONBOARD_CONTROLLER, True),
                                              (250, M.MAV_TYPE_GCS, True)):
                link.mav.srcSystem = sysid
                link.mav.heartbeat_send(mav_type, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                time.sleep(0.2)
                emu.say(4, f"hello {sysid}")
                assert emu.texts[-1][3] is expected, sysid
                emu.peer_heartbeat_ids.clear()
        finally:
            link.close()


def test_a_flood_of_texts_is_folded(scene: Any, tmp_path: Path, caplog: Any) -> None:
    def flood() -> None:
        for i in range(40):
            emu.say(4, f"Battery 1 is low {14.0 - i / 100:.2f}V")

    with fast_emulator(scene, "ardupilot") as emu, caplog.at_level(logging.WARNING):
        result = _fly(scene, emu, hook_policy([1, 1], 1, flood), tmp_path, target_cell=(7, 5))
        assert result.outcome == "reached", result.reason
    shown = [r.getMessage() for r in caplog.records if "Battery 1 is low" in r.getMessage()]
    assert shown == ["autopilot: Battery 1 is low 14.00V"]  # 39 repeats folded (-vv: DEBUG)
    rows = [r for r in read_record(result.record_path) if r["kind"] == "statustext"]
    assert [r["text"] for r in rows if "is low" in r["text"]] == ["Battery 1 is low 14.00V"]


# ---------------------------------------------------------------- failsafe or operator
@pytest.mark.parametrize(("autopilot", "backend"), [("px4", "pymavlink"),
                                                    ("ardupilot", "mavsdk")])
def test_an_autopilot_failsafe_is_not_an_operator(scene: Any, tmp_path: Path, autopilot: str,
                                                  backend: str) -> None:
    with fast_emulator(scene, autopilot, battery_pct=30.0, battery_drain_pct_per_s=0.6,
                   battery_failsafe="rtl") as emu:
        result = _fly(scene, emu, ScriptedPolicy(BACK_AND_FORTH, META), tmp_path, backend,
                      min_battery_pct=0.0)  # geonav leaves the battery to the autopilot
        assert result.outcome == "failsafe" and result.exit_code == 7, result.reason
        line = result.summary()
        assert line.startswith("autopilot failsafe: mode changed to 'rtl' by the autopilot")
        assert "critical" in line.lower() and "CRITICAL" in line
        assert "operator" not in line and "no end action (the autopilot has control)" in line
        assert "the autopilot landed, disarmed" in line and not emu.armed
        assert _geonav_after(emu, _event_t(emu, "failsafe: battery")) == []
        assert emu.fence_items == []  # down: the fence was taken back


def test_an_operator_is_still_an_operator(scene: Any, tmp_path: Path) -> None:
    with fast_emulator(scene, "px4") as emu:
        policy = hook_policy(BACK_AND_FORTH, 2, lambda: emu.operator_mode("posctl"))
        result = _fly(scene, emu, policy, tmp_path)
        assert result.outcome == "takeover" and result.exit_code == 5, result.reason
        assert "geonav's fence stays on the autopilot" in result.summary()
        assert emu.armed and emu.fence_items  # the operator flies on, inside the fence


# --------------------------------------------------------------- the autopilot's fence
@pytest.mark.parametrize(("autopilot", "backend"), [("px4", "pymavlink"), ("px4", "mavsdk"),
                                                    ("ardupilot", "pymavlink"),
                                                    ("ardupilot", "mavsdk")])
def test_the_autopilot_holds_the_scenes_fence_and_gives_it_back(
        scene: Any, tmp_path: Path, autopilot: str, backend: str) -> None:
    seen: dict[str, Any] = {}
    with fast_emulator(scene, autopilot) as emu:
        def look() -> None:
            with emu._lock:
                seen.update(items=list(emu.fence_items), params=dict(emu._params()),
                            action=emu.fence_action())

        result = _fly(scene, emu, hook_policy(path_actions(START, TARGET), 1, look), tmp_path,
                      backend, target_cell=TARGET, max_distance_m=20.0)
        assert result.outcome == "reached", result.reason
        corners = {(round(lat, 6), round(lon, 6)) for kind, lat, lon, _ in seen["items"]
                   if kind == "vertex"}
        xmin, ymin, xmax, ymax = scene.bounds_m
        want = {(round(q.lat_deg, 6), round(q.lon_deg, 6)) for q in (
            scene.frame.to_lonlat(ScenePoint(x, y), 0.0)
            for x, y in ((xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)))}
        assert corners == want
        [circle] = [it for it in seen["items"] if it[0] == "circle"]
        assert circle[3] == pytest.approx(25.0)  # --max-distance 20 + the 5 m fence margin
        assert seen["action"] == "land"
        if autopilot == "px4":
            assert seen["params"]["GF_ACTION"] == 5 and seen["params"]["GF_MAX_VER_DIST"] == 125
        else:
            assert (seen["params"]["FENCE_ENABLE"], seen["params"]["FENCE_ACTION"],
                    seen["params"]["FENCE_TYPE"]) == (1, 2, 5)
        # no setpoint came near it; after the landing it is gone, the parameters restored
        assert not any(emu.outside_fence(s.north_m, s.east_m) for s in emu.setpoints)
        assert emu.fence_items == []
        restored = emu._params()
        if autopilot == "px4":
            assert restored["GF_ACTION"] == 2 and restored["GF_MAX_VER_DIST"] == 0
        else:
            assert (restored["FENCE_ENABLE"], restored["FENCE_TYPE"]) == (0, 7)


def test_the_autopilot_enforces_the_fence_when_geonav_cannot(scene: Any, tmp_path: Path) -> None:
    """The link dies, then a gust carries the vehicle out of the scene: the autopilot's
    own copy of geonav's fence lands it (geonav's check, the second layer, is blind)."""
    with fast_emulator(scene, "ardupilot") as emu:
        def blow() -> None:
            emu.drop_link(None)
            emu.push(0.0, 40.0)

        result = _fly(scene, emu, hook_policy(BACK_AND_FORTH, 1, blow), tmp_path,
                      heartbeat_timeout_s=1.0, timeouts=FAST.__class__(
                          **{**FAST.__dict__, "dead_link_s": 2.0}))
        assert result.outcome == "link_lost" and result.exit_code == 4
        assert emu.fence_breached and "mode land (failsafe: fence)" in emu.mode_history()
        deadline = time.monotonic() + 10
        while emu.armed and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not emu.armed and emu.landed


def test_no_autopilot_fence_when_asked(scene: Any, tmp_path: Path) -> None:
    with fast_emulator(scene, "px4") as emu:
        result = _fly(scene, emu, hook_policy([1], 0, lambda: None), tmp_path, target_cell=(6, 5),
                      autopilot_fence=False)
        assert result.outcome == "reached"
        assert not [e for _, e in emu.events if e.startswith("fence")]
        assert not [e for _, e in emu.events if e.startswith("param")]


# ------------------------------------------------------------------------ position loss
@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_gps_loss_hands_the_vehicle_to_the_autopilot(scene: Any, tmp_path: Path,
                                                     backend: str) -> None:
    # The autopilot waits (its EKF failsafe 60 s away): geonav notices first and stops.
    with fast_emulator(scene, "px4", gps_failsafe_s=60.0) as emu:
        result = _fly(scene, emu, hook_policy(BACK_AND_FORTH, 1, emu.lose_gps), tmp_path, backend)
        assert result.outcome == "position_lost" and result.exit_code == 8, result.reason
        line = result.summary()
        assert line.startswith("position lost: no LOCAL_POSITION_NED for ")
        assert "geonav stopped commanding; the autopilot's failsafe has control" in line
        assert result.end_action == "none"
        lost_t = _event_t(emu, "fault: GPS lost")
        assert _geonav_after(emu, lost_t) == []  # no LAND, no mode from geonav
        # the stream stopped (within the 2 s position watchdog, 12 emulated s); the
        # autopilot's own failsafe then took the vehicle down
        stopped_t = max(s.t_s for s in emu.setpoints)
        assert stopped_t < lost_t + 18.0 and stopped_t < _event_t(emu, "mode land")


def test_gps_loss_the_autopilot_acts_on_first_is_its_failsafe(scene: Any,
                                                              tmp_path: Path) -> None:
    with fast_emulator(scene, "ardupilot", gps_failsafe_s=0.3) as emu:
        result = _fly(scene, emu, hook_policy(BACK_AND_FORTH, 1, emu.lose_gps), tmp_path)
        assert result.outcome in ("failsafe", "position_lost"), result.reason
        assert result.end_action == "none"
        assert _geonav_after(emu, _event_t(emu, "fault: GPS lost")) == []
        if result.outcome == "failsafe":
            assert "autopilot says 'EKF failsafe: position lost, landing'" in result.reason


# ---------------------------------------------------------------------- one line a fault
def test_a_lost_link_and_a_refusal_are_one_line_each(scene: Any, tmp_path: Path,
                                                     caplog: Any) -> None:
    with fast_emulator(scene, "px4") as emu, caplog.at_level(logging.WARNING):
        policy = hook_policy(path_actions(START, TARGET), 1, lambda: emu.drop_link(None))
        timeouts = FAST.__class__(**{**FAST.__dict__, "dead_link_s": 2.0})
        lost = _fly(scene, emu, policy, tmp_path / "lost", target_cell=TARGET,
                    heartbeat_timeout_s=1.0, timeouts=timeouts)
    with fast_emulator(scene, "ardupilot") as emu, caplog.at_level(logging.WARNING):
        emu.refuse_arming("Battery below minimum")
        timeouts = FAST.__class__(**{**FAST.__dict__, "arm_s": 2.0})
        refused = _fly(scene, emu, ScriptedPolicy([1], META), tmp_path / "refused",
                       timeouts=timeouts)
    assert lost.outcome == "link_lost" and refused.outcome == "refused"
    # Nothing from geonav itself above INFO: the result line is the one line (the
    # autopilot's own texts, "PreArm: ...", are the autopilot speaking).
    ours = [r for r in caplog.records if r.levelno >= logging.WARNING
            and r.name.startswith("geonav") and r.name != "geonav.mavlink_bridge.autopilot"]
    assert ours == [], [r.getMessage() for r in ours]
    for result in (lost, refused):
        line = result.summary()
        assert "\n" not in line and not _CLASS_NAME.search(line), line
    assert lost.summary().count("link lost") == 1
    assert "; 1 steps;" in lost.summary()  # the step the loss cut short is not counted


def test_a_refused_step_counts_but_is_not_flown(scene: Any, tmp_path: Path) -> None:
    with fast_emulator(scene, "px4") as emu:
        result = _fly(scene, emu, ScriptedPolicy([1], META), tmp_path, target_cell=(5, 7),
                      max_distance_m=11.0)  # the third step east would leave the fence
        assert result.outcome == "safety_stop" and result.steps == 3
        assert result.flown_steps == 2 and "; 3 steps (2 flown);" in result.summary()


def test_the_fly_command_takes_the_new_options() -> None:
    import argparse

    from geonav.mavlink_bridge import cli

    p = argparse.ArgumentParser()
    cli.add_parser(p.add_subparsers())
    a = p.parse_args(["fly", "c.pt", "--scene", "s", "--target", "1,1", "--dry-run"])
    assert (a.min_battery, a.autopilot_fence) == (25.0, True)
    a = p.parse_args(["fly", "c.pt", "--scene", "s", "--target", "1,1", "--min-battery", "0",
                      "--no-autopilot-fence"])
    assert (a.min_battery, a.autopilot_fence) == (0.0, False)
    with pytest.raises(SystemExit):
        p.parse_args(["fly", "c.pt", "--scene", "s", "--min-battery", "120"])
