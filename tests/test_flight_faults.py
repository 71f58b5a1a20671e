"""Every fault of issue 14: one line, a landing (or the operator's way), a record."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from flight_helpers import FAST as BASE_FAST
from flight_helpers import META, START, TARGET, fast_emulator, hook_policy

from geonav.errors import ConfigError, FlightTimeout
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge._mav import mavutil
from geonav.mavlink_bridge.backends import open_vehicle
from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig
from geonav.mavlink_bridge.flight import (
    FlightConfig,
    ScriptedPolicy,
    fly,
    path_actions,
    plan_flight,
    run_flight,
)
from geonav.mavlink_bridge.record import read_record
from geonav.mavlink_bridge.sequence import Timeouts
from geonav.scene import Scene
from geonav.tasks import Lattice
from geonav.testing import textured_scene

GEONAV = 255  # the pymavlink backend's source system id
FAST = replace(BASE_FAST, dead_link_s=2.0)


@pytest.fixture(scope="module")
def scene() -> Any:
    return textured_scene(60.0, 0.5, towers=False)




def _fly(scene: Any, emu: Emulator, policy: Any, out: Path, backend: str = "pymavlink",
         **cfg: Any):
    cfg.setdefault("target_cell", TARGET)
    cfg.setdefault("start_cell", START)
    cfg.setdefault("timeouts", FAST)
    return run_flight(open_vehicle(emu.connect_url, backend), scene, policy,
                      FlightConfig(**cfg), out)


def _geonav_commands(emu: Emulator, after_t: float = -1.0) -> list[Any]:
    return [c for c in emu.commands if c.source[0] == GEONAV and c.t_s > after_t]




# --------------------------------------------------------------------------- signals
_SIGNAL_SCRIPT = textwrap.dedent(
    """
    import sys
    from geonav.cli import main
    from geonav.mavlink_bridge import flight
    meta = {"obs_size_px": 32, "alt_m": 10.0, "step_m": 5.0, "fov_deg": 90.0}
    # A slow policy that never reaches the target: the test signals it mid-flight.
    flight.load_policy = lambda path: flight.ScriptedPolicy([0, 3] * 40, meta, delay_s=0.05)
    sys.exit(main(["fly", "ckpt.pt", "--scene", sys.argv[1], "--target", "9,9",
                   "--start", "5,5", "--dry-run", "--out", sys.argv[2]]))
    """
)


def test_sigterm_lands_a_background_fly_whose_sigint_is_ignored(scene: Any, tmp_path: Path) -> None:
    scene_dir = tmp_path / "scene"
    scene.save(scene_dir)
    out = tmp_path / "flight"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-c", _SIGNAL_SCRIPT, str(scene_dir), str(out)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # A shell's background job: SIGINT ignored.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    try:
        deadline = time.monotonic() + 60
        record = out / "flight.jsonl"
        while time.monotonic() < deadline:
            if record.exists() and any(
                r.get("kind") == "step" for r in read_record(record) if r
            ):
                break
            if proc.poll() is not None:
                pytest.fail(f"geonav fly ended early: {proc.communicate()}")
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)  # ignored, as in a background job
        time.sleep(0.3)
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, (stdout, stderr)
    assert "Traceback" not in stderr
    lines = [line for line in stdout.splitlines() if line.strip()]
    assert len(lines) == 2 and lines[0].startswith("interrupted by SIGTERM;")
    assert "end land confirmed, disarmed" in lines[0]
    assert lines[1] == f"track {out / 'track.png'}"  # drawn after the outcome is said
    result = read_record(out / "flight.jsonl")[-1]
    assert result["kind"] == "result" and result["outcome"] == "interrupted"
    assert result["signal"] == "SIGTERM" and result["end_ok"] and result["disarmed"]
    # The record says the exit code the process had (PX4 SIH: 130 in the record, 143 out).
    assert result["exit_code"] == proc.returncode == 143


def test_fly_says_the_outcome_before_drawing_the_track(scene: Any, tmp_path: Path, capsys: Any,
                                                     caplog: Any, monkeypatch: Any) -> None:
    """`geonav fly` prints its result line before track.png is drawn (30-70 s on a loaded
    machine held the line and the exit code back), and warns of an altitude clamp once
    (three times before: two plans and the command)."""
    from geonav.cli import main
    from geonav.mavlink_bridge import flight, record

    scene_dir = tmp_path / "scene"
    scene.save(scene_dir)
    monkeypatch.setattr(flight, "load_policy", lambda path: ScriptedPolicy(
        path_actions(START, TARGET), {**META, "alt_m": 30.0}))
    printed_before_plot: list[str] = []
    real_plot = record.FlightRecorder.plot

    def plot(self: Any, *args: Any, **kw: Any) -> Any:
        printed_before_plot.append(capsys.readouterr().out)
        return real_plot(self, *args, **kw)

    monkeypatch.setattr(record.FlightRecorder, "plot", plot)
    code = main(["fly", "ckpt.pt", "--scene", str(scene_dir), "--target",
                 f"{TARGET[0]},{TARGET[1]}", "--start", f"{START[0]},{START[1]}", "--dry-run",
                 "--max-alt", "20", "--out", str(tmp_path / "flight")])
    assert code == 0
    [before] = printed_before_plot
    assert before.count("\n") == 1 and "; 3 steps; end land confirmed, disarmed" in before
    assert "track" not in before
    assert capsys.readouterr().out == f"track {tmp_path / 'flight' / 'track.png'}\n"
    assert (tmp_path / "flight" / "track.png").stat().st_size > 5_000
    clamps = [r for r in caplog.records if "clamped to 20 m" in r.getMessage()]
    assert len(clamps) == 1 and clamps[0].levelname == "WARNING"


def test_sighup_ends_the_flight_like_ctrl_c(scene: Any, tmp_path: Path) -> None:
    before = signal.getsignal(signal.SIGHUP)  # SIG_IGN when the suite runs under nohup
    with fast_emulator(scene, "ardupilot") as emu:
        policy = hook_policy([0, 3] * 20, 2, lambda: os.kill(os.getpid(), signal.SIGHUP))
        result = _fly(scene, emu, policy, tmp_path, target_cell=(9, 9))
        assert result.outcome == "interrupted" and result.signal_name == "SIGHUP"
        assert result.exit_code == 129
        assert read_record(result.record_path)[-1]["exit_code"] == 129
        assert result.end_action == "land" and result.end_ok and not emu.armed
    assert signal.getsignal(signal.SIGHUP) is before  # handlers restored


# ------------------------------------------------------------- operator at each phase
class _SecondGCS:
    """Another MAVLink client (sysid 250) that changes the mode when ``when(emu)`` holds."""

    def __init__(self, emu: Emulator, when: Any, mode: str) -> None:
        self.emu, self.when, self.mode = emu, when, mode
        self.link = mavutil.mavlink_connection(emu.connect_url, source_system=250,
                                               source_component=190)
        self.t_s: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.01):
            self.link.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            with self.emu._lock:
                fire = self.t_s is None and self.when(self.emu)
            if fire:
                _, main, sub = M.encode_mode(self.emu.flavour, self.mode)
                self.link.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, main, sub,
                                                0, 0, 0, 0)
                t0 = time.monotonic()
                while time.monotonic() - t0 < 2:
                    cmds = [c for c in self.emu.commands if c.source[0] == 250]
                    if cmds:
                        self.t_s = cmds[0].t_s
                        return
                    time.sleep(0.005)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.link.close()


def _refused_arm(emu: Emulator) -> bool:
    return any(c.command == M.MAV_CMD_COMPONENT_ARM_DISARM and c.result == 4
               for c in emu.commands)


PHASES = {
    # ArduPilot refuses arming for ~2 s (PreArm); the operator switches to LOITER meanwhile.
    "arming": ("ardupilot", "hold", _refused_arm, {"prearm_s": 15.0}),
    # Climbing through 4 m of a 10 m take-off.
    "take-off": ("ardupilot", "hold", lambda e: e.armed and e.pos[2] < -4.0, {}),
    # PX4 descending in LAND after reaching the target, still above 4 m.
    "landing": ("px4", "hold", lambda e: e.mode == "land" and e.pos[2] < -4.0, {}),
}


@pytest.mark.parametrize("phase", sorted(PHASES))
def test_operator_wins_at_every_phase(scene: Any, tmp_path: Path, phase: str) -> None:
    autopilot, mode, when, kw = PHASES[phase]
    with fast_emulator(scene, autopilot, **kw) as emu:
        gcs = _SecondGCS(emu, when, mode)
        try:
            result = _fly(scene, emu, ScriptedPolicy(path_actions(START, TARGET), META),
                          tmp_path, timeouts=Timeouts(**{**FAST.__dict__, "arm_s": 20}))
        finally:
            gcs.close()
        assert gcs.t_s is not None, "the operator never acted"
        assert result.outcome == "takeover" and result.exit_code == 5, result.reason
        assert "outside geonav" in result.reason, result.reason
        line = result.summary()  # the outcome said once, the operator has control
        assert line.startswith("operator took over: "), line
        assert line.count("operator took over") == 1, line
        assert "operator takeover:" not in line and "failsafe must act" not in line, line
        # Nothing commanded after the operator's mode change: no LAND on top, no re-sent mode.
        assert _geonav_commands(emu, after_t=gcs.t_s) == []
        late = [s for s in emu.setpoints if s.t_s > gcs.t_s + 1.0]
        assert late == [], f"{len(late)} setpoints after the takeover"
        assert emu.mode == M.decode_mode(autopilot, M.custom_mode_value(autopilot, mode))
    rows = read_record(result.record_path)
    assert rows[-1]["outcome"] == "takeover"


# ------------------------------------------------------------------------ pump faults
def test_a_setpoint_send_that_raises_ends_in_geonavs_land(scene: Any, tmp_path: Path) -> None:
    with fast_emulator(scene, "px4") as emu:
        vehicle = open_vehicle(emu.connect_url, "pymavlink")
        broken = threading.Event()
        real_send = vehicle.send_position_target

        def send(target: Any, yaw_deg: float) -> None:
            if broken.is_set():
                raise RuntimeError("MAVSDK: setpoint not done within 1.0 s")
            real_send(target, yaw_deg)

        vehicle.send_position_target = send  # type: ignore[method-assign]
        policy = hook_policy(path_actions(START, TARGET), 1, broken.set)
        cfg = FlightConfig(target_cell=TARGET, start_cell=START, timeouts=FAST)
        result = run_flight(vehicle, scene, policy, cfg, tmp_path)
        assert result.outcome == "safety_stop" and result.exit_code == 6
        assert "setpoint send failed: RuntimeError" in result.reason
        assert result.end_action == "land" and result.end_ok and not emu.armed
        # geonav commanded LAND itself, before PX4's offboard-loss failsafe could act.
        lands = [c for c in _geonav_commands(emu) if c.command == M.MAV_CMD_NAV_LAND]
        assert lands and lands[0].result == M.MAV_RESULT_ACCEPTED
        assert not any("offboard loss" in m for m in emu.mode_history())


# ------------------------------------------------------------------ pre-flight state
def test_an_airborne_vehicle_is_refused_without_a_command(scene: Any, tmp_path: Path) -> None:
    with fast_emulator(scene, "px4", airborne_alt_m=20.0) as emu:
        result = _fly(scene, emu, ScriptedPolicy([1], META), tmp_path)
        assert result.outcome == "refused" and result.exit_code == 3
        assert "already armed" in result.reason and "--takeover-airborne" in result.reason
        assert result.end_action == "none"
        assert _geonav_commands(emu) == [] and not emu.setpoints
        assert emu.armed and emu.mode == "hold" and emu.pos[2] == pytest.approx(-20.0)


def test_takeover_airborne_starts_from_the_current_position(scene: Any, tmp_path: Path) -> None:
    with fast_emulator(scene, "ardupilot", airborne_alt_m=12.0) as emu:
        result = _fly(scene, emu, ScriptedPolicy(path_actions(START, TARGET), META), tmp_path,
                      takeover_airborne=True)
        assert result.success and result.outcome == "reached", result.reason
        assert result.end_ok and not emu.armed
        assert not emu.commands_named(M.MAV_CMD_NAV_TAKEOFF)
        assert not emu.commands_named(M.MAV_CMD_COMPONENT_ARM_DISARM)
    steps = [r for r in read_record(result.record_path) if r["kind"] == "step"]
    assert all(r["measured_alt_m"] == pytest.approx(12.0, abs=1.0) for r in steps)


def test_takeover_airborne_refuses_a_vehicle_armed_on_the_ground(scene: Any,
                                                                 tmp_path: Path) -> None:
    # Seen on ArduCopter SITL: after an operator's LOITER the vehicle sank to the ground
    # and stayed armed; the refusal said "give a positive number of metres".
    with fast_emulator(scene, "ardupilot", airborne_alt_m=0.3) as emu:
        result = _fly(scene, emu, ScriptedPolicy([1], META), tmp_path, takeover_airborne=True)
        assert result.outcome == "refused" and result.exit_code == 3
        assert "armed but on the ground" in result.reason, result.reason
        # only telemetry requests (SET_MESSAGE_INTERVAL, REQUEST_MESSAGE): no mode, arm,
        # take-off or landing command, no setpoint
        assert {c.command for c in _geonav_commands(emu)} <= {
            M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAV_CMD_REQUEST_MESSAGE}
        assert not emu.setpoints and emu.armed



@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_a_px4_whose_preflight_checks_fail_is_refused_in_words(scene: Any, tmp_path: Path,
                                                               backend: str) -> None:
    # Seen on PX4 SIH: after a landing, "Preflight: GPS Vertical Pos Drift too high" kept
    # the HEARTBEAT at UNINIT for minutes; a second flight was refused after 60 s with
    # "HEARTBEAT system_status STANDBY: not seen ... status 0".
    text = "Preflight: GPS Vertical Pos Drift too high"
    with fast_emulator(scene, "px4", preflight_fail=text) as emu:
        quick = Timeouts(**{**FAST.__dict__, "ready_s": 2.0})
        result = _fly(scene, emu, ScriptedPolicy([1], META), tmp_path, backend, timeouts=quick)
        assert result.outcome == "refused" and result.exit_code == 3, result.reason
        assert "pre-flight checks did not pass" in result.reason, result.reason
        assert text in result.reason
        assert not emu.armed and not emu.setpoints
        assert not emu.commands_named(M.MAV_CMD_COMPONENT_ARM_DISARM)


# ----------------------------------------------------------------- position fence
def test_overshoot_past_the_fence_ends_in_landing(scene: Any, tmp_path: Path) -> None:
    # Fence margin = one 5 m step: setpoints stay 5 m inside the scene, the vehicle may
    # overshoot 2.5 m more. A gust blows it 12 m east of the last setpoint (cell 9 -> x 17.5).
    with fast_emulator(scene, "px4") as emu:
        policy = hook_policy([1] * 3, 1, lambda: emu.push(0.0, 12.0))
        result = _fly(scene, emu, policy, tmp_path, start_cell=(8, 5), target_cell=(10, 5))
        assert result.outcome == "safety_stop", result.reason
        assert "position fence" in result.reason and "breached" in result.reason
        assert result.end_action == "land" and result.end_ok and not emu.armed
    lattice = Lattice(scene.bounds_m, 5.0)
    xmax = scene.bounds_m[2] - 5.0
    for s in emu.setpoints:  # no setpoint ever left the fence
        p = scene.frame.from_lonlat(emu.lonlat_of(s.north_m, s.east_m))
        assert p.x_m <= xmax + 1e-6
    assert lattice.shape == (12, 12)


# ----------------------------------------------------------------------- obstacles
def _tower_scene(base: Any, cell: tuple[int, int]) -> Any:
    dsm = np.zeros(base.rgb.shape[:2], np.float32)
    c = Lattice(base.bounds_m, 5.0).center(cell)
    col, row = base.to_pixel(c.x_m, c.y_m)
    half = int(1.0 / base.gsd_m)  # a 2 m tower: only its own cell is blocked
    dsm[int(row) - half : int(row) + half, int(col) - half : int(col) + half] = 60.0
    return Scene.from_arrays("towers", base.rgb, base.origin, base.gsd_m, dsm=dsm)


@pytest.mark.parametrize("on_obstacle", ["stay", "end"])
def test_a_dsm_obstacle_in_the_path_is_never_flown_into(
    scene: Any, tmp_path: Path, on_obstacle: str
) -> None:
    towers = _tower_scene(scene, (6, 5))
    with fast_emulator(towers, "ardupilot") as emu:
        result = _fly(towers, emu, ScriptedPolicy([1, 1, 1], META), tmp_path,
                      target_cell=(7, 6), max_steps=3, on_obstacle=on_obstacle)
        assert result.end_ok and not emu.armed
    lattice = Lattice(towers.bounds_m, 5.0)
    for s in emu.used_setpoints():
        p = towers.frame.from_lonlat(emu.lonlat_of(s.north_m, s.east_m))
        assert lattice.cell_of(p) != (6, 5)
    steps = [r for r in read_record(result.record_path) if r["kind"] == "step"]
    assert steps[0]["blocked"] and "obstacle: cell (6, 5)" in steps[0]["events"][0]
    if on_obstacle == "stay":
        assert result.outcome == "missed" and result.steps == 3 and result.final_cell == START
        assert "kept position" in steps[0]["events"][0]
    else:
        assert result.outcome == "safety_stop" and result.steps == 1
        assert "--on-obstacle end" in result.reason


def test_the_plan_is_checked_before_connecting(scene: Any, tmp_path: Path) -> None:
    towers = _tower_scene(scene, (7, 6))
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=r"target cell \(7, 6\) is an obstacle at 10 m"):
        fly(ScriptedPolicy([1], META), towers, target_cell=(7, 6), connect="tcp:127.0.0.1:9",
            out_dir=tmp_path)
    with pytest.raises(ConfigError, match="outside the lattice of shape"):
        fly(ScriptedPolicy([1], META), scene, target_cell=(40, 6), connect="tcp:127.0.0.1:9",
            out_dir=tmp_path)
    multi = {**META, "alt_m": [10.0, 20.0]}
    with pytest.raises(ConfigError, match="several altitudes.*--alt"):
        fly(ScriptedPolicy([1], multi), scene, target_cell=(7, 6), connect="tcp:127.0.0.1:9",
            out_dir=tmp_path)
    assert time.monotonic() - t0 < 30  # no connection was tried (it would wait 30 s)
    plan = plan_flight(scene, multi, FlightConfig(target_cell=(7, 6), alt_m=20.0))
    assert plan.alt_m == 20.0 and plan.margin_m == 5.0


def test_an_altitude_clamp_is_a_warning(scene: Any, caplog: Any) -> None:
    plan = plan_flight(scene, {**META, "alt_m": 300.0}, FlightConfig(target_cell=(7, 6)))
    assert plan.alt_m == 120.0
    assert plan.notes == ["altitude 300 m clamped to 120 m (--max-alt)"]
    assert any(r.levelname == "WARNING" and "clamped" in r.getMessage() for r in caplog.records)


# -------------------------------------------------------------------------- link loss
@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_a_dead_autopilot_is_one_line_and_bounded(
    scene: Any, tmp_path: Path, backend: str, capfd: Any
) -> None:
    errors: list[Any] = []
    old_hook = threading.excepthook
    threading.excepthook = errors.append
    try:
        with fast_emulator(scene, "ardupilot", listen="tcp:127.0.0.1:0") as emu:
            vehicle = open_vehicle(emu.connect_url, backend)
            policy = hook_policy(path_actions(START, TARGET), 1, emu.stop)  # the autopilot dies
            t0 = time.monotonic()
            quick = Timeouts(**{**FAST.__dict__, "command_s": 1.0})
            cfg = FlightConfig(target_cell=TARGET, start_cell=START, timeouts=quick,
                               heartbeat_timeout_s=1.0)
            result = run_flight(vehicle, scene, policy, cfg, tmp_path)
            elapsed = time.monotonic() - t0
    finally:
        threading.excepthook = old_hook
    assert result.outcome == "link_lost" and result.exit_code == 4
    assert "\n" not in result.reason and "failsafe must act" in result.reason
    assert not result.end_ok and "NOT confirmed" in result.summary()
    assert "link lost: link lost" not in result.summary()  # the outcome is said once
    # ... and so is the rest: PX4 SIH printed "link lost: LOCAL_POSITION_NED stream lost
    # ...; link lost: no autopilot heartbeat ...; the autopilot's own failsafe must act;
    # 3 steps; end land NOT confirmed (disarmed False); the autopilot's failsafe must act".
    assert result.summary().count("link lost") == 1, result.summary()
    assert result.summary().count("failsafe must act") == 1, result.summary()
    assert errors == []  # no thread died with a traceback
    # Nothing on the console from the libraries: pymavlink printed "EOF on TCP socket"
    # at every read of the closed port (649,379 lines when ArduCopter SITL was killed).
    printed = capfd.readouterr()
    assert "EOF on TCP socket" not in printed.out + printed.err
    assert elapsed < 60  # LAND retried for dead_link_s, not the 180 s landing timeout
    vehicle.close()  # a second close of a dead link never raises
    if backend == "mavsdk":
        # A stopped but unclosed loop printed "warning: unclosed event loop" at exit
        # after every MAVSDK flight on ArduCopter SITL.
        assert vehicle._loop.is_closed()
        # A LAND still blocking in MAVSDK's executor when it was destroyed never returned,
        # and Python waits for executor threads at exit: the process hung.
        assert not [t for t in threading.enumerate() if t.name.startswith("asyncio_")]


def test_a_late_ack_of_another_command_is_not_taken_for_lands(scene: Any) -> None:
    with fast_emulator(scene, "px4") as emu:
        v = open_vehicle(emu.connect_url, "pymavlink")
        v.connect(5.0)
        try:
            emu.drop_link(None)
            stale = v._m.mav.command_ack_encode(M.MAV_CMD_DO_SET_MODE, 0, 0, 0, GEONAV, 191)
            stale._header = type("H", (), {"srcSystem": 1, "srcComponent": 1})()

            def inject() -> None:
                time.sleep(0.2)
                v._on_message(stale)  # e.g. the late answer of an earlier mode change

            threading.Thread(target=inject, daemon=True).start()
            with pytest.raises(FlightTimeout, match="NAV_LAND"):
                v.land(1.0)
        finally:
            v.close()


def test_the_track_picture_is_zoomed_to_the_flight(tmp_path: Path) -> None:
    from geonav.mavlink_bridge.record import FlightRecorder, _backdrop, _view_box

    big = textured_scene(400.0, 2.0, towers=False)
    rec = FlightRecorder(tmp_path)
    for i in range(20):
        rec.sample(10.0 + i, 20.0, "autonomy" if i < 15 else "landing")
    box = _view_box(rec, big.bounds_m, Lattice(big.bounds_m, 5.0), (10.0, 20.0), (30.0, 20.0))
    assert box[2] - box[0] == pytest.approx(40.0)  # 20 m of flight + two 5 m cells each side
    png = rec.plot(big, Lattice(big.bounds_m, 5.0), (10.0, 20.0), (30.0, 20.0))
    assert png.stat().st_size > 5_000
    rec.close()
    assert math.isfinite(box[0])
    # only the zoomed part of the ortho is read and drawn, at most 1400 px a side: the
    # whole ortho (300 MB for 2.5 km at 0.25 m) made the picture take 30-70 s
    img, extent = _backdrop(big, box)
    assert img.shape[:2] == (20, 20) and extent == pytest.approx((box[0], box[2], box[1], box[3]))
    img, extent = _backdrop(big, big.bounds_m, max_px=50)
    assert max(img.shape[:2]) <= 50 and extent[0] == big.bounds_m[0]
    assert _backdrop(big, (1e4, 1e4, 1e4 + 10, 1e4 + 10)) is None


def test_mavsdk_log_goes_to_python_logging(scene: Any, tmp_path: Path, caplog: Any,
                                           capfd: Any) -> None:
    with fast_emulator(scene, "px4") as emu, caplog.at_level("DEBUG", logger="mavsdk"):
        v = open_vehicle(emu.connect_url, "mavsdk")
        v.connect(10.0)
        v.close()
    assert any(r.name == "mavsdk" and "MAVSDK version" in r.getMessage()
               for r in caplog.records)
    printed = capfd.readouterr()
    # MAVSDK's own printing looks like "[04:26:00|Info ] MAVSDK version: v4.1.0 (...)".
    assert "|Info ]" not in printed.out + printed.err


def test_mavsdk_repeats_its_errors_once_per_window(caplog: Any, capfd: Any) -> None:
    """A port that refuses: MAVSDK logged 'Connect error' and 'Sending message failed'
    once a second each (about 100 ERROR lines on the console after ArduCopter SITL
    was killed); now each shows at most once per window, the repeats at DEBUG."""
    import socket

    with socket.socket() as s:  # a free port that nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    v = open_vehicle(f"tcp:127.0.0.1:{port}", "mavsdk")
    with caplog.at_level("DEBUG", logger="mavsdk"), \
            pytest.raises(FlightTimeout, match="; MAVSDK: .*Connect error: Connection refused"):
        v.connect(3.0)  # geonav's one line quotes MAVSDK's reason
    v.close()
    refused = [r for r in caplog.records
               if r.name == "mavsdk" and "Connect error" in r.getMessage()]
    assert len(refused) >= 2  # MAVSDK retried (at 1 Hz) and every try reached logging
    assert all(r.levelno < 30 for r in refused), [r.getMessage() for r in refused]
    assert all(r.levelno == 10 for r in refused[1:])
    printed = capfd.readouterr()
    assert "|Error]" not in printed.out + printed.err  # nothing raw on the console


def test_mavsdk_log_forwarder_folds_repeats() -> None:
    import logging

    from geonav.mavlink_bridge.mavsdk_backend import MavsdkLogForwarder

    got: list[tuple[int, str]] = []

    class _Sink(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            got.append((record.levelno, record.getMessage()))

    logger = logging.getLogger("test.mavsdk.fold")
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    logger.addHandler(_Sink())
    now = [0.0]
    fwd = MavsdkLogForwarder(logger, window_s=10.0, clock=lambda: now[0])
    for t in range(25):  # one ERROR a second for 25 s, plus one INFO line
        now[0] = float(t)
        assert fwd(3, "Sending message failed", "mavsdk_impl.cpp", 1187) is True
    assert fwd(1, "MAVSDK version: v4.1.0", None, 0) is True
    shown = [(lvl, m) for lvl, m in got if lvl > logging.DEBUG]
    # one level down: geonav reports what ends a flight itself; MAVSDK's errors are the
    # diagnosis behind it (-v), its info lines -vv
    assert shown == [
        (logging.INFO, "Sending message failed"),
        (logging.INFO, "Sending message failed (and 9 more in 10 s)"),
        (logging.INFO, "Sending message failed (and 9 more in 10 s)"),
    ]
    assert (logging.DEBUG, "MAVSDK version: v4.1.0") in got
    assert sum(lvl == logging.DEBUG for lvl, _ in got) == 23
    assert fwd.problems[-1] == (24.0, "Sending message failed")
    # "Callback took more than 1 second" (MAVSDK WARN, on a loaded machine) stays off the
    # console at geonav's default level
    assert fwd(2, "Callback took more than 1 second to run.", None, 0) is True
    assert got[-1] == (logging.INFO, "Callback took more than 1 second to run.")
    assert fwd("not a level", None, None, 0) is False  # type: ignore[arg-type]


def test_emulate_stops_on_sigterm(capsys: Any) -> None:
    import argparse

    from geonav.mavlink_bridge import cli

    p = argparse.ArgumentParser()
    cli.add_parser(p.add_subparsers())
    args = p.parse_args(["mavlink", "emulate", "--listen", "udp:127.0.0.1:0"])
    before = signal.getsignal(signal.SIGTERM)  # not always SIG_DFL: ray.init installs one
    timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGTERM))
    timer.start()
    t0 = time.monotonic()
    assert args.handler(args) == 0
    timer.join()
    assert time.monotonic() - t0 < 10
    assert "emulator on udp:127.0.0.1:0" in capsys.readouterr().out
    assert signal.getsignal(signal.SIGTERM) == before  # the previous handler is back


def test_a_task_files_target_cell_flies_as_is(scene: Any, tmp_path: Path) -> None:
    from geonav.mavlink_bridge.flight import load_task
    from geonav.testing import tiny_taskset

    ts = tiny_taskset(scene, alt_m=10.0, cells=4, step_m=5.0, max_steps=6, target=(3, 2))
    path = ts.save(tmp_path / "tasks.json")
    assert load_task(f"{path}:tiny").target_cell == (3, 2)
    with pytest.raises(ConfigError, match="not in"):
        load_task(f"{path}:nope")
    ec = EmulatorConfig(time_scale=6.0, boot_s=1.0, prearm_s=2.0, origin_s=0.6,
                        local_position_s=1.2, offboard_loss_s=3.0)
    # Cells count in the task's 4 x 4 lattice (region -10..10 m), not over the scene.
    result = fly(ScriptedPolicy([1, 1, 1, 0, 0], META), scene, task=path, start_cell=(0, 0),
                 dry_run=True, emulator_config=ec, out_dir=tmp_path / "f", timeouts=FAST)
    assert result.success and result.final_cell == (3, 2) and result.steps == 5, result.reason
    header = read_record(result.record_path)[0]
    assert header["lattice_region_m"] == [-10.0, -10.0, 10.0, 10.0]


def test_a_process_freeze_right_after_arming_does_not_disarm(scene: Any, tmp_path: Path) -> None:
    """The old flake: a 1 s pause after the ARM ACK jumped the emulated clock past DISARM_DELAY."""
    import ctypes

    freeze = ctypes.PyDLL(None).usleep  # holds the GIL: the whole process stands still
    with fast_emulator(scene, "ardupilot", disarm_delay_s=4.0) as emu:
        done = threading.Event()

        def watch() -> None:
            while not done.is_set():
                if emu.armed:
                    freeze(1_000_000)
                    return
                time.sleep(0.002)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        try:
            result = _fly(scene, emu, ScriptedPolicy([1], META), tmp_path, target_cell=(6, 5))
        finally:
            done.set()
            watcher.join()
        assert result.success, result.reason
        assert not any("no take-off" in e for _, e in emu.events)
